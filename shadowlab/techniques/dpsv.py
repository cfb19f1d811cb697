"""Shadow map fused with deep partitioned shadow volumes: ``dpsv``, ``sm_dpsv``, ``sm_dpsv_soft``
[Wang 2022, §1.2–1.4], after [Gerhards 2015] and [Mora 2016].

``dpsv``: each shading point's visibility of the light's centre from the light's TOP tree
(:mod:`shadowlab.render.top_tree`: Algorithm 1 builds it from every triangle of the scene,
Algorithm 2 queries it with a per-point stack). It is exact up to the tolerance of a Mitsuba
shadow ray, which it shares. The "deep" part (§1, [Mora 2016]; ``deep``): every node keeps a lower
bound of the light distance (light-space depth for a directional light) of the triangles below
it, and a query skips the nodes whose triangles all lie beyond the point: they cannot shadow it.

``sm_dpsv`` (§1.3, fused hard shadows). The point is projected into ``hard``'s shadow map
(every bias of ``hard``, :data:`~shadowlab.techniques.shadow_map.BIAS_PARAMS`). Its depth test
is repeated one texel away in each of the four directions, (u ± 1, v) and (u, v ± 1).

* Where any of the four disagrees with the centre's result, the point is a *shadow-edge point*
  and takes the tree's visibility.
* Elsewhere the shadow map's result stands.

Only edge points enter the tree query's loop. A point the classifier misses keeps the shadow
map's (aliased) answer: all four neighbours agree with it, yet the true visibility differs
(:func:`edge_misses` counts them).

``sm_dpsv_soft`` (§1.4, soft shadows from the visibility map):

1. The *visibility map* is the fused hard visibility of every G-buffer point: a screen-space
   image, as the paper's shading-point visibility map.
2. A *sparse blocker search* looks in the shadow map over PCSS's search square,
   w_search = (z̃ − z_near)/z̃ · w_light (texels; ``pcss``'s formula and units). Taps lie on a
   grid with spacing Δ texels: Δ = ``interval`` (``interval_mode`` = ``constant``) or
   Δ = ``interval_k``·z̃/z_far (``depth``: coarser far from the light). The grid has at most
   ``search_taps`` taps per axis. Each tap is ``hard``'s nearest-texel test against the
   receiver's tangent plane ([Isidoro 2006], as ``pcss``'s ``receiver_plane``). The blocker depth
   z_avg is the mean depth of the taps that test "shadowed".
3. *Penumbra*: w_p = (z̃ − z_avg)/z_avg · w_light, world units at the receiver. For a directional
   light it is (z̃ − z_avg)·tan w_light. w_light = ``light_scale`` × the light's size, the shared
   convention; a point light's size is 0, so its shadow stays hard unless ``light_scale`` and a
   radius give it one.
4. *Filtering* the visibility map over a square at the receiver. Its full width in pixels of the
   map (``filter_size``, :func:`filter_pixels`):

   * ``world`` (default): w_p / s, s the world size of one pixel at the receiver's view depth. The
     kernel is fixed in world units, so a camera move changes the pixel count but not the penumbra.
   * ``light_distance``, the source's: [Wang 2022, §1.4] divides the filter size by the receiver's
     distance to the light "so that moving the camera does not change it". The formula itself is an
     image the text lacks; shadowlab reads it as PCSS's projection of the penumbra into the light's
     map: w_p / (2·z̃·tan θ) × H, the penumbra as a fraction of the map's width at the receiver's
     light-space depth z̃ (θ the map's half angle; an orthographic map: w_p over its width), times
     the visibility map's height H (the paper's frame and map are both 1024²). No camera quantity
     enters, so the kernel keeps its pixels when the camera moves and its world width changes.

   ``world`` is the default: against the committed truths of the 14 built-in scenes the family
   takes, its penumbra RMSE is lower in 9 and higher in 3 (in the other 2 neither filters; the
   family's notes give the table). Taps
   (``filter_samples``, ``pcss``'s centred Hammersley set) are rejected: off any surface, or
   farther than ``depth_reject`` × the filter's world width from the receiver's tangent plane (the
   shadow of one surface is not spread onto another). The accepted taps are averaged, box weights.
   A point without blockers, or whose kernel is under one pixel, keeps its fused hard visibility.

Light kinds. ``dpsv`` and ``sm_dpsv`` claim pixel-exact hard shadows. That exists only for a light
with one point of emission: point and spot lights, and directional lights as a light at infinity.
An area light's shadow is soft, so they refuse rect, disk and sphere lights. ``sm_dpsv_soft``
takes every kind: its tree and map are those of the light's centre, as ``pcss``'s map, and its
penumbra comes from the light's size.

Scenes. The tree holds every triangle of every shape. Rectangles, cubes and PLY/OBJ meshes are
exactly the triangles Mitsuba intersects. Curved primitives (sphere, disk, cylinder) are inscribed
with ``segments`` segments: their shadows are the tessellation's, which differs from Mitsuba's
analytic surface by up to the sagitta r·(1 − cos π/s). Alpha-tested casters are refused: the
tree has no texture lookups. SDF-only scenes have no triangles and are refused too.

Stats: the tree's ``nodes``, ``depth``, ``triangles`` and ``build_seconds`` per light;
``nodes_per_query`` (mean nodes visited per tree query); for the fused techniques
``edge_fraction`` (share of the active points that query the tree). AOVs: ``nodes_visited``,
``depth_visited`` (the deepest tree level a point's query reached), ``edge`` (fused), ``penumbra_width``,
``filter_pixels``, ``blocker_depth`` (soft).
"""

