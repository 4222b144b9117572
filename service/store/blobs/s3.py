"""Content-addressed blob store on S3 or any S3-compatible object store (MinIO, Ceph, moto).

Selected by ``FLEETMAP_BLOB_URL=s3://bucket/prefix``; ``FLEETMAP_S3_ENDPOINT_URL`` points at a
non-AWS endpoint, credentials and region come from the standard ``AWS_*`` variables (boto3's chain).

Keys are ``<prefix>/<sha[:2]>/<sha[2:4]>/<sha>`` where ``sha`` is the sha256 of the bytes, so a blob
is immutable and a repeated put of the same bytes is a no-op. Durability: a ``PutObject`` that
returns 200 is durable on S3 (read-after-write consistent); the store additionally sends
``ChecksumSHA256`` so the server rejects corrupted bodies, and on stores that do not echo the
checksum (older MinIO) it reads the object's size back before returning.
"""

from __future__ import annotations

import base64
import io
import logging
import os
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO
from urllib.parse import urlparse

import boto3
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from service.store.blobs.base import (
    SHA256_HEX,
    BlobInfo,
    BlobNotFoundError,
    BlobStoreUnavailableError,
    sha256_bytes,
    sha256_file,
)

log = logging.getLogger(__name__)

_NOT_FOUND_CODES = {"404", "NoSuchKey", "NotFound"}
# Blobs up to this size go in one PutObject with a server-checked sha256; larger ones are multipart.
_MAX_SINGLE_PUT = 256 * 1024 * 1024


class BlobStoreError(BlobStoreUnavailableError):
    """The object store failed or returned bytes that do not match their address (an I/O error)."""


