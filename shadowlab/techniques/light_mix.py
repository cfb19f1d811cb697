"""A technique per light: ``sun=csm,softbox=pcss`` renders each light with its own technique.

Engines mix techniques by light: cascades for the sun, PCSS or a cube map for local lights
[Engel 2006, §1; Dimitrov 2007]. A mix is a technique like any other to compare, fit, sweep, gate
and the report: :func:`~shadowlab.techniques.base.get` makes one from its name, ``LIGHT=TECHNIQUE``
pairs separated by commas, with ``*=TECHNIQUE`` for every light not named. Each light's
parameters are its technique's, named ``LIGHT.PARAM`` (``softbox.light_scale``), so a fit finds
each light's own values. The base class's loop over the lights is where the mix happens: each
light's technique renders a frame that shows that light only
(:meth:`~shadowlab.render.frame.FrameContext.for_lights`), sharing the G-buffer and the light
views.

>>> mix = parse("sun=csm, *=pcss")
>>> mix.assignment(["sun", "softbox", "bulb"])
{'sun': 'csm', 'softbox': 'pcss', 'bulb': 'pcss'}
>>> parse("sun=csm,sun=pcss")
Traceback (most recent call last):
...
shadowlab.errors.InputError: technique per light 'sun=csm,sun=pcss': light 'sun' is given twice
"""

from __future__ import annotations

import dataclasses

from ..errors import InputError
import drjit as dr
import mitsuba as mi

from .base import LightResult, Pooled, RenderContext, Technique, get, register_composer

__all__ = ["LightMix", "parse", "is_mix"]

_FORM = "LIGHT=TECHNIQUE pairs separated by commas, e.g. sun=csm,softbox=pcss (*=TECHNIQUE for the other lights)"


def is_mix(name: str) -> bool:
    """Whether ``name`` is a technique per light (it pairs lights with techniques)."""
    return "=" in str(name)


def parse(name: str) -> LightMix:
    """The :class:`LightMix` of a name such as ``sun=csm,softbox=pcss`` (InputError naming the problem)."""
    pairs, rest = {}, None
    for item in str(name).split(","):
        item = item.strip()
        if not item:
            continue
        light, eq, tech = (x.strip() for x in item.partition("="))
        if not eq or not light or not tech:
            raise InputError(f"technique per light {name!r}: {item!r} is not LIGHT=TECHNIQUE; expected {_FORM}")
        if is_mix(tech) or "," in tech:
            raise InputError(f"technique per light {name!r}: {item!r} names a technique per light inside one")
        get(tech)   # unknown technique: InputError listing the registered ones
        if light == "*":
            if rest is not None:
                raise InputError(f"technique per light {name!r}: '*' is given twice")
            rest = tech
        elif light in pairs:
            raise InputError(f"technique per light {name!r}: light {light!r} is given twice")
        else:
            pairs[light] = tech
    if not pairs and rest is None:
        raise InputError(f"technique per light {name!r}: no pair; expected {_FORM}")
    return LightMix(pairs, rest)


