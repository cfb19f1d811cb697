"""The ``shadowlab`` command line (typer).

Exit codes (docs/cli.md; docs/ARCHITECTURE.md, Conventions): 0 ok, 1 a gate failed, 2 bad input
or usage, 3 environment (no usable libLLVM, a file that cannot be written, out of memory: a frame
that cannot fit is refused before any work, :func:`shadowlab.pipeline.check_memory`), 4
internal error (a bug: one "please report" line; the traceback with ``SHADOWLAB_DEBUG=1``), 130
SIGINT (Ctrl-C), 143 SIGTERM, 141 the reader of stdout went away (``| head``). A signal stops the command with one
line on stderr; the atomic writers remove what they had begun, so nothing partial is left.

Start-up: registering the commands imports only typer and the standard library; each command
imports the parts of shadowlab it runs (and with them Mitsuba, Dr.Jit, numpy, Dask) inside its own
function, so ``shadowlab --help`` and a usage error answer without loading them. This module is
the top layer, which nothing imports, so such an import cannot hide a cycle; tests/test_imports.py
allows function-level imports here only, and tests/test_cli_startup.py checks that ``--help``
loads no Mitsuba or Dr.Jit.
"""

from __future__ import annotations

import errno
import math
import os
import signal
import shutil
import sys
import traceback
from pathlib import Path
from typing import List, Optional

from .errors import INTERNAL_ERROR, GateFailure, InputError, Interrupted, ShadowlabError


def _startup_signal(signum, frame):
    """SIGINT / SIGTERM while the command is still importing its modules: nothing has been done
    yet, so one line and the exit code, no traceback (:func:`main` installs the real handlers)."""
    os.write(2, f"interrupted by {signal.Signals(signum).name} while starting; nothing was done\n".encode())
    os._exit(128 + signum)


def _command_process() -> bool:
    """This process runs the command (not a worker process started from it, which imports the
    command's main module again: multiprocessing's spawn)."""
    if getattr(sys.modules.get("__main__"), "__name__", "") == "__mp_main__":  # spawn re-runs our main module
        return False
    return __name__ == "__main__" or os.path.basename(sys.argv[0] or "") == "shadowlab"


if _command_process():
    for _s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_s, _startup_signal)

import typer  # noqa: E402 - after the start-up handler: importing typer is most of start-up

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Real-time shadow techniques against Mitsuba 3 ground truth.",
                  epilog="Exit codes: 0 ok, 1 a gate failed, 2 bad input or usage, 3 environment (no usable libLLVM, "
                         "a missing package, a file that cannot be written; a resolution or shadow map whose frame "
                         "does not fit in the device's memory, refused before any work with the memory needed and "
                         "free), 4 a shadowlab bug, 130 / 143 interrupted. See docs/cli.md.")

DEBUG_ENV = "SHADOWLAB_DEBUG"

# Constants that the options' help texts show when the commands are registered, copied here so
# that --help needs no Mitsuba; tests/test_cli_startup.py checks that they equal their sources.
SEED_MAX = 4294966                    # shadowlab.reference.truth.SEED_MAX
SCHEDULER_ENV = "SHADOWLAB_SCHEDULER"  # shadowlab.cluster.SCHEDULER_ENV


def _check_variant(value):
    if value is None:
        return value
    from . import backend
    if value not in backend.SUPPORTED_VARIANTS:
        raise typer.BadParameter(f"unknown variant {value!r}; choose one of {', '.join(backend.SUPPORTED_VARIANTS)}")
    return value


def _number(lo=None, hi=None, lo_open=False, what="a number"):
    """A typer callback: the value must be finite and in [lo, hi] (``lo_open``: (lo, hi])."""
    def cb(value):
        if value is None:
            return value
        if isinstance(value, float) and not math.isfinite(value):
            raise typer.BadParameter(f"{value} is not a finite number; expected {what}")
        if lo is not None and (value <= lo if lo_open else value < lo) or hi is not None and value > hi:
            left = "(" if lo_open else "["
            raise typer.BadParameter(f"{value} is out of range; expected {what} in {left}{lo}, {hi}]")
        return value
    return cb


