"""Content-addressed blob storage (submap meshes, fused tile meshes, fields): ``base`` (interface, errors,
hashes), ``fs`` (files), ``s3`` (S3-compatible object store). :func:`blob_store_from_url` picks one."""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlparse

from service.store.blobs.base import (
    BlobInfo,
    BlobNotFoundError,
    BlobStore,
    BlobStoreUnavailableError,
    sha256_bytes,
    sha256_file,
)
from service.store.blobs.fs import FileBlobStore

__all__ = [
    "BlobInfo", "BlobNotFoundError", "BlobStore", "BlobStoreUnavailableError", "FileBlobStore", "blob_store_from_url",
    "sha256_bytes", "sha256_file",
]


def blob_store_from_url(url: str) -> BlobStore:
    """The blob store for ``FLEETMAP_BLOB_URL``: ``file:///path`` (or a plain path), ``s3://bucket/prefix``."""
    parsed = urlparse(url)
    if parsed.scheme in ("", "file"):
        return FileBlobStore(Path(parsed.netloc + parsed.path if parsed.scheme == "file" else url))
    if parsed.scheme == "s3":
        from service.store.blobs.s3 import S3BlobStore  # boto3 is imported only for s3:// stores

        return S3BlobStore.from_url(url)
    raise ValueError(f"unsupported blob URL scheme {parsed.scheme!r} (file:// or s3://)")
