"""Real engines as techniques: the page harness, the browser session and :class:`EngineTechnique`.

An engine technique (``three:pcf``, ``babylon:pcss``, ...) renders the scene in the engine itself,
headless in Chromium on WebGL 2 through SwiftShader (no GPU), and hands back per light the
engine's shadow term as visibility in [0, 1] at the truth's pixel centres, so ``compare``,
``fit``, ``sweep`` and ``gate`` treat it as any technique (docs/engines.md).

How a render runs:

* The scene is exported once per (scene, resolution) with :func:`shadowlab.scene.gltf.write_glb`
  [Khronos 2017] and served with the engine's npm files (``node_modules``, pinned by the committed
  ``package-lock.json``, installed by ``make engines``) and the adapter page (``engine_pages/``)
  from a loopback HTTP server (:mod:`shadowlab.io.browser`, [Chrome DevTools 2026]): ES modules need ``http:``; nothing
  comes from the network.
* One Chromium per process (launched on first use, closed at exit) and one tab per (engine page,
  scene): the page keeps the loaded glb; a new parameter point only sets the engine's shadow
  properties and re-renders.
* The page returns each light's visibility as the base64 of a Float32Array (read from an RGBA32F
  render target: float32 precision) through ``Runtime.evaluate``; rows are flipped (WebGL's origin
  is the bottom left) and, with supersampling, sub-pixels put in the G-buffer's point order.

A missing Chromium or missing npm packages are an EnvironmentProblem (exit 3) naming ``make
setup`` / ``make engines``; a page that fails to load is an EnvironmentProblem showing the console
errors; an engine that cannot express a scene's feature says which (``unsupported``, exit 2).
"""

from __future__ import annotations

import atexit
import base64
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..errors import EnvironmentProblem, InputError
from ..io import browser as browser_mod
from ..scene import gltf
from ..render.gbuffer import vec_numpy
from ..scene import lights as lights_mod
from .base import LightResult, Technique, needs_mitsuba_geometry

#: the adapter pages and their scripts (package data)
PAGES = Path(__file__).with_name("engine_pages")
#: seconds a page may take to load a scene, and one render
LOAD_TIMEOUT, RENDER_TIMEOUT = 120.0, 300.0


def node_modules() -> Path:
    """``$SHADOWLAB_NODE_MODULES``, else the checkout's ``node_modules`` (where ``make engines``
    installs the pinned engines)."""
    env = os.environ.get("SHADOWLAB_NODE_MODULES")
    return Path(env) if env else gltf.project_root() / "node_modules"


def package_version(package: str) -> str:
    """The installed version of npm ``package``; EnvironmentProblem naming ``make engines`` when it is missing."""
    f = node_modules() / package / "package.json"
    if not f.is_file():
        raise EnvironmentProblem(f"the npm package {package} is not installed in {node_modules()}; run `make engines` "
                                 "(npm ci from the committed package-lock.json)")
    return json.loads(f.read_text())["version"]


class Session:
    """One Chromium with WebGL 2 and one loopback server for the process; one tab per loaded
    (page, scene): :meth:`page` reuses the tab while the key is unchanged."""

    def __init__(self):
        self.dir = tempfile.TemporaryDirectory(prefix="shadowlab-engines-")
        self.server = browser_mod.serve({"node_modules": node_modules(), "page": PAGES})
        self.browser = browser_mod.Browser(Path(self.dir.name) / "profile", size=(256, 256), webgl=True)
        self.key, self.info = None, None
        #: (page key, light) -> the engine's unshadowed white-Lambert light at the points (N, 3)
        self.lit = {}

    def page(self, key, html: str, config: dict, glb: bytes) -> dict:
        """Load ``html`` with ``config`` (its ``glb`` URL set here) unless ``key`` is what is loaded;
        returns the page's load info. A page that fails: EnvironmentProblem with its console errors."""
        if key == self.key:
            return self.info
        self.key = None
        url = self.server.put("/scene/scene.glb", glb)
        try:
            self.browser.open(f"{self.server.url}/page/{html}", timeout=LOAD_TIMEOUT)
            ready, t0 = False, time.monotonic()
            while not ready and time.monotonic() - t0 < LOAD_TIMEOUT and not self.browser.errors():
                ready = self.browser.js("!!(window.shadowlab && window.shadowlab.ready)")
                if not ready:
                    time.sleep(0.05)
            if not ready:
                raise browser_mod.BrowserError("the page's script did not start")
            self.info = self.browser.js(f"window.shadowlab.load({json.dumps({**config, 'glb': url})})",
                                        timeout=LOAD_TIMEOUT)
        except (browser_mod.BrowserError, TimeoutError) as e:
            errs = "; ".join(self.browser.errors()[:5]) or "no console error"
            raise EnvironmentProblem(f"the engine page {html} failed to load ({e}; console: {errs}); run `make "
                                     "engines` to reinstall the pinned npm packages, and `make setup` for Chromium"
                                     ) from None
        self.key = key
        return self.info

    def render(self, params: dict) -> dict:
        try:
            return self.browser.js(f"window.shadowlab.render({json.dumps(params)})", timeout=RENDER_TIMEOUT)
        except (browser_mod.BrowserError, TimeoutError) as e:
            errs = "; ".join(self.browser.errors()[-5:]) or "no console error"
            self.key = None
            raise EnvironmentProblem(f"the engine page failed to render ({e}; console: {errs})") from None

    def close(self) -> None:
        self.browser.close()
        self.server.close()
        self.dir.cleanup()