VariantOpt = typer.Option(None, "--variant", callback=_check_variant,
                          help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb.")
ForceOpt = typer.Option(False, "--force", help="Write into an existing --out directory that shadowlab did not "
                        "create (only the report's own files are replaced).")


def _choose_references(value):
    """``--references DIR``: the reference store of this run (shadowlab.reference.location)."""
    if value is not None:
        from .reference.location import choose
        choose(value)
    return value


ReferencesOpt = typer.Option(None, "--references", callback=_choose_references, metavar="DIR",
                             help="The reference store (default: $SHADOWLAB_REFERENCES, else `references` in "
                             "[tool.shadowlab] of pyproject.toml or in shadowlab.toml, else ./references).")
FrameOpt = typer.Option(None, "--frame", help="Frame N of the scene's camera path (0..frames-1; a scene without "
                        "a path has only frame 0).")


def _init(variant):
    from . import backend
    backend.init(variant)


def builtin_names() -> list[str]:
    """The built-in scenes' names (:func:`shadowlab.scene.spec.builtin_names`; the ``scene``
    package loads Mitsuba, so it is imported when a command asks)."""
    from .scene.spec import builtin_names as names
    return names()


def _progress() -> bool:
    """Progress bars only on a terminal: in CI logs and pipes they are noise."""
    return sys.stderr.isatty()


def _split(csv: str) -> list[str]:
    return [x.strip() for x in csv.split(",") if x.strip()]


def _technique_list(text: str) -> list[str]:
    """``-t`` of compare: technique names separated by commas; consecutive ``LIGHT=TECHNIQUE``
    items make one technique per light (``sun=csm,softbox=pcss,pcss`` is that mix and pcss; a
    ``;`` separates two mixes)."""
    out = []
    for group in text.split(";"):
        mix: list[str] = []
        for item in _split(group):
            if "=" in item:
                mix.append(item)
                continue
            if mix:
                out.append(",".join(mix))
                mix = []
            out.append(item)
        if mix:
            out.append(",".join(mix))
    return out


@app.command()
def scenes(names: bool = typer.Option(False, "--names", help="Only the names, one per line.")):
    """List the built-in scenes."""
    from .scene.spec import load_spec, resolve
    for n in builtin_names():
        if names:
            typer.echo(n)
            continue
        spec = load_spec(resolve(n))
        lights = ", ".join(f"{l.name} ({l.kind})" for l in spec.lights)
        typer.echo(f"{n:18s} {spec.camera.resolution[0]}x{spec.camera.resolution[1]}  lights: {lights}")
        if spec.description:
            typer.echo(f"{'':18s} {spec.description}")


@app.command()
def techniques(markdown: bool = typer.Option(False, "--markdown", help="Print Markdown tables (README).")):
    """List the registered techniques with their parameter tables."""
    from .techniques import base
    for n in base.names():
        t = base.get(n)
        if markdown:
            typer.echo(
                f"### `{t.name}` — {t.title}\n\n{t.summary}\nSource: {t.source}\n\n{base.param_table_markdown(t)}\n"
            )
            continue
        typer.echo(f"{t.name}: {t.title}   [{t.source}]")
        for p in t.params:
            rng = p.range_text()
            typer.echo(f"    {p.name:24s} default {str(p.default):8s} {rng:22s} {p.units:12s} "
                       f"{'diff' if p.differentiable else '    '}  {p.doc}")


WorkersOpt = typer.Option(None, "--workers", help="Run the jobs on a local Dask cluster of N worker processes "
                          "(default: in this process).")
SchedulerOpt = typer.Option(None, "--scheduler", help="Run the jobs on an existing Dask cluster: tcp://HOST:8786 "
                            f"(default: ${SCHEDULER_ENV}).")


@app.command()
def reference(
    scenes_: Optional[List[str]] = typer.Argument(
        None, metavar="SCENE...", help="Built-in scene names or paths to .toml scenes."
    ),
    all_: bool = typer.Option(False, "--all", help="Every built-in scene."),
    resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing reference."),
    seed: int = typer.Option(
        0, "--seed", callback=_number(0, SEED_MAX, what="a seed"), help=f"Random seed, 0..{SEED_MAX}."
    ),
    target_se: float = typer.Option(
        0.005,
        "--target-se",
        callback=_number(0.0, 0.5, lo_open=True, what="a standard error"),
        help="Per-pixel standard error to reach, (0, 0.5].",
    ),
    spp: int = typer.Option(
        256,
        "--spp",
        callback=_number(0, 1 << 20, what="a sample count"),
        help="Samples per pixel of the mi.render image (0: none).",
    ),
    ss: int = typer.Option(1, "--ss", min=1, max=8, help="s×s shading points per pixel (supersampling)."),
    max_rounds: int = typer.Option(
        64, "--max-rounds", min=1, max=4096, help="Round cap of a penumbra pixel (8×8 shadow rays per round per light)."
    ),
    frame: Optional[int] = FrameOpt,
    frames: Optional[str] = typer.Option(
        None,
        "--frames",
        help="Frames A:B of each scene's camera path, both ends included, or all (every frame of each path).",
    ),
    workers: Optional[int] = WorkersOpt,
    scheduler: Optional[str] = SchedulerOpt,
    variant: Optional[str] = VariantOpt,
    references: Optional[str] = ReferencesOpt,
):
    """Render and store the Mitsuba ground truth of scenes (of each frame of a camera path: --frames)."""
    from .cluster import open_executor
    from .pipeline import parse_resolution, reference_batch
    _init(variant)
    names = _scene_list(scenes_, all_)
    with open_executor(workers, scheduler) as ex:
        done = reference_batch(names, parse_resolution(resolution), frames, frame=frame, force=force, seed=seed,
                               target_se=target_se, spp=spp, ss=ss, max_rounds=max_rounds, progress=_progress(),
                               executor=ex)
    for _, _, path, meta in done:
        _reference_done(path, meta)
    if len(done) > 1:
        typer.echo(f"{len(done)} references ({ex.kind}, {ex.workers} worker{'s' if ex.workers > 1 else ''})")


def _scene_list(scenes_, all_: bool) -> list[str]:
    """SCENE... or --all (not both)."""
    if all_ and scenes_:
        raise InputError(f"--all and scene names ({', '.join(scenes_)}): give one of them")
    return builtin_names() if all_ else list(scenes_ or [])


def _reference_done(path, meta):
    typer.echo(f"reference written to {path}: worst standard error {meta['max_std_error']:.4f}, "
               f"{meta['samples']['shadow_rays']:,} shadow rays, {meta['wall_time_s']:.1f} s")
    per = (meta.get("stats") or {}).get("per_light") or {}
    if len(per) > 1:
        typer.echo(
            "  per light: " + ", ".join(f"{n} {c['time_s']:.2f} s ({c['shadow_rays']:,} rays)" for n, c in per.items())
        )
    if (meta.get("stats") or {}).get("allocation") == "contribution":
        typer.echo("  allocation: contribution (each light's target error by its share of a pixel's light; the "
                   "shaded image keeps the target relative to the pixel's light)")
    tm = meta.get("target_missed") or {}
    if tm.get("pixels"):
        per = ", ".join(f"{n} {v['pixels']}" for n, v in tm["lights"].items())
        typer.echo(f"warning: {tm['pixels']} pixels ({per}) kept a standard error above the target {tm['target_se']:g} "
                   f"after the round cap of {tm['max_rounds']} rounds (worst {tm['worst_se']:.4f}; recorded in "
                   f"meta.json under target_missed); raise the cap with --max-rounds {min(4096, 4 * tm['max_rounds'])} "
                   "--force", err=True)
    for n, why in (meta.get("vacuous") or {}).items():   # lights that measure nothing (reference.vacuous)
        typer.echo(f"warning: light {n!r} {why}; its metrics are n/a in every comparison with this reference "
                   "(recorded in meta.json under vacuous)", err=True)


@app.command()
def references(store: Optional[str] = ReferencesOpt):
    """List the stored references (and the built-in scenes' committed ones the store does not hold)."""
    from .reference.location import locate
    from .reference.store import list_references
    loc = locate()
    typer.echo(f"reference store: {loc.path} (from {loc.source})", err=True)
    for r in list_references():
        m = r["meta"]
        se = m.get("max_std_error")
        se = f"{se:.4f}" if isinstance(se, (int, float)) and not isinstance(se, bool) else "   n/a"
        res = r["resolution"] + ("" if r.get("frame") is None else f" f{r['frame']}")
        typer.echo(f"{r['scene']:18s} {res:10s} worst se {se}  seed {m.get('seed')}  {r['path']}"
                   + ("  (built-in, read-only)" if r.get("builtin") else "")
                   + "".join(f"\n{'':18s} {p}" for p in r["status"]))


def _columns() -> int:
    """The terminal's width in characters (100 when it has none, e.g. in a pipe)."""
    return shutil.get_terminal_size((100, 24)).columns


def _compare(scene, techs, sets, out, resolution, variant, preset=None, force=False, frame=None, frames=None):
    from .pipeline import compare as cmp
    from .pipeline import parse_resolution
    from .report.frames import frames_summary
    from .report.tables import terminal_table
    _init(variant)
    run = cmp(scene, techs, sets, Path(out) if out else None, parse_resolution(resolution),
              params=preset.values if preset else None, preset=preset.info() if preset else None, force=force,
              progress=_progress(), frame=frame, frames=frames)
    typer.echo(frames_summary(run) if frames else terminal_table(run, width=_columns()))
    if out:
        typer.echo(f"report: {Path(out) / 'index.html'}")
    return run


@app.command()
def compare(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
            techniques_: Optional[str] = typer.Option(None, "--techniques", "-t", help="Comma-separated technique "
                                                      "names, or all (every technique that renders the scene; the "
                                                      "others listed with the reason) (default: hard,pcf, or the "
                                                      "preset's techniques)."),
            set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE, repeatable."),
            preset: Optional[str] = typer.Option(None, "--preset", help="Preset file (TOML/JSON, e.g. written by "
                                                 "`shadowlab fit`): {technique: {param: value}}; --set overrides it."),
            out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory."),
            resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
            force: bool = ForceOpt,
            frame: Optional[int] = FrameOpt,
            frames: Optional[str] = typer.Option(None, "--frames", help="Frames A:B of the camera path, both ends "
                                                 "included: a report per frame in OUT/frame_NNNN/ and a top-level "
                                                 "technique × frame table with the shimmer (two frames or more)."),
            variant: Optional[str] = VariantOpt, references: Optional[str] = ReferencesOpt):
    """Compare techniques with the ground truth; write index.html, summary.md, metrics.json."""
    from .fit.preset import load as load_preset
    out = out or f"reports/{Path(scene).stem}"
    pre = load_preset(preset) if preset else None
    techs = _technique_list(techniques_) if techniques_ is not None else list(pre.values) if pre else ["hard", "pcf"]
    if techs == ["all"]:
        techs = _applicable(scene)
    _compare(scene, techs, set_, out, resolution, variant, pre, force, frame, frames)


def _applicable(scene: str) -> list[str]:
    """``-t all``: every technique that renders ``scene``; those that cannot are listed with the reason."""
    from .api import techniques_for
    from .techniques import get
    why = techniques_for(scene)
    external = [n for n in why if get(n).external]
    for n, reason in why.items():
        if reason and n not in external:
            typer.echo(f"skipping {n}: {reason}", err=True)
    if external:
        typer.echo(f"not in all: {', '.join(external)} (real engines in a browser; name them with -t)", err=True)
    return [n for n, reason in why.items() if not reason and n not in external]


@app.command()
def demo(out: str = typer.Option("reports/demo", "--out", "-o"), force: bool = ForceOpt,
         resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's, "
                                                  "whose reference comes with shadowlab; another needs its own)."),
         variant: Optional[str] = VariantOpt, references: Optional[str] = ReferencesOpt):
    """Compare every registered technique that renders the built-in `contact` scene and print the table."""
    _compare("contact", _applicable("contact"), [], out, resolution, variant, force=force)


