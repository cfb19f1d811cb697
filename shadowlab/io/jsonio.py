"""JSON metadata (meta.json, metrics.json): atomic writes, numpy-aware, readable errors.

NaN and ±Infinity (an empty-mask metric, the PSNR of identical images) are written as the
``NaN`` / ``Infinity`` tokens of Python's ``json`` module, so a round trip is exact; strict JSON
parsers (a browser's ``JSON.parse``) reject them, so convert them before handing a file to one.

>>> import tempfile, os
>>> p = os.path.join(tempfile.mkdtemp(), "m.json")
>>> write_json_atomic(p, {"spp": 64})
>>> read_json(p)
{'spp': 64}
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..errors import InputError
from .outdir import write_error

__all__ = ["write_json_atomic", "read_json", "to_python"]


def to_python(obj, _where: str = "$"):
    """Convert numpy scalars/arrays (and tuples, Paths) inside ``obj`` to plain JSON-able Python.

    >>> import numpy as np
    >>> to_python({"a": np.float32(0.5), "b": np.arange(2), np.int64(3): (np.bool_(True),)})
    {'a': 0.5, 'b': [0, 1], '3': [True]}
    """
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj.item() if isinstance(obj, np.generic) else obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            key = k.item() if isinstance(k, np.generic) else k
            if not isinstance(key, str):
                if isinstance(key, (bool, int, float)) or key is None:
                    key = json.dumps(key)
                else:
                    raise TypeError(f"JSON object key {k!r} at {_where} is not a string or number")
            out[key] = to_python(v, f"{_where}.{key}")
        return out
    if isinstance(obj, (list, tuple)):
        return [to_python(v, f"{_where}[{i}]") for i, v in enumerate(obj)]
    raise TypeError(f"value of type {type(obj).__name__} at {_where} is not JSON serialisable")


def write_json_atomic(path, obj) -> None:
    """Write ``obj`` as JSON (indent 2, keys in insertion order) atomically.

    numpy scalars and arrays are converted to Python numbers and lists. The text goes to a temporary
    file in the target directory (created if missing), which then replaces ``path`` (``os.replace``).

    >>> import numpy as np, tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "meta.json")
    >>> write_json_atomic(p, {"rmse": np.float32(0.25), "shape": np.array([2, 3])})
    >>> read_json(p)
    {'rmse': 0.25, 'shape': [2, 3]}
    """
    path = Path(path)
    text = json.dumps(to_python(obj), indent=2, sort_keys=False) + "\n"
    directory = path.parent if str(path.parent) else Path(".")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise (write_error(path, exc, what="create") or exc) from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:  # a full disk, permissions: exit 3 with the fix (outdir.write_error)
        raise (write_error(path, exc) or exc) from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def read_json(path):
    """Read a JSON file; a missing, unreadable or malformed file raises :class:`InputError`.

    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "bad.json")
    >>> _ = open(p, "w").write("{oops")
    >>> try:
    ...     read_json(p)
    ... except InputError as e:
    ...     print("malformed" in str(e))
    True
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"JSON file {path} does not exist; check the path.") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read JSON file {path}: {exc}; check the path and permissions.") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"JSON file {path} is malformed (line {exc.lineno}, column {exc.colno}: {exc.msg}); "
            "fix or delete it and regenerate it."
        ) from exc
