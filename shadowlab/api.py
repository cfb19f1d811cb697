"""The public Python API: ``import shadowlab`` and test a shadow technique in a few lines.

The steps of the data flow (docs/ARCHITECTURE.md), one function each:

* :func:`load_scene`: a built-in scene or a TOML file;
* :func:`make_frame`: camera, G-buffer, unshadowed light and light views, shared by every technique;
* :func:`render_technique`: one technique on a frame, with its parameters by keyword;
* :func:`load_reference`: the stored ground truth;
* :func:`compare`: a technique's result against the truth, every metric of ``shadowlab compare``;
* :func:`gate_image`: any image (an array, e.g. from your own engine) against the truth or another
  array, with the thresholds of the CI gates;
* :func:`techniques_for`: what applies to a scene, and why the others do not;
* :func:`shaded_image`: the shaded image Σ_L U_L·V_L of any visibility, a technique's or your engine's;
* :func:`load_preset`: the parameter values of a preset file (``shadowlab fit`` writes them), to pass
  to :func:`render_technique`.

A user's own pytest gate:

>>> import shadowlab
>>> frame = shadowlab.make_frame(shadowlab.load_scene("parallel_planes"))
>>> truth = shadowlab.load_reference("parallel_planes")
>>> result = shadowlab.render_technique(frame, "pcss", light_scale=1.0)
>>> metrics = shadowlab.compare(frame, truth, result)
>>> bool(metrics["vis_rmse_penumbra"] < 0.02)
True
>>> v = shadowlab.visibility(frame, result, "panel")          # (H, W) numpy image
>>> shadowlab.gate_image(v, truth, target="visibility", light="panel", rmse_penumbra=0.02).passed
True

Names of the package's internals may change; these do not without a note in the README.
"""

from __future__ import annotations

import numpy as np

from . import backend
from .errors import InputError
from .fit.preset import load as _load_preset
from .gate.check import GateResult, check
from .gate.thresholds import from_keywords
from .metrics.compare import compare_visibility
from .pipeline import load_scene as _load_scene
from .pipeline import technique_metrics
from .reference import store
from .render.frame import FrameContext
from .render.frame import make_frame as _make_frame
from .render.shading import compose
from .scene.spec import scene_spec
from .techniques import base as _techniques
from .techniques.base import ShadowResult

__all__ = ["load_scene", "make_frame", "render_technique", "visibility", "load_reference", "compare", "gate_image",
           "techniques_for", "shaded_image", "load_preset"]


def load_scene(scene: str, *, resolution: tuple | None = None, frame: int | None = None):
    """A built-in scene name or a ``.toml`` path -> the loaded scene (Mitsuba scene, lights,
    camera), at another ``resolution`` (W, H) or ``frame`` of its camera path if given. Selects
    the Mitsuba variant first (``$SHADOWLAB_VARIANT``, else ``llvm_ad_rgb``).

    >>> load_scene("contact", resolution=(32, 24)).resolution
    (32, 24)
    """
    backend.init()
    return _load_scene(scene, resolution, frame)


def make_frame(scene, *, supersampling: int = 1) -> FrameContext:
    """The frame every technique of a comparison shares: G-buffer at pixel centres (``supersampling`` ×
    ``supersampling`` per pixel), unshadowed light per light, light views made on demand and cached.

    >>> make_frame(load_scene("contact", resolution=(32, 24))).gbuffer.size
    768
    """
    return _make_frame(scene, ss=int(supersampling))


def render_technique(frame: FrameContext, technique: str, **params) -> ShadowResult:
    """Technique ``technique`` on ``frame``: visibility per light (flat Dr.Jit arrays in G-buffer
    order; :func:`visibility` gives images), AOVs and stats. ``params`` are the technique's
    declared parameters (``shadowlab techniques`` lists them); unknown names and values outside
    the declared range raise :class:`~shadowlab.errors.InputError`.

    >>> fr = make_frame(load_scene("contact", resolution=(32, 24)))
    >>> sorted(render_technique(fr, "pcf", kernel=5).visibility)
    ['key']
    """
    t = _techniques.get(technique)
    return t.render(frame, t.resolve(params))


def visibility(frame: FrameContext, result: ShadowResult, light: str) -> np.ndarray:
    """The (H, W) visibility image of ``light`` in ``result`` (1 lit, 0 shadowed).

    >>> fr = make_frame(load_scene("contact", resolution=(32, 24)))
    >>> visibility(fr, render_technique(fr, "hard"), "key").shape
    (24, 32)
    """
    if light not in result.visibility:
        raise InputError(f"no light {light!r} in this result; its lights: {', '.join(result.visibility)}")
    return frame.image(result.visibility[light])


def load_reference(scene: str, *, resolution: tuple | None = None, frame: int | None = None):
    """The stored ground truth of ``scene`` (a :class:`~shadowlab.reference.truth.Truth`: shaded
    image, per-light visibility V with its variance, masks); raises
    :class:`~shadowlab.errors.ReferenceError_` naming the command that renders a missing one.

    >>> load_reference("parallel_planes").lights["panel"].V.shape
    (128, 128)
    """
    truth, _ = store.load(scene_spec(scene, resolution, frame))
    return truth


