"""Garbage collection of the blob store: blobs no database row names any more.

Every reconstruction stores a new field (several MB per tile) and an alignment that trains a tile again
replaces its field; the superseded ones, and blobs of writes whose transaction never committed (a crash
between the blob and its row), are named by no row. Tile versions keep their meshes (the history stays
downloadable), submaps their meshes.

Safety: blobs are written before the row naming them commits, so a blob can be unreferenced for the
few seconds in between. Only blobs older than ``min_age`` are removed, and a put of content already
stored counts as a new write (the store restarts its age), so a blob is never taken from under a
transaction that is about to name it, as long as jobs commit within ``min_age`` of their writes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.store.blobs import BlobStore
from service.store.models import Submap, Tile, TileVersion, utcnow

log = logging.getLogger(__name__)

DEFAULT_MIN_AGE = timedelta(hours=24)

# every column that names a blob
_BLOB_COLUMNS = (
    Submap.mesh_sha256,
    TileVersion.mesh_sha256,
    TileVersion.glb_sha256,
    TileVersion.border_sha256,
    Tile.align_field_sha256,
    Tile.recon_field_sha256,
)


def referenced(db: Session) -> set[str]:
    """The sha256 of every blob a row names."""
    found: set[str] = set()
    for column in _BLOB_COLUMNS:
        found.update(sha for sha in db.execute(select(column).distinct()).scalars() if sha is not None)
    return found


@dataclass
class GcReport:
    """What a collection found: blobs kept (named by a row, or younger than the grace period) and
    removed (or, in a dry run, that would be), with their bytes."""

    dry_run: bool
    referenced: int = 0
    young: int = 0
    removed: list[str] = field(default_factory=list)
    removed_bytes: int = 0
    kept_bytes: int = 0
    partial: int = 0  # dead writers' partial files removed (file store)
    partial_bytes: int = 0

    def summary(self) -> str:
        verb = "would remove" if self.dry_run else "removed"
        return (f"{verb} {len(self.removed)} unreferenced blobs ({self.removed_bytes / 1e6:.1f} MB) and "
                f"{self.partial} partial writes ({self.partial_bytes / 1e6:.1f} MB); kept "
                f"{self.referenced} referenced and {self.young} younger than the grace period "
                f"({self.kept_bytes / 1e6:.1f} MB)")


def collect(blobs: BlobStore, keep: set[str], *, min_age: timedelta = DEFAULT_MIN_AGE, dry_run: bool = False,
            now: datetime | None = None) -> GcReport:
    """Remove every blob not in ``keep`` that was last written more than ``min_age`` ago (``dry_run``:
    only report them). ``keep``: :func:`referenced`, read before this lists the store (a blob written
    after that is young)."""
    if min_age < timedelta(0):
        raise ValueError(f"min_age must not be negative, got {min_age}")
    cutoff = (now or utcnow()) - min_age
    report = GcReport(dry_run=dry_run)
    for blob in blobs.list_blobs():
        if blob.sha256 in keep:
            report.referenced += 1
        elif blob.modified > cutoff:
            report.young += 1
        else:
            if not dry_run:
                blobs.delete(blob.sha256)
            report.removed.append(blob.sha256)
            report.removed_bytes += blob.size
            continue
        report.kept_bytes += blob.size
    report.partial, report.partial_bytes = blobs.sweep_partial_writes(cutoff, dry_run)
    log.info("blob garbage collection: %s", report.summary())
    return report
