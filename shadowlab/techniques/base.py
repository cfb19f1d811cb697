"""Technique registry and the single declaration of every parameter (docs/ARCHITECTURE.md, Technique).

A technique declares its parameters once, as :class:`Param` objects; the CLI (``--set
tech.param=value``), ``shadowlab techniques``, the README table, the fitting search space and
the reports all read that declaration.

>>> from shadowlab.techniques import get, names
>>> names()[:3]
['hard', 'pcf', 'pcss']
>>> get("pcf").param("kernel").default
3
"""

from __future__ import annotations

import importlib
import math
import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from ..scene.twins import why_no_sdf

#: the kinds of value a :class:`Param` holds (checked when a Param is made)
KINDS = ("float", "int", "bool", "choice")


@dataclass(frozen=True)
class FromScene:
    """A parameter value that means "the scene's own" instead of a number, e.g. ``resolution`` 0:
    each light's ``shadow_map``. ``value`` is that sentinel; ``of(frame)`` the one value it stands
    for where one number is needed (the start and window centre of a fit); ``floor`` the least
    value a search may reach (the sentinel is a rule, not a value to fit). ``of`` is a
    module-level function, so a Param stays picklable."""

    value: object
    of: Callable
    floor: object = None


@dataclass(frozen=True)
class Param:
    """One parameter of a technique.

    ``kind`` is one of :data:`KINDS`; ``lo``/``hi`` bound float and int values (inclusive);
    ``choices`` lists the values of a ``choice``; ``differentiable`` says whether fitting may
    use gradients (continuous and used smoothly by the technique's filter); ``source`` names
    the document and section; ``from_scene``: the value, if any, that means "the scene's own"
    (:class:`FromScene`).

    >>> Param("bias", 0.1, "number")
    Traceback (most recent call last):
    ...
    ValueError: Param bias: kind 'number' is not one of float, int, bool, choice
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
    from_scene: FromScene | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Param {self.name}: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        if self.kind == "choice" and not self.choices:
            raise ValueError(f"Param {self.name}: a choice needs its choices")

    def scene_value(self, value, frame):
        """``value``, or what it stands for on ``frame`` when it is the :attr:`from_scene` sentinel."""
        fs = self.from_scene
        return fs.of(frame) if fs is not None and value == fs.value else value

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
    [0, 1] (differentiable where the technique is); ``aovs``: ``<light>.<aov>`` -> (H, W[, C])
    numpy image for debugging (penumbra width, fallback mask, ...; an :class:`Images` mapping, read
    back from the device on first access); ``stats``: JSON-able numbers,
    laid out by :meth:`Technique.render`. ``colour[light]``: flat Dr.Jit Color3f RGB visibility,
    only for lights whose shadows the technique colours (translucent casters); ``visibility`` is
    then its channel mean."""

    visibility: dict
    aovs: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    colour: dict = field(default_factory=dict)
    #: the :class:`Technique` that rendered it (its report images and error bands read the AOVs)
    technique: object = None


#: how the report draws the images of a :class:`Panel` (kinds of picture, not families):
#: ``colour``: H×W×3 colours in [0, 1], shown as they are; ``log2_ratio``: H×W ratio (≤ 0: none,
#: grey) shown as a signed heat map of its log₂ on a symmetric integer scale; ``levels``: H×W
#: log₂ levels (−1: none, grey), blue → white → red over one range shared by the panel's images;
#: ``excess_levels``: H×W levels ≥ 0 (−1: none, grey), white (0) → red, on one shared scale
PANEL_KINDS = ("colour", "log2_ratio", "levels", "excess_levels")


