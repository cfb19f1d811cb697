"""Technique registry and the single declaration of every parameter (DESIGN.md, Technique).

A technique declares its parameters once, as :class:`Param` objects; the CLI (``--set
tech.param=value``), ``shadowlab techniques``, the README table, the fitting search space and
the reports all read that declaration.

>>> from shadowlab.techniques import registry
>>> sorted(registry.names())[:2]  # doctest: +SKIP
['hard', 'pcf']
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import InputError

KINDS = ("float", "int", "bool", "choice")


@dataclass(frozen=True)
class Param:
    """One parameter of a technique.

    ``lo``/``hi`` bound float and int values (inclusive); ``choices`` lists the values of a
    ``choice``; ``differentiable`` says whether fitting may use gradients (continuous and
    used smoothly by the technique's filter); ``source`` names the document and section.
    """

    name: str
    default: object
    kind: str = "float"
    lo: float | None = None
    hi: float | None = None
    units: str = ""
    differentiable: bool = False
    choices: tuple = ()
    source: str = ""
    doc: str = ""

    def parse(self, value, technique: str = "?"):
        """Validate and convert ``value`` (a Python value or a CLI string)."""
        where = f"{technique}.{self.name}"
        if self.kind == "bool":
            if isinstance(value, str):
                v = value.strip().lower()
                if v in ("1", "true", "yes", "on"):
                    return True
                if v in ("0", "false", "no", "off"):
                    return False
                raise InputError(f"{where}: expected true or false, got {value!r}")
            return bool(value)
        if self.kind == "choice":
            v = value if not isinstance(value, str) else value.strip()
            for c in self.choices:
                if str(c) == str(v):
                    return c
            raise InputError(f"{where}: expected one of {', '.join(map(str, self.choices))}, got {value!r}")
        try:
            v = float(value) if self.kind == "float" else int(str(value).strip()) if isinstance(value, str) else value
        except (TypeError, ValueError):
            raise InputError(f"{where}: expected {'a number' if self.kind == 'float' else 'an integer'}, "
                             f"got {value!r}") from None
        if self.kind == "int":
            if isinstance(v, float) and not v.is_integer():
                raise InputError(f"{where}: expected an integer, got {value!r}")
            v = int(v)
        if self.kind == "float" and not math.isfinite(v):
            raise InputError(f"{where}: expected a finite number, got {value!r}")
        if (self.lo is not None and v < self.lo) or (self.hi is not None and v > self.hi):
            raise InputError(f"{where}={v} is out of range: allowed [{self.lo}, {self.hi}] {self.units}".rstrip())
        return v

    def range_text(self) -> str:
        if self.kind == "choice":
            return ", ".join(map(str, self.choices))
        if self.kind == "bool":
            return "true, false"
        return f"[{self.lo:g}, {self.hi:g}]" if self.lo is not None and self.hi is not None else ""


@dataclass
class ShadowResult:
    """What a technique returns. ``visibility[light]``: flat per-G-buffer-point Dr.Jit Float in
    [0, 1] (differentiable where the technique is); ``aovs``: name -> (H, W[, C]) numpy image
    for debugging (penumbra width, fallback mask, ...); ``stats``: JSON-able numbers."""

    visibility: dict
    aovs: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)


class Technique:
    """Base class. Subclasses set ``name``, ``title``, ``source`` and ``params`` and implement
    :meth:`render`; ``render`` must be pure (same inputs, same bits)."""

    name: str = ""
    title: str = ""
    source: str = ""
    params: tuple = ()
    summary: str = ""

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise InputError(f"technique {self.name!r} has no parameter {name!r}; its parameters: "
                         f"{', '.join(p.name for p in self.params) or '(none)'}")

    def defaults(self) -> dict:
        return {p.name: p.default for p in self.params}

    def resolve(self, overrides: dict | None = None) -> dict:
        """Defaults updated with ``overrides`` (validated; unknown names raise InputError)."""
        values = self.defaults()
        for k, v in (overrides or {}).items():
            values[k] = self.param(k).parse(v, self.name)
        return values

    def render(self, frame, params: dict) -> ShadowResult:  # pragma: no cover - interface
        raise NotImplementedError


_REGISTRY: dict = {}


def register(cls):
    """Class decorator: add a Technique subclass to the registry under ``cls.name``."""
    if not cls.name or cls.name in _REGISTRY:
        raise ValueError(f"technique name {cls.name!r} empty or registered twice")
    _REGISTRY[cls.name] = cls()
    return cls


def names() -> list[str]:
    """Registered techniques, family by family in :data:`_ORDER` (then by module name), each
    family's techniques in the order its module declares them, whatever was imported first."""
    _load_all()
    mods = sorted({t.__class__.__module__.rsplit(".", 1)[-1] for t in _REGISTRY.values()}, key=_module_rank)
    return [n for m in mods for n, t in _REGISTRY.items() if t.__class__.__module__.rsplit(".", 1)[-1] == m]


def get(name: str) -> Technique:
    _load_all()
    if name not in _REGISTRY:
        raise InputError(f"unknown technique {name!r}; registered techniques: {', '.join(names())}")
    return _REGISTRY[name]


def parse_sets(sets: list[str], techniques: list[str]) -> dict:
    """``["pcf.kernel=5", ...]`` -> {technique: {param: parsed value}} (validated)."""
    out = {t: {} for t in techniques}
    for s in sets or []:
        if "=" not in s or "." not in s.split("=", 1)[0]:
            raise InputError(f"--set {s!r}: expected TECHNIQUE.PARAM=VALUE, e.g. pcf.kernel=5")
        key, val = s.split("=", 1)
        tech, pname = key.split(".", 1)
        t = get(tech)
        if tech not in out:
            raise InputError(f"--set {s!r}: technique {tech!r} is not among the ones being run "
                             f"({', '.join(techniques)})")
        out[tech][pname] = t.param(pname).parse(val, tech)
    return out


# the order techniques are listed in (reports, README); modules not named here follow, sorted
_ORDER = ("shadow_map", "pcf", "pcss", "vsm", "esm", "evsm", "msm")


def _module_rank(name: str):
    return (_ORDER.index(name) if name in _ORDER else len(_ORDER), name)


def _load_all():
    """Import every technique module of this package: importing a module registers its
    techniques, so a new family needs no edit here."""
    import importlib
    import pkgutil
    from pathlib import Path
    mods = [m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if not m.name.startswith("_")
            and m.name != "base"]
    mods.sort(key=_module_rank)
    for m in mods:
        importlib.import_module(f"{__package__}.{m}")


def param_table_markdown(t: Technique) -> str:
    """The parameter table of a technique, Mitsuba-plugin style (README and `shadowlab techniques`)."""
    rows = ["| parameter | default | range | units | differentiable | source | description |",
            "|---|---|---|---|---|---|---|"]
    for p in t.params:
        rows.append(f"| `{p.name}` | {p.default} | {p.range_text()} | {p.units} | "
                    f"{'yes' if p.differentiable else 'no'} | {p.source} | {p.doc} |")
    return "\n".join(rows)
