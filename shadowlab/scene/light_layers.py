"""Light layers: the lit volume of each light, the graph of intersecting volumes and its greedy
colouring [Tamás 2015, §5] (the layers of ``ssss``).

Lights whose lit volumes do not intersect cannot cast overlapping shadows, so their shadows can
share one screen-space layer (one bit, or one 8-bit channel, per pixel) and one blur. The lit
volume of a light (:func:`lit_volume`):

* a point light with a ``range`` R: the ball of radius R about its position (the range window
  of ``render/shading.py`` is 0 outside it, measured from the light's centre);
* a spot light with a range: the cone ∩ that ball; a spot with a radius > 0 lights the whole half
  space in front of its disk (Mitsuba has no area spot, README "Scene format"), so its cone is
  taken as the hemisphere (half-angle 90°). The graph uses the cone sector's bounding sphere
  (conservative: an edge may join two lights whose sectors miss each other, never the reverse):
  half-angle θ ≤ 45°: centre apex + R/(2 cos θ)·axis, radius R/(2 cos θ) (through the apex and the
  cap's rim); θ > 45°: centre apex + R cos θ·axis, radius R sin θ (the rim's circle; θ = 90° gives
  the ball);
* a directional light (the sun) or a light without a range: everything.

Graph: a vertex per light, an edge where two volumes may intersect (:func:`intersects`: bounding
spheres closer than the sum of their radii; "everything" meets every volume). Colouring
(:func:`colour`), as [Tamás 2015, §5]: every directional light gets a layer of its own first;
the others are taken in ascending order of degree (ties in the scene's order) and each gets the
smallest layer that none of its neighbours has. Greedy colouring needs at most max degree + 1
layers, and ascending degree often needs far fewer (the document's example: a light of degree 5,
so up to 6 layers, coloured with 3).

A bound k on the layers (k-colouring, ``ssss.max_layers``; [Tamás 2015, §5] bounds the shadow
filtering's cost by it and asks artists to keep within it): a light whose smallest free layer is
≥ k does not fit. It then **shares the least-conflicting layer**: of the non-sun layers < k, the
one holding the fewest of its neighbours (ties: the lowest index). Each such shared neighbour is
a *conflict* (``Layering.conflicts``, an edge inside a layer); where two conflicting lights both
light a point, the layer holds the product of their hard visibilities (for binary layers: a pixel
is lit only if lit by both), so one light's shadow darkens the other's light there. k must be at
least the number of suns plus 1 (one layer for the other lights) and at most the number of lights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import InputError

EVERYTHING = math.inf  # the radius of the lit volume of a sun or a light without a range


@dataclass(frozen=True)
class LitVolume:
    """A light's lit volume: ``bound`` (centre, radius) encloses it (radius inf = everything);
    ``apex``, ``axis``, ``cos_half`` and ``reach`` give the exact shape for point tests (a ball
    of radius ``reach`` about ``apex``, cut to the cone of half-angle acos(``cos_half``) about
    ``axis``; ``cos_half`` −1 = no cone)."""

    name: str
    sun: bool
    center: tuple
    radius: float
    apex: tuple = (0.0, 0.0, 0.0)
    axis: tuple = (0.0, 0.0, 1.0)
    cos_half: float = -1.0
    reach: float = EVERYTHING

    @property
    def everything(self) -> bool:
        return math.isinf(self.radius)


def _unit(v):
    n = math.sqrt(sum(x * x for x in v))
    return tuple(x / n for x in v)


def cone_bound(apex, axis, half_angle_deg: float, reach: float):
    """(centre, radius) of the smallest sphere around the cone sector of half-angle θ and radius
    ``reach`` (module docstring)."""
    th = math.radians(half_angle_deg)
    a = _unit(axis)
    if th <= math.pi / 4:
        r = reach / (2.0 * math.cos(th))
        return tuple(p + r * x for p, x in zip(apex, a)), r
    return tuple(p + reach * math.cos(th) * x for p, x in zip(apex, a)), reach * math.sin(th)


def lit_volume(light) -> LitVolume:
    """The lit volume of a LightSpec (module docstring)."""
    rng = getattr(light, "range", None)
    if light.kind == "directional":
        return LitVolume(light.name, True, (0.0, 0.0, 0.0), EVERYTHING)
    if rng is None:
        return LitVolume(light.name, False, tuple(light.position), EVERYTHING)
    if light.kind == "spot":
        axis = _unit([t - p for t, p in zip(light.target, light.position)])
        half = light.angle if light.radius == 0 else 90.0
        c, r = cone_bound(light.position, axis, half, rng)
        return LitVolume(light.name, False, c, r, tuple(light.position), axis, math.cos(math.radians(half)), rng)
    return LitVolume(light.name, False, tuple(light.position), rng, tuple(light.position), reach=rng)


def intersects(a: LitVolume, b: LitVolume) -> bool:
    """Whether the volumes may intersect (conservative: bounding spheres)."""
    if a.everything or b.everything:
        return True
    d = math.sqrt(sum((x - y) ** 2 for x, y in zip(a.center, b.center)))
    return d < a.radius + b.radius


def graph(volumes: list) -> list:
    """Adjacency sets (indices) of the lit volumes' intersection graph."""
    n = len(volumes)
    adj = [set() for _ in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if intersects(volumes[i], volumes[j]):
                adj[i].add(j)
                adj[j].add(i)
    return adj


@dataclass
class Layering:
    """The colouring: ``layer[name]`` per light, ``layers_used``, the graph's ``max_degree``,
    ``conflicts`` (edges inside a layer; 0 unless a bound k was too small), ``overflow`` (the
    lights that shared a layer with a neighbour), ``order`` (the greedy order, light names)."""

    layer: dict
    layers_used: int
    max_degree: int
    conflicts: int = 0
    overflow: list = field(default_factory=list)
    order: list = field(default_factory=list)
    edges: int = 0

    def members(self, layer: int) -> list:
        return [n for n, l in self.layer.items() if l == layer]


def colour(lights, max_layers: int | None = None, key: str = "max_layers") -> Layering:
    """Greedy colouring of ``lights`` (LightSpecs or LitVolumes) by ascending degree, suns on layers
    of their own, at most ``max_layers`` layers (None or 0: unbounded); see the module docstring.
    ``key`` names the bound in errors (exit 2)."""
    vols = [l if isinstance(l, LitVolume) else lit_volume(l) for l in lights]
    n = len(vols)
    adj = graph(vols)
    deg = [len(a) for a in adj]
    suns = [i for i in range(n) if vols[i].sun]
    rest = [i for i in range(n) if not vols[i].sun]
    k = int(max_layers) if max_layers else None
    if k is not None:
        if k > n:
            raise InputError(f"{key}={k}: more layers than the scene's {n} light{'s' * (n != 1)}; "
                             f"allowed 1…{n} (0 = unbounded)")
        need = len(suns) + (1 if rest else 0)
        if k < need:
            raise InputError(f"{key}={k}: too few layers: each of the {len(suns)} directional light(s) has a "
                             f"layer of its own and the other lights need one more; allowed {need}…{n} "
                             f"(0 = unbounded)")
    col = [-1] * n
    for j, i in enumerate(suns):
        col[i] = j
    first = len(suns)
    order = sorted(rest, key=lambda i: (deg[i], i))
    conflicts, overflow = 0, []
    for i in order:
        used = {col[j] for j in adj[i] if col[j] >= 0}
        c = first
        while c in used:
            c += 1
        if k is not None and c >= k:
            counts = [sum(1 for j in adj[i] if col[j] == L) for L in range(first, k)]
            best = min(range(len(counts)), key=lambda t: (counts[t], t))
            c = first + best
            conflicts += counts[best]
            overflow.append(vols[i].name)
        col[i] = c
    used_layers = len(set(col))
    return Layering(layer={vols[i].name: col[i] for i in range(n)}, layers_used=used_layers,
                    max_degree=max(deg) if deg else 0, conflicts=conflicts, overflow=overflow,
                    order=[vols[i].name for i in suns + order], edges=sum(deg) // 2)