@app.command()
def fit(
    scenes_: List[str] = typer.Argument(
        ...,
        metavar="SCENE...",
        help="Built-in scene names or paths to .toml scenes; several: one preset minimising the mean loss over them.",
    ),
    technique: Optional[str] = typer.Option(None, "--technique", "-t", help="The technique to fit (all: as --all)."),
    params: Optional[str] = typer.Option(
        None,
        "--params",
        "-p",
        help="Comma-separated parameters to fit "
        "(default: the differentiable ones; hard: biases; pcf: kernel, softness).",
    ),
    method: str = typer.Option(
        "auto",
        "--method",
        help="auto | adam | golden | grid (auto: Adam on the "
        "differentiable parameters, derivative-free search on the others).",
    ),
    loss: Optional[str] = typer.Option(
        None,
        "--loss",
        help="rmse_penumbra | rmse | flip (default: "
        "rmse_penumbra; rmse for hard, whose biases act outside the penumbra).",
    ),
    all_: bool = typer.Option(False, "--all", help="Fit every technique's default parameters; one table."),
    set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE: fixed values and start values."),
    preset: Optional[str] = typer.Option(None, "--preset", help="Start from a preset file (--set overrides it)."),
    range_: List[str] = typer.Option([], "--range", help="[TECHNIQUE.]PARAM=LO:HI: the window searched."),
    steps: int = typer.Option(25, "--steps", help="Adam steps."),
    lr: float = typer.Option(0.1, "--lr", help="Adam learning rate, as a fraction of the window."),
    evals: int = typer.Option(20, "--evals", help="Evaluations per 1-D golden-section search."),
    grid_points: int = typer.Option(21, "--grid-points", help="Grid points per parameter (--method grid)."),
    rounds: int = typer.Option(0, "--rounds", help="Coordinate rounds over the parameters (0: automatic)."),
    out: Optional[str] = typer.Option(
        None,
        "--out",
        "-o",
        help="Report directory (default reports/fit/SCENE-TECHNIQUE, several scenes: SCENE1+SCENE2…-TECHNIQUE).",
    ),
    save_preset: Optional[str] = typer.Option(
        None,
        "--save-preset",
        help="Also write the fitted preset to this file (an existing file only if shadowlab fit wrote it, or --force).",
    ),
    preset_name: Optional[str] = typer.Option(None, "--preset-name", help="Name of the saved preset."),
    resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
    force: bool = typer.Option(
        False,
        "--force",
        help="Replace a --save-preset file and write into an --out directory that shadowlab did not create.",
    ),
    frame: Optional[int] = FrameOpt,
    frames: Optional[str] = typer.Option(
        None,
        "--frames",
        help="A:B, frames of the camera path (both ends included): one preset minimising the mean loss over them.",
    ),
    workers: Optional[int] = WorkersOpt,
    scheduler: Optional[str] = SchedulerOpt,
    variant: Optional[str] = VariantOpt,
    references: Optional[str] = ReferencesOpt,
):
    """Fit technique parameters to the ground truth; write DIR/fit.json, index.html, summary.md, preset.toml.
    Several scenes: one preset for all of them, each scene's loss beside it; each evaluation is one job
    per scene frame (--workers / --scheduler: on a Dask cluster, same results)."""
    from .cluster import open_executor
    from .fit import Budget
    from .fit import fit as run_fit
    from .fit.report import summary_table as fit_table
    from .fit.run import default_out as fit_default_out
    from .pipeline import parse_resolution
    _init(variant)
    if technique == "all":              # -t all: every technique that applies (the others listed with the reason)
        technique, all_ = None, True
    out = out or fit_default_out(scenes_, technique, all_)
    with open_executor(workers, scheduler) as ex:
        run = run_fit(scenes_, technique, params=params, method=method, loss=loss, all_techniques=all_, sets=set_,
                      preset=preset, ranges=range_, budget=Budget(steps, lr, evals, grid_points, rounds), out=out,
                      save_preset=save_preset, preset_name=preset_name, resolution=parse_resolution(resolution),
                      echo=lambda m: typer.echo(m, err=True), force=force, frame=frame, frames=frames, executor=ex)
    typer.echo(fit_table(run))
    typer.echo(f"report: {run['out']}")
    if save_preset:
        typer.echo(f"preset: {save_preset}")