_SESSION: list = []


def session() -> Session:
    """The process's browser session, started on first use (Chromium checked, then the npm files)."""
    if _SESSION and not _SESSION[0].browser.alive():
        _SESSION.pop().close()
    if not _SESSION:
        browser_mod.chromium()
        _SESSION.append(Session())
        atexit.register(close_session)
    return _SESSION[0]


def close_session() -> None:
    """Close the process's browser session (the next render starts a new one)."""
    while _SESSION:
        _SESSION.pop().close()


def decode(b64: str, width: int, height: int) -> np.ndarray:
    """A base64 Float32Array of a WebGL read-back (rows bottom to top) -> (H, W) float32, top row first.

    >>> a = np.arange(6, dtype=np.float32)
    >>> decode(base64.b64encode(a.tobytes()).decode(), 3, 2).tolist()
    [[3.0, 4.0, 5.0], [0.0, 1.0, 2.0]]
    """
    a = np.frombuffer(base64.b64decode(b64), dtype="<f4")
    if a.size != width * height:
        raise EnvironmentProblem(f"the engine page returned {a.size} values for a {width}x{height} image")
    return a.reshape(height, width)[::-1].copy()


def decode_rgb(b64: str, width: int, height: int) -> np.ndarray:
    """:func:`decode` of an RGB read-back (3 floats per pixel) -> (H, W, 3), top row first."""
    a = np.frombuffer(base64.b64decode(b64), dtype="<f4")
    if a.size != 3 * width * height:
        raise EnvironmentProblem(f"the engine page returned {a.size} values for a {width}x{height} RGB image")
    return a.reshape(height, width, 3)[::-1].copy()


def direct_ratio(engine_direct: np.ndarray, truth_unshadowed: np.ndarray) -> float:
    """Median over the lit points of the engine's unshadowed direct light over the truth's ``U_L``
    (channel sums): 1 where the engine's Lambertian light matches the truth's emitter.

    >>> direct_ratio(np.array([[2.0, 0, 0], [1, 1, 0], [0, 0, 0]]), np.array([[1.0, 0, 0], [1, 0, 0], [0, 0, 0]]))
    2.0
    """
    e, u = engine_direct.sum(1), truth_unshadowed.sum(1)
    m = u > 1e-6 * max(float(u.max()), 1e-30)
    return float(np.median(e[m] / u[m])) if m.any() else float("nan")


def to_points(img: np.ndarray, ss: int) -> np.ndarray:
    """An (H·ss, W·ss) image at sub-pixel centres -> flat values in the G-buffer's point order
    (pixel by pixel, row major; each pixel's ss² sub-pixels row major, as ``camera.pixel_uv``).

    >>> to_points(np.arange(16.0).reshape(4, 4), 2)[:8].tolist()
    [0.0, 1.0, 4.0, 5.0, 2.0, 3.0, 6.0, 7.0]
    """
    Hs, Ws = img.shape
    H, W = Hs // ss, Ws // ss
    return img.reshape(H, ss, W, ss).transpose(0, 2, 1, 3).reshape(-1)


