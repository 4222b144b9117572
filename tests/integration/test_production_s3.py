"""The S3 blob store against a real S3 protocol server (moto in server mode on loopback)."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.store.blobs import BlobNotFoundError, blob_store_from_url
from service.store.blobs.s3 import BlobStoreError, S3BlobStore, parse_s3_url

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def s3_endpoint() -> Iterator[str]:
    """moto's S3 server on a free 127.0.0.1 port, with dummy credentials in the environment."""
    from moto.server import ThreadedMotoServer

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("AWS_ACCESS_KEY_ID", "fleetmap-test")
        mp.setenv("AWS_SECRET_ACCESS_KEY", "fleetmap-test-secret")
        mp.setenv("AWS_DEFAULT_REGION", "us-east-1")
        server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        server.start()
        host, port = server.get_host_and_port()
        try:
            yield f"http://{host}:{port}"
        finally:
            server.stop()


@pytest.fixture()
def store(s3_endpoint: str, monkeypatch: pytest.MonkeyPatch) -> S3BlobStore:
    monkeypatch.setenv("FLEETMAP_S3_ENDPOINT_URL", s3_endpoint)
    created = blob_store_from_url("s3://fleetmap-blobs/tests/prefix")
    assert isinstance(created, S3BlobStore)
    created.ensure_bucket()
    return created


def test_parse_url() -> None:
    assert parse_s3_url("s3://bucket/a/b/") == ("bucket", "a/b")
    assert parse_s3_url("s3://bucket") == ("bucket", "")
    with pytest.raises(ValueError):
        parse_s3_url("file:///tmp/x")


def test_put_get_exists_round_trip(store: S3BlobStore) -> None:
    data = bytes(range(256)) * 1000
    sha = store.put(data)
    assert sha == hashlib.sha256(data).hexdigest()
    assert store.exists(sha)
    assert store.get(sha) == data
    assert store.open(sha).read() == data
    assert store.path(sha) is None
    # content-addressed: a second put of the same bytes is the same blob
    assert store.put(data) == sha
    key = store.key(sha)
    assert key.startswith("tests/prefix/") and key.endswith(sha)


def test_missing_and_invalid_names(store: S3BlobStore) -> None:
    absent = "0" * 64
    assert not store.exists(absent)
    assert not store.exists("../etc/passwd")
    with pytest.raises(BlobNotFoundError):
        store.get(absent)
    with pytest.raises(BlobNotFoundError):
        store.get("not-a-sha")


def test_corrupt_object_is_detected(store: S3BlobStore) -> None:
    sha = store.put(b"original bytes")
    store.client.put_object(Bucket=store.bucket, Key=store.key(sha), Body=b"tampered bytes")
    with pytest.raises(BlobStoreError):
        store.get(sha)


def test_put_file(store: S3BlobStore, tmp_path: Path) -> None:
    path = tmp_path / "mesh.ply"
    path.write_bytes(b"ply\n" + b"x" * 100_000)
    sha = store.put_file(path)
    assert store.get(sha) == path.read_bytes()


def test_list_and_delete_for_the_garbage_collection(store: S3BlobStore) -> None:
    from datetime import UTC, datetime, timedelta

    from service.store.gc import collect

    kept, gone = store.put(b"named by a row"), store.put(b"named by none")
    # a foreign object under the prefix and one outside it are not blobs of this store
    store.client.put_object(Bucket=store.bucket, Key="tests/prefix/notes.txt", Body=b"x")
    store.client.put_object(Bucket=store.bucket, Key=f"elsewhere/{gone[:2]}/{gone[2:4]}/{gone}", Body=b"y")
    listed = {b.sha256: b for b in store.list_blobs()}
    assert {kept, gone} <= set(listed) and listed[gone].size == len(b"named by none")
    assert all(store.key(sha).startswith("tests/prefix/") for sha in listed)
    assert abs(listed[kept].modified - datetime.now(UTC)) < timedelta(minutes=5)

    report = collect(store, {kept}, now=datetime.now(UTC) + timedelta(days=2))
    assert gone in report.removed and kept not in report.removed and report.partial == 0
    assert store.exists(kept) and not store.exists(gone)
    assert store.client.get_object(Bucket=store.bucket, Key="tests/prefix/notes.txt")["Body"].read() == b"x"
    store.delete(gone)  # idempotent


def test_ping(store: S3BlobStore, s3_endpoint: str) -> None:
    store.ping()
    with pytest.raises(BlobStoreError):
        S3BlobStore("s3://no-such-bucket-here", endpoint_url=s3_endpoint).ping()
    # an endpoint nobody listens on fails fast instead of hanging
    dead = S3BlobStore("s3://fleetmap-blobs", endpoint_url="http://127.0.0.1:9", connect_timeout_s=1)
    with pytest.raises(BlobStoreError):
        dead.ping()


@pytest.mark.slow
def test_ingest_fuse_download_with_s3_blobs(s3_endpoint: str, tmp_path: Path) -> None:
    """The production path with every blob in S3: upload → `fleetmap worker` fuses → mesh download."""
    import httpx

    from tests.production_support import deployment, post_submap, small_mesh, submap_meta, wait_until
    from tests.worker_support import tile_fused

    bucket_url = "s3://fleetmap-e2e/blobs"
    store = S3BlobStore(bucket_url, endpoint_url=s3_endpoint)
    store.ensure_bucket()
    with deployment(tmp_path, blob_url=bucket_url, s3_endpoint_url=s3_endpoint) as dep:
        try:
            _, base = dep.api()
            dep.worker()
            with httpx.Client(base_url=base, timeout=30, headers=dep.headers) as client:
                assert client.get("/readyz").json()["checks"]["blob_store"] == "ok"
                meshes = [small_mesh(seq) for seq in range(2)]
                for seq, mesh in enumerate(meshes):
                    meta = submap_meta("veh-s3/e2e", seq, [20.0 + 4 * seq, 20.0, 0.0])
                    response = post_submap(client, dep.headers, meta, mesh)
                    assert response.status_code == 201, response.text
                    assert store.get(response.json()["sha256"]) == mesh  # the upload landed in S3
                assert (tmp_path / "blobs").exists() is False
                accepted = client.post("/v1/tiles/0/0/fuse")
                assert accepted.status_code == 202, accepted.text
                assert client.get(f"/v1/jobs/{accepted.json()['job_id']}").json()["kind"] == "align"
                wait_until(tile_fused(client, 0, 0, 1), 240, "tile (0, 0) aligned and fused", interval_s=0.5)
                ply = client.get("/v1/tiles/0/0/mesh")
                assert ply.status_code == 200 and ply.content.startswith(b"ply")
                etag = ply.headers["etag"]
                assert client.get("/v1/tiles/0/0/mesh", headers={"If-None-Match": etag}).status_code == 304
                # The fused mesh came from the object store: its bytes are a stored blob.
                assert store.exists(hashlib.sha256(ply.content).hexdigest())
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{dep.logs()}") from None
