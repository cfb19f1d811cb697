"""Typed access to the tables of a scene file (:mod:`shadowlab.scene.spec`, :mod:`shadowlab.scene.sdf_spec`):
every error names the file, the key and what was expected."""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping

from ..errors import InputError, SceneError

#: common misspellings and synonyms that difflib's ratio does not catch (``field_of_view`` is far
#: from ``fov`` by edit distance); each maps to the key of the format that means it
SYNONYMS = {"colour": "color", "field_of_view": "fov", "fovy": "fov", "fov_degrees": "fov", "angle_of_view": "fov",
            "res": "resolution", "look_at": "target", "lookat": "target", "at": "target",
            "centre": "center", "eye": "position", "origin": "position", "pos": "position", "type": "kind",
            "kind": "type", "albedo_color": "albedo", "reflectance": "albedo", "two-sided": "two_sided",
            "twosided": "two_sided", "shadowmap": "shadow_map", "shadow_map_size": "shadow_map",
            "shadow_map_resolution": "shadow_map", "diameter": "radius", "half_extents": "half",
            "half_size": "half", "width": "size", "height": "size", "desc": "description", "title": "name"}


def did_you_mean(word, choices) -> str:
    """``" (did you mean 'x'?)"`` for the choice closest to ``word`` (difflib, case-insensitive,
    plus :data:`SYNONYMS`), or ``""`` when none is close.

    >>> did_you_mean("colour", ["color", "power"]), did_you_mean("powr", ["color", "power"])
    (" (did you mean 'color'?)", " (did you mean 'power'?)")
    >>> did_you_mean("zzz", ["color", "power"])
    ''
    """
    choices = [str(c) for c in choices]
    w = str(word)
    syn = SYNONYMS.get(w.lower())
    if syn in choices and syn != w:
        return f" (did you mean {syn!r}?)"
    lower = {c.lower(): c for c in choices}
    m = difflib.get_close_matches(w.lower(), list(lower), n=1, cutoff=0.6)
    return f" (did you mean {lower[m[0]]!r}?)" if m else ""


def unknown_key_text(key, allowed, what: str) -> str:
    """The message for an unknown ``key``: the suggestion, what the table takes and the fix."""
    return (f"unknown key {key!r}{did_you_mean(key, allowed)}; {what} takes: {', '.join(sorted(allowed))}. "
            "Fix the spelling or remove the key")


