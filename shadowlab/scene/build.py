"""SceneSpec -> a loaded Mitsuba scene, its camera and its lights' emitters.

Shapes are loaded with ``optimize=False`` so each keeps its own id (docs/ARCHITECTURE.md, Dr.Jit facts);
the shape id of a pixel in the G-buffer is the index into ``Scene.shape_names``.

An alpha-tested shape (``alpha_texture``, [Buljan 2020, §2.4]) gets Mitsuba's ``mask``
BSDF around its diffuse BSDF, with a binary opacity texture (:func:`opacity_texture`), looked up
at the hit's Mitsuba uv (rectangle: u = (x + 1)/2, v = (y + 1)/2 in its local [−1, 1]², image
row 0 at v = 0; other shapes: Mitsuba's own uv, meshes: their uv, if any).
``Scene.has_alpha`` tells the ray paths (G-buffer, light views, ground-truth shadow rays) to look
through transparent texels (:func:`transparent`); without alpha shapes they stay as they were.

A translucent shape (``transmittance``, ``opacity``) keeps its plain diffuse BSDF: the camera sees
it as an opaque surface and it is lit as one. Only shadow rays and light views see through it, by
straight-line transmission: each crossing multiplies the light by the shape's τ (``ShapeSpec.tau``),
looked up by :func:`surface_tau` from :meth:`Scene.translucency` (the Mitsuba shapes of each
translucent shape and their τ); without translucent shapes every ray path stays as it was.

What casts shadows (``casts_shadows``). A shape casts by default; a light's own panel (an area light's
emitting rectangle, disk or sphere) does not: engines draw a soft box's light but do not let its panel
shadow the sun, and a panel that casts turned a soft box into a hard sun shadow on the floor. Every
shadow path (the truth's shadow rays, the light views and tiles, the TOP tree, :func:`Scene.casters`)
sees only the casting geometry; the camera sees everything (the G-buffer keeps its shape ids).
Where some geometry does not cast, :func:`build` loads a second Mitsuba scene of the casting shapes
and panels (:class:`Casters`); where all of it casts, the scene is its own.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import SceneError
from . import lights as lights_mod
from .gltf_file import mesh_arrays
from .sdf_spec import bounds as sdf_bounds
from .spec import SceneSpec, scene_spec
from .textures import AlphaTextureError, opacity_mask, read_alpha


def _transform(s):
    T = mi.ScalarTransform4f
    m = T().translate(list(s.translate))
    for ax, ay, az, deg in s.rotate:
        # Mitsuba's rotate() does not normalise its axis (a non-unit axis shears the shape)
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        m = m @ T().rotate([ax / norm, ay / norm, az / norm], deg)
    return m @ T().scale(list(s.scale))


def _bsdf(s):
    d = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(s.albedo)}}
    d = {"type": "twosided", "material": d} if s.two_sided else d
    if s.alpha_texture is None:
        return d
    return {"type": "mask", "opacity": opacity_texture(s), "material": d}


def opacity_texture(s) -> dict:
    """Mitsuba ``bitmap`` texture of a shape's binary opacity (1 = alpha ≥ cutoff, 0 = discarded).

    Thresholded once here, from :func:`shadowlab.scene.textures.read_alpha`, and looked up with
    ``filter_type = "nearest"`` (no interpolation, so the cut-off is exact per texel), ``raw``
    (no sRGB decoding of the 0/1 data) and ``wrap_mode = "clamp"`` (uv = 1 on the border stays in
    the last texel). The ``mask`` BSDF around the shape's diffuse BSDF makes opacity-0 texels
    transparent (null transmission 1). A fresh dict per call: loading takes the tensor over
    (a second ``mi.load_dict`` of the same dict finds it empty)."""
    try:
        a = read_alpha(s.alpha_texture)
    except AlphaTextureError as e:
        raise SceneError(f"shape {s.name!r}: alpha_texture {s.alpha_texture} {e}") from e
    m = opacity_mask(a, s.alpha_cutoff)
    # Mitsuba wants bitmap textures of at least 2×2 texels; doubling a 1-texel axis keeps every
    # nearest lookup the same (texel ⌊2uW⌋ div 2 = ⌊uW⌋)
    for ax in (0, 1):
        if m.shape[ax] < 2:
            m = np.repeat(m, 2, axis=ax)
    return {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(m[..., None])), "raw": True,
            "filter_type": "nearest", "wrap_mode": "clamp"}


def shape_dicts(s) -> dict:
    """Mitsuba dicts of one ShapeSpec (a cylinder with caps gives three shapes)."""
    T = mi.ScalarTransform4f
    M = _transform(s)
    b = _bsdf(s)
    if s.type == "rectangle":
        return {s.name: {"type": "rectangle", "to_world": M, "bsdf": b}}
    if s.type == "disk":
        return {s.name: {"type": "disk", "to_world": M, "bsdf": b}}
    if s.type == "cube":
        return {s.name: {"type": "cube", "to_world": M, "bsdf": b}}
    if s.type == "sphere":
        c = s.center or (0, 0, 0)
        return {s.name: {"type": "sphere", "to_world": M @ T().translate(list(c)) @ T().scale(s.radius), "bsdf": b}}
    if s.type == "cylinder":
        p0, p1 = list(s.p0), list(s.p1)
        axis = [b_ - a_ for a_, b_ in zip(p0, p1)]
        length = math.sqrt(sum(x * x for x in axis))
        if length == 0:
            raise SceneError(f"shape {s.name!r}: cylinder p0 and p1 are the same point")
        up = [0, 1, 0] if abs(axis[1]) < 0.99 * length else [1, 0, 0]
        frame = T().look_at(origin=p0, target=p1, up=up)
        out = {s.name: {"type": "cylinder", "to_world": M @ frame @ T().scale([s.radius, s.radius, length]), "bsdf": b}}
        if s.caps:
            # a BSDF dict each: Mitsuba takes over the tensor of an alpha-tested shape's opacity
            out[s.name + "__cap0"] = {"type": "disk", "to_world": M @ frame @ T().scale([s.radius, s.radius, 1])
                                     @ T().rotate([1, 0, 0], 180), "bsdf": _bsdf(s)}
            out[s.name + "__cap1"] = {"type": "disk", "to_world": M @ frame @ T().translate([0, 0, length])
                                     @ T().scale([s.radius, s.radius, 1]), "bsdf": _bsdf(s)}
        return out
    if s.type == "gltf":  # not a Mitsuba plugin: build() makes the mesh (gltf_mesh), triangulate reads it
        return {s.name: {"type": "gltf", "filename": s.filename, "node": s.node, "primitive": s.primitive,
                         "to_world": M, "bsdf": b}}
    return {s.name: {"type": s.type, "filename": s.filename, "to_world": M, "bsdf": b,
                     "face_normals": True}}


def gltf_mesh(name: str, d: dict):
    """The ``mi.Mesh`` of a ``gltf`` shape dict (:func:`shape_dicts`): the glTF primitive's triangles
    in world space (:func:`shadowlab.scene.gltf_file.mesh_arrays`, then ``to_world``) as float32,
    its uvs, no vertex normals (flat face normals, as ``ply`` / ``obj`` shapes with ``face_normals``),
    the shape's BSDF; id ``name``."""
    P, _, UV, F = mesh_arrays(d["filename"], d["node"], d.get("primitive"), np.array(d["to_world"].matrix, np.float64))
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(d["bsdf"])
    mesh = mi.Mesh(name, len(P), len(F), props, has_vertex_normals=False, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(P, np.float32).reshape(-1))
    params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(UV, np.float32).reshape(-1))
    params["faces"] = mi.UInt(np.ascontiguousarray(F, np.uint32).reshape(-1))
    params.update()
    return mesh