@app.command()
def transfer(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene (needs its stored "
                                         "reference)."),
             technique: str = typer.Option(..., "--technique", "-t", help="The shadowlab technique whose values are "
                                           "transferred (hard, pcf, vsm)."),
             to: str = typer.Option(..., "--to", help="The engine technique that receives them (three:basic, "
                                    "three:pcf, three:vsm, babylon:basic)."),
             preset: Optional[str] = typer.Option(None, "--preset", help="The technique's values from a preset file "
                                                  "(e.g. the one shadowlab fit saved); --set overrides it."),
             set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE: the technique's values, or the "
                                            "engine's settings the transfer keeps (e.g. three:pcf.mapSize=1024)."),
             fit_engine: bool = typer.Option(False, "--fit-engine", help="Also fit the engine itself, for its error "
                                             "beside the transferred values'."),
             save_preset: Optional[str] = typer.Option(None, "--save-preset", help="Write the transferred values as "
                                                       "a preset of the engine's property names (.json or .toml)."),
             resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
             force: bool = typer.Option(False, "--force", help="Replace a --save-preset file shadowlab did not write."),
             variant: Optional[str] = VariantOpt, references: Optional[str] = ReferencesOpt):
    """Map a shadowlab technique's values onto an engine's shadow parameters (per receiver point in world
    units, the median over the points) and give the engine's error with them against its defaults."""
    from .fit.transfer import summary as transfer_summary
    from .fit.transfer import transfer as run_transfer
    from .pipeline import parse_resolution
    _init(variant)
    rec = run_transfer(scene, technique, to, sets=set_, preset=preset, resolution=parse_resolution(resolution),
                       save_preset=save_preset, force=force, fit_engine=fit_engine)
    typer.echo(transfer_summary(rec))
    if save_preset:
        typer.echo(f"preset: {save_preset}")


