"""The typed result of one comparison: what ``compare`` and ``ingest`` produce and a report renders.

A :class:`Run` holds the numbers (scene, resolution, the reference's statistics, per technique its
parameters, timings, metrics pooled and per light, stats and error bands) and, in
:class:`RunImages`, the images (numpy, H×W or H×W×C, float64). Each type checks its own fields
when it is made and names the bad key in the message (``run.techniques.pcf.metrics.rmse: expected
a number``), so a report never meets a malformed run and nothing is written for one.

Read access by key is the shape of ``metrics.json``: every type is a read-only mapping of its
fields (``run["techniques"]["pcf"]["metrics"]["rmse"]`` is ``run.techniques["pcf"].metrics["rmse"]``),
with the optional fields that are unset left out and a run's ``extras`` (machine, frame, preset,
gate, ingest, command, …) beside its fields. :meth:`Run.from_mapping` makes a run from that shape,
as a user or a test writes it; the report accepts either.

>>> import numpy as np
>>> z, s = np.zeros((2, 2)), np.full((2, 2, 3), .5)
>>> run = Run.from_mapping({"scene": "s", "resolution": [2, 2], "reference": {"spp": 16, "max_std_error": .01},
...     "lights": ["key"], "techniques": {"hard": {"params": {}, "time_s": .002, "metrics": {"rmse": .1},
...     "per_light": {"key": {"rmse": .1}}}},
...     "images": {"truth": {"shaded": s, "vis": {"key": z}}, "techniques": {"hard": {"shaded": s, "vis": {"key": z}}}},
...     "machine": {"cpu": "x"}})
>>> run.techniques["hard"].metrics["rmse"], run["machine"]["cpu"], run.images.truth.vis["key"].dtype
(0.1, 'x', dtype('float64'))
>>> Run.from_mapping({**run, "lights": ["key", "key"]})
Traceback (most recent call last):
...
shadowlab.errors.InputError: run.lights: light names must be unique, got ['key', 'key']
"""  # noqa: E501

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .jsonable import to_jsonable

__all__ = ["Run", "Reference", "TechniqueRun", "Images", "RunImages", "PANEL_CHANNELS"]

#: the channels (0: H×W) of a panel's images by the panel's kind (``Technique.panels``: a family's
#: own report rows, whose images ``Technique.report_images`` builds from its AOVs)
PANEL_CHANNELS = {"colour": (3,), "log2_ratio": (0,), "levels": (0,), "excess_levels": (0,)}


# --------------------------------------------------------------------------------------------
# field checks


def _number(v, key: str, allow_none: bool = True, finite: bool = False) -> float | None:
    if v is None and allow_none:
        return None
    if isinstance(v, np.ndarray) and v.ndim == 0:
        v = v.item()
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise InputError(f"{key}: expected a number, got {type(v).__name__} {v!r:.60}")
    v = float(v)
    if finite and not math.isfinite(v):
        raise InputError(f"{key}: expected a finite number, got {v}")
    return v


def _mapping(d, key: str) -> Mapping:
    if not isinstance(d, Mapping):
        raise InputError(f"{key}: expected a dict, got {type(d).__name__}")
    return d


def _get(d: Mapping, name: str, where: str):
    if name not in d:
        raise InputError(f"{where}: the key {name!r} is missing (needed: {where}.{name})")
    return d[name]


def _metrics(d, key: str) -> dict:
    out = {}
    for m, v in _mapping(d, key).items():
        if not isinstance(m, str):
            raise InputError(f"{key}: metric name {m!r} is not a string")
        out[m] = _number(v, f"{key}.{m}")
    return out