@dataclass(frozen=True)
class Panel:
    """One row a family adds to its section of the report, per light: the images
    ``images`` = ((key, label), ...) that :meth:`Technique.report_images` builds from the
    family's AOVs, drawn as ``kind`` (:data:`PANEL_KINDS`). The row's header is the light's name,
    ``title`` and, on a second line, ``note``; a cell with several images prefixes each with its
    label; each image's alt text is "<technique> ``alt`` [label] <light>"; its PNG is named after
    its key; ``legend``: what the colour bar's values are (heat-map kinds)."""

    kind: str
    title: str
    images: tuple
    alt: str
    note: str = ""
    legend: str = ""

    def __post_init__(self):
        if self.kind not in PANEL_KINDS:
            raise ValueError(f"Panel {self.title!r}: kind {self.kind!r} is not one of {', '.join(PANEL_KINDS)}")

    @property
    def keys(self) -> tuple:
        return tuple(k for k, _ in self.images)


@dataclass
class Pooled:
    """A per-light stat that is a mean over points: ``total / count`` per light (or ``value``
    where given) and ``Σ total / Σ count`` over the lights as ``stats[name]["all"]``."""

    total: float
    count: int
    value: float | None = None

    def mean(self) -> float:
        return float(self.value) if self.value is not None else (self.total / self.count if self.count else 0.0)


@dataclass
class LightResult:
    """What a family's per-light part (:meth:`Technique.render_light`) returns.

    ``visibility``: flat Dr.Jit Float over the G-buffer points; ``aovs``: AOV name -> flat Dr.Jit
    Float (detached and evaluated by the base, then stored as ``<light>.<name>`` images);
    ``active``: optional Bool mask: outside it the base sets visibility 1 and every AOV 0;
    ``stats``: JSON-able per-light numbers (a :class:`Pooled` value is a mean over points);
    ``maps``: one JSON-able dict per shadow map / tile of the light (a light with cascades or
    tiles has several; each dict holds that map's own numbers, e.g. resolution, near, far);
    ``colour``: optional flat Dr.Jit Color3f RGB visibility (coloured shadows of translucent
    casters), whose channel mean is ``visibility``; ``images``: AOVs that are images already
    (H×W[×C] numpy: a technique made of others passes their AOVs through), stored as
    ``<light>.<name>`` like ``aovs``; ``counts``: reductions (:func:`device_count`,
    :func:`device_total`) made in the render's kernel that :meth:`Technique.light_stats` turns
    into stats; like a Dr.Jit value in ``stats`` they are read back once, after the evaluation,
    and ``light_stats`` sees them as Python numbers. (A reduction's result used in a further
    Dr.Jit expression would need a kernel of its own: arithmetic on counts belongs to
    ``light_stats``.)"""

    visibility: object
    aovs: dict = field(default_factory=dict)
    active: object = None
    stats: dict = field(default_factory=dict)
    maps: list = field(default_factory=list)
    colour: object = None
    images: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)


class RenderContext:
    """Per-render state the base hands to a family's :meth:`~Technique.prepare` and
    :meth:`~Technique.render_light`: the resolved ``values`` and :meth:`scalar`; a family
    stores what it prepares once per render as attributes."""

    def __init__(self, technique, values: dict):
        self.technique, self.values = technique, values
        self._scalars: dict = {}

    def scalar(self, name: str):
        """Parameter ``name`` as a Dr.Jit Float of width 1 that enters kernels opaquely (a new
        value reuses the compiled kernel); a Dr.Jit input is used as is (made opaque, gradients
        kept), so ``dr.backward`` of a loss on the visibility reaches it."""
        if name not in self._scalars:
            self._scalars[name] = opaque_scalar(self.values[name])
        return self._scalars[name]


def opaque_scalar(v):
    """``v`` as an opaque Dr.Jit Float: a Dr.Jit array as is (made opaque), a number by ``dr.opaque``."""
    if isinstance(v, dr.ArrayBase):
        dr.make_opaque(v)
        return v
    return dr.opaque(mi.Float, float(v))


