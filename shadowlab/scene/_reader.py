"""Typed access to the tables of a scene file (:mod:`shadowlab.scene.spec`, :mod:`shadowlab.scene.sdf_spec`):
every error names the file, the key and what was expected."""

from __future__ import annotations

import math

from ..errors import SceneError


class _Reader:
    """Typed access to a TOML table, with errors naming file, key and expectation."""

    def __init__(self, path: str, where: str, table: dict):
        self.path, self.where, self.t = path, where, table

    def fail(self, key: str, expected: str, got=None):
        shown = "" if got is None else f", got {got!r}"
        raise SceneError(f"{self.path}: {self.where}{'.' if self.where else ''}{key}: expected {expected}{shown}")

    def has(self, key):
        return key in self.t

    def str(self, key, default=None, choices=None):
        if key not in self.t:
            if default is None:
                self.fail(key, "a string" + (f" (one of {', '.join(choices)})" if choices else ""), None)
            return default
        v = self.t[key]
        if not isinstance(v, str):
            self.fail(key, "a string", v)
        if choices and v not in choices:
            self.fail(key, f"one of {', '.join(choices)}", v)
        return v

    def num(self, key, default=None, lo=None, hi=None):
        if key not in self.t:
            if default is None:
                self.fail(key, "a number (missing)")
            return default
        v = self.t[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, "a finite number", v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            self.fail(key, f"a number in [{lo}, {hi}]", v)
        return float(v)

    def int(self, key, default=None, choices=None, lo=None):
        v = self.t.get(key, default)
        if v is None:
            self.fail(key, "an integer (missing)")
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, "an integer", v)
        if choices and v not in choices:
            self.fail(key, f"one of {', '.join(map(str, choices))}", v)
        if lo is not None and v < lo:
            self.fail(key, f"an integer >= {lo}", v)
        return v

    def vec(self, key, n=3, default=None, positive=False):
        if key not in self.t:
            if default is None:
                self.fail(key, f"a list of {n} numbers (missing)")
            return tuple(default)
        v = self.t[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool) and n == 3 and key in ("scale", "color", "albedo"):
            v = [v] * 3
        if (not isinstance(v, list) or len(v) != n or
                any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)):
            self.fail(key, f"a list of {n} finite numbers", v)
        if positive and any(x <= 0 for x in v):
            self.fail(key, f"a list of {n} positive numbers", v)
        return tuple(float(x) for x in v)


def rotations(r: _Reader, table: dict) -> list:
    """The ``rotate`` key of a shape: [ax, ay, az, degrees] or a list of them, axes non-zero."""
    rot = table.get("rotate", [])
    if rot and isinstance(rot[0], (int, float)):
        rot = [rot]
    if not isinstance(rot, list) or any(not isinstance(q, list) or len(q) != 4 or
                                        any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in q)
                                        for q in rot):
        r.fail("rotate", "[ax, ay, az, degrees] or a list of them", table.get("rotate"))
    if any(not any(q[:3]) for q in rot):
        r.fail("rotate", "a non-zero rotation axis in every [ax, ay, az, degrees]", table.get("rotate"))
    return rot