from __future__ import annotations


import drjit as dr
import mitsuba as mi

from ..render.top_tree import ORDERS, offset_point, query
from .base import (LightResult, Param, Pooled, Technique, device_count, device_total, light_scale_param,
                   param_table_markdown, register, scaled_size)
from .blocker_search import (PCF_COUNTS, blocked, pattern_arrays, pcf_pattern, penumbra_width, scene_light_size,
                             search_width)
from .shadow_map import (BIAS_PARAMS, ShadowMapTechnique, depth_test, map_entry, map_stats, receiver,
                         receiver_plane_gradient, texel_index, to_light)

SOURCE = "[Wang 2022, §1.2]"
SOFT_SOURCE = "[Wang 2022, §1.4]"
POINT_KINDS = ("point", "spot", "directional")
FILTER_SIZES = ("world", "light_distance")

TREE_PARAMS = (
    Param("segments", 64, "int", 3, 1024, "segments", False, source="[Wang 2022, §1.2]",
          doc="tessellation of curved primitives (sphere, disk, cylinder) into the tree's triangles; meshes, "
              "cubes and rectangles are exact"),
    Param("deep", True, "bool", source="[Mora 2016]",
          doc="skip a tree node whose subtree's triangles all lie farther from the light than the point (the "
              "light-space depth of deep partitioned shadow volumes); the visibility is the same, the nodes "
              "visited fewer"),
    Param("order", "random", "choice", choices=ORDERS, source="[Gerhards 2015]",
          doc="insertion order of Algorithm 1: random = a fixed permutation (shallow trees), light = nearest to "
              "the light first, scene = as the scene lists them; the visibility does not depend on it, the "
              "tree's depth and the nodes a query visits do"),
)

SOFT_PARAMS = (
    light_scale_param(SOFT_SOURCE, differentiable=False,
                      doc="w_light of the penumbra estimate (pcss's light size: rect √(w·h), disk/sphere √π·r, "
                          "directional √π/2·angular diameter)"),
    Param("interval_mode", "constant", "choice", choices=("constant", "depth"), source=SOFT_SOURCE,
          doc="blocker-search tap spacing: constant = `interval` texels; depth = interval_k·z̃/z_far texels"),
    Param("interval", 2.0, "float", 0.25, 64.0, "texels", False, source=SOFT_SOURCE,
          doc="tap spacing of the sparse blocker search when interval_mode = constant"),
    Param("interval_k", 4.0, "float", 0.25, 256.0, "texels", False, source=SOFT_SOURCE,
          doc="k of the depth-dependent spacing k·z̃/z_far (interval_mode = depth)"),
    Param("search_taps", 8, "int", 1, 32, "taps per axis", False, source=SOFT_SOURCE,
          doc="most taps per axis of the sparse search grid (the spacing widens to cover w_search)"),
    Param("filter_samples", 32, "choice", units="taps", choices=PCF_COUNTS, source=SOFT_SOURCE,
          doc="taps of the screen-space filter of the visibility map (centred Hammersley set, box weights)"),
    Param("depth_reject", 0.5, "float", 0.0, 10.0, "× filter width", False, source=SOFT_SOURCE,
          doc="a filter tap farther than this × the filter's width from the receiver's tangent plane is rejected"),
    Param("filter_size", "world", "choice", choices=FILTER_SIZES, source=SOFT_SOURCE,
          doc="the visibility map's filter width: world = w_p at the receiver (w_p / the pixel's world size); "
              "light_distance = the source's, w_p divided by the receiver's distance to the light, as a fraction "
              "of the light's map × the map's height in pixels"),
)


