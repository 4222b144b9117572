"""Query parameters shared by the listing routes: map-frame boxes and opaque page cursors.

Both answer bad input with a 422 problem naming the parameter (``errors[].loc`` = ``["query", name]``).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from collections.abc import Callable, Sequence
from typing import Annotated, Any, TypeVar

from fastapi import Path

from service.api.problems import ProblemError, validation_error

T = TypeVar("T")

TileRange = tuple[int, int, int, int]  # i0, j0, i1, j1, inclusive


def _invalid(name: str, msg: str, code: str) -> ProblemError:
    return ProblemError(422, msg, code=code, errors=[validation_error(["query", name], msg, code)])


def parse_bbox(bbox: str, tile_size: float) -> TileRange:
    """Tile index range (i0, j0, i1, j1) touched by a map-frame box ``xmin,ymin,xmax,ymax`` (metres)."""
    try:
        xmin, ymin, xmax, ymax = (float(v) for v in bbox.split(","))
    except ValueError as exc:
        raise _invalid("bbox", "bbox is 'xmin,ymin,xmax,ymax' in metres", "invalid_bbox") from exc
    if not all(math.isfinite(v) for v in (xmin, ymin, xmax, ymax)) or xmin > xmax or ymin > ymax:
        raise _invalid("bbox", "bbox needs finite values with xmin <= xmax and ymin <= ymax", "invalid_bbox")
    return (
        math.floor(xmin / tile_size),
        math.floor(ymin / tile_size),
        math.floor(xmax / tile_size),
        math.floor(ymax / tile_size),
    )


def encode_cursor(*key: Any) -> str:
    """An opaque cursor holding the sort key of the last item of a page."""
    return base64.urlsafe_b64encode(json.dumps(list(key)).encode()).decode().rstrip("=")


def keyset_page(rows: Sequence[T], limit: int, key: Callable[[T], tuple[Any, ...]]) -> tuple[list[T], str | None]:
    """A listing's page from ``rows`` fetched with ``limit + 1``: the first ``limit`` rows and the cursor
    of the last one (``key`` gives its sort key) when more rows follow, else None."""
    page = list(rows[:limit])
    return page, encode_cursor(*key(page[-1])) if len(rows) > limit and page else None


def decode_cursor(cursor: str, *types: Callable[[Any], Any]) -> tuple[Any, ...]:
    """The sort key in ``cursor``, each part converted by ``types`` (e.g. ``int, int``); 422 unless it
    is one :func:`encode_cursor` made with that many parts."""
    try:
        key = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if not isinstance(key, list) or len(key) != len(types):
            raise ValueError("wrong shape")
        return tuple(convert(part) for convert, part in zip(types, key, strict=True))
    except (binascii.Error, ValueError, TypeError, UnicodeDecodeError) as exc:
        raise _invalid("cursor", "cursor is not one this API returned", "invalid_cursor") from exc


def string(value: Any) -> str:
    """A cursor part that must be a string (``str`` would accept anything)."""
    if not isinstance(value, str):
        raise TypeError("expected a string")
    return value


def integer(value: Any) -> int:
    """A cursor part that must be an integer (``int`` would accept ``"7"`` and ``7.9``)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError("expected an integer")
    return value


# Tile indices in paths: the database column is a 32-bit integer, so a larger index is a 422, not a 500.
TileIndex = Annotated[int, Path(ge=-(2**31), le=2**31 - 1, description="tile index (x east for i, y north for j)")]