def scaled_size(scale, size: float):
    """(``scale`` × ``size`` as an opaque Dr.Jit Float of width 1, its value as a float): the
    :data:`LIGHT_SCALE` rule. A Dr.Jit ``scale`` stays in the expression (gradients reach it);
    a number is multiplied in double precision first, so ``scale`` 1 gives ``size`` exactly."""
    if isinstance(scale, dr.ArrayBase):
        return scale * float(size), float(dr.detach(scale)[0]) * float(size)
    v = float(scale) * float(size)
    return dr.opaque(mi.Float, v), v


#: The one light-size convention of every family: a multiplier of each light's own physical
#: size (``LightSpec.physical_size``), so one value fits every light of a scene in proportion
#: to its size. What "size" means to a family's model (the side of an equal-area square, a
#: sphere's radius, ...) its module says; families reuse this declaration (``dataclasses.replace``
#: only for ``source`` and ``differentiable``).
LIGHT_SCALE = Param("light_scale", 1.0, "float", 0.0, 16.0, "× the light's size", True, source="",
                    doc="multiplier of each light's own size (1 = the scene's light, 0 = a point light); "
                        "the family's model of the light is scaled by it")


def light_scale_param(source: str, differentiable: bool = True, doc: str = "") -> Param:
    """:data:`LIGHT_SCALE` with a family's ``source``, differentiability and, optionally, the
    family's sentence on what it scales (appended to the shared text)."""
    return replace(LIGHT_SCALE, source=source, differentiable=differentiable,
                   doc=LIGHT_SCALE.doc + (f": {doc}" if doc else ""))


def needs_mitsuba_geometry(name: str, spec) -> str | None:
    """The reason a technique that casts Mitsuba rays from the light (every shadow map) cannot
    render ``spec``: SDF-only objects, which Mitsuba does not see; None for other scenes."""
    if spec.kind == "sdf":
        return (f"{name}: the scene has SDF-only objects ([[sdf]]) that Mitsuba does not see, so shadow maps "
                "(Mitsuba ray casts from the light) would miss them: use the SDF techniques (sdf_hard, sdf_quilez, "
                "...) on it, or this technique on a scene with Mitsuba twins")
    return None


def needs_sdf(name: str, spec) -> str | None:
    """The reason an SDF technique (sphere and cone tracing of the scene's signed distance field)
    cannot render ``spec``: a shape without an SDF twin (a PLY/OBJ mesh, an alpha-tested or open
    shape, :func:`shadowlab.scene.twins.why_no_sdf`); None when the scene has its SDF."""
    if why := why_no_sdf(spec):
        return (f"{name}: the scene has no signed distance field ({why}; meshes and alpha-tested shapes have no "
                "SDF twin): use the shadow-map techniques on it, or this technique on a scene of rectangles, disks, "
                "cubes, spheres and capped cylinders or with [[sdf]] objects (e.g. sdf_simple, contact)")
    return None