def camera_config(frame) -> dict:
    """The truth's camera for the page: position, target, the actual up, the full vertical field of
    view (the scene's ``fov`` spans the width) and the clip planes."""
    cam = frame.camera
    return {"position": cam.position.tolist(), "target": cam.target.tolist(), "up": cam.up.tolist(),
            "fovY": cam.fov_y, "near": cam.near, "far": cam.far}


@dataclass(frozen=True)
class ReceiverPoints:
    """Per receiver point (flat numpy arrays), what a shadowlab shadow-map technique does in world
    units and the engine's shadow camera there (:mod:`shadowlab.techniques.transfer`): ``dz`` the
    distance the compared depth moves toward the light, ``normal`` the distance the point moves
    along its normal, ``filter_var`` the per-axis variance of the filter footprint (m²), ``cos`` the
    cosine between the point's normal and the direction to the light;
    ``engine_z`` the depth along the engine camera's axis, ``engine_texel`` its texel's world size,
    ``engine_depth_per_unit`` its stored depth per world unit."""

    dz: np.ndarray
    normal: np.ndarray
    filter_var: np.ndarray
    cos: np.ndarray
    engine_z: np.ndarray
    engine_texel: np.ndarray
    engine_depth_per_unit: np.ndarray

    @property
    def size(self) -> int:
        return int(self.dz.size)

    @classmethod
    def pooled(cls, parts: list) -> "ReceiverPoints":
        names = cls.__dataclass_fields__
        return cls(**{k: np.concatenate([getattr(p, k) for p in parts]) if parts else np.zeros(0) for k in names})


def shadow_cameras(stats: dict) -> dict:
    """light name -> the engine's shadow camera of its one map (the page's ``maps`` entries: position,
    direction, near, far, resolution, projection and its field of view or half-size), from the
    ``stats`` of an engine render; lights with cascades or without a camera are left out."""
    out = {}
    for name, st in stats.get("lights", {}).items():
        maps = st.get("maps") or []
        if len(maps) == 1 and "projection" in maps[0]:
            out[name] = maps[0]
    return out


