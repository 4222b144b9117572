"""Geodetic ↔ map frame (torch-free).

The map frame is the deployment's ENU frame (x east, y north, z up, metres) anchored at a geodetic
origin (WGS84 latitude/longitude in degrees, ellipsoidal altitude in metres). A geodetic GPS pose
carries its orientation relative to the local ENU axes *at that point*; those axes are tilted
against the map origin's ENU axes (about 1° per 111 km), so the orientation is rotated into the
map frame rather than copied.
"""

from __future__ import annotations

import math

import numpy as np
import pymap3d

from fusion.errors import PoseError
from fusion.types import UNIT_QUATERNION_TOLERANCE, Pose, matrix_to_quat, quat_to_matrix

Origin = tuple[float, float, float]


def parse_origin(text: str) -> Origin:
    """Parse ``"lat,lon,alt"`` (degrees, degrees, metres), e.g. ``FLEETMAP_ORIGIN``.

    Raises ``ValueError`` with a readable message for anything else.
    """
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ValueError(f"origin must be 'lat,lon,alt' (degrees, degrees, metres), not {text!r}")
    try:
        lat, lon, alt = (float(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"origin must be three numbers 'lat,lon,alt', not {text!r}") from exc
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        raise ValueError(f"origin values must be finite, not {text!r}")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise ValueError(f"origin latitude must be in [-90, 90] and longitude in [-180, 180], not {text!r}")
    return lat, lon, alt


def _enu_axes_in_ecef(lat: float, lon: float) -> np.ndarray:
    """(3, 3) matrix whose columns are the east, north, up unit vectors at (lat, lon) in ECEF."""
    cols = [pymap3d.enu2uvw(*axis, lat, lon) for axis in np.eye(3)]
    return np.array(cols, dtype=np.float64).T


def enu_rotation(lat: float, lon: float, origin: Origin) -> np.ndarray:
    """Rotation (3, 3) taking vectors in the local ENU axes at (lat, lon) into the map frame."""
    return _enu_axes_in_ecef(origin[0], origin[1]).T @ _enu_axes_in_ecef(lat, lon)


def _unit_quaternion(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64).reshape(4)
    if not np.all(np.isfinite(q)):
        raise PoseError("quaternion values must be finite numbers")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise PoseError(
            f"quaternion must be unit length within {UNIT_QUATERNION_TOLERANCE} (norm {norm:.6f})"
        )
    return q / norm


def geodetic_to_map(lat: float, lon: float, alt: float, q_enu: np.ndarray, origin: Origin) -> Pose:
    """Local → map pose of a submap whose GPS fix is (lat, lon in degrees, alt in metres) with
    orientation ``q_enu`` ([w, x, y, z], local frame → local ENU axes at that point).

    Raises ``PoseError`` for a quaternion that is not unit length within 1e-3, or non-finite values.
    """
    if not all(math.isfinite(float(v)) for v in (lat, lon, alt)):
        raise PoseError("lat, lon and alt must be finite numbers")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise PoseError("lat must be in [-90, 90] and lon in [-180, 180] degrees")
    q = _unit_quaternion(q_enu)
    east, north, up = pymap3d.geodetic2enu(lat, lon, alt, *origin)
    rotation = enu_rotation(lat, lon, origin) @ quat_to_matrix(q)
    return Pose(np.array([east, north, up], dtype=np.float64), matrix_to_quat(rotation))


def map_to_geodetic(pose: Pose, origin: Origin) -> tuple[float, float, float, np.ndarray]:
    """Inverse of ``geodetic_to_map``: (lat, lon, alt, q_enu) of a local → map pose."""
    lat, lon, alt = pymap3d.enu2geodetic(*(float(v) for v in pose.t), *origin)
    lat, lon, alt = float(lat), float(lon), float(alt)
    rotation = enu_rotation(lat, lon, origin).T @ pose.rotation()
    return lat, lon, alt, matrix_to_quat(rotation)


def enu_to_ecef(origin: Origin) -> np.ndarray:
    """(4, 4) homogeneous transform taking map-frame points (ENU metres at ``origin``) to ECEF metres
    (WGS84): columns are the east, north and up axes in ECEF, then the origin's ECEF position. Exactly
    the affine map behind ``pymap3d.enu2ecef``; 3D Tiles stores it column-major as a root ``transform``."""
    lat, lon, alt = origin
    matrix = np.eye(4)
    matrix[:3, :3] = _enu_axes_in_ecef(lat, lon)
    matrix[:3, 3] = pymap3d.geodetic2ecef(lat, lon, alt)
    return matrix