def compare(frame: FrameContext, truth, result: ShadowResult, *, light: str | None = None) -> dict:
    """Metrics of ``result`` against ``truth``: those of ``shadowlab compare`` (shaded image: RMSE,
    FLIP, penumbra RMSE, ...; visibility pooled over the lights: ``vis_rmse``,
    ``vis_rmse_penumbra``, ``leak_rate``, ``overdark_rate``, ...); with ``light``, the visibility
    metrics of that light alone (``rmse``, ``rmse_penumbra``, ``leak_rate``, ...).

    >>> fr = make_frame(load_scene("parallel_planes"))
    >>> m = compare(fr, load_reference("parallel_planes"), render_technique(fr, "hard"), light="panel")
    >>> m["leak_rate"] == 0.0 and m["rmse_penumbra"] > 0.2
    True
    """
    if light is None:
        metrics, _, _ = technique_metrics(frame, truth, result)
        return metrics
    if light not in truth.lights:
        raise InputError(f"no light {light!r} in the truth; its lights: {', '.join(truth.lights)}")
    valid = truth.mask & frame.lit_mask(light)
    return compare_visibility(visibility(frame, result, light), truth.lights[light].V, valid)


def gate_image(image, reference, *, target: str | None = None, light: str | None = None, name: str = "gate",
               **thresholds) -> GateResult:
    """Gate ``image`` (H×W×3 shaded or H×W visibility, a numpy array from anywhere) against
    ``reference`` (a truth from :func:`load_reference`, or an array of the same shape) with the
    CI gates' thresholds as keywords: budgets (``rmse=0.01``, ``flip=0.05``, ``vis_rmse_penumbra=...``)
    and statistical settings (``alpha``, ``atol``, ...; none: the statistical test with its
    defaults). Returns the result (``passed``, ``lines()``); never raises on a failed check.

    >>> import numpy as np
    >>> gate_image(np.full((4, 4), 0.5), np.full((4, 4), 0.5), rmse=0.0).passed
    True
    """
    arr = np.asarray(image)
    if target is None:
        target = "shaded" if arr.ndim == 3 and arr.shape[-1] == 3 else "visibility"
    return check(arr, reference, from_keywords(thresholds, where=f"gate {name!r}"), target=target, light=light,
                 name=name)


def techniques_for(scene=None) -> dict:
    """Every registered technique -> None where it applies to ``scene`` (a name, path or loaded
    scene; None: any scene) and can run on this machine, else the reason it does not
    (:meth:`~shadowlab.techniques.base.Technique.unsupported`, then ``unavailable``).

    >>> t = techniques_for("parallel_planes")
    >>> t["pcss"] is None, "area" in t["dpsv"]
    (True, True)
    """
    spec = None if scene is None else getattr(scene, "spec", None) or scene_spec(scene)
    return {n: (None if spec is None else t.unsupported(spec)) or t.unavailable()
            for n, t in ((n, _techniques.get(n)) for n in _techniques.names())}


def shaded_image(frame: FrameContext, visibility=None) -> np.ndarray:
    """The shaded image (H, W, 3) Σ_L U_L·V_L that ``shadowlab compare`` measures: the frame's
    unshadowed light U_L of each light times its visibility V_L, summed over the lights.
    ``visibility``: a technique's result (:func:`render_technique`; its coloured visibility where it
    has one), or {light: (H, W) image} from anywhere, e.g. your engine (one value per pixel, applied
    to each of its sub-pixels); None: every light unshadowed (V = 1). A light left out of the dict is
    unshadowed too.

    >>> fr = make_frame(load_scene("contact", resolution=(32, 24)))
    >>> lit = shaded_image(fr)
    >>> hard = render_technique(fr, "hard")
    >>> v = visibility(fr, hard, "key")
    >>> bool(np.allclose(shaded_image(fr, {"key": v}), shaded_image(fr, hard), atol=1e-6))
    True
    >>> bool((shaded_image(fr, hard) <= lit + 1e-6).all()), bool(np.allclose(shaded_image(fr, {"key": 0 * v}), 0))
    (True, True)
    """
    lights = [l.name for l in frame.lights]
    if isinstance(visibility, ShadowResult):
        return compose(frame, visibility.visibility, visibility.colour)
    vis = dict(visibility or {})
    unknown = sorted(set(vis) - set(lights))
    if unknown:
        raise InputError(f"no light {unknown[0]!r} in this frame; its lights: {', '.join(lights)}")
    gb = frame.gbuffer
    flat = {}
    for name in lights:
        img = np.asarray(vis.get(name, 1.0), dtype=np.float32)
        if img.ndim == 0:
            img = np.full((gb.height, gb.width), float(img), np.float32)
        if img.shape != (gb.height, gb.width):
            raise InputError(f"visibility of light {name!r} is {img.shape}, not the frame's (H, W) = "
                             f"{(gb.height, gb.width)}")
        flat[name] = np.repeat(img.reshape(-1), gb.ss * gb.ss)
    return compose(frame, flat)


def load_preset(path) -> dict:
    r"""The values of a preset file (TOML or JSON, e.g. the ``preset.toml`` of ``shadowlab fit``):
    {technique: {parameter: value}}, each value validated by its technique's declaration; pass a
    technique's to :func:`render_technique`. InputError (exit 2) names the file and the problem.

    >>> import pathlib, tempfile
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "preset.toml"
    >>> _ = p.write_text('name = "soft"\n[pcss]\nlight_scale = 0.75\n[pcf]\nkernel = 5\n')
    >>> load_preset(p)
    {'pcss': {'light_scale': 0.75}, 'pcf': {'kernel': 5}}
    >>> fr = make_frame(load_scene("contact", resolution=(32, 24)))
    >>> sorted(render_technique(fr, "pcss", **load_preset(p)["pcss"]).visibility)
    ['key']
    """
    return {t: dict(v) for t, v in _load_preset(path).values.items()}
