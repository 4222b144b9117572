"""Vectorised reader of ASCII PLY bodies (numpy; plyfile's row-by-row reader is ~40x slower), used by
``fusion.meshio`` for the usual layouts: scalar properties, plus the face index list when every face is
a triangle. Anything else is left to plyfile (``read_ascii`` returns None), so results and errors stay
plyfile's; a broken row is a ``MeshValidationError`` (``malformed_ply``) at ``("mesh", element, row)``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import plyfile

from fusion.errors import MeshValidationError


def _fail(code: str, message: str, loc: tuple[str | int, ...]) -> MeshValidationError:
    return MeshValidationError(message, code=code, loc=loc)


def _parse_rows(block: bytes, dtype: type[Any], count: int) -> np.ndarray | None:
    """The ``count`` whitespace-separated numbers of ``block`` (numpy's C parser); None if a token is
    not a number (numpy 2 raises; older ones warn and stop early)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            values = np.fromstring(block, dtype=dtype, sep=" ")
    except ValueError:
        return None
    return values if values.size == count else None


def _first_bad_row(body: bytes, starts: np.ndarray, ends: np.ndarray, dtype: Any, width: int) -> int:
    """Index (within ``starts``/``ends``) of the first line holding a token that is not a number:
    bisection over line ranges, so about two parses of the block whatever its size."""
    lo, hi = 0, len(starts)  # the bad line is in [lo, hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _parse_rows(body[starts[lo] : ends[mid - 1]], dtype, (mid - lo) * width) is None:
            hi = mid
        else:
            lo = mid
    return lo


def _rows_not_of_width(
    token_at: np.ndarray, token: int, starts: np.ndarray, ends: np.ndarray, width: int
) -> tuple[int, int] | None:
    """None if each line [starts[k], ends[k]) holds exactly ``width`` of the values that start at
    byte offsets ``token_at[token:]``; else the first line that does not, and how many it holds.

    Lines hold exactly ``width`` each iff line k holds values k·width and k·width + width - 1 and the
    value after the last line's is beyond it: strided comparisons, no counting per line."""
    n = len(starts)
    if n == 0:
        return None
    ours = token_at[token : token + n * width]
    if len(ours) == n * width:
        ok = np.all(ours[::width] >= starts) and np.all(ours[width - 1 :: width] < ends)
        after = token + n * width
        if ok and (after == len(token_at) or token_at[after] > ends[-1]):
            return None
    counts = np.searchsorted(token_at, ends) - np.searchsorted(token_at, starts)
    bad = np.flatnonzero(counts != width)
    k = int(bad[0]) if bad.size else n - 1
    return k, int(counts[k])


_INTEGER_BYTES = np.zeros(256, dtype=bool)  # what integer values (and the blanks between) are made of
_INTEGER_BYTES[: 33] = True
_INTEGER_BYTES[list(b"0123456789+-")] = True


def _first_non_integer_row(
    body: bytes,
    start: int,
    end: int,
    token_at: np.ndarray,
    token: int,
    columns: list[tuple[str, int, int]],
    is_int: list[bool],
) -> int | None:
    """First row of body[start:end] whose integer-typed column holds something other than digits and
    a sign (``1.0``, ``1e3``: numbers, but not integers to plyfile), for elements parsed as floats."""
    width = sum(w + (w > 1) for _, _, w in columns)
    int_column = np.zeros(width, dtype=bool)
    for (_, first, w), integer in zip(columns, is_int, strict=True):
        int_column[first - (w > 1) : first + w] = integer  # a list's count is an integer too
    other = np.flatnonzero(~_INTEGER_BYTES[np.frombuffer(body, dtype=np.uint8)[start:end]]) + start
    value = np.searchsorted(token_at, other, side="right") - 1 - token
    bad = value[int_column[value % width]]
    return int(bad[0] // width) if bad.size else None


def read_ascii(header: plyfile.PlyData, body: bytes, index_name: str) -> plyfile.PlyData | None:
    """Vectorised reader of an ASCII body (plyfile's reads it row by row, ~40x slower).

    Handles elements of scalar properties plus the face index list when every face is a triangle;
    returns None for anything else (polygons, other lists), which plyfile's reader then takes, so
    results and errors are plyfile's. Rows with the wrong number of values, values that are not
    numbers or that do not fit their property's type are ``malformed_ply`` at their row; the element
    data is set on ``header``'s elements, laid out as plyfile's memory-mapped reader lays it out.
    """
    if b"\r" in body:  # universal newlines, as plyfile's text stream reads them
        body = body.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    text = _AsciiBody.of(body)
    if len(text.starts) < sum(e.count for e in header.elements):
        return None
    row, token = 0, 0
    for element in header.elements:
        layout = _AsciiLayout.of(element, index_name)
        data = None if layout is None else _read_ascii_element(text, element, layout, row, token)
        if layout is None or data is None:
            return None
        element.data = data
        row += element.count
        token += element.count * layout.width
    return header


@dataclass
class _AsciiBody:
    """An ASCII body's bytes, its lines (``body[starts[k] : ends[k]]``) and where each value starts."""

    body: bytes
    starts: np.ndarray
    ends: np.ndarray
    token_at: np.ndarray

    @classmethod
    def of(cls, body: bytes) -> _AsciiBody:
        raw = np.frombuffer(body, dtype=np.uint8)
        newlines = np.flatnonzero(raw == ord("\n"))
        starts = np.concatenate(([0], newlines + 1))
        ends = np.append(newlines, len(body))
        # a value starts at a non-blank byte after a blank one (bytes <= 32 are blanks here, so control
        # characters separate values, and then fail numpy's parse)
        space = raw <= 32
        token_start = np.empty(len(raw), dtype=bool)
        token_start[:1] = ~space[:1]
        np.greater(space[:-1], space[1:], out=token_start[1:])
        return cls(body, starts, ends, np.flatnonzero(token_start))


@dataclass
class _AsciiLayout:
    """The row layout of one element: numpy fields, (name, first column, width) per property, values
    per row, which properties are integers and the parse type of the whole block."""

    fields: list[tuple[str, np.dtype[Any], tuple[int, ...]]]
    columns: list[tuple[str, int, int]]
    width: int
    is_int: list[bool]
    dtype: type

    @classmethod
    def of(cls, element: plyfile.PlyElement, index_name: str) -> _AsciiLayout | None:
        """None for a list property other than the faces' index list."""
        fields: list[tuple[str, np.dtype[Any], tuple[int, ...]]] = []
        columns: list[tuple[str, int, int]] = []
        width = 0
        for prop in element.properties:
            kind = np.dtype(prop.val_dtype).newbyteorder("=")
            if isinstance(prop, plyfile.PlyListProperty):
                if element.name != "face" or prop.name != index_name:
                    return None
                fields.append((prop.name, kind, (3,)))
                columns.append((prop.name, width + 1, 3))
                width += 4  # the count, then three indices
            else:
                fields.append((prop.name, kind, ()))
                columns.append((prop.name, width, 1))
                width += 1
        is_int = [np.dtype(kind).kind in "iu" for _, kind, _ in fields]
        return cls(fields, columns, width, is_int, np.int64 if all(is_int) else np.float64)


def _read_ascii_element(
    text: _AsciiBody, element: plyfile.PlyElement, layout: _AsciiLayout, row: int, token: int
) -> np.ndarray | None:
    """The rows ``row …`` of ``element`` as a structured array; None when they hold polygons."""
    n, width, body, starts, ends = element.count, layout.width, text.body, text.starts, text.ends
    lines = slice(row, row + n)
    wrong = _rows_not_of_width(text.token_at, token, starts[lines], ends[lines], width)
    if wrong is not None:
        if element.name == "face":
            return None  # maybe polygons
        k, found = wrong
        if not (k and _parse_rows(body[starts[row] : ends[row + k - 1]], layout.dtype, k * width) is None):
            raise _fail(
                "malformed_ply",
                f"bad PLY data: element '{element.name}' row {k} has {found} values, its properties need {width}",
                ("mesh", element.name, k),
            )
        lines = slice(row, row + k)  # a value that is not a number comes first: find it
    block = body[starts[row] : ends[row + n - 1]] if n else b""
    values = _parse_rows(block, layout.dtype, n * width) if lines.stop == row + n else None
    if values is None:
        k = _first_bad_row(body, starts[lines], ends[lines], layout.dtype, width)
        raise _fail("malformed_ply", f"bad PLY data: element '{element.name}' row {k}: a value is not a number",
                    ("mesh", element.name, k))
    if n and layout.dtype is np.float64 and any(layout.is_int):
        decimal = _first_non_integer_row(body, starts[row], ends[row + n - 1], text.token_at, token, layout.columns,
                                         layout.is_int)
        if decimal is not None:
            raise _fail(
                "malformed_ply",
                f"bad PLY data: element '{element.name}' row {decimal}: an integer property holds a value "
                "written as a decimal",
                ("mesh", element.name, decimal),
            )
    table = values.reshape(n, width)
    counts = next((first - 1 for _, first, w in layout.columns if w == 3), None)
    if counts is not None and np.any(table[:, counts] != 3):
        return None  # polygons (or a count that disagrees with the row: plyfile says which)
    return _typed_columns(element.name, table, layout)


def _typed_columns(name: str, table: np.ndarray, layout: _AsciiLayout) -> np.ndarray:
    """The parsed ``table`` (n, width) as the element's structured array; integers checked to fit."""
    n = len(table)
    data = np.empty(n, dtype=layout.fields)
    for (prop, first, w), (_, kind, _), integer in zip(layout.columns, layout.fields, layout.is_int, strict=True):
        part = table[:, first : first + w] if w > 1 else table[:, first]
        if integer:
            info = np.iinfo(kind)
            ok = (part >= info.min) & (part <= info.max)
            if layout.dtype is np.float64:
                ok &= part == np.floor(part)
            if not np.all(ok):
                k = int(np.flatnonzero(~ok.reshape(n, -1).all(axis=1))[0])
                raise _fail(
                    "malformed_ply",
                    f"bad PLY data: element '{name}' row {k}: property '{prop}' needs integers in "
                    f"{info.min}..{info.max}",
                    ("mesh", name, k),
                )
        data[prop] = part
    return data