def parse_s3_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` → ``("bucket", "some/prefix")`` (prefix without slashes at the ends)."""
    parsed = urlparse(url)
    if parsed.scheme != "s3" or not parsed.netloc:
        raise ValueError(f"not an s3:// blob URL: {url!r}")
    return parsed.netloc, parsed.path.strip("/")


class S3BlobStore:
    """Blobs addressed by the sha256 hex digest of their bytes, stored as S3 objects."""

    def __init__(
        self,
        url: str,
        endpoint_url: str | None = None,
        *,
        connect_timeout_s: float = 5.0,
        read_timeout_s: float = 60.0,
        max_attempts: int = 4,
        max_pool_connections: int = 32,
    ) -> None:
        self.url = url
        self.bucket, self.prefix = parse_s3_url(url)
        self.endpoint_url = endpoint_url or os.environ.get("FLEETMAP_S3_ENDPOINT_URL") or None
        common: dict[str, Any] = {
            "max_pool_connections": max_pool_connections,
            # Only compute/verify checksums where we ask for them (MinIO/moto differ in defaults).
            "request_checksum_calculation": "when_required",
            "response_checksum_validation": "when_required",
        }
        self._config = Config(
            connect_timeout=connect_timeout_s,
            read_timeout=read_timeout_s,
            retries={"max_attempts": max_attempts, "mode": "standard"},
            **common,
        )
        # Readiness probes must answer within a few seconds, so no retries and short timeouts.
        self._probe_config = Config(
            connect_timeout=min(connect_timeout_s, 2.0),
            read_timeout=min(read_timeout_s, 2.0),
            retries={"max_attempts": 1, "mode": "standard"},
            **common,
        )
        self._clients: dict[tuple[int, str], Any] = {}
        self._lock = threading.Lock()

    def _client_for(self, kind: str, config: Config) -> Any:
        # boto3 clients are thread-safe but must not cross a fork (uvicorn/celery pools fork): one
        # client per process id.
        key = (os.getpid(), kind)
        client = self._clients.get(key)
        if client is None:
            with self._lock:
                client = self._clients.get(key)
                if client is None:
                    client = boto3.session.Session().client(
                        "s3", endpoint_url=self.endpoint_url, config=config
                    )
                    self._clients = {k: v for k, v in self._clients.items() if k[0] == key[0]}
                    self._clients[key] = client
        return client

    @property
    def client(self) -> Any:
        """The boto3 S3 client of this process (created lazily, recreated after a fork)."""
        return self._client_for("data", self._config)

    @classmethod
    def from_url(cls, url: str) -> S3BlobStore:
        """The store for ``FLEETMAP_BLOB_URL=s3://bucket/prefix`` (endpoint from ``FLEETMAP_S3_ENDPOINT_URL``)."""
        return cls(url)

    def key(self, sha256: str) -> str:
        """Object key of the blob ``sha256`` (lower-case hex); ``BlobNotFoundError`` for other names."""
        if not SHA256_HEX.match(sha256):
            raise BlobNotFoundError(sha256)
        name = f"{sha256[:2]}/{sha256[2:4]}/{sha256}"
        return f"{self.prefix}/{name}" if self.prefix else name

    def put(self, data: bytes) -> str:
        """Store ``data``; returns its sha256 hex digest. Durable when it returns (S3 PUT semantics)."""
        sha = sha256_bytes(data)
        # No HEAD first: re-putting identical bytes under their own address is harmless and saves
        # a round trip on the hot path (duplicates are rare: idempotent retries only).
        checksum = base64.b64encode(bytes.fromhex(sha)).decode("ascii")
        try:
            response = self.client.put_object(
                Bucket=self.bucket,
                Key=self.key(sha),
                Body=data,
                ChecksumSHA256=checksum,
                ContentLength=len(data),
                ContentType="application/octet-stream",
            )
        except (ClientError, BotoCoreError) as exc:
            raise BlobStoreError(f"s3 put of blob {sha} failed: {exc}") from exc
        echoed = response.get("ChecksumSHA256")
        if echoed is not None:
            if echoed != checksum:
                raise BlobStoreError(f"s3 put of blob {sha}: server checksum {echoed} differs")
        else:
            # The store did not confirm the checksum: confirm at least that the object exists whole.
            size = self._head_size(sha)
            if size != len(data):
                raise BlobStoreError(f"s3 put of blob {sha}: stored {size} bytes, sent {len(data)}")
        return sha

    def put_file(self, path: Path) -> str:
        """Store the file at ``path``; returns its sha256 hex digest. Durable when it returns."""
        path = Path(path)
        if path.stat().st_size <= _MAX_SINGLE_PUT:
            return self.put(path.read_bytes())
        sha = sha256_file(path)
        try:
            # Managed multipart upload; S3 completes it atomically, so readers never see a part.
            self.client.upload_file(str(path), self.bucket, self.key(sha))
        except (ClientError, BotoCoreError) as exc:
            raise BlobStoreError(f"s3 multipart put of blob {sha} failed: {exc}") from exc
        size = self._head_size(sha)
        if size != path.stat().st_size:
            raise BlobStoreError(f"s3 put of blob {sha}: stored {size} bytes, file has {path.stat().st_size}")
        return sha

    def open(self, sha256: str) -> BinaryIO:
        """A binary file object over the verified bytes of blob ``sha256``."""
        return io.BytesIO(self.get(sha256))

    def path(self, sha256: str) -> Path | None:
        """Objects have no local path (responses stream the bytes instead)."""
        return None

    def get(self, sha256: str) -> bytes:
        """The bytes of blob ``sha256``; ``BlobNotFoundError`` if absent, ``BlobStoreError`` if corrupt."""
        try:
            response = self.client.get_object(Bucket=self.bucket, Key=self.key(sha256))
            data: bytes = response["Body"].read()
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in _NOT_FOUND_CODES:
                raise BlobNotFoundError(sha256) from exc
            raise BlobStoreError(f"s3 get of blob {sha256} failed: {exc}") from exc
        except BotoCoreError as exc:
            raise BlobStoreError(f"s3 get of blob {sha256} failed: {exc}") from exc
        if sha256_bytes(data) != sha256:
            raise BlobStoreError(f"s3 blob {sha256} is corrupt (content hash differs)")
        return data

    def exists(self, sha256: str) -> bool:
        """Whether blob ``sha256`` is stored."""
        if not SHA256_HEX.match(sha256):
            return False
        return self._head_size(sha256) is not None

    def size(self, sha256: str) -> int | None:
        """Stored size of blob ``sha256`` in bytes, None if absent."""
        return self._head_size(sha256)

    def list_blobs(self) -> Iterator[BlobInfo]:
        """Every blob under the store's prefix (paginated listing)."""
        try:
            pages = self.client.get_paginator("list_objects_v2").paginate(
                Bucket=self.bucket, Prefix=f"{self.prefix}/" if self.prefix else "")
            for page in pages:
                for obj in page.get("Contents", []):
                    name = obj["Key"].rsplit("/", 1)[-1]
                    if SHA256_HEX.match(name) and obj["Key"] == self.key(name):
                        yield BlobInfo(name, int(obj["Size"]), obj["LastModified"])
        except (ClientError, BotoCoreError) as exc:
            raise BlobStoreError(f"s3 listing of {self.bucket!r} failed: {exc}") from exc

    def delete(self, sha256: str) -> None:
        """Remove blob ``sha256`` (idempotent). Only for garbage collection of unreferenced blobs."""
        try:
            self.client.delete_object(Bucket=self.bucket, Key=self.key(sha256))
        except (ClientError, BotoCoreError) as exc:
            raise BlobStoreError(f"s3 delete of blob {sha256} failed: {exc}") from exc

    def sweep_partial_writes(self, older_than: datetime, dry_run: bool = False) -> tuple[int, int]:
        """Nothing: an object appears whole or not at all (incomplete multipart uploads are the bucket's
        lifecycle rule's to abort, ``AbortIncompleteMultipartUpload``)."""
        return 0, 0

    def ping(self) -> None:
        """Raise ``BlobStoreError`` unless the bucket is reachable with the configured credentials."""
        try:
            self._client_for("probe", self._probe_config).head_bucket(Bucket=self.bucket)
        except (ClientError, BotoCoreError) as exc:
            raise BlobStoreError(f"s3 bucket {self.bucket!r} unreachable: {exc}") from exc

    def ensure_bucket(self) -> None:
        """Create the bucket if it does not exist (deployment bootstrap and tests)."""
        try:
            self.client.head_bucket(Bucket=self.bucket)
            return
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") not in _NOT_FOUND_CODES | {"NoSuchBucket"}:
                raise BlobStoreError(f"s3 bucket {self.bucket!r}: {exc}") from exc
        try:
            self.client.create_bucket(Bucket=self.bucket)
        except ClientError as exc:
            code = exc.response.get("Error", {}).get("Code")
            if code not in {"BucketAlreadyOwnedByYou", "BucketAlreadyExists"}:
                raise BlobStoreError(f"s3 create bucket {self.bucket!r}: {exc}") from exc

    def _head_size(self, sha256: str) -> int | None:
        try:
            response = self.client.head_object(Bucket=self.bucket, Key=self.key(sha256))
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in _NOT_FOUND_CODES:
                return None
            raise BlobStoreError(f"s3 head of blob {sha256} failed: {exc}") from exc
        except BotoCoreError as exc:
            raise BlobStoreError(f"s3 head of blob {sha256} failed: {exc}") from exc
        return int(response["ContentLength"])
