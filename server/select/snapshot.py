"""An object's fields as plain data for a snapshot, and the checked way back.

Each part of a session that outlives a connection (cost models, the path
predictor, the clock, the client-cache mirror) says which of its fields a
snapshot holds and writes them with ``dump_fields``; its ``from_state`` reads
them back with ``load_fields`` *into* a freshly built object, whose current
values say what type and shape each field must have, so a corrupt or foreign
blob is refused (ValueError) instead of producing an object that fails later.
Arrays (and deques) travel as raw bytes with dtype and shape, so the result
packs straight into msgpack.

The snapshot name of a field may differ from its attribute's (a mapping
{snapshot name: attribute}): the format of saved sessions stays fixed while the
code's names move.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Mapping, Union

import numpy as np

__all__ = ["dump_fields", "load_fields", "Names"]

#: The fields a snapshot holds: attribute names, or a mapping {snapshot name: attribute name}.
Names = Union[tuple, Mapping]

_PLAIN = {int, float, bool, str, type(None)}


def _enc(value: Any) -> Any:
    """One attribute as msgpack-able data: arrays (and deques) as raw bytes with dtype and shape."""
    if type(value) in _PLAIN:
        return value
    if isinstance(value, deque):
        if value and type(value[0]) is float:  # the common history: no list in between
            value = np.fromiter(value, np.float64, len(value))
        else:
            value = np.asarray(list(value)) if value else np.zeros(0)
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        return {"nd": a.dtype.str, "shape": list(a.shape), "b": a.tobytes()}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple):
        return list(value)
    return value


def _array(value: Any, name: str) -> np.ndarray:
    if not (isinstance(value, dict) and set(value) == {"nd", "shape", "b"}):
        raise ValueError(f"{name}: expected an array")
    try:
        dtype = np.dtype(value["nd"])
        shape = tuple(int(s) for s in value["shape"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: bad array header: {exc}") from None
    if dtype.kind not in "biuf" or any(s < 0 for s in shape):
        raise ValueError(f"{name}: bad array header")
    b = value["b"]
    if not isinstance(b, bytes) or len(b) != dtype.itemsize * math.prod(shape):
        raise ValueError(f"{name}: array payload does not match its shape")
    return np.frombuffer(b, dtype).reshape(shape).copy()


def _dec(value: Any, current: Any, name: str, variable: bool) -> Any:
    """``value`` decoded as the type and shape of ``current`` (the fresh object's attribute); ValueError if not."""
    if isinstance(current, np.ndarray):
        a = _array(value, name)
        if a.dtype != current.dtype or a.shape[1:] != current.shape[1:] or (not variable and a.shape != current.shape):
            raise ValueError(f"{name}: expected {current.dtype} {current.shape}, got {a.dtype} {a.shape}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{name}: not finite")
        return a
    if isinstance(current, deque):
        a = _array(value, name)
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{name}: not finite")
        items = a.tolist() if a.ndim == 1 else [tuple(row) for row in a.tolist()]
        if current.maxlen is not None and len(items) > current.maxlen:
            raise ValueError(f"{name}: {len(items)} items, at most {current.maxlen}")
        return deque(items, maxlen=current.maxlen)
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{name}: expected a bool")
        return value
    if isinstance(current, (int, float, np.integer, np.floating)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: expected a number")
        if isinstance(value, float) and not math.isfinite(value) and value != current:
            raise ValueError(f"{name}: not finite")  # (-inf "never yet" markers stay allowed)
        return float(value) if isinstance(current, (float, np.floating)) else value
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ValueError(f"{name}: expected a string")
        return value
    if isinstance(current, list):
        if not isinstance(value, list) or len(value) != len(current):
            raise ValueError(f"{name}: expected a list of {len(current)}")
        return [_dec(v, c, f"{name}[{i}]", variable) for i, (v, c) in enumerate(zip(value, current))]
    if isinstance(current, dict):
        if not isinstance(value, dict):
            raise ValueError(f"{name}: expected a map")
        return value
    if current is None:  # optional: None, a finite number or an array
        if value is None:
            return None
        if isinstance(value, dict):
            return _array(value, name)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise ValueError(f"{name}: expected None, a number or an array")
    raise ValueError(f"{name}: cannot restore a {type(current).__name__}")


def dump_fields(obj: Any, names: Names, optional: bool = False) -> dict:
    """The named attributes of ``obj`` as plain data, keyed by their snapshot names; with ``optional`` those it
    lacks are left out (code that may evolve)."""
    pairs = _pairs(names)
    return {key: _enc(getattr(obj, attr)) for key, attr in pairs if not optional or hasattr(obj, attr)}


def load_fields(obj: Any, state: Any, names: Names, what: str, optional: bool = False,
                variable: tuple[str, ...] = ()) -> None:
    """Set the named attributes of ``obj`` from ``dump_fields``' dict, checked against their current values.

    All are decoded before any is set, so a bad blob leaves ``obj`` as it was.
    ``variable``: snapshot names of arrays whose first dimension may differ from the current one.
    """
    if not isinstance(state, dict):
        raise ValueError(f"{what}: expected a map")
    out = {}
    for key, attr in _pairs(names):
        if not hasattr(obj, attr):
            if optional:
                continue
            raise ValueError(f"{what}: has no {key}")
        if key not in state:
            if optional:
                continue
            raise ValueError(f"{what}.{key} is missing")
        out[attr] = _dec(state[key], getattr(obj, attr), f"{what}.{key}", key in variable)
    for attr, v in out.items():
        setattr(obj, attr, v)


def _pairs(names: Names) -> list[tuple[str, str]]:
    """(snapshot name, attribute name) pairs: a tuple names both alike, a mapping maps the first to the second."""
    return list(names.items()) if isinstance(names, Mapping) else [(n, n) for n in names]
