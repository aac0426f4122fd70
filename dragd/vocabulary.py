"""The pydantic vocabulary of dragd's files (configuration, parameters, programs, the sim's truth and scripts).

One owner for what every schema shares: the base model (``Strict``), the constrained number types with the words an
error uses for them (``Expect``), the error type (``ConfigError``), the message that names file, key path and
expectation (``format_validation_error``) and the YAML reader (``read_yaml``).
"""

from __future__ import annotations

import types
from pathlib import Path
from typing import Annotated, Any, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError


class ConfigError(ValueError):
    """A configuration or parameters file that cannot be used; the message names file, key path and expectation."""


class Expect:
    """Annotation marker: how to describe a field's expected value in an error message."""

    def __init__(self, text: str) -> None:
        self.text = text


PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False), Expect("a positive number")]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False), Expect("a number >= 0")]
NonPosFloat = Annotated[float, Field(le=0, allow_inf_nan=False), Expect("a number <= 0 (negative direction level)")]
Finite = Annotated[float, Field(allow_inf_nan=False), Expect("a finite number")]
PosInt = Annotated[int, Field(gt=0, strict=False), Expect("a positive integer")]
NodeId = Annotated[int, Field(ge=1, le=127), Expect("a CANopen node id 1..127")]
Fraction = Annotated[float, Field(ge=0, le=1), Expect("a number between 0 and 1")]


class Strict(BaseModel):
    """Base of every schema: unknown keys are errors, defaults are validated, instances are frozen."""

    model_config = ConfigDict(extra="forbid", validate_default=True, frozen=True)


class StrictEditable(BaseModel):
    """``Strict`` for a document edited in place after loading (a taught program): not frozen."""

    model_config = ConfigDict(extra="forbid", validate_default=True)


def _unwrap_optional(t: Any) -> Any:
    """``X | None`` -> X (keeps ``Annotated`` metadata on X)."""
    if get_origin(t) in (Union, types.UnionType):
        args = [a for a in get_args(t) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return t


def _schema_at(model: type[BaseModel], loc: tuple[Any, ...]) -> tuple[Any, Any]:
    """Follow an error location through the schema: (FieldInfo of the last field or None, type at loc)."""
    current: Any = model
    info = None
    for part in loc:
        t = _unwrap_optional(current)
        base = get_args(t)[0] if get_origin(t) is Annotated else t
        base = _unwrap_optional(base)
        origin = get_origin(base)
        if isinstance(base, type) and issubclass(base, BaseModel) and isinstance(part, str):
            info = base.model_fields.get(part)
            if info is None:
                return None, None
            current = info.annotation
            if info.metadata:
                current = Annotated[(current, *info.metadata)]
        elif origin in (list, tuple) and isinstance(part, int):
            args = get_args(base)
            homogeneous = origin is list or len(args) == 2 and args[1] is Ellipsis
            current = args[0] if homogeneous else args[min(part, len(args) - 1)]
            info = None
        elif origin is dict:
            current = get_args(base)[1]
            info = None
        else:
            return None, None
    return info, current


def _annotation_expect(model: type[BaseModel], loc: tuple[Any, ...]) -> str | None:
    """The ``Expect`` text of the schema element at an error location, if any."""
    _, t = _schema_at(model, loc)
    stack = [t]
    while stack:
        a = _unwrap_optional(stack.pop())
        if a is None:
            continue
        for meta in getattr(a, "__metadata__", ()):
            if isinstance(meta, Expect):
                return meta.text
        if not (isinstance(a, type) and issubclass(a, BaseModel)):
            stack.extend(get_args(a))
    return None


def _loc_text(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after", "constrained-str", "tagged-union") or str(part).startswith(("function-",
                                                                                                   "union[")):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _describe(model: type[BaseModel], err: dict[str, Any]) -> str:
    """One validation error as ``key.path: expected ..., got ...`` (the ``Expect`` text where the schema has one)."""
    loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and ("[" in p or p.startswith("function"))))
    kind = err["type"]
    given = err.get("input")
    if kind == "value_error":
        msg = str(err.get("ctx", {}).get("error", err["msg"]))
        if ": expected" in msg and not loc:
            return msg
        return f"{_loc_text(loc)}: {msg}" if loc else msg
    if kind == "extra_forbidden":
        parent = loc[:-1]
        allowed = _allowed_keys(model, parent)
        hint = f"; expected one of: {', '.join(allowed)}" if allowed else ""
        return f"{_loc_text(loc)}: unknown key{hint}"
    if kind == "missing":
        return f"{_loc_text(loc)}: missing required key"
    expect = _annotation_expect(model, loc)
    if expect is None:
        if kind == "literal_error":
            expect = f"one of {err.get('ctx', {}).get('expected', '')}"
        elif kind in ("float_parsing", "float_type"):
            expect = "a number"
        elif kind in ("int_parsing", "int_type", "int_from_float"):
            expect = "an integer"
        elif kind in ("bool_parsing", "bool_type"):
            expect = "true or false"
        elif kind in ("list_type", "tuple_type"):
            expect = "a list"
        elif kind == "too_short" or kind == "too_long":
            expect = err["msg"].lower()
        elif kind in ("model_type", "dict_type", "model_attributes_type"):
            expect = "a mapping of keys"
        elif kind == "string_type":
            expect = "a string"
        else:
            expect = err["msg"][0].lower() + err["msg"][1:]
    return f"{_loc_text(loc)}: expected {expect}, got {given!r}"


def _allowed_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    _, t = _schema_at(model, loc)
    t = _unwrap_optional(t)
    if get_origin(t) is Annotated:
        t = _unwrap_optional(get_args(t)[0])
    if isinstance(t, type) and issubclass(t, BaseModel):
        return [k for k, f in t.model_fields.items() if not f.exclude]
    return []


def format_validation_error(path: str, model: type[BaseModel], exc: ValidationError) -> str:
    """Every error of ``exc`` on a line of its own: ``path: key.path: expected ..., got ...``."""
    lines = [f"{path}: {_describe(model, dict(e))}" for e in exc.errors(include_url=False)]
    return "\n".join(lines)


def read_yaml(path: Path) -> Any:
    """A YAML file's data; ConfigError naming the file (and line and column) for what cannot be read."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory; expected a YAML file")
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        with path.open(encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02X} at offset {exc.start}); "
                          "expected a YAML file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        raise ConfigError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from exc
