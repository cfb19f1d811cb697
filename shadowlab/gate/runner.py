"""Run a gate file: load each gate's stored reference and candidate, check, write JUnit + HTML.

Order of work (so that bad input is refused before anything is written): the whole gate file is
validated (:func:`~shadowlab.gate.gatefile.load_gate_file`); then gate by gate the reference is
loaded (missing or stale: :class:`~shadowlab.errors.ReferenceError_`, exit 2), the candidate is
rendered or read (NaN/Inf, wrong size, missing channels: :class:`~shadowlab.errors.InputError`,
exit 2) and checked. Only when every gate has been evaluated are ``junit.xml`` and ``index.html``
written to the output directory. References are only read, never written.

The output directory is checked first (:func:`shadowlab.io.outdir.claim_dir`): never inside
the reference store, not a file, and an existing directory only if shadowlab made it (it holds
``.shadowlab-report``) or with ``force``. An interrupted run (SIGINT, SIGTERM) does not look green:
``junit.xml`` is written with an ``interrupted`` error and the gates finished so far, and the
interruption propagates (exit 130 / 143).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import drjit as dr
import numpy as np

from .. import backend
from ..errors import InputError, Interrupted
from ..io.exr import read_exr
from ..reference import store
from ..reference.truth import LightTruth, Truth, render_truth
from ..render.frame import make_frame
from ..render.shading import compose
from ..io.outdir import MARKER, claim_dir, marker_text
from ..pipeline import check_memory
from ..scene import load
from ..scene.spec import load_spec, resolve
from ..techniques import base as tbase
from .check import GateResult, check, truth_target
from .gatefile import GateFile, GateSpec, gate_frames, load_gate_file
from .html import write_page
from .junit import write_junit

__all__ = ["run_gates", "run_gate_file", "exr_candidate", "truth_from_channels"]


# ------------------------------------------------------------------------------------------ EXR
def truth_from_channels(ch: dict):
    """A :class:`~shadowlab.reference.truth.Truth` from the channels of a shadowlab ``truth.exr``
    (another reference used as a candidate), or None if the file does not have that layout."""
    lights = sorted(k[2:] for k in ch if k.startswith("V.") and not k.endswith(".se"))
    need = ["mask", "shaded.R", "shaded.G", "shaded.B", "shaded.var.R", "shaded.var.G", "shaded.var.B"]
    for n in lights:
        need += [f"V.{n}.se", f"B.{n}"] + [f"U.{n}.{c}" for c in "RGB"]
    if not lights or any(k not in ch for k in need):
        return None
    rgb = lambda p: np.stack([ch[f"{p}.{c}"] for c in "RGB"], -1) if f"{p}.R" in ch else None  # noqa: E731
    lt = {n: LightTruth(V=ch[f"V.{n}"], V_se=ch[f"V.{n}.se"], A=ch.get(f"A.{n}", ch[f"V.{n}"]),
                        A_se=ch.get(f"A.{n}.se", ch[f"V.{n}.se"]), samples=ch.get(f"N.{n}", ch[f"B.{n}"] * 0),
                        bound=ch[f"B.{n}"]) for n in lights}
    return Truth(lights=lt, U={n: rgb(f"U.{n}") for n in lights}, shaded=rgb("shaded"), shaded_var=rgb("shaded.var"),
                 mitsuba=rgb("mitsuba"), mitsuba_var=rgb("mitsuba.var"), mask=ch["mask"] > 0.5,
                 view_depth=ch.get("depth", ch["mask"] * 0))


def _rgb_names(prefix: str) -> list[str]:
    return [f"{prefix}.{c}" if prefix else c for c in "RGB"]


def _pick(ch: dict, prefix: str, rgb: bool):
    if rgb:
        names = _rgb_names(prefix)
        return np.stack([ch[n] for n in names], -1) if all(n in ch for n in names) else None
    return ch.get(prefix)


def exr_candidate(path, target: str, light: str | None, channel: str | None = None,
                  variance: str | None = None, std_error: str | None = None):
    """(image, variance or None, its degrees of freedom or None) of an EXR candidate for ``target``.

    ``channel`` is a prefix: ``P.R|G|B`` (or plain ``R|G|B`` for ``channel = ""``) for the RGB
    targets, the channel ``P`` itself for a visibility target. Without it: a shadowlab
    ``truth.exr`` gives its target image and variance exactly as the reference does
    (:func:`~shadowlab.gate.check.truth_target`, with its degrees of freedom); otherwise RGB targets look for
    ``shaded.*`` then
    ``R|G|B``, a visibility target for ``V.<light>``, ``shadow.<light>``, ``<light>`` or the only
    channel. The variance is ``variance`` (a prefix like the image's) or ``std_error`` squared; by
    default ``<P>.var`` (RGB or single) or ``<P>.se`` squared if present, else none (exact)."""
    ch = read_exr(path)
    rgb = target != "visibility"
    if channel is None and variance is None and std_error is None:
        tr = truth_from_channels(ch)
        if tr is not None:
            if target == "mitsuba" and tr.mitsuba is None:
                raise InputError(f"{path} is a truth file without mitsuba.R|G|B channels; pick channel = \"shaded\"")
            t = truth_target(tr, target, light)
            return t.image, t.var, t.dof
    if channel is None:
        tries = ["shaded", ""] if rgb else [f"V.{light}", f"shadow.{light}", str(light)]
        channel = next((p for p in tries if _pick(ch, p, rgb) is not None), None)
        if channel is None and not rgb and len(ch) == 1:
            channel = next(iter(ch))
        if channel is None:
            want = "shaded.R|G|B or R|G|B" if rgb else f"V.{light}, shadow.{light} or {light}"
            raise InputError(f"{path}: no {want} channel(s) for target {target!r}; its channels: "
                             f"{', '.join(sorted(ch))}. Name the candidate's channel with channel = \"...\"")
    img = _pick(ch, channel, rgb)
    if img is None:
        want = ", ".join(_rgb_names(channel)) if rgb else channel
        raise InputError(f"{path}: channel(s) {want} not found for target {target!r}; its channels: "
                         f"{', '.join(sorted(ch))}")
    var = None
    if variance is not None:
        var = _pick(ch, variance, rgb)
        if var is None:
            raise InputError(
                f"{path}: variance channel(s) {variance!r} not found; its channels: {', '.join(sorted(ch))}"
            )
    elif std_error is not None:
        se = _pick(ch, std_error, rgb)
        if se is None:
            raise InputError(
                f"{path}: std_error channel(s) {std_error!r} not found; its channels: {', '.join(sorted(ch))}"
            )
        var = np.asarray(se, np.float64) ** 2
    else:
        for suffix, sq in ((".var", False), (".se", True)):
            v = _pick(ch, f"{channel}{suffix}" if channel else suffix[1:], rgb)
            if v is not None:
                var = np.asarray(v, np.float64) ** 2 if sq else v
                break
    return np.asarray(img, np.float64), (None if var is None else np.asarray(var, np.float64)), None


# ------------------------------------------------------------------------------------------ run
class _Context:
    """Scenes, references and frames shared by the gates of one run (loaded once each)."""

    def __init__(self, gf: GateFile, variant=None):
        self.gf, self.variant = gf, variant
        self.specs, self.truths, self.scenes, self.frames = {}, {}, {}, {}

    def spec(self, g: GateSpec):
        key = (g.scene, g.resolution, g.frame)
        if key not in self.specs:
            spec = load_spec(resolve(g.scene))
            spec = spec.with_resolution(*g.resolution) if g.resolution else spec
            self.specs[key] = spec if g.frame is None else spec.at_frame(g.frame)
        return self.specs[key]

    def truth(self, g: GateSpec):
        key = (g.scene, g.resolution, g.frame)
        if key not in self.truths:
            spec = self.spec(g)
            self.truths[key] = store.load(spec, spec.camera.resolution, self.gf.references)
        return self.truths[key]

    def scene(self, g: GateSpec):
        key = (g.scene, g.resolution, g.frame)
        if key not in self.scenes:
            base_key = (g.scene, g.resolution, None)
            if base_key not in self.scenes:  # the geometry is loaded once; a frame only gets its own sensor
                backend.init(self.variant)
                self.scenes[base_key] = load(g.scene, resolution=g.resolution)
            self.scenes[key] = self.scenes[base_key] if g.frame is None else self.scenes[base_key].at_frame(g.frame)
        return self.scenes[key]

    def frame(self, g: GateSpec, seed: int | None = None):
        _, meta = self.truth(g)
        seed = int(meta.get("seed", 0)) if seed is None else seed
        key = (g.scene, g.resolution, g.frame, seed)
        if key not in self.frames:
            self.frames[key] = make_frame(self.scene(g), ss=int(meta.get("supersampling", 1)), seed=seed)
        return self.frames[key]


def _technique_candidate(ctx: _Context, g: GateSpec):
    frame = ctx.frame(g)
    t = tbase.get(g.candidate.technique)
    params = t.resolve(g.candidate.params)
    res = t.render(frame, params)
    dr.eval(*res.visibility.values())
    vis = {l.name: frame.image(res.visibility[l.name]) for l in frame.lights}
    img = vis[g.light] if g.target == "visibility" else compose(frame, res.visibility, res.colour)
    return img, None, None, vis


def _truth_candidate(ctx: _Context, g: GateSpec):
    _, meta = ctx.truth(g)
    if int(meta.get("seed", 0)) == g.candidate.seed:
        raise InputError(f"gate {g.name!r}: candidate seed {g.candidate.seed} is the reference's own seed, so the "
                         "candidate would be the same bits; pick another seed")
    frame = ctx.frame(g, seed=g.candidate.seed)
    s = meta.get("samples", {})
    tr = render_truth(frame, k=int(meta.get("stats", {}).get("strata", 8)), target_se=float(s.get("target_se", 0.005)),
                      max_rounds=int(s.get("max_rounds", 64)), seed=g.candidate.seed,
                      spp=int(s.get("mitsuba_spp", 256)) if g.target == "mitsuba" else 0)
    t = truth_target(tr, g.target, g.light)
    return t.image, t.var, t.dof, None


def run_gate(ctx: _Context, g: GateSpec) -> GateResult:
    """Evaluate one gate of a loaded gate file."""
    t0 = time.perf_counter()
    truth, meta = ctx.truth(g)
    c = g.candidate
    if c.kind == "technique":
        img, var, dof, vis = _technique_candidate(ctx, g)
    elif c.kind == "truth":
        img, var, dof, vis = _truth_candidate(ctx, g)
    else:
        img, var, dof = exr_candidate(c.path, g.target, g.light, c.channel, c.variance, c.std_error)
        vis = None
    try:
        res = check(img, truth, g.thresholds, target=g.target, light=g.light, candidate_var=var, candidate_dof=dof,
                    visibility=vis, name=g.name)
    except InputError as e:
        raise InputError(f"gate {g.name!r} ({c.describe()}): {e}") from None
    spec = ctx.spec(g)
    res.info.update({"scene": spec.name, "candidate": c.describe(), "description": g.description,
                     **({} if g.frame is None else {"frame": g.frame}),
                     "reference": str(store.path_for(spec.name, spec.camera.resolution, ctx.gf.references,
                                                     frame=spec.frame)),
                     "time_s": time.perf_counter() - t0})
    return res


def at_frames(gf: GateFile, gates: list, frame=None, frames=None) -> list:
    """``shadowlab gate --frame N`` / ``--frames A:B``: every gate at those frames (instead of
    the gate file's own ``frame`` / ``frames``); a frame out of a scene's range exits 2."""
    if frame is None and frames is None:
        return gates
    out, seen = [], set()
    for g in gates:
        key = g.group or g.name
        if key in seen:
            continue
        seen.add(key)
        spec = load_spec(resolve(g.scene))
        sel = gate_frames(f"{gf.path}: gate {key!r} (--frame/--frames)", spec, frame,
                          None if frames is None else str(frames))
        out.extend(replace(g, name=key, group=None).at_frame(f) for f in sel)
    return out


def run_gates(gf: GateFile, only=None, variant=None, echo=None, into: list | None = None, frame=None,
              frames=None) -> list[GateResult]:
    """Evaluate the gates of ``gf`` (all, or the names in ``only``); ``echo(line)`` gets one line
    per check as soon as a gate is done. Bad input raises before any output file is written.
    ``into``: a list the results are appended to as they come (what was done when interrupted).
    ``frame`` / ``frames``: run every gate at these camera path frames (:func:`at_frames`)."""
    ctx = _Context(gf, variant)
    out = [] if into is None else into
    for g in at_frames(gf, gf.select(only), frame, frames):
        r = run_gate(ctx, g)
        out.append(r)
        if echo:
            for line in r.lines():
                echo(line)
    return out


OUTPUT_FILES = ("junit.xml", "index.html")


def _write_outputs(out_dir: Path, path, results, wall: float, interrupted: str | None = None):
    write_junit(out_dir / "junit.xml", results, suite=Path(path).stem, time_s=wall, interrupted=interrupted)
    title = f"shadowlab gate: {path}" + (f" (INTERRUPTED: {interrupted})" if interrupted else "")
    write_page(out_dir / "index.html", results, title=title)
    if not (out_dir / MARKER).is_file():
        (out_dir / MARKER).write_text(marker_text("gate", OUTPUT_FILES), encoding="utf-8")


def check_gates_memory(gates: list, variant=None) -> None:
    """Exit 3 before any gate runs when a gate's frame does not fit in the device's memory
    (:func:`shadowlab.pipeline.check_memory`; an image file candidate needs no frame)."""
    for g in gates:
        if g.candidate.kind == "exr":
            continue
        backend.init(variant)
        spec = load_spec(resolve(g.scene))
        spec = spec.with_resolution(*g.resolution) if g.resolution else spec
        tech = {g.candidate.technique: dict(g.candidate.params)} if g.candidate.kind == "technique" else {}
        check_memory(spec, tech)


def run_gate_file(path, out_dir=None, only=None, variant=None, echo=print,
                  force: bool = False, frame=None, frames=None) -> tuple[int, list[GateResult]]:
    """``shadowlab gate``: evaluate, print one line per check, write ``out_dir/junit.xml`` and
    ``out_dir/index.html``; returns (exit code 0 all passed / 1 a gate failed, results). The CLI
    turns 1 into :class:`~shadowlab.errors.GateFailure` (exit code 1). Interrupted (SIGINT /
    SIGTERM: :class:`~shadowlab.errors.Interrupted` or ``KeyboardInterrupt``), it writes a
    ``junit.xml`` that says so and re-raises."""
    gf = load_gate_file(path)
    if out_dir is not None:
        out_dir = Path(out_dir)
        claim_dir(out_dir, "gate", force=force, protected=[gf.references, store.root()], files=OUTPUT_FILES)
    t0 = time.perf_counter()
    results: list = []
    gates = at_frames(gf, gf.select(only), frame, frames)
    n_gates = len(gates)
    check_gates_memory(gates, variant)
    try:
        run_gates(gf, only=only, variant=variant, echo=echo, into=results, frame=frame, frames=frames)
    except (KeyboardInterrupt, Interrupted) as e:
        what = e.signal_name if isinstance(e, Interrupted) else "SIGINT"
        note = f"after {len(results)} of {n_gates} gates; the run is incomplete"
        if out_dir is not None:
            _write_outputs(
                out_dir, path, results, time.perf_counter() - t0, interrupted=f"interrupted by {what} {note}"
            )
            note += f" ({out_dir / 'junit.xml'} records it as an error)"
        if isinstance(e, Interrupted):
            e.detail = note
        raise
    wall = time.perf_counter() - t0
    n_fail = sum(not r.passed for r in results)
    n_checks = sum(len(r.checks) for r in results)
    if out_dir is not None:
        _write_outputs(out_dir, path, results, wall)
    if echo:
        echo(f"{len(results) - n_fail} of {len(results)} gates passed ({n_checks} checks, {wall:.1f} s)"
             + (f"; JUnit {out_dir / 'junit.xml'}, failures {out_dir / 'index.html'}" if out_dir is not None else ""))
    return (1 if n_fail else 0), results