@app.command()
def sweep(scenes_: List[str] = typer.Argument(..., metavar="SCENE...", help="Built-in scene names or paths to "
                                              ".toml scenes (each needs its stored reference)."),
          technique: str = typer.Option(..., "--technique", "-t", help="The technique whose parameter is swept."),
          param: str = typer.Option(..., "--param", "-p", help="NAME=LO:HI:N: N >= 2 values from LO to HI (both "
                                    "included; int parameters rounded, duplicates merged); add :log for log spacing."),
          set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE: the other parameters, fixed "
                                         "(repeatable; default: their declared defaults)."),
          resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's)."),
          frame: Optional[int] = FrameOpt,
          out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory (default "
                                            "reports/sweep/TECHNIQUE-PARAM)."),
          force: bool = ForceOpt,
          workers: Optional[int] = WorkersOpt, scheduler: Optional[str] = SchedulerOpt,
          variant: Optional[str] = VariantOpt, references: Optional[str] = ReferencesOpt):
    """Every metric of a technique against one parameter, per scene; write sweep.json, summary.md, index.html."""
    from .pipeline import parse_resolution
    from .sweep import default_out as sweep_default_out
    from .sweep import summary_markdown as sweep_summary
    from .sweep import sweep as run_sweep
    _init(variant)
    out = out or str(sweep_default_out(technique, param))
    rec = run_sweep(scenes_, technique, param, sets=set_, resolution=parse_resolution(resolution), frame=frame,
                    out=Path(out), force=force, workers=workers, scheduler=scheduler, progress=_progress())
    typer.echo(sweep_summary(rec))
    typer.echo(f"report: {rec['report']}")


