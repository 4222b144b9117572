"""Content-addressed blob storage (submap meshes, fused tile meshes).

Blobs are named by the sha256 of their bytes and written atomically and durably (temporary file
in the target folder, fsync, rename, fsync of the folder) *before* the database row naming them
commits, so a committed row never points at a missing or partial blob.
"""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO, Protocol, runtime_checkable
from urllib.parse import urlparse

_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_CHUNK = 1024 * 1024


class BlobNotFoundError(KeyError):
    """No blob with that sha256."""


class BlobStoreUnavailableError(OSError):
    """The blob store cannot be reached or answered wrongly (the API answers 503)."""


@runtime_checkable
class BlobStore(Protocol):
    """What the service and workers need from blob storage."""

    def put(self, data: bytes) -> str:
        """Store ``data`` durably; return its sha256 (hex). Storing existing content is a no-op."""
        ...

    def put_file(self, path: Path) -> str:
        """Store the file at ``path`` durably; return its sha256 (hex)."""
        ...

    def get(self, sha256: str) -> bytes:
        """The blob's bytes; raises :class:`BlobNotFoundError`."""
        ...

    def open(self, sha256: str) -> BinaryIO:
        """A binary file object for reading the blob; raises :class:`BlobNotFoundError`."""
        ...

    def path(self, sha256: str) -> Path | None:
        """A local filesystem path of the blob, if the store has one (for zero-copy responses)."""
        ...

    def exists(self, sha256: str) -> bool: ...

    def ping(self) -> None:
        """Raise if the store is unreachable or not writable."""
        ...


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class FileBlobStore:
    """Blobs as files under ``root/sha256/ab/cd/<sha256>``."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def _path(self, sha256: str) -> Path:
        if not _SHA256.match(sha256):
            raise BlobNotFoundError(sha256)
        return self.root / "sha256" / sha256[:2] / sha256[2:4] / sha256

    def _write(self, sha256: str, writer: Callable[[BinaryIO], object]) -> str:
        target = self._path(sha256)
        if target.exists():
            return sha256
        folder = target.parent
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=".tmp-", dir=folder)
        try:
            with os.fdopen(fd, "wb") as fh:
                writer(fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp_name, target)
        except BaseException:
            Path(tmp_name).unlink(missing_ok=True)
            raise
        _fsync_dir(folder)
        return sha256

    def put(self, data: bytes) -> str:
        return self._write(sha256_bytes(data), lambda fh: fh.write(data))

    def put_file(self, path: Path) -> str:
        def copy(fh: BinaryIO) -> None:
            with open(path, "rb") as src:
                while chunk := src.read(_CHUNK):
                    fh.write(chunk)

        return self._write(sha256_file(Path(path)), copy)

    def get(self, sha256: str) -> bytes:
        try:
            return self._path(sha256).read_bytes()
        except FileNotFoundError as exc:
            raise BlobNotFoundError(sha256) from exc

    def open(self, sha256: str) -> BinaryIO:
        try:
            return open(self._path(sha256), "rb")
        except FileNotFoundError as exc:
            raise BlobNotFoundError(sha256) from exc

    def path(self, sha256: str) -> Path | None:
        return self._path(sha256)

    def exists(self, sha256: str) -> bool:
        try:
            return self._path(sha256).is_file()
        except BlobNotFoundError:
            return False

    def ping(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        if not os.access(self.root, os.W_OK):
            raise OSError(f"blob store {self.root} is not writable")


def blob_store_from_url(url: str) -> BlobStore:
    """The blob store for ``FLEETMAP_BLOB_URL`` (``file:///path``; ``s3://bucket/prefix`` when the
    optional ``service.blobs_s3`` module provides ``S3BlobStore``)."""
    parsed = urlparse(url)
    if parsed.scheme in ("", "file"):
        return FileBlobStore(Path(parsed.netloc + parsed.path if parsed.scheme == "file" else url))
    if parsed.scheme == "s3":
        try:
            from service.blobs_s3 import S3BlobStore  # type: ignore[import-not-found]
        except ImportError as exc:
            raise ValueError("s3:// blob URLs need service.blobs_s3, which is not installed") from exc
        return S3BlobStore.from_url(url)  # type: ignore[no-any-return]
    raise ValueError(f"unsupported blob URL scheme {parsed.scheme!r} (file:// or s3://)")