def _tree_stats(tree) -> dict:
    st = tree.stats()
    return {"tree_nodes": st["nodes"], "tree_depth": st["depth"], "tree_triangles": st["triangles"],
            "tree_dropped": st["dropped"], "tree_build_seconds": st["build_seconds"]}


def tree_visibility(frame, light, values, active):
    """(visibility, AOVs ``nodes_visited`` and ``depth_visited``, tree) of ``light`` at the G-buffer
    points where ``active``."""
    tree = frame.top_tree(light.name, int(values["segments"]), values["order"])
    gb = frame.gbuffer
    vis, visits, deepest = query(tree, offset_point(tree, gb.p, gb.ng), active, deep=bool(values["deep"]))
    return vis, {"nodes_visited": mi.Float(visits), "depth_visited": mi.Float(deepest)}, tree


def edge_classify(view, rec, bias):
    """(hard visibility at the point's texel, shadow-edge mask): the depth test one texel away in
    each of the four directions disagrees with the centre's [Wang 2022, §1.3]."""
    ix, iy = texel_index(rec["u"]), texel_index(rec["v"])
    h0 = depth_test(view, rec, ix, iy, bias)
    edge = mi.Bool(False)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        edge |= depth_test(view, rec, ix + dx, iy + dy, bias) != h0
    return h0, edge & rec["active"]


class _TreeFamily:
    """What every technique of the family shares: the scenes a TOP tree can hold."""

    source = "[Wang 2022]"

    def unsupported(self, spec) -> str | None:
        if not spec.shapes:
            return (f"{self.name}: the scene has no triangles (no [[shapes]]); a TOP tree is built from the scene's "
                    "triangles: add a mesh or a primitive shape")
        if spec.kind == "sdf":
            return (f"{self.name}: the scene has SDF-only objects ([[sdf]]) without triangles, which the TOP tree "
                    "would miss: use the SDF techniques (sdf_hard, sdf_quilez, ...) on it")
        if any(s.alpha_tested for s in spec.shapes):
            return (f"{self.name}: the scene has alpha-tested casters; a TOP tree holds whole triangles and cannot "
                    "look up their opacity: use hard, pcf or pcss")
        return None


class _Fused(_TreeFamily, ShadowMapTechnique):
    """The fused techniques: ``hard``'s map, the edge classifier and the tree at edge points."""

    def fused(self, frame, light, view, values, ctx):
        """The fused hard visibility (§1.3) and its parts."""
        rec = receiver(frame, view, ctx.bias)
        h0, edge = edge_classify(view, rec, ctx.bias)
        tv, tree_aovs, tree = tree_visibility(frame, light, values, edge)
        return rec, dr.select(edge, tv, h0), edge, tree_aovs, tree

    def light_stats(self, frame, light, values, ctx, result):
        """Edge points per active point and tree nodes per query, counted on the device (read with
        the render's other stats)."""
        edge = result.aovs["edge"] > 0.5
        return {"edge_fraction": Pooled(device_total(dr.select(edge & result.active, 1.0, 0.0)),
                                        device_count(result.active)),
                "nodes_per_query": Pooled(device_total(dr.select(edge, result.aovs["nodes_visited"], 0.0)),
                                          device_count(edge))}


def _point_only(name, spec):
    for l in spec.lights:
        if l.kind not in POINT_KINDS:
            return (f"{name}: light {l.name!r} is a {l.kind} (area) light; {name} gives pixel-exact hard shadows, "
                    "which exist only for lights with one point of emission (point, spot, directional): use "
                    "sm_dpsv_soft (tree and map of the light's centre, penumbra from its size) or pcss")
    return None


@register
class DPSV(_TreeFamily, Technique):
    """Visibility from the TOP tree alone (Algorithm 2 at every point)."""

    name = "dpsv"
    title = "Deep partitioned shadow volumes (TOP tree)"
    summary = "exact point-light visibility from the TOP tree of the scene's triangles (Algorithm 2, per-point stack)"
    params = TREE_PARAMS

    def unsupported(self, spec):
        return super().unsupported(spec) or _point_only(self.name, spec)

    def prepare(self, frame, values, ctx):
        frame.require_mitsuba_geometry()

    def render_light(self, frame, light, values, ctx):
        gb = frame.gbuffer
        vis, tree_aovs, tree = tree_visibility(frame, light, values, gb.valid)
        return LightResult(vis, tree_aovs, active=gb.valid, stats=_tree_stats(tree))

    def light_stats(self, frame, light, values, ctx, result):
        act = result.active.numpy()
        nv = result.aovs["nodes_visited"].numpy()
        return {"nodes_per_query": Pooled(float(nv[act].sum()), int(act.sum()))}