@app.command()
def export(
    scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
    out: str = typer.Option(..., "--out", "-o", help="Directory to write (scene.xml, meshes/, camera.json, ...)."),
    resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's)."),
    segments: int = typer.Option(64, "--segments", help="Tessellation of spheres, cylinders and disks."),
    spp: int = typer.Option(64, "--spp", help="Default samples per pixel written into scene.xml."),
    force: bool = typer.Option(False, "--force", help="Replace the exported files in an existing directory."),
    fmt: str = typer.Option("mitsuba", "--format", help="mitsuba (scene.xml, PLY, JSON) or gltf (scene.glb)."),
    variant: Optional[str] = VariantOpt,
):
    """Export a scene for another renderer: Mitsuba XML, PLY meshes, camera.json, lights.json; or glTF 2.0."""
    from .exchange.export import FORMATS, export_gltf, export_scene
    from .pipeline import parse_resolution
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    _init(variant)
    if fmt == "gltf":
        r = export_gltf(scene, Path(out), resolution=parse_resolution(resolution), segments=segments, force=force)
        W, H = r["manifest"]["resolution"]
        v = r["validation"]
        check = (f"glTF validator: {v['errors']} errors, {v['warnings']} warnings" if v.get("skipped") is None
                 else f"not validated: {v['skipped']}")
        typer.echo(f"exported {r['scene']} ({W}x{H}, {len(r['manifest']['lights'])} lights) to {r['path']}; {check}")
        for line in v.get("lines", []):
            typer.echo(f"  {line}")
        return
    m = export_scene(scene, Path(out), resolution=parse_resolution(resolution), segments=segments, spp=spp,
                     force=force)
    W, H = m["resolution"]
    typer.echo(f"exported {m['scene']} ({W}x{H}, scene hash {m['scene_hash'][:12]}) to {out}: scene.xml, "
               f"scene_mesh.xml, camera.json, lights.json, scene.json, {len(m['files']['meshes'])} PLY meshes"
               + (f", {len(m['files']['textures'])} textures" if m["files"]["textures"] else ""))


@app.command()
def ingest(
    scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
    image: str = typer.Argument(..., help="The EXR image rendered elsewhere."),
    channel: List[str] = typer.Option(
        [], "--channel", "-c", help="A light's visibility channel, NAME or NAME=LIGHT; repeatable."
    ),
    shaded: bool = typer.Option(False, "--shaded", help="The image is RGB direct light (R,G,B or LAYER.R|G|B)."),
    layer: Optional[str] = typer.Option(None, "--layer", help="With --shaded: the RGB layer's name."),
    against: Optional[str] = typer.Option(
        None,
        "--against",
        help="Truth compared with: V (default) or A for --channel; shaded (default) or mitsuba for --shaded.",
    ),
    resolution: Optional[str] = typer.Option(
        None, "--resolution", "-r", help="The reference's WxH (default: the image's size)."
    ),
    out: Optional[str] = typer.Option(
        None,
        "--out",
        "-o",
        help="Report directory (default "
        "reports/ingest/SCENE-IMAGE, -2, -3, … when it exists: a new ingest "
        "never replaces the previous one).",
    ),
    gate: Optional[str] = typer.Option(None, "--gate", help="Gate file to run on the image (exit 1 on failure)."),
    label: List[str] = typer.Option(
        [],
        "--label",
        help="TEXT: the image's name in the report (default: its "
        "file name); CHANNEL=TEXT: a channel's title; repeatable.",
    ),
    force: bool = ForceOpt,
    variant: Optional[str] = VariantOpt,
    references: Optional[str] = ReferencesOpt,
):
    """Compare an image rendered elsewhere with the stored ground truth; write a report."""
    from .exchange.ingest import default_out
    from .exchange.ingest import ingest as run_ingest
    from .pipeline import parse_resolution
    from .report.tables import terminal_table
    _init(variant)
    out = out or str(default_out(scene, image))
    names = [x for x in label if "=" not in x]
    if len(names) > 1:
        raise InputError(f"--label: one name for the image, got {', '.join(map(repr, names))}; title channels "
                         "with CHANNEL=TEXT")
    run = run_ingest(scene, image, channels=channel, shaded=shaded, layer=layer, against=against,
                     resolution=parse_resolution(resolution), out=Path(out), gate=gate, force=force,
                     label=names[0] if names else None, labels=[x for x in label if "=" in x])
    typer.echo(terminal_table(run, width=_columns()))
    for light, d in next(iter(run["techniques"].values()))["per_light"].items():
        typer.echo(f"{light}: " + ", ".join(f"{k} {v:.4g}" for k, v in d.items()))
    for note in run["ingest"]["notes"]:
        typer.echo(f"note: {note}")
    typer.echo(f"report: {Path(out) / 'index.html'}")
    g = run.get("gate")
    if g is not None:
        for line in g["lines"]:
            typer.echo(line)
        if not g["passed"]:
            raise GateFailure(f"gate failed on {image}: {', '.join(g['failed'])}")


