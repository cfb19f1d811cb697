"""The ``shadowlab`` command line (typer). Exit codes: 0 ok, 1 gate failed, 2 bad input or
usage, 3 environment (docs/ARCHITECTURE.md, Conventions)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Optional

import typer

from . import backend
from .bench import run as run_bench
from .errors import GateFailure, ShadowlabError
from .exchange.export import export_scene
from .exchange.ingest import ingest as run_ingest
from .fit import Budget
from .fit import fit as run_fit
from .fit.preset import load as load_preset
from .fit.report import summary_table as fit_table
from .gate.gatefile import SEED_MAX
from .gate.runner import run_gate_file
from .pipeline import compare as cmp
from .pipeline import parse_resolution
from .pipeline import reference as ref
from .reference.store import list_references
from .report import summary_table
from .scene.spec import builtin_names, load_spec, resolve
from .techniques import base

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Real-time shadow techniques against Mitsuba 3 ground truth.")

VariantOpt = typer.Option(None, "--variant", help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb.")


def _init(variant):
    backend.init(variant)


def _split(csv: str) -> list[str]:
    return [x.strip() for x in csv.split(",") if x.strip()]


@app.command()
def scenes(names: bool = typer.Option(False, "--names", help="Only the names, one per line.")):
    """List the built-in scenes."""
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
    for n in base.names():
        t = base.get(n)
        if markdown:
            typer.echo(f"### `{t.name}` — {t.title}\n\n{t.summary}\nSource: {t.source}\n\n{base.param_table_markdown(t)}\n")
            continue
        typer.echo(f"{t.name}: {t.title}   [{t.source}]")
        for p in t.params:
            rng = p.range_text()
            typer.echo(f"    {p.name:24s} default {str(p.default):8s} {rng:22s} {p.units:12s} "
                       f"{'diff' if p.differentiable else '    '}  {p.doc}")


@app.command()
def reference(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
              resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's)."),
              force: bool = typer.Option(False, "--force", help="Replace an existing reference."),
              seed: int = typer.Option(0, "--seed", min=0, max=SEED_MAX, help=f"Random seed, 0..{SEED_MAX}."),
              target_se: float = typer.Option(0.005, "--target-se", help="Per-pixel standard error to reach."),
              spp: int = typer.Option(256, "--spp", help="Samples per pixel of the mi.render image."),
              ss: int = typer.Option(1, "--ss", min=1, max=8, help="s×s shading points per pixel (supersampling)."),
              variant: Optional[str] = VariantOpt):
    """Render and store the Mitsuba ground truth of a scene."""
    _init(variant)
    path, meta = ref(scene, parse_resolution(resolution), force=force, seed=seed, target_se=target_se, spp=spp, ss=ss)
    typer.echo(f"reference written to {path}: worst standard error {meta['max_std_error']:.4f}, "
               f"{meta['samples']['shadow_rays']:,} shadow rays, {meta['wall_time_s']:.1f} s")


@app.command()
def references():
    """List the stored references."""
    for r in list_references():
        m = r["meta"]
        typer.echo(f"{r['scene']:18s} {r['resolution']:10s} worst se {m.get('max_std_error', float('nan')):.4f}  "
                   f"seed {m.get('seed')}  {r['path']}")


def _compare(scene, techs, sets, out, resolution, variant, preset=None):
    _init(variant)
    run = cmp(scene, techs, sets, Path(out) if out else None, parse_resolution(resolution),
              params=preset.values if preset else None, preset=preset.info() if preset else None)
    typer.echo(summary_table(run))
    if out:
        typer.echo(f"report: {Path(out) / 'index.html'}")
    return run


@app.command()
def compare(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
            techniques_: Optional[str] = typer.Option(None, "--techniques", "-t", help="Comma-separated technique "
                                                      "names (default: hard,pcf, or the preset's techniques)."),
            set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE, repeatable."),
            preset: Optional[str] = typer.Option(None, "--preset", help="Preset file (TOML/JSON, e.g. written by "
                                                 "`shadowlab fit`): {technique: {param: value}}; --set overrides it."),
            out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory."),
            resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
            variant: Optional[str] = VariantOpt):
    """Compare techniques with the ground truth; write index.html, summary.md, metrics.json."""
    out = out or f"reports/{Path(scene).stem}"
    pre = load_preset(preset) if preset else None
    techs = _split(techniques_) if techniques_ is not None else list(pre.values) if pre else ["hard", "pcf"]
    _compare(scene, techs, set_, out, resolution, variant, pre)


@app.command()
def demo(out: str = typer.Option("reports/demo", "--out", "-o"), variant: Optional[str] = VariantOpt):
    """Compare every registered technique on the built-in `contact` scene and print the table."""
    _compare("contact", base.names(), [], out, None, variant)


@app.command()
def fit(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
        technique: Optional[str] = typer.Option(None, "--technique", "-t", help="The technique to fit."),
        params: Optional[str] = typer.Option(None, "--params", "-p", help="Comma-separated parameters to fit "
                                             "(default: the differentiable ones; hard: biases; pcf: kernel, softness)."),
        method: str = typer.Option("auto", "--method", help="auto | adam | golden | grid (auto: Adam on the "
                                   "differentiable parameters, derivative-free search on the others)."),
        loss: Optional[str] = typer.Option(None, "--loss", help="rmse_penumbra | rmse | flip (default: "
                                           "rmse_penumbra; rmse for hard, whose biases act outside the penumbra)."),
        all_: bool = typer.Option(False, "--all", help="Fit every technique's default parameters; one table."),
        set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE: fixed values and start values."),
        preset: Optional[str] = typer.Option(None, "--preset", help="Start from a preset file (--set overrides it)."),
        range_: List[str] = typer.Option([], "--range", help="[TECHNIQUE.]PARAM=LO:HI: the window searched."),
        steps: int = typer.Option(25, "--steps", help="Adam steps."),
        lr: float = typer.Option(0.1, "--lr", help="Adam learning rate, as a fraction of the window."),
        evals: int = typer.Option(20, "--evals", help="Evaluations per 1-D golden-section search."),
        grid_points: int = typer.Option(21, "--grid-points", help="Grid points per parameter (--method grid)."),
        rounds: int = typer.Option(0, "--rounds", help="Coordinate rounds over the parameters (0: automatic)."),
        out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory (default reports/fit/SCENE-TECHNIQUE)."),
        save_preset: Optional[str] = typer.Option(None, "--save-preset", help="Also write the fitted preset to this file."),
        preset_name: Optional[str] = typer.Option(None, "--preset-name", help="Name of the saved preset."),
        resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
        variant: Optional[str] = VariantOpt):
    """Fit technique parameters to the ground truth; write DIR/fit.json, index.html, summary.md, preset.toml."""
    _init(variant)
    out = out or f"reports/fit/{Path(scene).stem}-{'all' if all_ else technique or 'fit'}"
    run = run_fit(scene, technique, params=params, method=method, loss=loss, all_techniques=all_, sets=set_,
                  preset=preset, ranges=range_, budget=Budget(steps, lr, evals, grid_points, rounds), out=out,
                  save_preset=save_preset, preset_name=preset_name, resolution=parse_resolution(resolution),
                  echo=lambda m: typer.echo(m, err=True))
    typer.echo(fit_table(run))
    typer.echo(f"report: {run['out']}")
    if save_preset:
        typer.echo(f"preset: {save_preset}")


@app.command()
def export(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
           out: str = typer.Option(..., "--out", "-o", help="Directory to write (scene.xml, meshes/, camera.json, ...)."),
           resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="WxH (default: the scene's)."),
           segments: int = typer.Option(64, "--segments", help="Tessellation of spheres, cylinders and disks."),
           spp: int = typer.Option(64, "--spp", help="Default samples per pixel written into scene.xml."),
           force: bool = typer.Option(False, "--force", help="Replace the exported files in an existing directory."),
           variant: Optional[str] = VariantOpt):
    """Export a scene for another renderer: Mitsuba XML, PLY meshes, camera.json, lights.json."""
    _init(variant)
    m = export_scene(scene, Path(out), resolution=parse_resolution(resolution), segments=segments, spp=spp,
                     force=force)
    W, H = m["resolution"]
    typer.echo(f"exported {m['scene']} ({W}x{H}, scene hash {m['scene_hash'][:12]}) to {out}: scene.xml, "
               f"scene_mesh.xml, camera.json, lights.json, scene.json, {len(m['files']['meshes'])} PLY meshes"
               + (f", {len(m['files']['textures'])} textures" if m["files"]["textures"] else ""))


@app.command()
def ingest(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
           image: str = typer.Argument(..., help="The EXR image rendered elsewhere."),
           channel: List[str] = typer.Option([], "--channel", "-c", help="A light's visibility channel, NAME or "
                                             "NAME=LIGHT; repeatable."),
           shaded: bool = typer.Option(False, "--shaded", help="The image is RGB direct light (R,G,B or LAYER.R|G|B)."),
           layer: Optional[str] = typer.Option(None, "--layer", help="With --shaded: the RGB layer's name."),
           against: Optional[str] = typer.Option(None, "--against", help="Truth compared with: V (default) or A "
                                                 "for --channel; shaded (default) or mitsuba for --shaded."),
           resolution: Optional[str] = typer.Option(None, "--resolution", "-r", help="The reference's WxH "
                                                    "(default: the image's size)."),
           out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory (default "
                                             "reports/ingest/SCENE)."),
           gate: Optional[str] = typer.Option(None, "--gate", help="Gate file to run on the image (exit 1 on failure)."),
           variant: Optional[str] = VariantOpt):
    """Compare an image rendered elsewhere with the stored ground truth; write a report."""
    out = out or f"reports/ingest/{Path(scene).stem}"
    run = run_ingest(scene, image, channels=channel, shaded=shaded, layer=layer, against=against,
                     resolution=parse_resolution(resolution), out=Path(out), gate=gate)
    typer.echo(summary_table(run))
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
         variant: Optional[str] = VariantOpt):
    """Gate candidates against stored references; exit 0 pass, 1 a gate failed, 2 bad input."""
    code, results = run_gate_file(gatefile, out_dir=Path(out), only=_split(only) if only else None, variant=variant,
                                  echo=typer.echo)
    if code:
        raise GateFailure(f"{sum(not r.passed for r in results)} gate(s) failed: "
                          f"{', '.join(r.name for r in results if not r.passed)}; see {Path(out) / 'index.html'}")


@app.command()
def bench(out: str = typer.Option("reports/bench", "--out", "-o"),
          quick: bool = typer.Option(False, "--quick", help="Small sizes (a smoke run, not for figures)."),
          only: Optional[str] = typer.Option(None, "--only", help="Run one part: sdf (SDF soft shadows, sdf.md)."),
          variant: Optional[str] = VariantOpt):
    """Measure ground-truth throughput and technique compile / warm run times."""
    _init(variant)
    path_md = run_bench(Path(out), quick=quick, only=only)
    typer.echo(Path(path_md).read_text())


def main(argv=None) -> int:
    """Entry point: run the typer app and map errors to exit codes."""
    try:
        app(args=argv, standalone_mode=False)
    except ShadowlabError as e:
        typer.echo(f"error: {e}", err=True)
        return e.exit_code
    except typer.Exit as e:
        return int(getattr(e, "exit_code", 0) or 0)
    except typer.Abort:
        typer.echo("aborted", err=True)
        return 130
    except typer.TyperException as e:  # usage errors: unknown option, missing argument
        if hasattr(e, "show"):
            e.show()
        else:
            typer.echo(f"error: {e}", err=True)
        return 2
    except KeyboardInterrupt:
        typer.echo("interrupted; nothing stored was changed", err=True)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