def _loadable(dicts: dict) -> dict:
    """Shape dicts Mitsuba can load: a ``gltf`` dict becomes its mesh object."""
    return {k: gltf_mesh(k, v) if v.get("type") == "gltf" else v for k, v in dicts.items()}


@dataclass(frozen=True)
class Casters:
    """The Mitsuba scene of the geometry that casts shadows, when it differs from the whole scene:
    its ``mi_scene``, ``shape_names`` and ``light_shapes`` (the casting lights' panels)."""

    mi_scene: object
    shape_names: list
    light_shapes: dict


@dataclass
class Scene:
    """A loaded scene: spec, Mitsuba scene, camera sensor and light emitters.

    ``center`` / ``radius`` bound the non-emitting geometry (light cameras are fitted to it);
    ``shape_boxes`` also holds the panels of the lights that cast shadows (the light cameras' depth
    ranges reach them).
    ``shape_names[i]`` is the name of Mitsuba shape ``i``; ``emitters[name]`` the light's emitter.
    """

    spec: SceneSpec
    mi_scene: object
    sensor: object
    emitters: dict
    light_shapes: dict
    shape_names: list
    center: tuple
    radius: float
    bbox_min: tuple = field(default=(0, 0, 0))
    bbox_max: tuple = field(default=(0, 0, 0))
    shape_boxes: list = field(default_factory=list)  # (min, max) of each non-emitting shape and casting panel
    occluders: Casters | None = None  # the casting geometry's own Mitsuba scene; None: every surface casts
    #: what frames derive from the geometry alone, made once and shared by every frame of the scene (and
    #: its camera path's frames, which keep the geometry): keyed by what it was made from
    derived: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def casters(self) -> "Scene":
        """This scene as its shadow rays and light views see it: the same spec, camera, lights and
        bounds, with ``mi_scene``, ``shape_names`` and ``light_shapes`` of the geometry that casts
        (``casts_shadows``; module docstring). The scene itself when every surface casts."""
        o = self.occluders
        if o is None:
            return self
        return replace(self, mi_scene=o.mi_scene, shape_names=o.shape_names, light_shapes=o.light_shapes,
                       occluders=None)

    @functools.cached_property
    def shape_index(self):
        """Mitsuba's registry id of each shape -> its index into ``shape_names`` (an mi.Int32 table,
        −1 for any other id): the G-buffer's shape id is one gather, since Dr.Jit holds shape
        pointers as registry ids. Made once per scene (one read of the ids), not in a frame."""
        ids = np.asarray(dr.reinterpret_array(mi.UInt32, self.mi_scene.shapes_dr()).numpy(), np.int64)
        table = np.full(int(ids.max()) + 1 if ids.size else 1, -1, np.int32)
        table[ids] = np.arange(ids.size, dtype=np.int32)
        return mi.Int32(table)

    @property
    def has_alpha(self) -> bool:
        """Some shape is an alpha-tested caster (``alpha_texture``): every ray path must then look
        through its transparent texels (:func:`transparent`); without one the fast paths
        (``ray_test``, a single ``ray_intersect``) are exact and are kept."""
        return any(s.alpha_tested for s in self.spec.shapes)

    @property
    def has_translucent(self) -> bool:
        """Some shape is a translucent caster (``transmittance``): shadow rays and the light views
        made for translucency (:func:`shadowlab.render.lightview.light_view`) then multiply the
        τ of every translucent surface they cross (:func:`surface_tau`)."""
        return any(s.translucent for s in self.spec.shapes)

    def translucency(self) -> tuple:
        """((shape pointer, τ as mi.Color3f), ...) of every Mitsuba shape of a translucent
        ShapeSpec (a cylinder's caps included): the table :func:`surface_tau` reads."""
        shapes = self.mi_scene.shapes_dr()
        out = []
        for spec in self.spec.shapes:
            if not spec.translucent:
                continue
            for i, n in enumerate(self.shape_names):
                if n == spec.name or n.startswith(spec.name + "__"):
                    # opaque: a scene's colours are data in memory, not literals compiled into the kernels
                    out.append((dr.gather(type(shapes), shapes, i), dr.opaque(mi.Color3f, spec.tau)))
        return tuple(out)

    def mitsuba_notes(self) -> dict:
        """Caveats of Mitsuba's own ``direct`` integrator image (``mi.render``) for this scene, for a
        reference's meta.json; empty when there are none. Lights with a ``range``: ``direct`` cannot
        window a light's falloff, so its image ignores ranges (``mitsuba_direct_ignores_range``).

        Measured on mitsuba 3.9.1: ``direct`` shadow rays are ``ray_test``, which ignores a
        ``mask`` BSDF's opacity, so an alpha-tested card casts the shadow of its whole quad; its
        camera rays stop on the card too (a hole shows the card's BSDF times opacity 0, i.e. black,
        not what lies behind). Shadowlab's own truth (V, shaded) sees through the holes."""
        notes = {}
        if self.has_alpha:
            notes["mitsuba_direct_ignores_alpha"] = (
                "scene has alpha-tested shapes (mask BSDF): Mitsuba's direct integrator (the mitsuba.* "
                "channels) does not see through their transparent texels: shadow rays (ray_test) are "
                "blocked by the whole card and camera rays stop on it (holes render black). Compare "
                "with the V.* and shaded.* channels, which do see through them.")
        if self.has_translucent:
            notes["mitsuba_direct_ignores_translucency"] = (
                "scene has translucent shapes (transmittance): Mitsuba's direct integrator (the mitsuba.* "
                "channels) treats them as opaque blockers of shadow rays; the V.*, C.* and shaded.* channels "
                "use straight-line transmission through them. Compare with those.")
        if self.occluders is not None:
            notes["mitsuba_direct_ignores_casts_shadows"] = (
                "scene has surfaces that cast no shadow (casts_shadows = false, the default of a light's panel): "
                "Mitsuba's direct integrator (the mitsuba.* channels) lets every surface block its shadow rays; "
                "the V.* and shaded.* channels do not. Compare with those.")
        ranged = [l.name for l in self.spec.lights if getattr(l, "range", None) is not None]
        if ranged:
            notes["mitsuba_direct_ignores_range"] = (
                f"lights with a range ({', '.join(ranged)}): Mitsuba's direct integrator (the mitsuba.* "
                "channels) has no light range, so it lights every point with the unwindowed falloff; "
                "the shaded.* channels (and U) use the windowed falloff w(d) = clamp(1 − (d/range)^4, 0, 1)^2 "
                "of render/shading.py. Compare with the V.* and shaded.* channels.")
        return notes

    @property
    def name(self):
        return self.spec.name

    @property
    def frame(self):
        """The camera path frame this scene is at (None for a scene without a camera path)."""
        return self.spec.frame

    def at_frame(self, i: int) -> "Scene":
        """This scene at frame ``i`` of its camera path, without reloading the geometry: the same
        Mitsuba scene and emitters, a new sensor with frame ``i``'s camera (``sensor`` is what the
        G-buffer's camera rays and the truth's ``mi.render`` use). SceneError (exit 2) naming the
        valid range when ``i`` is out of range; a scene without a path has only frame 0 (itself)."""
        spec = self.spec.at_frame(i)
        if spec is self.spec:
            return self
        return replace(self, spec=spec, sensor=mi.load_dict(sensor_dict(spec.camera)))

    @property
    def kind(self) -> str:
        """``"mitsuba"`` or ``"sdf"``: :attr:`shadowlab.scene.spec.SceneSpec.kind`."""
        return self.spec.kind

    @property
    def resolution(self):
        return tuple(self.spec.camera.resolution)

    @property
    def lights(self):
        return self.spec.lights


