"""Blobs as files on a local or shared volume (temporary file in the target folder, fsync, rename,
fsync of the folder)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO

from service.store.blobs.base import CHUNK, SHA256_HEX, BlobInfo, BlobNotFoundError, sha256_bytes, sha256_file


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
        if not SHA256_HEX.match(sha256):
            raise BlobNotFoundError(sha256)
        return self.root / "sha256" / sha256[:2] / sha256[2:4] / sha256

    def _write(self, sha256: str, writer: Callable[[BinaryIO], object]) -> str:
        target = self._path(sha256)
        if target.exists():
            # a new write of stored content: its age restarts, so the garbage collection, which only
            # removes blobs older than its grace period, cannot take it before the row naming it commits
            try:
                os.utime(target)
                return sha256
            except FileNotFoundError:  # the collection took it just now: write it again
                pass
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
                while chunk := src.read(CHUNK):
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

    def list_blobs(self) -> Iterator[BlobInfo]:
        base = self.root / "sha256"
        if not base.is_dir():
            return
        for path in base.glob("*/*/*"):
            if SHA256_HEX.match(path.name):
                try:
                    stat = path.stat()
                except FileNotFoundError:  # deleted meanwhile
                    continue
                yield BlobInfo(path.name, stat.st_size, datetime.fromtimestamp(stat.st_mtime, UTC))

    def delete(self, sha256: str) -> None:
        self._path(sha256).unlink(missing_ok=True)

    def sweep_partial_writes(self, older_than: datetime, dry_run: bool = False) -> tuple[int, int]:
        """The ``.tmp-*`` files of writers killed between creating and renaming them."""
        count = size = 0
        base = self.root / "sha256"
        for path in base.glob("*/*/.tmp-*") if base.is_dir() else []:
            try:
                stat = path.stat()
                if datetime.fromtimestamp(stat.st_mtime, UTC) >= older_than:
                    continue
                if not dry_run:
                    path.unlink()
            except FileNotFoundError:  # renamed or removed meanwhile
                continue
            count, size = count + 1, size + stat.st_size
        return count, size

    def ping(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        if not os.access(self.root, os.W_OK):
            raise OSError(f"blob store {self.root} is not writable")