class Technique:
    """Base class. Subclasses set ``name``, ``title``, ``source`` and ``params`` and implement
    the per-light part :meth:`render_light` (and, optionally, :meth:`prepare`, once per render,
    :meth:`light_stats`, after a light is evaluated, and :meth:`summarise`, the render's global
    stats); :meth:`render` does the rest, as a Mitsuba integrator supplies ``sample`` and its
    base class the render loop. ``render`` must be pure (same inputs, same bits)."""

    name: str = ""
    title: str = ""
    source: str = ""
    params: tuple = ()
    summary: str = ""
    #: the loss ``shadowlab fit`` uses when none is given (a loss of :mod:`shadowlab.fit.objective`)
    fit_loss: str = "rmse_penumbra"
    #: the rows the family adds to its report section (built from its AOVs by :meth:`report_images`)
    panels: tuple = ()
    #: label AOVs (an integer per point, −1 = none) by whose labels ``compare`` breaks the visibility
    #: error down, beside the distance bands (``pipeline.error_bands``)
    band_aovs: tuple = ()
    #: renders in an external program (a real engine in a browser): ``-t all``, ``fit --all``, ``demo``
    #: and the bench's per-technique loops leave it out (it is run when named)
    external: bool = False

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise InputError(f"technique {self.name!r} has no parameter {name!r}; its parameters: "
                         f"{', '.join(p.name for p in self.params) or '(none)'}")

    def defaults(self) -> dict:
        return {p.name: p.default for p in self.params}

    def resolve(self, overrides: dict | None = None) -> dict:
        """Defaults updated with ``overrides`` (validated; unknown names raise InputError).

        A ``differentiable`` parameter may be a Dr.Jit Float of width 1 (e.g. with gradients
        enabled): its value is validated like a number and the array itself is kept, so that
        gradients flow through the technique; any other parameter must be a plain value."""
        values = self.defaults()
        arrays = {}
        for k, v in (overrides or {}).items():
            p = self.param(k)
            if isinstance(v, dr.ArrayBase):
                if not p.differentiable:
                    diff = ", ".join(q.name for q in self.params if q.differentiable) or "none"
                    raise InputError(f"{self.name}.{k}: only differentiable parameters ({diff}) may be Dr.Jit "
                                     f"arrays; pass a number")
                if dr.width(v) != 1:
                    raise InputError(f"{self.name}.{k}: a Dr.Jit parameter must hold one value, got {dr.width(v)}")
                values[k] = p.parse(float(dr.detach(v)[0]), self.name)
                arrays[k] = v
            else:
                values[k] = p.parse(v, self.name)
        values.update(arrays)
        return values

    def unsupported(self, spec) -> str | None:
        """Why the technique cannot render scenes like ``spec`` (a SceneSpec), e.g. a light kind it
        does not handle; None (the default) when it can. ``demo`` and the bench skip such pairs;
        :meth:`render` refuses them with that text (InputError)."""
        return None

    def unavailable(self) -> str | None:
        """Why the technique cannot run on this machine (a program or package outside Python that it
        needs is missing, e.g. an engine's npm package or Chromium, which ``pip install`` does not
        bring), None (the default) when it can: ``-t all`` and ``demo`` skip it with this reason;
        asked for by name it fails with exit 3 and the fix."""
        return None


    def fit_params(self, values: dict) -> tuple:
        """The parameters ``shadowlab fit`` searches when none are named, for the resolved
        ``values``: the differentiable ones (a family without any says which to search)."""
        return tuple(p.name for p in self.params if p.differentiable)

    def report_images(self, frame, result: "ShadowResult", mask, vis: dict) -> dict:
        """The images of :attr:`panels`, built from ``result``'s AOVs: {key: {light: H×W[×3]}},
        only for the lights that have them. ``mask``: H×W bool, the surface pixels; ``vis``:
        {light: H×W visibility image}. None by default."""
        return {}

    # -- the family's part ---------------------------------------------------------------------
    def prepare(self, frame, values: dict, ctx: RenderContext) -> None:
        """Once per render, before the lights: check the frame, build what every light shares
        (opaque biases, tap tables, ...) and store it on ``ctx``."""

    def render_light(self, frame, light, values: dict, ctx: RenderContext) -> LightResult:  # pragma: no cover
        """The family's per-light part: visibility, AOVs and stats of one light."""
        raise NotImplementedError

    def light_stats(self, frame, light, values: dict, ctx: RenderContext, result: LightResult) -> dict:
        """Per-light stats that need the evaluated arrays (``result.visibility``, ``result.aovs``
        and ``result.active`` hold them, evaluated) or the device counts (``result.counts``, read
        back: Python numbers); merged over ``result.stats``."""
        return {}

    def summarise(self, frame, values: dict, ctx: RenderContext, lights: dict) -> dict:
        """The render's global stats, from the per-light ones (``lights[name]``, with ``maps``)."""
        return {}

    # -- the loop ------------------------------------------------------------------------------
    def render(self, frame, params: dict | None = None) -> ShadowResult:
        """Resolve ``params``, :meth:`prepare`, then per light :meth:`render_light` and the
        evaluation of its visibility and AOVs (a kernel per light, none waited for: nothing is
        read back between lights) and gather the stats.

        Stats layout: ``stats["lights"][light]`` holds the light's stats and, where the family
        reports them, ``maps`` (one dict per shadow map or tile); every per-light stat is also
        ``stats[stat][light]`` (plus ``["all"]``, pooled over lights, for a :class:`Pooled`
        mean); the family's global stats (:meth:`summarise`) sit at the top level. A stat may
        be a Dr.Jit array of width 1 (a reduction left on the device): every such value of the
        render is read back at once, after every light's kernel: the render's one wait."""
        values = self.resolve(params)
        why = self.unsupported(frame.light_spec)
        if why:
            raise InputError(why)
        ctx = RenderContext(self, values)
        self.prepare(frame, values, ctx)
        gb = frame.gbuffer
        results = {}
        for light in frame.lights:
            r = results[light.name] = self.render_light(frame, light, values, ctx)
            extra = {k: dr.detach(a) for k, a in r.aovs.items()}
            if r.active is not None:
                r.visibility = dr.select(r.active, r.visibility, 1.0)
                r.colour = dr.select(r.active, r.colour, 1.0) if r.colour is not None else None
                extra = {k: dr.select(r.active, a, 0.0) for k, a in extra.items()}
            r.aovs = extra
            # a kernel per light, launched without waiting for it: one kernel for every light reads
            # every light's map at once and loses the caches (measured on LLVM, many_lights at
            # 320x180: pcss 589 vs 280 ms, dpsv 319 vs 241 ms, none faster together)
            dr.eval(r.visibility, *extra.values(), *(x for x in (r.active, r.colour) if x is not None))
        host = to_host({ln: (r.stats, r.counts) for ln, r in results.items()})
        aovs = Images(gb.to_image)
        lights = {}
        for light in frame.lights:
            r = results[light.name]
            r.stats, r.counts = host[light.name]
            for k, a in r.aovs.items():
                aovs.defer(f"{light.name}.{k}", a)
            for k, img in r.images.items():
                aovs[f"{light.name}.{k}"] = img
            lights[light.name] = {**r.stats, **self.light_stats(frame, light, values, ctx, r)}
        lights = to_host(lights)
        pools = {}
        for st in lights.values():
            for k, s in st.items():
                if isinstance(s, Pooled):
                    tot, cnt = pools.get(k, (0.0, 0))
                    pools[k] = (tot + s.total, cnt + s.count)
                    st[k] = s.mean()
        for ln, r in results.items():
            if r.maps:
                lights[ln]["maps"] = [dict(m) for m in r.maps]
        stats = dict(self.summarise(frame, values, ctx, lights))
        for ln, st in lights.items():
            for k, s in st.items():
                if k != "maps":
                    stats.setdefault(k, {})[ln] = s
        for k, (tot, cnt) in pools.items():
            stats[k]["all"] = tot / cnt if cnt else 0.0
        stats["lights"] = lights
        return ShadowResult(visibility={ln: r.visibility for ln, r in results.items()}, aovs=aovs, stats=stats,
                            colour={ln: r.colour for ln, r in results.items() if r.colour is not None},
                            technique=self)