@app.command()
def gate(gatefile: str = typer.Argument(..., help="Gate file (TOML), e.g. references/gates.toml."),
         out: str = typer.Option("reports/gate", "--out", "-o", help="Directory for junit.xml and index.html."),
         only: Optional[str] = typer.Option(None, "--only", help="Comma-separated gate names to run."),
         force: bool = ForceOpt,
         frame: Optional[int] = typer.Option(None, "--frame", help="Run every gate at frame N of its scene's camera "
                                             "path (instead of the gate file's frame/frames)."),
         frames: Optional[str] = typer.Option(None, "--frames", help="Run every gate at frames A:B (both ends "
                                              "included), one gate per frame, named NAME@frameN."),
         variant: Optional[str] = VariantOpt, references: Optional[str] = ReferencesOpt):
    """Gate candidates against stored references; exit 0 pass, 1 a gate failed, 2 bad input, 3 a gate's frame
    does not fit in memory (before any gate runs)."""
    from .gate import run_gate_file
    code, results = run_gate_file(gatefile, out_dir=Path(out), only=_split(only) if only else None, variant=variant,
                                  echo=typer.echo, force=force, frame=frame, frames=frames)
    if code:
        raise GateFailure(f"{sum(not r.passed for r in results)} gate(s) failed: "
                          f"{', '.join(r.name for r in results if not r.passed)}; see {Path(out) / 'index.html'}")


@app.command()
def bench(
    out: str = typer.Option("reports/bench", "--out", "-o"),
    quick: bool = typer.Option(False, "--quick", help="Small sizes (a smoke run, not for figures)."),
    only: Optional[str] = typer.Option(
        None,
        "--only",
        help="Run one part: sdf (SDF soft shadows, sdf.md), cascades (cascaded shadow maps, cascades.md), "
        "virtual (virtual shadow maps, virtual.md), dpsv (shadow maps fused with deep partitioned shadow volumes, "
        "dpsv.md), "
        "ssss (layered screen-space soft shadows against kernel and lights, ssss.md), "
        "scaling (the Dask executor on 1, 2, 4, 8 workers, scaling.md; not in the full run), truth (the ground "
        "truth's throughput against raw ray_test, truth.md) or frames (every technique's new and warm frame split "
        "into G-buffer, light views, technique and host time, its kernels and first host sync, beside raw ray_test; "
        "frames.md; not in the full run) or transfer (shadowlab's fitted pcf and hard transferred to three.js, "
        "beside the engine's defaults and its own fit; transfer.md; not in the full run: it needs the engines).",
    ),
    size: Optional[str] = typer.Option(None, "--size", help="WIDTHxHEIGHT of --only frames (default 1920x1080; "
                                       "e.g. 640x360 on a CPU)."),
    variant: Optional[str] = VariantOpt,
):
    """Measure ground-truth throughput and technique compile / warm run times."""
    from .bench import run as run_bench
    _init(variant)
    path_md = run_bench(Path(out), quick=quick, only=only, size=size)
    typer.echo(Path(path_md).read_text())


_signal_state = {"caught": None}


def _on_signal(signum, frame):
    """SIGINT / SIGTERM: stop the command by raising :class:`Interrupted` (once; a second signal
    while the writers clean up is ignored, so the cleanup finishes)."""
    if _signal_state["caught"] is not None:
        return
    _signal_state["caught"] = signum
    raise Interrupted(signum)


def _install_signal_handlers() -> dict:
    """Our handlers for SIGINT and SIGTERM, also where SIGINT was inherited as ignored (a
    background job of a script); returns the previous handlers."""
    _signal_state["caught"] = None
    old = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        try:
            old[s] = signal.signal(s, _on_signal)
        except ValueError:  # not the main thread (an embedding application): leave its handlers alone
            pass
    return old


def _environment_oserror(e: OSError) -> str | None:
    """The message of an OSError that is the machine's (permissions, full disk, read-only file
    system), or None."""
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT):
        what = f"{e.filename}" if e.filename else "a file"
        return (f"cannot write {what}: {e.strerror}; make the directory writable (or free disk space) and run "
                "the command again")
    return None


#: exit code when the reader of our output went away (`shadowlab techniques | head -1`): 128 + SIGPIPE, as a
#: program killed by SIGPIPE exits in a shell
PIPE_CLOSED = 128 + 13


def _broken_pipe(e) -> bool:
    return isinstance(e, BrokenPipeError) or isinstance(e, OSError) and e.errno == errno.EPIPE


