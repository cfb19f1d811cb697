"""FrameContext: scene + G-buffer + unshadowed light + light views, built once per run.

Every technique of a comparison reads the same FrameContext (docs/ARCHITECTURE.md, data flow), so
primary rays, unshadowed light and shadow maps are computed once and shared.

``frame.sdf`` is the scene's signed distance field (:func:`shadowlab.scene.twins.sdf_of`), None for
scenes with meshes. The scene's ``kind`` chooses the G-buffer: a ``"mitsuba"`` scene (every object
has a Mitsuba twin, or none needs one) keeps the Mitsuba G-buffer (techniques are then evaluated at
the ground truth's own points); an ``"sdf"`` scene (SDF-only objects, ``[[sdf]]``, e.g. a
Mandelbulb, which Mitsuba cannot see) gets the cone-traced G-buffer of [Bán 2019, §2.9]
(:func:`shadowlab.render.sdf_gbuffer.cone_gbuffer`), and shadow maps, which Mitsuba ray casts,
refuse it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ..scene.lights import forward as light_forward
from ..scene.mesh import panel_triangles, scene_triangles
from ..scene.twins import sdf_of
from . import sdf_gbuffer
from .camera import Camera
from .gbuffer import GBuffer, gbuffer, vec_numpy
from .gbuffer import evaluate as evaluate_gbuffer
from .lightview import LightView, SceneSphere, ViewRequest, cast_views
from .replay import replayed
from .screen import Screen
from .shading import unshadowed
from .top_tree import TopTree, build_top_tree, upload_triangles


class ViewKey(NamedTuple):
    """A light view a frame casts once: :func:`~shadowlab.render.lightview.light_view`'s arguments,
    the light by name (``res``/``bits`` None: the light's own; ``fit`` None: the whole scene)."""

    name: str
    res: int | None = None
    bits: int | None = None
    backface: bool = False
    fit: object = None
    layers: int = 1
    translucent: bool = False

    def resolved(self, scene) -> ViewKey:
        """The key with the light's own settings filled in (translucency only where the scene has it)."""
        sp = scene.spec.light(self.name)
        return ViewKey(self.name, int(self.res or sp.shadow_map), int(self.bits or sp.depth_bits), bool(self.backface),
                       SceneSphere() if self.fit is None else self.fit, int(self.layers),
                       bool(self.translucent and scene.has_translucent))

    def request(self, scene) -> ViewRequest:
        return ViewRequest(scene.spec.light(self.name), self.fit, self.res, self.bits, self.backface, self.layers,
                           self.translucent)


@dataclass
class FrameContext:
    scene: object
    gbuffer: GBuffer
    unshadowed: dict                       # light name -> flat mi.Color3f U_L
    sdf: object = None                     # shadowlab.sdf.SDF of the scene, None with meshes
    _views: dict = field(default_factory=dict, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)
    #: the names of the lights this context shows (None: every light of the scene); see :meth:`for_lights`
    only: tuple | None = None

    def clear_light_views(self) -> None:
        """Forget the cached light views, so the next request casts its map again (the benchmarks
        time a cold frame this way)."""
        self._views.clear()

    def share_light_views(self, other: FrameContext, lights) -> None:
        """Use ``other``'s cached light views of the named ``lights`` (a frame of the same scene
        geometry with fewer lights reuses the maps already cast)."""
        names = set(lights)
        self._views.update({k: v for k, v in other.light_views.items() if k[0] in names})

    @property
    def light_views(self) -> dict:
        """The light views cast so far, by their key (light name, resolution, bits, back faces, fit)."""
        return dict(self._views)

    @property
    def lights(self):
        """The scene's lights, or those of :meth:`for_lights`."""
        ls = self.scene.spec.lights
        return ls if self.only is None else [l for l in ls if l.name in self.only]

    @property
    def light_spec(self):
        """The scene's spec with only :attr:`lights` (what a technique restricted to them must support)."""
        return self.scene.spec if self.only is None else replace(self.scene.spec, lights=tuple(self.lights))

    def for_lights(self, names) -> FrameContext:
        """The same frame showing only the lights ``names`` (a technique per light renders each
        light's technique on it); it shares this frame's G-buffer, unshadowed light and cached
        light views."""
        names = tuple(names)
        unknown = [n for n in names if n not in {l.name for l in self.scene.spec.lights}]
        if unknown:
            raise InputError(f"no light named {unknown[0]!r} in scene {self.scene.name!r}; its lights: "
                             f"{', '.join(l.name for l in self.scene.spec.lights)}")
        return replace(self, only=names)

    @property
    def resolution(self):
        return self.scene.resolution

    @property
    def camera(self) -> Camera:
        """The scene's :class:`~shadowlab.render.camera.Camera` at the frame's resolution (made once per scene)."""
        return Camera.from_scene(self.scene)

    @property
    def screen(self) -> Screen:
        """The G-buffer as screen-space Dr.Jit arrays (:class:`~shadowlab.render.screen.Screen`, made once)."""
        if "screen" not in self._cache:
            self._cache["screen"] = Screen.from_frame(self)
        return self._cache["screen"]

    def require_mitsuba_geometry(self) -> None:
        """Refuse (InputError) a scene with SDF-only objects: light views are Mitsuba ray casts from
        the light, which would not see them."""
        if self.scene.kind == "sdf":
            raise InputError(f"scene {self.scene.name!r} has SDF-only objects ([[sdf]]) that Mitsuba does not see, "
                             "so its shadow maps (Mitsuba ray casts from the light) would miss them; compare the "
                             "SDF techniques on it, or the shadow-map techniques on a scene with Mitsuba twins")

    @property
    def own_gbuffer(self) -> GBuffer:
        """The G-buffer of the frame's own camera: ``gbuffer``, or, where that came from another
        camera (the shimmer's frame-0 points seen with frame t's camera and light views), one cast
        from this frame's camera for what depends on the view itself (a virtual map's demand and
        focus), made once."""
        gb = self.gbuffer
        if gb.view is None or gb.view == self.scene.spec.camera:
            return gb
        if "own_gbuffer" not in self._cache:
            self._cache["own_gbuffer"] = gbuffer(self.scene, ss=gb.ss)
        return self._cache["own_gbuffer"]

    @property
    def own_screen(self) -> Screen:
        """:attr:`screen` of :attr:`own_gbuffer` (the same object where the G-buffer is the frame's own)."""
        gb = self.own_gbuffer
        if gb is self.gbuffer:
            return self.screen
        if "own_screen" not in self._cache:
            self._cache["own_screen"] = Screen(self.camera, gb.ss, gb.p, gb.n, gb.valid)
        return self._cache["own_screen"]

    def light_view(self, light_name: str, res: int | None = None, bits: int | None = None,
                   backface: bool = False, fit=None, layers: int = 1, translucent: bool = False) -> LightView:
        """The light's depth map, cast once per (light, resolution, depth bits, back faces, fit,
        layers, translucency); ``fit`` None is :class:`~shadowlab.render.lightview.SceneSphere` (the
        whole scene); ``layers`` > 1 keeps that many surfaces per texel (the rasterizer's bias);
        ``translucent`` (only in a scene with translucent shapes; ignored elsewhere): the opaque
        depth plus the translucent casters' colour and depth."""
        return self.light_views_of(light_name, [fit], res=res, bits=bits, backface=backface, layers=layers,
                                translucent=translucent)[0]

    def light_views_of(self, light_name, fits, res: int | None = None, bits: int | None = None,
                       backface: bool = False, layers: int = 1, translucent: bool = False) -> list:
        """:meth:`light_view` for each fit of ``fits`` of the light ``light_name`` (or of each light
        of a list of names, one per fit), through :meth:`views`."""
        names = list(light_name) if isinstance(light_name, (list, tuple)) else [light_name] * len(fits)
        return self.views([ViewKey(n, res, bits, backface, f, layers, translucent) for n, f in zip(names, fits)])

    def views(self, keys) -> list:
        """The light views of ``keys`` (:class:`ViewKey`), each cast once per frame; those not cast
        yet are cast together, whatever their lights, fits and map settings
        (:func:`~shadowlab.render.lightview.cast_views`: one stage)."""
        self.require_mitsuba_geometry()
        keys = [k.resolved(self.scene) for k in keys]
        missing = list(dict.fromkeys(k for k in keys if k not in self._views))
        if missing:
            self._views.update(zip(missing, self.cast([k.request(self.scene) for k in missing])))
        return [self._views[k] for k in keys]

    def has_view(self, key: ViewKey) -> bool:
        """Whether the light view of ``key`` is cast already (:meth:`views` returns it without a cast)."""
        return key.resolved(self.scene) in self._views

    def cast(self, requests) -> list:
        """The light views of ``requests`` (:class:`~shadowlab.render.lightview.ViewRequest`), cast now,
        uncached (:meth:`views` caches what it casts here; the benchmarks time this call)."""
        return cast_views(self.scene, requests)

    def triangles(self, segments: int = 64) -> np.ndarray:
        """The scene's triangles (T×3×3, world; :func:`~shadowlab.scene.mesh.scene_triangles`), made
        once per scene and tessellation; InputError for a scene without any (e.g. SDF objects only)."""
        key = ("triangles", int(segments), self.scene.spec.shapes)
        derived = self.scene.derived
        if key not in derived:
            self.require_mitsuba_geometry()
            V, _ = scene_triangles(self.scene.spec, segments)
            if not len(V):
                raise InputError(f"scene {self.scene.name!r} has no triangles (no [[shapes]]): a TOP tree is built "
                                 "from the scene's triangles; add a mesh or a primitive shape")
            derived[key] = V
        return derived[key]

    def top_tree(self, light_name: str, segments: int = 64, order: str = "random") -> TopTree:
        """The TOP tree of the light's centre (a point light's position, or a directional light at
        infinity) over :meth:`triangles` and the other lights' panels that cast shadows
        (``casts_shadows``), built on the device once per frame and (light, tessellation, insertion
        order); its triangles are uploaded once per scene."""
        key = ("top_tree", light_name, int(segments), order)
        if key not in self._cache:
            spec = self.scene.spec.light(light_name)
            if spec.kind == "directional":
                light = [-x for x in light_forward(spec)] + [0.0]
            else:
                light = list(spec.position) + [1.0]
            tkey = ("tree_triangles", light_name, int(segments), self.scene.spec.shapes, self.scene.spec.lights)
            derived = self.scene.derived
            if tkey not in derived:
                V = self.triangles(segments)
                panels = panel_triangles(self.scene.spec, segments, exclude=light_name)
                derived[tkey] = upload_triangles(np.concatenate([V, panels]) if len(panels) else V)
            self._cache[key] = build_top_tree(derived[tkey], np.asarray(light, np.float64), order=order)
        return self._cache[key]

    def lit_mask(self, light_name: str) -> np.ndarray:
        """(H, W) bool: pixels the light reaches at all (U_L > 0); visibility only matters there."""
        U = vec_numpy(self.unshadowed[light_name]).sum(1)
        return self.gbuffer.to_image(U) > 0

    def image(self, flat) -> np.ndarray:
        return self.gbuffer.to_image(flat)


def make_frame(scene, ss: int = 1, u_strata: int = 16, seed: int = 0) -> FrameContext:
    """G-buffer at pixel (sub-)centres and U_L for every light (cone traced for ``"sdf"`` scenes,
    see the module docstring)."""
    sdf = sdf_of(scene)
    if scene.kind == "sdf":
        gb = sdf_gbuffer.cone_gbuffer(scene, sdf, ss=ss, evaluated=False)
        U = {l.name: sdf_gbuffer.unshadowed(scene, gb, l.name, k=u_strata, seed=seed) for l in scene.spec.lights}
        sdf_gbuffer.evaluate(gb, *U.values())
    else:
        def stage(*_inputs):  # the scene's arrays are the inputs; the rest is the key's
            gb = gbuffer(scene, ss=ss, evaluated=False)
            U = {l.name: unshadowed(scene, gb, l.name, k=u_strata, seed=seed) for l in scene.spec.lights}
            evaluate_gbuffer(gb, *U.values())
            return gb.arrays(), U

        arrays, U = replayed("frame", (scene.spec, int(ss), int(u_strata), int(seed)), stage, scene,
                             scene.mi_scene, scene.sensor, scene.shape_index)
        gb = GBuffer.of(scene, ss, arrays)
    return FrameContext(scene=scene, gbuffer=gb, unshadowed=U, sdf=sdf)
