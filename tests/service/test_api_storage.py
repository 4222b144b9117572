"""Blob store (content addressing, atomic durable writes) and structured JSON logs."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from service.store.blobs import BlobNotFoundError, BlobStore, FileBlobStore, blob_store_from_url, sha256_bytes
from service.telemetry import JsonFormatter, RequestIdFilter, request_id_var


def test_file_blob_store_roundtrip(tmp_path: Path) -> None:
    store = blob_store_from_url(f"file://{tmp_path / 'blobs'}")
    assert isinstance(store, FileBlobStore) and isinstance(store, BlobStore)
    store.ping()
    sha = store.put(b"hello mesh")
    assert sha == sha256_bytes(b"hello mesh")
    path = store.path(sha)
    assert path == tmp_path / "blobs" / "sha256" / sha[:2] / sha[2:4] / sha
    assert store.exists(sha) and store.get(sha) == b"hello mesh"
    with store.open(sha) as fh:
        assert fh.read() == b"hello mesh"
    assert store.put(b"hello mesh") == sha  # idempotent
    source = tmp_path / "src.bin"
    source.write_bytes(b"x" * 3_000_000)
    assert store.get(store.put_file(source)) == source.read_bytes()
    assert not [p for p in (tmp_path / "blobs").rglob(".tmp-*")]  # no temp files left behind


def test_file_blob_store_missing_and_invalid(tmp_path: Path) -> None:
    store = FileBlobStore(tmp_path)
    with pytest.raises(BlobNotFoundError):
        store.get("0" * 64)
    with pytest.raises(BlobNotFoundError):
        store.get("../../etc/passwd")
    assert not store.exists("not-a-sha")
    with pytest.raises(ValueError):
        blob_store_from_url("ftp://somewhere")


def test_json_log_lines_carry_request_id() -> None:
    record = logging.LogRecord("fleetmap.test", logging.INFO, __file__, 1, "uploaded %s", ("x",), None)
    record.tile = [1, 2]
    token = request_id_var.set("req-1")
    try:
        RequestIdFilter().filter(record)
    finally:
        request_id_var.reset(token)
    line = json.loads(JsonFormatter().format(record))
    assert line["message"] == "uploaded x" and line["request_id"] == "req-1"
    assert line["level"] == "INFO" and line["tile"] == [1, 2]
