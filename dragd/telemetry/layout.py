"""`RowLayout`: a layout's offsets, slices and JSON Schema, and the JSON encoding of its rows.

Floats are formatted through a precompiled %-template with a fixed number of significant digits: formatting
dominates the writer thread's CPU (and GIL) time. Non-finite values are written as ``null``.
"""

from __future__ import annotations

import enum
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dragd.telemetry.schema import CYCLE_SCHEMA, Field, Labels

__all__ = ["RowLayout", "dumps"]


def normalize_labels(name: str, labels: Labels) -> dict[int, str]:
    if isinstance(labels, type) and issubclass(labels, enum.Enum):
        out = {}
        for member in labels:
            if not isinstance(member.value, int):
                raise ValueError(f"field {name!r}: enum {labels.__name__} needs integer values")
            out[int(member.value)] = member.name
        return out
    if isinstance(labels, Mapping):
        return {int(k): str(v) for k, v in labels.items()}
    if isinstance(labels, (list, tuple)):
        return {i: str(v) for i, v in enumerate(labels)}
    raise ValueError(
        f"field {name!r}: labels must be an int Enum, a mapping int -> str or a list of names; "
        f"got {type(labels).__name__}"
    )


@dataclass(frozen=True)
class _Column:
    name: str
    offset: int
    width: int
    kind: str  # "float" | "int" | "bool" | "enum"
    labels: dict[int, str] | None
    description: str | None
    digits: int


_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class RowLayout:
    """Ordered fields of a telemetry row: offsets, slices, JSON Schema and row encoders.

    Floats are written with ``float_digits`` significant digits (12 by default:
    1 us resolution for a ``t_s`` up to 10^6 s; ``Field(digits=17)`` round-trips
    float64 exactly). Formatting floats dominates the writer's CPU (and GIL) time,
    hence the precompiled %-template in `encode_json`.
    """

    def __init__(self, layout: Mapping[str, int | Field], float_digits: int = 12) -> None:
        if not layout:
            raise ValueError("telemetry layout is empty; expected e.g. {'t_s': 1, 'q_rad': 6}")
        if not 1 <= float_digits <= 17:
            raise ValueError(f"float_digits must be in 1..17; got {float_digits}")
        cols: list[_Column] = []
        offset = 0
        for name, spec in layout.items():
            if not isinstance(name, str) or not _NAME_RE.match(name):
                raise ValueError(f"telemetry field name {name!r} must be an identifier like 'q_rad'")
            f = spec if isinstance(spec, Field) else Field(width=spec)
            if isinstance(f.width, bool) or not isinstance(f.width, int) or f.width < 1:
                raise ValueError(f"telemetry field {name!r}: width must be an int >= 1; got {f.width!r}")
            if f.kind not in ("float", "int", "bool"):
                raise ValueError(
                    f"telemetry field {name!r}: kind must be 'float', 'int' or 'bool'; got {f.kind!r}"
                )
            digits = float_digits if f.digits is None else f.digits
            if not 1 <= digits <= 17:
                raise ValueError(f"telemetry field {name!r}: digits must be in 1..17; got {digits}")
            labels = normalize_labels(name, f.labels) if f.labels is not None else None
            kind = "enum" if labels is not None else f.kind
            cols.append(_Column(name, offset, f.width, kind, labels, f.description, digits))
            offset += f.width
        self.columns: tuple[_Column, ...] = tuple(cols)
        self.width = offset
        self.names = tuple(c.name for c in cols)
        self.slices: dict[str, slice] = {c.name: slice(c.offset, c.offset + c.width) for c in cols}
        self._plan = tuple((c.name, c.offset, c.width, c.kind, c.labels, c.digits) for c in cols)
        parts = []
        special: list[tuple[int, dict[int, str] | None]] = []
        for c in cols:
            fmt = {"float": f"%.{c.digits}g", "int": "%d"}.get(c.kind, "%s")
            if c.kind in ("enum", "bool"):
                quoted = (
                    {k: json.dumps(v) for k, v in c.labels.items()} if c.labels is not None else None
                )
                special.extend((c.offset + j, quoted) for j in range(c.width))
            body = fmt if c.width == 1 else "[" + ",".join([fmt] * c.width) + "]"
            parts.append(f'"{c.name}":{body}')
        self._template = "{" + ",".join(parts) + "}"
        self._special = tuple(special)

    def encode_json(self, values: list[Any]) -> bytes:
        """Compact JSON of one row of *finite* values (flat list; modified in place)."""
        for off, quoted in self._special:
            v = int(values[off])
            if quoted is None:
                values[off] = "true" if v else "false"
            else:
                values[off] = quoted.get(v) or f'"{v}"'
        return (self._template % tuple(values)).encode()

    def json_schema(self, title: str = CYCLE_SCHEMA) -> dict[str, Any]:
        """JSON Schema of an encoded row (what Foxglove reads to type the fields)."""
        props: dict[str, Any] = {}
        for c in self.columns:
            if c.kind == "enum":
                assert c.labels is not None
                item: dict[str, Any] = {
                    "type": "string",
                    "description": "one of " + ", ".join(c.labels[k] for k in sorted(c.labels)),
                }
            elif c.kind == "int":
                item = {"type": "integer"}
            elif c.kind == "bool":
                item = {"type": "boolean"}
            else:
                item = {"type": "number"}
            if c.description and c.kind != "enum":
                item["description"] = c.description
            if c.width == 1:
                props[c.name] = item
            else:
                props[c.name] = {
                    "type": "array",
                    "items": item,
                    "minItems": c.width,
                    "maxItems": c.width,
                }
                if c.description:
                    props[c.name]["description"] = c.description
        return {
            "title": title,
            "type": "object",
            "description": "one dragd control cycle; non-finite numbers are written as null",
            "properties": props,
            "required": list(self.names),
        }

    def encode(self, values: Sequence[float]) -> dict[str, Any]:
        """Row values (flat, e.g. ``row.tolist()``) -> JSON-ready dict (non-finite -> None)."""
        out: dict[str, Any] = {}
        for name, off, w, kind, labels, digits in self._plan:
            if w == 1:
                out[name] = _convert(values[off], kind, labels, digits)
            else:
                out[name] = [_convert(v, kind, labels, digits) for v in values[off : off + w]]
        return out

    def encode_any(self, values: list[float]) -> bytes:
        """Compact JSON of one row; rows with NaN/inf take the slower dict path (-> null)."""
        if all(map(math.isfinite, values)):
            return self.encode_json(values)
        return dumps(self.encode(values))


def _convert(v: float, kind: str, labels: dict[int, str] | None, digits: int) -> Any:
    if v != v or v in (math.inf, -math.inf):
        return None
    if kind == "float":
        return float(f"{v:.{digits}g}")
    if kind == "int":
        return int(v)
    if kind == "bool":
        return bool(v)
    assert labels is not None
    i = int(v)
    return labels.get(i, str(i))


def dumps(obj: Any) -> bytes:
    """Compact JSON; NaN/inf -> null (strict JSON for Foxglove)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_default).encode()
    except ValueError:
        return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False, default=_default).encode()


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _default(obj: Any) -> Any:
    tolist = getattr(obj, "tolist", None)
    if callable(tolist):
        return tolist()
    if isinstance(obj, enum.Enum):
        return obj.name
    return str(obj)

