"""The ``shadowlab`` command line (typer). Exit codes: 0 ok, 1 gate failed, 2 bad input or
usage, 3 environment (DESIGN.md, Conventions)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Optional

import typer

from .errors import ShadowlabError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Real-time shadow techniques against Mitsuba 3 ground truth.")

VariantOpt = typer.Option(None, "--variant", help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb.")


def _init(variant):
    from . import backend
    backend.init(variant)


def _split(csv: str) -> list[str]:
    return [x.strip() for x in csv.split(",") if x.strip()]


@app.command()
def scenes(names: bool = typer.Option(False, "--names", help="Only the names, one per line.")):
    """List the built-in scenes."""
    from .scene.spec import builtin_names, load_spec, resolve
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
              seed: int = typer.Option(0, "--seed"),
              target_se: float = typer.Option(0.005, "--target-se", help="Per-pixel standard error to reach."),
              spp: int = typer.Option(256, "--spp", help="Samples per pixel of the mi.render image."),
              ss: int = typer.Option(1, "--ss", min=1, max=8, help="s×s shading points per pixel (supersampling)."),
              variant: Optional[str] = VariantOpt):
    """Render and store the Mitsuba ground truth of a scene."""
    from .pipeline import parse_resolution, reference as ref
    _init(variant)
    path, meta = ref(scene, parse_resolution(resolution), force=force, seed=seed, target_se=target_se, spp=spp, ss=ss)
    typer.echo(f"reference written to {path}: worst standard error {meta['max_std_error']:.4f}, "
               f"{meta['samples']['shadow_rays']:,} shadow rays, {meta['wall_time_s']:.1f} s")


@app.command()
def references():
    """List the stored references."""
    from .reference.store import list_references
    for r in list_references():
        m = r["meta"]
        typer.echo(f"{r['scene']:18s} {r['resolution']:10s} worst se {m.get('max_std_error', float('nan')):.4f}  "
                   f"seed {m.get('seed')}  {r['path']}")


def _compare(scene, techs, sets, out, resolution, variant):
    from .pipeline import compare as cmp, parse_resolution
    from .report import summary_table
    _init(variant)
    run = cmp(scene, techs, sets, Path(out) if out else None, parse_resolution(resolution))
    typer.echo(summary_table(run))
    if out:
        typer.echo(f"report: {Path(out) / 'index.html'}")
    return run


@app.command()
def compare(scene: str = typer.Argument(..., help="Built-in scene name or path to a .toml scene."),
            techniques_: str = typer.Option("hard,pcf", "--techniques", "-t", help="Comma-separated technique names."),
            set_: List[str] = typer.Option([], "--set", help="TECHNIQUE.PARAM=VALUE, repeatable."),
            out: Optional[str] = typer.Option(None, "--out", "-o", help="Report directory."),
            resolution: Optional[str] = typer.Option(None, "--resolution", "-r"),
            variant: Optional[str] = VariantOpt):
    """Compare techniques with the ground truth; write index.html, summary.md, metrics.json."""
    out = out or f"reports/{Path(scene).stem}"
    _compare(scene, _split(techniques_), set_, out, resolution, variant)


@app.command()
def demo(out: str = typer.Option("reports/demo", "--out", "-o"), variant: Optional[str] = VariantOpt):
    """Compare every registered technique on the built-in `contact` scene and print the table."""
    from .techniques import base
    _compare("contact", base.names(), [], out, None, variant)


@app.command()
def bench(out: str = typer.Option("reports/bench", "--out", "-o"),
          quick: bool = typer.Option(False, "--quick", help="Small sizes (a smoke run, not for figures)."),
          variant: Optional[str] = VariantOpt):
    """Measure ground-truth throughput and technique compile / warm run times."""
    from .bench import run as run_bench
    _init(variant)
    path_md = run_bench(Path(out), quick=quick)
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