def transparent(si, active=True):
    """mi.Bool: ``si`` is a valid hit whose BSDF lets light through unscattered (null
    transmission > 1/2): a transparent texel of a ``mask`` BSDF with binary opacity. A free
    function so that symbolic loops can call it (a Scene dataclass inside a loop body would be
    traversed as loop state)."""
    valid = si.is_valid() & active
    t = si.bsdf().eval_null_transmission(si, valid)
    return valid & (t[0] > 0.5)


def surface_tau(si, table, active=True):
    """(mi.Bool translucent, mi.Color3f τ) of the hits ``si``: whether each valid hit is a surface of
    a translucent shape and its τ there (1 elsewhere). ``table``: :meth:`Scene.translucency`. A free
    function, for symbolic loops (like :func:`transparent`)."""
    valid = si.is_valid() & active
    hit = mi.Bool(False)
    tau = mi.Color3f(1.0)
    for ptr, t in table:  # one select per translucent shape, unrolled into the kernel
        mine = valid & (si.shape == ptr)
        hit |= mine
        tau = dr.select(mine, t, tau)
    return hit, tau


def sensor_dict(cam, spp: int = 1, seed: int = 0) -> dict:
    W, H = cam.resolution
    return {
        "type": "perspective",
        "fov": cam.fov,
        "fov_axis": "x",
        "near_clip": cam.near_clip,
        "far_clip": cam.far_clip,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=list(cam.position),
            target=list(cam.target),
            up=list(lights_mod.up_for(lights_mod.unit([t - p for t, p in zip(cam.target, cam.position)]), cam.up)),
        ),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
    }