class EngineTechnique(Technique):
    """A technique whose shadows a real engine renders. Subclasses set ``engine`` (the npm package
    whose version the stats record), ``page_html`` (the adapter page), ``shadow_type`` (the page's
    name of the engine's shadow type) and ``params`` (the engine's own parameter names), and may
    refuse scenes in :meth:`unsupported`; :meth:`engine_values` turns the resolved values into what
    the page sets (default: as they are). The base class's render loop runs it: :meth:`prepare`
    renders every light in the engine, :meth:`render_light` hands each light its image."""

    engine: str = ""
    external = True
    page_html: str = ""
    shadow_type: str = ""
    #: False: one loaded page serves every shadow type of the engine (the type is sent with each render)
    page_per_type: bool = True

    def unsupported(self, spec) -> str | None:
        casting = [l.name for l in spec.lights if l.casts_shadows]
        return needs_mitsuba_geometry(self.name, spec) or (
            f"{self.name}: the scene has no lights for the engine to shadow" if not spec.lights else None) or (
            f"{self.name}: the panel of light {casting[0]!r} casts shadows (casts_shadows = true), and the glb "
            "gives the engine its light, not its panel: leave casts_shadows out (the default)" if casting else None)

    def unavailable(self) -> str | None:
        try:
            package_version(self.engine)
            browser_mod.chromium()
        except EnvironmentProblem as e:
            return f"{self.name}: {e}"
        return None

    def fit_params(self, values: dict) -> tuple:
        """The engine's filter and bias parameters (nothing here is differentiable)."""
        return tuple(p.name for p in self.params if p.kind == "float")[:3]

    def engine_values(self, values: dict) -> dict:
        return dict(values)

    #: shadowlab techniques whose parameters :meth:`from_shadowlab` maps onto this engine's
    transfer_from: tuple = ()

    def from_shadowlab(self, points: ReceiverPoints, values: dict) -> dict:
        """Per point, the engine's parameter values that do there what the shadowlab technique
        does (:mod:`shadowlab.techniques.transfer`), with the engine's other settings ``values``
        kept: param -> (N,) array."""
        raise InputError(f"{self.name} has no transfer from shadowlab's techniques; fit it itself")

    def clip_values(self, values: dict) -> dict:
        """``values`` clipped to the declared ranges (the transfer's medians may fall outside)."""
        out = {}
        for k, v in values.items():
            prm = self.param(k)
            lo = prm.lo if prm.lo is not None else v
            hi = prm.hi if prm.hi is not None else v
            out[k] = float(min(max(v, lo), hi))
        return out

    def _load(self, frame, sess: Session) -> dict:
        gb = frame.gbuffer
        W, H = gb.width * gb.ss, gb.height * gb.ss
        spec = frame.scene.spec
        camera = camera_config(frame)
        # what the page holds: the engine, the scene's content and the camera (not the frame object: a
        # fit's jobs may rebuild the frame, and the page need not be loaded again)
        key = (self.page_html, self.shadow_type if self.page_per_type else "", spec.name, spec.digest(), W, H,
               json.dumps(camera))
        if key == sess.key:
            return sess.info
        with tempfile.TemporaryDirectory(prefix="shadowlab-glb-") as d:
            manifest = gltf.write_glb(frame.scene, Path(d) / "scene.glb", resolution=(W, H))
            glb = (Path(d) / "scene.glb").read_bytes()
        lights = []                      # the page holds every light of the scene (the glb's, in its order),
        for entry, l in zip(manifest["lights"], spec.lights):   # also for a frame that shows fewer
            lights.append({"name": l.name, "node": entry["node"], "kind": l.kind, "type": entry["type"],
                           "direction": [float(x) for x in lights_mod.forward(l)],
                           "position": [float(x) for x in (l.position or (0.0, 0.0, 0.0))]})
        cfg = {"type": self.shadow_type, "width": W, "height": H, "camera": camera, "lights": lights}
        return sess.page(key, self.page_html, cfg, glb)

    # -- the base's render loop: the engine renders every light once (prepare), each light takes its own
    def prepare(self, frame, values: dict, ctx) -> None:
        """Load the page (once per scene) and render every light at these values."""
        ctx.version = package_version(self.engine)     # missing npm packages: exit 3 naming `make engines`
        ctx.session = session()
        ctx.info = self._load(frame, ctx.session)
        t0 = time.perf_counter()
        out = ctx.session.render({**self.engine_values(values), "__type": self.shadow_type})
        ctx.wall, ctx.page_ms = time.perf_counter() - t0, float(out["ms"])
        ctx.lights = {r["name"]: (r, maps) for r, maps in zip(out["lights"], out["maps"])}

    def render_light(self, frame, light, values: dict, ctx) -> LightResult:
        """The light's visibility as the engine returned it; with the engine's unshadowed light (sent
        once per page), its shaded direct light (AOV ``engine_direct``, the channel mean of albedo ×
        light × visibility) and ``direct_ratio``."""
        gb = frame.gbuffer
        W, H = gb.width * gb.ss, gb.height * gb.ss
        r, maps = ctx.lights[light.name]
        flat = to_points(decode(r["vis"], W, H), gb.ss)
        stats, aovs = {"above_one": int(r["above_one"])}, {}
        sess = ctx.session
        if "lit" in r:
            sess.lit[(sess.key, light.name)] = np.stack([to_points(c, gb.ss) for c in
                                                         decode_rgb(r["lit"], W, H).transpose(2, 0, 1)], 1)
        lit = sess.lit.get((sess.key, light.name))
        if lit is not None:
            direct = gb.albedo.reshape(-1, 3) * lit      # the engine's unshadowed Lambertian direct light
            aovs["engine_direct"] = mi.Float((direct * flat[:, None]).mean(1).astype(np.float32))
            stats["direct_ratio"] = direct_ratio(direct, vec_numpy(frame.unshadowed[light.name]))
        return LightResult(mi.Float(flat.astype(np.float32)), aovs=aovs, active=gb.valid, stats=stats, maps=maps)

    def summarise(self, frame, values: dict, ctx, lights: dict) -> dict:
        return {"engine": {"package": self.engine, "version": ctx.version, "shadow_type": self.shadow_type,
                           "renderer": ctx.info.get("renderer", ""), "page_ms": ctx.page_ms, "render_s": ctx.wall}}
