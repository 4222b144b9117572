"""What the download routes share (fused meshes, 3D Tiles): conditional requests and blob reads."""

from __future__ import annotations

from service.api.problems import ProblemError
from service.store.blobs import BlobNotFoundError, BlobStore

IMMUTABLE = "public, max-age=31536000, immutable"


def matches(if_none_match: str | None, etag: str) -> bool:
    """True when an ``If-None-Match`` header names ``etag`` (weak comparison, ``*`` included)."""
    if not if_none_match:
        return False
    candidates = [c.strip().removeprefix("W/") for c in if_none_match.split(",")]
    return "*" in candidates or etag in candidates


def read_blob(blobs: BlobStore, sha256: str) -> bytes:
    """A blob's bytes; 503 problem when the store has lost it."""
    try:
        return blobs.get(sha256)
    except BlobNotFoundError as exc:
        raise ProblemError(503, "the mesh blob is unavailable", code="blob_unavailable") from exc