def build(spec: SceneSpec) -> Scene:
    """Load ``spec`` into Mitsuba (the backend must be initialised)."""

    def geometry(casting_only: bool = False):  # fresh dicts per load: Mitsuba takes over a bitmap's "data" tensor
        geom = {}
        for s in spec.shapes:
            if s.casts_shadows or not casting_only:
                geom.update(_loadable(shape_dicts(s)))
        return geom

    try:
        probe = mi.load_dict({"type": "scene", **geometry()}, optimize=False)
    except Exception as e:  # Mitsuba's message names the plugin and the parameter
        raise SceneError(f"{spec.source}: Mitsuba could not load the shapes: {e}") from e
    boxes = [(tuple(sh.bbox().min), tuple(sh.bbox().max)) for sh in probe.shapes()]
    bb = probe.bbox()
    lo, hi = tuple(bb.min), tuple(bb.max)
    sb = None
    if spec.kind == "sdf":  # SDF-only objects ([[sdf]], no Mitsuba twin) count for the scene's bounds too
        sb = sdf_bounds(spec.sdf)
    if sb is not None:
        lo = tuple(float(c) if not boxes else min(a, float(c)) for a, c in zip(lo, sb[0]))
        hi = tuple(float(c) if not boxes else max(a, float(c)) for a, c in zip(hi, sb[1]))
    elif not boxes:
        raise SceneError(f"{spec.source}: the scene has no bounded object (only [[sdf]] planes); add a shape or a "
                         "bounded [[sdf]] object")
    center = tuple((a + b) / 2 for a, b in zip(lo, hi))
    radius = max(1e-3, 0.5 * math.sqrt(sum((b - a) ** 2 for a, b in zip(lo, hi))))
    for l in spec.lights:  # a light's panel that casts shadows is a caster: the light cameras' depth ranges
        if l.casts_shadows and l.has_panel:  # (from shape_boxes) must reach it; the scene's sphere stays
            pb = mi.load_dict(lights_mod.mitsuba_dict(l, (0.0, 0.0, 0.0), 1.0)[1]).bbox()
            boxes.append((tuple(pb.min), tuple(pb.max)))
    d = {"type": "scene", **geometry(), "sensor": sensor_dict(spec.camera)}
    for l in spec.lights:
        key, ld = lights_mod.mitsuba_dict(l, center, radius)
        d[key] = ld
    try:
        ms = mi.load_dict(d, optimize=False)
    except Exception as e:
        raise SceneError(f"{spec.source}: Mitsuba could not load the scene: {e}") from e
    names = [sh.id() for sh in ms.shapes()]
    emitters, light_shapes = {}, {}
    by_id = {sh.id(): sh for sh in ms.shapes()}
    em_by_id = {e.id(): e for e in ms.emitters()}
    for l in spec.lights:
        key = f"light_{l.name}"
        if key in by_id:
            emitters[l.name] = by_id[key].emitter()
            light_shapes[l.name] = names.index(key)
        else:
            emitters[l.name] = em_by_id[key]
    return Scene(spec=spec, mi_scene=ms, sensor=ms.sensors()[0], emitters=emitters, light_shapes=light_shapes,
                 shape_names=names, center=center, radius=radius, bbox_min=lo, bbox_max=hi,
                 shape_boxes=boxes, occluders=_casters(spec, geometry, center, radius, light_shapes))