class Reader:
    """Typed access to a TOML table, with errors naming file, key and expectation."""

    def __init__(self, path: str, where: str, table: dict):
        self.path, self.where, self.t = path, where, table

    def fail(self, key: str, expected: str, got=None, choices=None):
        shown = "" if got is None else f", got {got!r}"
        if choices is not None and isinstance(got, str):
            shown += did_you_mean(got, choices)
        raise SceneError(f"{self.path}: {self.where}{'.' if self.where else ''}{key}: expected {expected}{shown}")

    def has(self, key):
        return key in self.t

    def refuse(self, key: str, text: str):
        """Refuse ``key`` with ``text`` (what is wrong and the fix)."""
        raise SceneError(f"{self.path}: {self.where}{'.' if self.where else ''}{key}: {text}")

    def unknown(self, key: str, allowed, what: str):
        """Refuse a key ``what`` (e.g. "[camera]") does not take, suggesting the closest allowed one."""
        raise SceneError(f"{self.path}: {self.where}{'.' if self.where else ''}{key}: "
                         f"{unknown_key_text(key, allowed, what)}")

    def check_keys(self, allowed, what: str):
        """Refuse the first key of the table not in ``allowed``."""
        for k in self.t:
            if k not in allowed:
                self.unknown(k, allowed, what)

    def bool(self, key, default: bool):
        """A TOML boolean (``true`` / ``false``); a string such as ``"no"`` or a number is refused."""
        if key not in self.t:
            return default
        v = self.t[key]
        if not isinstance(v, bool):
            self.fail(key, "true or false (a TOML boolean, without quotes)", v)
        return v

    def str(self, key, default=None, choices=None):
        if key not in self.t:
            if default is None:
                self.fail(key, "a string" + (f" (one of {', '.join(choices)})" if choices else ""), None)
            return default
        v = self.t[key]
        if not isinstance(v, str):
            self.fail(key, "a string", v)
        if choices and v not in choices:
            self.fail(key, f"one of {', '.join(choices)}", v, choices=choices)
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
            self.fail(key, f"a number in [{lo}, {hi}]" if lo is not None and hi is not None else
                      f"a number >= {lo:g}" if lo is not None else f"a number <= {hi:g}", v)
        return float(v)

    def int(self, key, default=None, choices=None, lo=None, hi=None, why: str = ""):
        v = self.t.get(key, default)
        if v is None:
            self.fail(key, "an integer (missing)")
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, "an integer", v)
        if choices and v not in choices:
            self.fail(key, f"one of {', '.join(map(str, choices))}", v)
        if lo is not None and v < lo:
            self.fail(key, f"an integer >= {lo}", v)
        if hi is not None and v > hi:
            self.fail(key, f"an integer <= {hi}{why}", v)
        return v

    def vec(self, key, n=3, default=None, positive=False):
        if key not in self.t:
            if default is None:
                self.fail(key, f"a list of {n} numbers (missing)")
            return tuple(default)
        v = self.t[key]
        if (
            isinstance(v, (int, float))
            and not isinstance(v, bool)
            and n == 3
            and key in ("scale", "color", "albedo", "transmittance")
        ):
            v = [v] * 3
        if (not isinstance(v, list) or len(v) != n or
                any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)):
            self.fail(key, f"a list of {n} finite numbers", v)
        if positive and any(x <= 0 for x in v):
            self.fail(key, f"a list of {n} positive numbers", v)
        return tuple(float(x) for x in v)


def check_param_values(where: str, t, params: Mapping) -> None:
    """Names and TOML types of a technique's parameter values from a file (a gate's ``params``, a
    preset): an unknown name gets the closest one; a boolean parameter takes only true / false and a
    number parameter only a number (``"no"`` or ``1`` for a boolean is refused, not read as true).
    Ranges are checked by the parameter itself (:meth:`Param.parse`). ``t``: a
    :class:`~shadowlab.techniques.base.Technique` (read by duck typing: scene imports no technique)."""
    have = [p.name for p in t.params]
    for k, v in params.items():
        if k not in have:
            raise InputError(f"{where}: technique {t.name!r} has no parameter {k!r}{did_you_mean(k, have)}; its "
                             f"parameters: {', '.join(have) or '(none)'}")
        p = t.param(k)
        if p.kind == "bool" and not isinstance(v, bool):
            raise InputError(f"{where}: {t.name}.{k}: expected true or false (a boolean, without quotes), got {v!r}")
        if p.kind in ("int", "float") and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise InputError(f"{where}: {t.name}.{k}: expected a number (without quotes), got {v!r}")


def rotations(r: Reader, table: dict) -> list:
    """The ``rotate`` key of a shape: [ax, ay, az, degrees] or a list of them, axes non-zero."""
    rot = table.get("rotate", [])
    if rot and isinstance(rot[0], (int, float)):
        rot = [rot]
    if not isinstance(rot, list) or any(not isinstance(q, list) or len(q) != 4 or
                                        any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in q)
                                        for q in rot):
        r.fail("rotate", "[ax, ay, az, degrees] or a list of them", table.get("rotate"))
    if any(not all(math.isfinite(x) for x in q) for q in rot):
        r.fail("rotate", "finite numbers in every [ax, ay, az, degrees]", table.get("rotate"))
    if any(not any(q[:3]) for q in rot):
        r.fail("rotate", "a non-zero rotation axis in every [ax, ay, az, degrees]", table.get("rotate"))
    return rot


def norm(v) -> float:
    """Euclidean length of a 3-vector (a tuple).

    >>> norm((3.0, 4.0, 0.0))
    5.0
    """
    return math.sqrt(sum(x * x for x in v))


def cross(a, b) -> tuple:
    """Cross product of two 3-vectors (tuples)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
