"""An EDS's object dictionary for a node, parsed once per file version (python-canopen's ``import_od``).

``canopen.import_od(path, node_id)`` reads the whole file (configparser) for every node; a daemon and a simulator
load the same EDS for each of their six joints. Only ``$NODEID``-relative values depend on the node: a default or
parameter value such as ``$NODEID+0x180`` (canopen keeps the text in ``default_raw`` / ``value_raw``) and the
dictionary's ``node_id`` (set when the file has a [DeviceComissioning] section). :func:`import_od` parses a file
once, keeps that dictionary as a template, and gives each node its own copy with exactly those values recomputed by
canopen's own conversion: the result equals ``canopen.import_od(path, node_id)`` object by object, attribute by
attribute (tests/test_eds_cache.py). Files other than EDS/DCF go to canopen unchanged.

The dictionaries are cached per file version and node id and shared by their callers: treat them as read-only.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any, TypeVar

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.objectdictionary.eds import _convert_variable

_T = TypeVar("_T")
_TEMPLATE_NODE = 1  # the node id the template is parsed for (any valid id: every relative value is recomputed)
_MUTABLE = ("value_descriptions", "bit_definitions")  # a variable's containers (the rest are numbers and strings)


def import_od(path: str | Path, node_id: int) -> canopen.ObjectDictionary:
    """``canopen.import_od(path, node_id)``, the file parsed once per version (cached; treat as read-only).

    Raises what canopen and the file system raise for a missing or broken file."""
    real = os.path.realpath(path)
    mtime_ns = os.stat(real).st_mtime_ns
    try:
        return _for_node(real, mtime_ns, node_id)
    except Exception:  # a broken file (never cached): canopen's own error, naming the file as the caller did
        return canopen.import_od(os.fspath(path), node_id)


@functools.lru_cache(maxsize=64)
def _for_node(path: str, mtime_ns: int, node_id: int) -> canopen.ObjectDictionary:
    if not path.lower().endswith((".eds", ".dcf")):
        return canopen.import_od(path, node_id)
    return for_node(_template(path, mtime_ns), node_id)


@functools.lru_cache(maxsize=32)
def _template(path: str, mtime_ns: int) -> canopen.ObjectDictionary:
    return canopen.import_od(path, _TEMPLATE_NODE)


def for_node(template: canopen.ObjectDictionary, node_id: int) -> canopen.ObjectDictionary:
    """A copy of ``template`` (an EDS/DCF import for node ``_TEMPLATE_NODE``) for ``node_id``: its own objects,
    ``$NODEID``-relative values and ``node_id`` recomputed."""
    memo: dict[int, Any] = {}

    def var(v: ODVariable) -> ODVariable:
        got: ODVariable | None = memo.get(id(v))
        if got is None:
            got = memo[id(v)] = _shallow(v)
            for name in _MUTABLE:
                if name in v.__dict__:
                    container = v.__dict__[name]
                    if id(container) not in memo:
                        memo[id(container)] = container.copy()
                    got.__dict__[name] = memo[id(container)]
            _relocate(got, node_id)
        return got

    def member(obj: ODVariable | ODRecord | ODArray) -> ODVariable | ODRecord | ODArray:
        if isinstance(obj, ODVariable):
            return var(obj)
        got: ODRecord | ODArray | None = memo.get(id(obj))
        if got is None:
            got = memo[id(obj)] = _shallow(obj)
            got.subindices = {k: var(v) for k, v in obj.subindices.items()}
            got.names = {k: var(v) for k, v in obj.names.items()}
            for v in got.subindices.values():
                v.parent = got
            for v in got.names.values():
                v.parent = got
        return got

    od = _shallow(template)
    od.indices = {k: member(o) for k, o in template.indices.items()}
    od.names = {k: member(o) for k, o in template.names.items()}
    for o in (*od.indices.values(), *od.names.values()):
        o.parent = od
    od.device_information = _shallow(template.device_information)
    od.device_information.allowed_baudrates = set(template.device_information.allowed_baudrates)
    for name, value in template.__dict__.items():  # [FileInfo] (canopen keeps it as ``__edsFileInfo``)
        if isinstance(value, dict) and name not in ("indices", "names"):
            od.__dict__[name] = dict(value)
    if template.node_id is not None:  # set from the call's node id where the file has [DeviceComissioning]
        od.node_id = node_id
    return od


def _shallow(obj: _T) -> _T:
    """``copy.copy`` of a plain object (its attributes shared), without copy's protocol lookups."""
    new = object.__new__(type(obj))
    new.__dict__.update(obj.__dict__)
    return new


def _relocate(v: ODVariable, node_id: int) -> None:
    """Recompute ``default``/``value`` from their EDS text where it names ``$NODEID`` (canopen's conversion)."""
    for raw_name, name in (("default_raw", "default"), ("value_raw", "value")):
        raw = v.__dict__.get(raw_name)
        if isinstance(raw, str) and "$NODEID" in raw.replace(" ", "").upper():
            try:
                v.__dict__[name] = _convert_variable(node_id, v.data_type, raw)  # type: ignore[no-untyped-call]
            except ValueError:  # as canopen: the value stays unset (the template's failed the same way)
                pass