def _pipe_closed() -> int:
    """The reader closed our stdout: stop quietly. As Python's docs advise (signal module, "Note on
    SIGPIPE"), stdout is pointed at /dev/null so that the flush at exit raises nothing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return PIPE_CLOSED


def _write_error(e: BaseException):
    """The exit-2/3 error of an OS error that is a path's or the machine's (io.outdir.write_error), or None."""
    from .io.outdir import write_error
    return write_error(getattr(e, "filename", None) or "a file", e)


def _internal_error(e: BaseException) -> int:
    typer.echo(f"internal error: {type(e).__name__}: {e}. This is a shadowlab bug; please report it with the "
               f"command line and its input files (set {DEBUG_ENV}=1 to print the traceback).", err=True)
    if os.environ.get(DEBUG_ENV, "") not in ("", "0"):
        traceback.print_exception(e, file=sys.stderr)
    return INTERNAL_ERROR


def _interrupted(signum: int, detail: str = "") -> int:
    name = Interrupted(signum).signal_name
    typer.echo(f"interrupted by {name}: " + (detail or "stopped; nothing partial was written (stored references "
               "and reports are as they were)"), err=True)
    return 128 + signum


def _exit_code(e: BaseException) -> int:
    """Print the one line for an exception that ended a command; return its exit code."""
    if isinstance(e, Interrupted):
        return _interrupted(e.signum, e.detail() if callable(e.detail) else e.detail)
    if _signal_state["caught"] is not None and not isinstance(e, SystemExit):
        # the signal arrived inside a C extension or an import, which wrapped it in its own error
        return _interrupted(_signal_state["caught"])
    if isinstance(e, ShadowlabError):
        typer.echo(f"error: {e}", err=True)
        return e.exit_code
    if isinstance(e, typer.Exit):
        return int(getattr(e, "exit_code", 0) or 0)
    if isinstance(e, typer.Abort):
        typer.echo("aborted", err=True)
        return 130
    if isinstance(e, typer.TyperException):  # usage errors: unknown option, missing argument
        if hasattr(e, "show"):
            e.show()
        else:
            typer.echo(f"error: {e}", err=True)
        return 2
    if isinstance(e, KeyboardInterrupt):
        typer.echo("interrupted; nothing stored was changed", err=True)
        return 130
    if isinstance(e, SystemExit):
        if _broken_pipe(e.__context__):  # click caught the EPIPE and exits 1, which means "a gate failed"
            return _pipe_closed()
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    if isinstance(e, MemoryError):
        typer.echo("error: out of memory; use a smaller --resolution, smaller shadow maps (shadow_map) or fewer "
                   "techniques at once", err=True)
        return 3
    if _broken_pipe(e):
        return _pipe_closed()
    if isinstance(e, OSError) and _environment_oserror(e) is not None:
        typer.echo(f"error: {_environment_oserror(e)}", err=True)
        return 3
    if isinstance(e, (OSError, RuntimeError)) and _write_error(e) is not None:  # e.g. EXDEV, /proc: ENOENT
        err = _write_error(e)
        typer.echo(f"error: {err}", err=True)
        return err.exit_code
    if isinstance(e, OSError) and e.errno in (errno.ENAMETOOLONG, errno.ELOOP, errno.ENOTDIR, errno.EISDIR):
        typer.echo(f"error: bad path {e.filename or ''}: {e.strerror}; give a shorter path or one whose folders "
                   "are directories", err=True)
        return 2
    return _internal_error(e)  # a bug: one line, not a traceback


def _run(argv) -> int:
    try:
        rc = app(args=argv, standalone_mode=False)
    except BaseException as e:  # noqa: BLE001 - every way out of a command gets its exit code and one line
        return _exit_code(e)
    if _signal_state["caught"] is not None:  # a signal swallowed on the way (typer: KeyboardInterrupt -> 130)
        return _interrupted(_signal_state["caught"])
    if isinstance(rc, int) and rc == 130:  # typer turned a KeyboardInterrupt into Exit(130) and returned it
        typer.echo("interrupted; nothing stored was changed", err=True)
        return 130
    return 0


def main(argv=None) -> int:
    """Entry point: run the typer app and map errors and signals to exit codes."""
    old = _install_signal_handlers()
    try:
        rc = _run(argv)
        sys.stdout.flush()  # here, not at exit: a reader that went away is seen now (exit PIPE_CLOSED)
        return rc
    except BrokenPipeError:
        return _pipe_closed()
    except Interrupted as e:  # arrived between the command's end and the exit
        return _interrupted(e.signum)
    finally:
        for s, h in old.items():   # the start-up handler's line would be wrong now: the default instead
            signal.signal(s, signal.SIG_DFL if h is _startup_signal else h)


if __name__ == "__main__":
    sys.exit(main())