def _image(a, key: str, hw: tuple[int, int], channels: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(a)
    except Exception as e:  # e.g. a Dr.Jit tensor that fails to convert
        raise InputError(f"{key}: cannot be converted to a numpy array ({e})") from None
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{key}: expected a numeric image, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    ok_shapes = [hw if c == 0 else (*hw, c) for c in channels]
    if arr.shape not in ok_shapes:
        want = " or ".join("×".join(map(str, s)) for s in ok_shapes)
        raise InputError(f"{key}: image shape {arr.shape} does not match the run resolution; expected {want}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise InputError(f"{key}: image contains {int(bad.sum())} NaN or inf values; fix the renderer output first")
    return arr


def _panels(panels, where: str) -> tuple:
    panels = panels or ()
    if not isinstance(panels, (list, tuple)):
        raise InputError(f"{where}.panels: expected a list of panels, got {type(panels).__name__}")
    for i, pn in enumerate(panels):
        if not all(hasattr(pn, a) for a in ("kind", "title", "images", "alt", "note", "legend")):
            raise InputError(f"{where}.panels[{i}]: expected a Panel (kind, title, images, alt, note, legend)")
        if pn.kind not in PANEL_CHANNELS:
            raise InputError(f"{where}.panels[{i}].kind: {pn.kind!r} is not one of {', '.join(PANEL_CHANNELS)}")
    return tuple(panels)


# --------------------------------------------------------------------------------------------
# the types


class _Record(Mapping):
    """Read-only key access to a dataclass's fields, as ``metrics.json`` names them; optional
    fields that are unset are left out."""

    def as_dict(self) -> dict:
        """The mapping's keys and values, one level deep (nested records stay records)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if not (f.metadata.get("optional") and getattr(self, f.name) is None)}

    def __getitem__(self, key):
        return self.as_dict()[key]

    def __iter__(self):
        return iter(self.as_dict())

    def __len__(self) -> int:
        return len(self.as_dict())


def _optional():
    return field(default=None, metadata={"optional": True})


@dataclass(frozen=True, eq=False)
class Reference(_Record):
    """The truth a run was measured against: mean shadow rays per pixel (``spp``, the mean over
    the lights of rays per pixel, fractional because the truth adds rays where its standard error
    is above target) and the largest standard error of a pixel; ``details``: the rest (rays per
    light, shadow rays, seed, supersampling, store path)."""
    spp: float
    max_std_error: float
    details: Mapping = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "spp", _number(self.spp, "run.reference.spp", allow_none=False, finite=True))
        object.__setattr__(self, "max_std_error",
                           _number(self.max_std_error, "run.reference.max_std_error", allow_none=False))
        object.__setattr__(self, "details", dict(_mapping(self.details, "run.reference")))

    def as_dict(self) -> dict:
        return {"spp": self.spp, "max_std_error": self.max_std_error, **self.details}

    @classmethod
    def from_mapping(cls, d) -> Reference:
        d = _mapping(d, "run.reference")
        return cls(_get(d, "spp", "run.reference"), _get(d, "max_std_error", "run.reference"),
                   {k: v for k, v in d.items() if k not in ("spp", "max_std_error")})


@dataclass(frozen=True, eq=False)
class TechniqueRun(_Record):
    """One technique's numbers: the parameter values it ran with, its warm (``time_s``) and first
    (``first_run_s``) run times in seconds, its metrics pooled over lights and per light, its
    stats (maps, cascades, tiles, …) and its visibility error by distance band and by label."""
    params: Mapping
    time_s: float | None
    metrics: Mapping
    per_light: Mapping
    first_run_s: float | None = _optional()
    stats: Mapping | None = _optional()
    bands: Mapping | None = _optional()
    name: str = field(default="", repr=False, metadata={"optional": True})

    def __post_init__(self):
        where = f"run.techniques.{self.name}"
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"run.techniques: technique name {self.name!r} is not a non-empty string")
        object.__setattr__(self, "params", _mapping(self.params, f"{where}.params"))
        object.__setattr__(self, "time_s", _number(self.time_s, f"{where}.time_s"))
        object.__setattr__(self, "first_run_s", _number(self.first_run_s, f"{where}.first_run_s"))
        object.__setattr__(self, "metrics", _metrics(self.metrics, f"{where}.metrics"))
        per_light = _mapping(self.per_light, f"{where}.per_light")
        object.__setattr__(self, "per_light", {ln: _metrics(d, f"{where}.per_light.{ln}")
                                               for ln, d in per_light.items()})

    def as_dict(self) -> dict:
        v = super().as_dict()
        v.pop("name", None)
        return v

    @classmethod
    def from_mapping(cls, name: str, d) -> TechniqueRun:
        where = f"run.techniques.{name}"
        d = _mapping(d, where)
        return cls(_get(d, "params", where), _get(d, "time_s", where), _get(d, "metrics", where),
                   _get(d, "per_light", where), d.get("first_run_s"), d.get("stats"), d.get("bands"), name=name)


@dataclass(frozen=True, eq=False)
class Images(_Record):
    """One side's images: the shaded image (H×W×3, H×W or H×W×1), the visibility per light and,
    for a technique whose family declares report panels, those panels and, per image key of a
    panel, {light: image} (``extra``; see :data:`PANEL_CHANNELS`)."""
    shaded: np.ndarray
    vis: Mapping
    panels: tuple = ()
    extra: Mapping = field(default_factory=dict)

    def as_dict(self) -> dict:
        v = {"shaded": self.shaded, "vis": self.vis, **self.extra}
        if self.panels:
            v["panels"] = self.panels
        return v

    @classmethod
    def checked(cls, d, where: str, hw: tuple[int, int], lights) -> Images:
        """The images of mapping ``d`` (at ``where``) as float64 arrays of shape ``hw``, one
        visibility image per light of ``lights``."""
        d = _mapping(d, where)
        shaded = _image(_get(d, "shaded", where), f"{where}.shaded", hw, (3, 0, 1))
        vis_d = _mapping(_get(d, "vis", where), f"{where}.vis")
        extra = [k for k in vis_d if k not in lights]
        if extra:
            raise InputError(f"{where}.vis.{extra[0]}: {extra[0]!r} is not in run.lights {list(lights)}")
        vis = {ln: _image(_get(vis_d, ln, f"{where}.vis"), f"{where}.vis.{ln}", hw, (0, 1, 3)) for ln in lights}
        panels = _panels(d.get("panels"), where)
        more = {}
        for pn in panels:
            for key in pn.keys:
                if key in d:
                    a = _mapping(d[key], f"{where}.{key}")
                    more[key] = {ln: _image(a[ln], f"{where}.{key}.{ln}", hw, PANEL_CHANNELS[pn.kind])
                                 for ln in lights if ln in a}
        return cls(shaded, vis, panels, more)


@dataclass(frozen=True, eq=False)
class RunImages(_Record):
    """The images of a run: the truth's, each technique's, Mitsuba's own ``mi.render`` (optional)
    and the pixels on a light the camera sees (``emitter``, optional, boolean H×W)."""
    truth: Images
    techniques: Mapping
    mitsuba: np.ndarray | None = _optional()
    emitter: np.ndarray | None = _optional()

    @classmethod
    def checked(cls, d, hw: tuple[int, int], lights, techniques) -> RunImages:
        d = _mapping(d, "run.images")
        timgs = _mapping(_get(d, "techniques", "run.images"), "run.images.techniques")
        for name in timgs:
            if name not in techniques:
                raise InputError(f"run.images.techniques.{name}: there is no run.techniques.{name} entry for it")
        mts, em = d.get("mitsuba"), d.get("emitter")
        return cls(
            Images.checked(_get(d, "truth", "run.images"), "run.images.truth", hw, lights),
            {n: Images.checked(_get(timgs, n, "run.images.techniques"), f"run.images.techniques.{n}", hw, lights)
             for n in techniques},
            None if mts is None else _image(mts, "run.images.mitsuba", hw, (3, 0, 1)),
            None if em is None else _image(em, "run.images.emitter", hw, (0,)) > 0.5)


#: the keys of a run that are its fields; any other key is an extra
_RUN_FIELDS = ("scene", "resolution", "reference", "lights", "techniques", "images", "light_info")


@dataclass(frozen=True, eq=False)
class Run(_Record):
    """One comparison of techniques with the truth on one scene (and frame): see the module.

    ``extras``: JSON values the run carries beside its fields (``machine``, ``frame``, ``preset``,
    ``gate``, ``ingest``, ``command``, …), written to metrics.json and listed by the report."""
    scene: str
    resolution: tuple
    reference: Reference
    lights: tuple
    techniques: Mapping
    images: RunImages | None = _optional()
    light_info: Mapping | None = _optional()
    extras: Mapping = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.scene, str) or not self.scene:
            raise InputError(f"run.scene: expected a non-empty string, got {self.scene!r}")
        res = self.resolution
        try:
            res = list(res)
        except TypeError:
            raise InputError(f"run.resolution: expected [W, H], got {res!r}") from None
        if len(res) != 2 or not all(isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_)) and x > 0
                                    for x in res):
            raise InputError(f"run.resolution: expected [W, H] with positive integers, got {res!r}")
        object.__setattr__(self, "resolution", (int(res[0]), int(res[1])))
        lights = self.lights
        if not isinstance(lights, (list, tuple)) or not all(isinstance(x, str) and x for x in lights):
            raise InputError(f"run.lights: expected a list of light names, got {lights!r}")
        if len(set(lights)) != len(lights):
            raise InputError(f"run.lights: light names must be unique, got {list(lights)}")
        object.__setattr__(self, "lights", tuple(lights))
        if not isinstance(self.reference, Reference):
            raise InputError("run.reference: expected a Reference (Reference.from_mapping makes one from a dict)")
        techs = _mapping(self.techniques, "run.techniques")
        for name, t in techs.items():
            if not isinstance(t, TechniqueRun):
                raise InputError(f"run.techniques.{name}: expected a TechniqueRun")
            for ln in t.per_light:
                if ln not in lights:
                    raise InputError(f"run.techniques.{name}.per_light.{ln}: {ln!r} is not in run.lights "
                                     f"{list(lights)}")
        if self.light_info is not None:
            for ln, d in _mapping(self.light_info, "run.light_info").items():
                _mapping(d, f"run.light_info.{ln}")
        extras = dict(_mapping(self.extras, "run"))
        clash = [k for k in extras if k in _RUN_FIELDS or k == "extras"]
        if clash:
            raise InputError(f"run.{clash[0]}: an extra key may not be named like a field of the run")
        object.__setattr__(self, "extras", extras)
        self.to_json()  # every value that is not an image must be JSON-serialisable

    @property
    def hw(self) -> tuple[int, int]:
        """(H, W), the shape of the run's images."""
        return self.resolution[1], self.resolution[0]

    def as_dict(self) -> dict:
        v = super().as_dict()
        v.pop("extras")
        v["resolution"] = list(self.resolution)
        v["lights"] = list(self.lights)
        return {**v, **self.extras}

    def to_json(self) -> dict:
        """The run without its images, as plain JSON (what metrics.json holds)."""
        return to_jsonable({k: v for k, v in self.items() if k != "images"})

    @classmethod
    def from_mapping(cls, d, *, need_images: bool = True) -> Run:
        """A run from the shape of metrics.json (plus ``images`` when ``need_images``); a
        :class:`Run` is returned as it is. Raises ``InputError`` naming the bad key."""
        if isinstance(d, Run):
            if need_images and d.images is None:
                raise InputError("run: the key 'images' is missing (needed: run.images)")
            return d
        d = _mapping(d, "run")
        lights = _get(d, "lights", "run")
        techs = {n: TechniqueRun.from_mapping(n, t)
                 for n, t in _mapping(_get(d, "techniques", "run"), "run.techniques").items()}
        run = cls(_get(d, "scene", "run"), _get(d, "resolution", "run"),
                  Reference.from_mapping(_get(d, "reference", "run")), lights, techs, None, d.get("light_info"),
                  {k: v for k, v in d.items() if k not in _RUN_FIELDS})
        if not need_images:
            return run
        imgs = RunImages.checked(_get(d, "images", "run"), run.hw, run.lights, techs)
        return dataclasses.replace(run, images=imgs)