class Images(Mapping):
    """A render's AOV images, ``<light>.<aov>`` -> (H, W[, C]) numpy: kept as the flat evaluated
    Dr.Jit arrays and read back (``to_image``) when first asked for, so a render moves no image
    to the host that nobody looks at. Pickles as a plain dict of images."""

    def __init__(self, to_image):
        self._to_image, self._flat, self._img, self._keys = to_image, {}, {}, {}

    def defer(self, key: str, flat) -> None:
        """Add ``key`` as a flat per-point array, converted on first access."""
        self._flat[key] = flat
        self._keys[key] = None

    def __setitem__(self, key: str, image) -> None:
        self._flat.pop(key, None)
        self._img[key] = image
        self._keys[key] = None

    def __getitem__(self, key: str):
        if key not in self._img:
            if key not in self._flat:
                raise KeyError(key)
            self._img[key] = self._to_image(self._flat.pop(key))
        return self._img[key]

    def __iter__(self):
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __reduce__(self):
        return dict, (dict(self.items()),)


def device_count(mask):
    """How many entries of ``mask`` are True, as a UInt32 of width 1 left on the device: a symbolic
    reduction (atomic adds fused into the kernel that evaluates ``mask``; integers, so the count
    does not depend on their order). :func:`to_host` reads it."""
    return dr.sum(dr.select(mask, mi.UInt32(1), mi.UInt32(0)), mode="symbolic")


