"""``KEY=VALUE`` overrides of a dataclass's fields, each value parsed as the field's type: the bench's and the
service's ``--set`` / ``FLEETMAP_FUSION_SET`` (``FusionConfig``), ``--camera`` (``CameraSensor``) and ``--world``
(``WorldParams``)."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

from fusion.labels import LABEL_BY_NAME


def with_overrides(obj: Any, items: list[str]) -> Any:
    """A copy of the dataclass ``obj`` with ``KEY=VALUE`` overrides (``--set``, ``--camera``, ``--world``),
    each value parsed as the field's type: bool (true/false/1/0), int, float, str, ``int | None`` (``none``),
    a comma list for ``tuple[str, ...]`` / ``tuple[float, ...]`` / ``tuple[float, float]``, and for tables
    keyed by label names a comma list of colon-joined entries: ``pole:0.3,traffic_sign:0.3`` (a
    ``tuple[tuple[str, float], ...]``, replaced whole), ``road:sidewalk:0.05`` (``tuple[tuple[str, str, float],
    ...]``, replaced whole), ``vehicle:2`` (a ``dict[str, float]``: merged into the field's). Raises
    ``ValueError`` naming an unknown key, a field of another type, or a value that does not parse."""
    cls = type(obj)
    types = {f.name: str(f.type) for f in fields(cls)}
    changes: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in types:
            raise ValueError(f"{item!r}: expected KEY=VALUE with KEY a {cls.__name__} field")
        kind = types[key]
        try:
            value = _parse_value(kind, text.strip())
            changes[key] = {**getattr(obj, key), **value} if isinstance(value, dict) else value
        except TypeError:
            raise ValueError(f"{item!r}: {key} ({kind}) cannot be set as KEY=VALUE") from None
        except ValueError:
            raise ValueError(f"{item!r}: {text!r} is not a valid {kind}") from None
    return replace(obj, **changes)


def _parse_value(kind: str, text: str) -> Any:
    """``text`` as a value of the annotation ``kind`` (a string: ``from __future__ import annotations``)."""
    if kind == "bool":
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(text)
        return text.lower() in ("true", "1")
    if kind in ("int", "float", "str"):
        return {"int": int, "float": float, "str": str}[kind](text)
    if kind == "int | None":
        return None if text.lower() == "none" else int(text)
    if kind == "tuple[str, ...]":
        return tuple(v.strip() for v in text.split(",") if v.strip())
    if kind in ("tuple[float, ...]", "tuple[float, float]"):
        values = tuple(float(v) for v in text.split(",") if v.strip())
        if kind == "tuple[float, float]" and len(values) != 2:
            raise ValueError(text)
        return values
    if kind in ("tuple[tuple[str, float], ...]", "tuple[tuple[str, str, float], ...]", "dict[str, float]"):
        names = 2 if "str, str" in kind else 1
        entries: list[tuple[Any, ...]] = []
        for entry in (e.strip() for e in text.split(",") if e.strip()):
            parts = entry.split(":")
            if len(parts) != names + 1 or any(n.strip() not in LABEL_BY_NAME for n in parts[:names]):
                raise ValueError(entry)
            entries.append((*(n.strip() for n in parts[:names]), float(parts[names])))
        return {e[0]: e[1] for e in entries} if kind.startswith("dict") else tuple(entries)
    raise TypeError(kind)
