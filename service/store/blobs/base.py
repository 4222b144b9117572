"""Content-addressed blob storage: the interface every store implements, its errors and the hashes.

Blobs are named by the sha256 of their bytes and written atomically and durably *before* the database
row naming them commits, so a committed row never points at a missing or partial blob.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import BinaryIO, Protocol, runtime_checkable

SHA256_HEX = re.compile(r"^[0-9a-f]{64}$")
CHUNK = 1024 * 1024


class BlobNotFoundError(KeyError):
    """No blob with that sha256."""


class BlobStoreUnavailableError(OSError):
    """The blob store cannot be reached or answered wrongly (the API answers 503)."""


@dataclass(frozen=True)
class BlobInfo:
    """One stored blob: its sha256 (hex), size in bytes and when it was last written (UTC)."""

    sha256: str
    size: int
    modified: datetime


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

    def list_blobs(self) -> Iterator[BlobInfo]:
        """Every stored blob (any order). A put of content already stored counts as a write."""
        ...

    def delete(self, sha256: str) -> None:
        """Remove the blob (idempotent). Only for garbage collection of unreferenced blobs
        (``service.store.gc``)."""
        ...

    def sweep_partial_writes(self, older_than: datetime, dry_run: bool = False) -> tuple[int, int]:
        """Remove what writers that died mid-write left (not blobs: never readable), last touched before
        ``older_than``; returns (count, bytes) removed (``dry_run``: that would be). Garbage collection only."""
        ...

    def ping(self) -> None:
        """Raise if the store is unreachable or not writable."""
        ...


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