def _casters(spec: SceneSpec, geometry, center, radius, light_shapes: dict) -> Casters | None:
    """The Mitsuba scene of the casting geometry (shapes with ``casts_shadows``, the panels of the
    lights with ``casts_shadows``), or None where it blocks what all of the scene's surfaces block: a
    light's own panel never blocks its own light, so with one light a panel that does not cast changes
    nothing (and the scene keeps its one Mitsuba scene)."""
    panels = [l for l in spec.lights if l.name in light_shapes]
    quiet = [l for l in panels if not l.casts_shadows] if len(spec.lights) > 1 else []
    if all(s.casts_shadows for s in spec.shapes) and not quiet:
        return None
    d = {"type": "scene", **geometry(casting_only=True)}
    for l in panels:
        if l.casts_shadows:
            key, ld = lights_mod.mitsuba_dict(l, center, radius)
            d[key] = ld
    try:
        ms = mi.load_dict(d, optimize=False)
    except Exception as e:
        raise SceneError(f"{spec.source}: Mitsuba could not load the shapes that cast shadows: {e}") from e
    names = [sh.id() for sh in ms.shapes()]
    return Casters(mi_scene=ms, shape_names=names,
                   light_shapes={l.name: names.index(f"light_{l.name}") for l in panels if l.casts_shadows})


def load(scene: str, resolution: tuple | None = None, frame: int | None = None) -> Scene:
    """Built-in scene name or TOML path -> loaded Scene, optionally at another resolution and at
    frame ``frame`` of its camera path (None: the scene as it is, frame 0 of a path)."""
    return build(scene_spec(scene, resolution, frame))
