"""Typed errors of the fusion library. Each carries a stable code and a message a user can act on;
the service maps them to RFC 9457 problem documents in one place."""

from __future__ import annotations

from collections.abc import Sequence


class FusionLibraryError(Exception):
    """Base class: ``code`` is stable and machine-readable, ``message`` is for people.

    ``loc`` optionally says where in the input the problem is, as a path of names and indices, e.g.
    ``("mesh", "header")``, ``("mesh", "vertex", 17)`` or ``("mesh", "face", 1234)``.
    """

    code = "fusion_error"

    def __init__(self, message: str, code: str | None = None, loc: Sequence[str | int] | None = None) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        self.loc: tuple[str | int, ...] | None = tuple(loc) if loc is not None else None


class MeshValidationError(FusionLibraryError):
    """A submap mesh that cannot be accepted.

    Codes: ``malformed_ply``, ``truncated_ply``, ``count_mismatch``, ``missing_property``,
    ``not_triangles``, ``non_finite_coordinates``, ``coordinate_limit``, ``unknown_label``,
    ``no_labelled_face``, ``too_many_faces``, ``empty_mesh``, ``bad_vertex_index``.
    """

    code = "invalid_mesh"


class PoseError(FusionLibraryError):
    """A pose that is not a valid rigid transform (e.g. a quaternion far from unit length)."""

    code = "invalid_pose"


class FusionError(FusionLibraryError):
    """A fusion that could not run (no data in the tile, diverged optimisation, ...)."""

    code = "fusion_failed"
