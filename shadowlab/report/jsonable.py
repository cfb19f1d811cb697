"""Plain JSON of a run: numpy scalars and arrays become Python values and **NaN / ±inf become
null** (JSON has no NaN; a null metric means "not available", e.g. the PSNR of identical images,
which is +inf, or a penumbra metric without penumbra)."""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping

import numpy as np

from ..errors import InputError

__all__ = ["to_jsonable", "run_to_json"]


def to_jsonable(obj, key: str = "run"):
    """Plain-JSON copy of ``obj``: numpy scalars/arrays -> Python values, tuples -> lists,
    NaN/±inf -> None. Anything else that JSON cannot hold raises ``InputError`` naming ``key``.

    >>> to_jsonable({"a": np.float32(0.5), "b": float("nan"), "c": (np.int64(3),)})
    {'a': 0.5, 'b': None, 'c': [3]}
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, numbers.Integral):
        return int(obj)
    if isinstance(obj, numbers.Real):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise InputError(f"{key}: a numpy array of dtype {obj.dtype} cannot be written to metrics.json")
        return to_jsonable(obj.tolist(), key)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise InputError(f"{key}: dictionary key {k!r} is not a string; metrics.json needs string keys")
            out[str(k)] = to_jsonable(v, f"{key}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, f"{key}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise InputError(f"{key}: a value of type {type(obj).__name__} cannot be written to metrics.json")


def run_to_json(run: Mapping) -> dict:
    """The run (a :class:`~shadowlab.report.run.Run` or its mapping) without ``"images"``, as plain
    JSON (what ``metrics.json`` holds).

    >>> run_to_json({"scene": "s", "images": {}, "resolution": (2, 2)})
    {'scene': 's', 'resolution': [2, 2]}
    """
    return to_jsonable({k: v for k, v in run.items() if k != "images"})