class LightMix(Technique):
    """Each light rendered by its own technique; parameters ``LIGHT.PARAM``.

    The parameters are declared for the lights the name gives; with ``*=TECHNIQUE`` the other
    lights of a scene use that technique's defaults and can be set as ``*.PARAM``."""

    source = "per light: each light's own technique and source"
    summary = "a technique per light, as engines mix them (cascades for the sun, PCSS for local lights)"

    def __init__(self, pairs: dict, rest: str | None):
        self.pairs, self.rest = dict(pairs), rest
        items = [f"{l}={t}" for l, t in self.pairs.items()] + ([f"*={rest}"] if rest else [])
        self.name = ",".join(items)
        self.title = "; ".join(f"{l}: {get(t).title or t}" for l, t in self.pairs.items()) + \
            (f"; other lights: {get(rest).title or rest}" if rest else "")
        self.params = tuple(dataclasses.replace(p, name=f"{light}.{p.name}", doc=f"{light}: {p.doc}".rstrip(": "))
                            for light, t in self.slots() for p in get(t).params)
        subs = [get(t) for _, t in self.slots()]
        self.panels = tuple({p.title: p for s in subs for p in s.panels}.values())
        self.band_aovs = tuple(dict.fromkeys(k for s in subs for k in s.band_aovs))
        losses = {s.fit_loss for s in subs}
        self.fit_loss = losses.pop() if len(losses) == 1 else Technique.fit_loss

    def slots(self) -> list[tuple[str, str]]:
        """(light or ``*``, technique) in the order of the name."""
        return list(self.pairs.items()) + ([("*", self.rest)] if self.rest else [])

    def assignment(self, lights) -> dict:
        """{light: technique} for the light names ``lights``; a light not named takes ``*``'s."""
        return {ln: self.pairs.get(ln, self.rest) for ln in lights}

    def _values_of(self, light: str, values: dict) -> dict:
        slot = light if light in self.pairs else "*"
        n = len(slot) + 1
        return {k[n:]: v for k, v in values.items() if k[:n] == f"{slot}."}

    def unsupported(self, spec) -> str | None:
        names = [l.name for l in spec.lights]
        unknown = [l for l in self.pairs if l not in names]
        if unknown:
            return (f"{self.name}: scene {spec.name!r} has no light {unknown[0]!r}; its lights: {', '.join(names)}")
        missing = [ln for ln, t in self.assignment(names).items() if t is None]
        if missing:
            return (f"{self.name}: no technique for light(s) {', '.join(missing)}; name them, or add *=TECHNIQUE "
                    "for every light not named")
        for ln, t in self.assignment(names).items():
            why = get(t).unsupported(dataclasses.replace(spec, lights=tuple(l for l in spec.lights if l.name == ln)))
            if why:
                return f"{self.name}: light {ln!r}: {why}"
        return None

    def fit_params(self, values: dict) -> tuple:
        return tuple(f"{slot}.{p}" for slot, t in self.slots()
                     for p in get(t).fit_params(self._values_of(slot, values)))

    def prepare(self, frame, values, ctx) -> None:
        """Each light's technique prepares on a frame showing that light only; the lights are then
        rendered by the base loop, evaluated together (no light waits for another's kernel)."""
        ctx.subs = {}
        for ln, t in self.assignment([l.name for l in frame.lights]).items():
            tech, sub = get(t), frame.for_lights([ln])
            vals = tech.resolve(self._values_of(ln, values))
            why = tech.unsupported(sub.light_spec)
            if why:
                raise InputError(why)
            sctx = RenderContext(tech, vals)
            tech.prepare(sub, vals, sctx)
            ctx.subs[ln] = (tech, sub, vals, sctx)

    def render_light(self, frame, light, values, ctx) -> LightResult:
        tech, sub, vals, sctx = ctx.subs[light.name]
        return tech.render_light(sub, light, vals, sctx)

    def light_stats(self, frame, light, values, ctx, result) -> dict:
        """The light's technique's stats; a mean over points stays that light's mean (the lights'
        techniques differ, so nothing is pooled over them), and ``technique`` names it."""
        tech, sub, vals, sctx = ctx.subs[light.name]
        st = {**result.stats, **tech.light_stats(sub, light, vals, sctx, result)}
        return {**{k: mean_of(s) if isinstance(s, Pooled) else s for k, s in st.items()}, "technique": tech.name}

    def report_images(self, frame, result, mask, vis: dict) -> dict:
        out = {}
        for ln, t in self.assignment(list(vis)).items():
            tech = get(t)
            if not tech.panels:
                continue
            pre = f"{ln}."
            sub = dataclasses.replace(result, aovs={k: a for k, a in result.aovs.items() if k.startswith(pre)},
                                      visibility={ln: result.visibility[ln]}, technique=tech)
            for key, per_light in tech.report_images(frame, sub, mask, {ln: vis[ln]}).items():
                out.setdefault(key, {}).update(per_light)
        return out


def mean_of(p: Pooled):
    """:meth:`Pooled.mean` of a value whose numbers may still be on the device (Dr.Jit, width 1)."""
    if p.value is not None:
        return p.value
    if isinstance(p.total, dr.ArrayBase) or isinstance(p.count, dr.ArrayBase):
        cnt = mi.Float64(p.count)
        return dr.select(cnt > 0, mi.Float64(p.total) / dr.maximum(cnt, 1.0), 0.0)
    return p.total / p.count if p.count else 0.0


register_composer(is_mix, parse)