@register
class FusedDPSV(_Fused):
    """Shadow map everywhere but at shadow-edge points, which query the TOP tree (§1.3)."""

    name = "sm_dpsv"
    title = "Shadow map + DPSV at shadow edges (fused hard)"
    summary = ("hard's biased shadow map; points whose depth test changes one texel away query the TOP tree, "
               "so edges are exact")
    params = TREE_PARAMS + BIAS_PARAMS

    def unsupported(self, spec):
        return super().unsupported(spec) or _point_only(self.name, spec)

    def evaluate(self, frame, light, view, values, ctx):
        rec, vis, edge, tree_aovs, tree = self.fused(frame, light, view, values, ctx)
        return LightResult(vis, {"edge": dr.select(edge, 1.0, 0.0), **tree_aovs, "texel": rec["texel"]},
                           active=rec["active"],
                           stats={**map_stats(view), **_tree_stats(tree)}, maps=[map_entry(view)])


def _search_grid(view, rec, g, bias, w_search, spacing, n_max: int):
    """Sparse blocker search: (count, Σ z) of the shadowed taps of an n×n grid of spacing
    max(``spacing``, w_search/n_max) texels centred on the point (n = the taps that fit in w_search)."""
    step = dr.maximum(spacing, w_search / n_max)
    n = mi.UInt32(dr.clip(dr.floor(w_search / step) + 1.0, 1.0, float(n_max)))
    n = dr.select(rec["active"], n, 0)
    half = (mi.Float(n) - 1.0) * 0.5
    u, v, face = rec["u"], rec["v"], rec["face"]

    def body(k, cnt, zs):
        j, i = k % dr.maximum(n, 1), k // dr.maximum(n, 1)
        du, dv = (mi.Float(j) - half) * step, (mi.Float(i) - half) * step
        ix, iy = texel_index(u + du), texel_index(v + dv)
        hit = blocked(view, face, ix, iy, rec["dt"] + g[0] * du + g[1] * dv, bias)
        z = view.fetch("z", face, ix, iy)
        return k + 1, cnt + dr.select(hit, 1.0, 0.0), zs + dr.select(hit, z, 0.0)

    m = dr.width(u)
    _, cnt, zs = dr.while_loop((dr.zeros(mi.UInt32, m), dr.zeros(mi.Float, m), dr.zeros(mi.Float, m)),
                               lambda k, c, z: k < n * n, body, labels=("k", "count", "zsum"),
                               label="sm_dpsv_soft_search", max_iterations=n_max * n_max)
    return cnt, zs


def _filter_visibility(screen, vis_map, f, w_pen, reject, px, py, nt: int, run):
    """Box filter of the screen-space visibility map ``vis_map`` over the light-facing square of
    full width ``w_pen`` (world units) at each receiver: tap (a, b)·w_pen of the square
    perpendicular to the light direction ``f`` is slid along ``f`` onto the receiver's tangent
    plane, projected to the screen and read there (nearest pixel). A tap off any surface, or whose
    surface lies farther than ``reject`` from the tangent plane, is rejected."""
    p, nrm = screen.position, screen.normal
    side = dr.select(dr.abs(f.y) < 0.9, mi.Vector3f(0, 1, 0), mi.Vector3f(1, 0, 0))
    r = dr.normalize(dr.cross(side, f))
    u = dr.cross(f, r)
    nf = dr.dot(nrm, f)
    nf = dr.select(nf < 0.0, dr.minimum(nf, -0.2), dr.maximum(nf, 0.2))

    def body(k, acc, wsum):
        o = (r * dr.gather(mi.Float, px, k) + u * dr.gather(mi.Float, py, k)) * w_pen
        q = p + o - f * (dr.dot(nrm, o) / nf)
        sx, sy, _ = screen.project(q)
        idx = screen.index(mi.Int32(dr.floor(sx)), mi.Int32(dr.floor(sy)))
        qs = dr.gather(mi.Point3f, p, idx)
        ok = dr.gather(mi.Bool, screen.valid, idx) & (dr.abs(dr.dot(nrm, qs - p)) <= reject)
        return k + 1, acc + dr.select(ok, dr.gather(mi.Float, vis_map, idx), 0.0), wsum + dr.select(ok, 1.0, 0.0)

    m = dr.width(vis_map)
    _, acc, wsum = dr.while_loop((dr.zeros(mi.UInt32, m), dr.zeros(mi.Float, m), dr.zeros(mi.Float, m)),
                                 lambda k, a, w: run & (k < nt), body, labels=("k", "acc", "wsum"),
                                 label="sm_dpsv_soft_filter", max_iterations=nt)
    return dr.select(wsum > 0.0, acc / dr.maximum(wsum, 1.0), vis_map)