def device_total(values):
    """Σ ``values`` as a Float64 of width 1 left on the device (symbolic, like
    :func:`device_count`); exact, hence independent of the order of the atomic adds, for
    integer-valued inputs below 2⁵³ (counts of steps or taps)."""
    return dr.sum(mi.Float64(values), mode="symbolic")


def to_host(tree):
    """``tree`` (dicts, lists, tuples, :class:`Pooled`) with every Dr.Jit value of width 1 replaced by
    its Python number (int for integer arrays), all of them evaluated together and read back
    once: the stats of a render."""
    found = []

    def walk(x, f):
        if isinstance(x, dict):
            return {k: walk(v, f) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return type(x)(walk(v, f) for v in x)
        if isinstance(x, Pooled):
            return Pooled(walk(x.total, f), walk(x.count, f), walk(x.value, f))
        if isinstance(x, dr.ArrayBase):
            return f(x)
        return x

    walk(tree, lambda x: found.append(x))
    if not found:
        return tree
    # the render's one wait for the device: stats are Python numbers, so they are read, all in one
    # array (float64 holds every count and float32 exactly), after every light's kernels
    values = dr.concat([mi.Float64(dr.detach(x)) for x in found]).numpy()
    host = {id(x): int(v) if dr.is_integral_v(x) else float(v) for x, v in zip(found, values)}
    return walk(tree, lambda x: host[id(x)])


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


#: (is_composite(name), make(name)) of the technique that composes others from a name
#: (``light_mix``: ``sun=csm,softbox=pcss``), registered by its module; made techniques are kept
_COMPOSERS: list = []
_COMPOSED: dict = {}


def register_composer(matches, make) -> None:
    """Let :func:`get` make a technique from a name that ``matches`` (e.g. a technique per light)."""
    _COMPOSERS.append((matches, make))


def composes(name: str) -> bool:
    """Whether ``name`` is a technique composed from its name (e.g. a technique per light)."""
    _load_all()
    return name not in _REGISTRY and any(matches(name) for matches, _ in _COMPOSERS)


def get(name: str) -> Technique:
    """The registered technique ``name`` (or one composed from its name, e.g. a technique per
    light); the technique modules are imported only when it is not registered yet, so a family
    that composes others (``import``s their modules, then asks for them here while its own module
    is being imported) gets them without a circular import."""
    if name in _COMPOSED:
        return _COMPOSED[name]
    if name not in _REGISTRY:
        _load_all()
    for matches, make in _COMPOSERS:
        if name not in _REGISTRY and matches(name):
            t = make(name)
            _COMPOSED[name] = _COMPOSED[t.name] = t
            return t
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
        composed = [t for t in techniques if t not in _REGISTRY]
        owner = [t for t in composed if key in {p.name for p in get(t).params}] or \
            [t for t in composed if any(p.name.startswith(key.split(".", 1)[0] + ".") for p in get(t).params)]
        if len(owner) == 1:     # LIGHT.PARAM of a technique per light (an unknown PARAM: the error lists them)
            out[owner[0]][key] = get(owner[0]).param(key).parse(val, owner[0])
            continue
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