def filter_pixels(view, w_pen, zr, *, mode: str, pixel_world, height: int):
    """Full width in visibility-map pixels of the filter of a penumbra ``w_pen`` (world units) at a
    receiver of light-space depth ``zr``, whose pixel covers ``pixel_world`` world units.

    ``world``: w_pen / pixel_world. ``light_distance`` [Wang 2022, §1.4]: w_pen / (2·z̃·tan θ) × height,
    the penumbra divided by the distance to the light, in widths of the light's map at the receiver
    (an orthographic map: w_pen / its width), so a camera move changes no pixel count."""
    if mode == "world":
        return w_pen / dr.maximum(pixel_world, 1e-12)
    f0 = view.proj.faces[0]
    across = 2.0 * f0.scale if f0.ortho else 2.0 * f0.scale * dr.maximum(zr, f0.near)
    return w_pen / across * float(height)


@register
class FusedDPSVSoft(_Fused):
    """Soft shadows: PCSS-style sparse blocker search, then a world-sized filter of the fused hard
    visibility map (§1.4)."""

    name = "sm_dpsv_soft"
    title = "Shadow map + DPSV, filtered visibility map (soft)"
    summary = ("fused hard visibility (sm_dpsv) stored per shading point, penumbra from a sparse blocker search, "
               "filtered in screen space with a kernel of fixed world size")
    params = SOFT_PARAMS + TREE_PARAMS + BIAS_PARAMS

    def evaluate(self, frame, light, view, values, ctx):
        # everything the tree does not enter is traced first: the tree's build waits for the device (the
        # G-buffer's kernels still running), and the host traces this meanwhile instead of after it
        rec = receiver(frame, view, ctx.bias)
        h0, edge = edge_classify(view, rec, ctx.bias)
        w_light, w_val = scaled_size(values["light_scale"], scene_light_size(light))
        zr = rec["z"]
        for name in ("depth", "slope", "z"):  # upload before the symbolic loops record
            view.dr(name)
        g = receiver_plane_gradient(view, rec, rec["ng"])
        w_search = search_width(view, zr, w_light)
        if values["interval_mode"] == "constant":
            spacing = dr.opaque(mi.Float, float(values["interval"]))
        else:
            spacing = dr.opaque(mi.Float, float(values["interval_k"])) * zr / float(view.proj.faces[0].far)
        cnt, zsum = _search_grid(view, rec, g, ctx.bias, w_search, dr.maximum(spacing, 1e-3),
                                 int(values["search_taps"]))
        found = rec["active"] & (cnt > 0.0)
        z_avg = dr.select(found, zsum / dr.maximum(cnt, 1e-20), zr)
        w_pen = penumbra_width(view, zr, z_avg, w_light)
        screen = frame.screen
        pixel_world = 2.0 * screen.depth * frame.camera.tan_y / screen.height
        mode = values["filter_size"]
        w_px = filter_pixels(view, w_pen, zr, mode=mode, pixel_world=pixel_world, height=screen.height)
        w_filter = w_pen if mode == "world" else w_px * pixel_world
        run = found & (w_px >= 1.0)
        nt = int(values["filter_samples"])
        px, py = pattern_arrays(pcf_pattern(nt))
        reject = dr.opaque(mi.Float, float(values["depth_reject"])) * w_filter
        tv, tree_aovs, tree = tree_visibility(frame, light, values, edge)
        hard_vis = dr.select(edge, tv, h0)
        dr.eval(hard_vis)  # the visibility map: a stage boundary, read by the filter at other pixels
        vis = _filter_visibility(screen, hard_vis, to_light(view, frame.gbuffer.p), w_filter, reject, px, py, nt, run)
        aovs = {"edge": dr.select(edge, 1.0, 0.0), **tree_aovs, "texel": rec["texel"],
                "penumbra_width": dr.select(found, w_pen, 0.0), "filter_pixels": dr.select(run, w_px, 0.0),
                "blocker_depth": dr.select(found, z_avg, 0.0)}
        return LightResult(vis, aovs, active=rec["active"],
                           stats={**map_stats(view), **_tree_stats(tree), "light_size": w_val},
                           maps=[map_entry(view)])


__doc__ += ("\n\nParameters of ``sm_dpsv_soft`` (generated from the declaration; ``dpsv`` has the tree's, "
            "``sm_dpsv`` the tree's and ``hard``'s):\n\n" + param_table_markdown(FusedDPSVSoft))
