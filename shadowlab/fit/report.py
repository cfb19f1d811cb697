"""The fit report: ``DIR/fit.json``, ``DIR/summary.md``, ``DIR/preset.toml``, ``DIR/index.html``
with the loss history plot(s) (``img/loss_<technique>.png``, matplotlib) and, per technique and
light, the visibility before / after / truth with signed error heat maps (blue = darker than the
truth, red = brighter; before and after share one colour scale), and the same for the shaded image.

Written atomically like the comparison reports: built in a temporary sibling directory, then
moved into place; in an existing DIR only these files and ``img/`` are replaced.
"""

from __future__ import annotations

import html as _html
import json
import math
import re
import shlex
import textwrap
from pathlib import Path
from urllib.parse import quote

import numpy as np

from ..errors import InputError
from ..io.png import encode_png
from ..report import images as _im
from ..report.jsonable import to_jsonable
from ..io.outdir import claim_dir, write_dir
from ..reference.location import chosen as chosen_store
from . import preset as P

OUTPUT_FILES = ("fit.json", "summary.md", "preset.toml", "index.html")

_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: .2em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table.t { border-collapse: collapse; font-variant-numeric: tabular-nums; margin: .5em 0; }
table.t th, table.t td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
table.t th:first-child, table.t td:first-child { text-align: left; }
table.grid { border-collapse: collapse; } table.grid th, table.grid td { padding: 4px 6px; vertical-align: top; text-align: left; }
img.im { width: 192px; height: auto; image-rendering: pixelated; border: 1px solid #bbb; display: block; }
img.plot { max-width: 720px; border: 1px solid #ddd; }
img.cbar { width: 192px; height: 10px; image-rendering: pixelated; display: block; margin-top: 3px; }
.ticks { width: 192px; display: flex; justify-content: space-between; font-size: .75em; color: #444; }
.note { font-size: .85em; color: #555; } code { font-size: .9em; }
"""  # noqa: E501


def check_out(out: Path, force: bool = False, protected=()):
    """Refuse an output path that cannot hold the report (before any fitting is done): inside the
    reference store (``protected``), an existing file, or an existing directory shadowlab did not
    make (unless ``force``; :func:`shadowlab.io.outdir.claim_dir`)."""
    out = Path(out)
    claim_dir(out, "fit", force=force, protected=protected, files=OUTPUT_FILES + ("img/",))
    for f in OUTPUT_FILES:
        if (out / f).is_dir():
            raise InputError(f"--out: {out / f} is a directory; remove it or choose another --out")


def _e(s) -> str:
    return _html.escape(str(s), quote=True)


def _fmt(v, digits=4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return "n/a" if math.isnan(v) else f"{v:.{digits}g}"
    return str(v)


def _slug(s: str) -> str:
    return (re.sub(r"[^A-Za-z0-9_-]+", "-", s).strip("-") or "x")[:40]


# ------------------------------------------------------------------------------------------------
# text


def param_text(r: dict) -> str:
    return ", ".join(f"{n} {_fmt(d['start'])} → {_fmt(d['fitted'])}" for n, d in r["params"].items())


def scenes_text(run: dict) -> str:
    """``scene (WxH)``, or for a fit over several scenes each of them with its resolution."""
    if run.get("scenes"):
        return " + ".join(f"{e['name']} ({e['resolution'][0]}x{e['resolution'][1]})" for e in run["scenes"])
    w, h = run["resolution"]
    return f"{run['scene']} ({w}x{h})"


def _frames(frames) -> str:
    fr = [f for f in frames if f is not None]
    return ", ".join(map(str, fr)) if fr else "–"


def scene_rows(run: dict) -> list:
    """[(technique, scene, entry)] of a fit over several scenes (each scene's loss with the joint preset)."""
    return [(t, n, e) for t, r in run["techniques"].items() for n, e in (r.get("scenes") or {}).items()]


def compare_command(run: dict, preset) -> str:
    """The command that compares with the fitted ``preset`` file, as it can be pasted: the (first)
    scene as the user gave it (``scene_arg``: a built-in name, else its file's path, quoted for the
    shell by :func:`shadowlab.reference.store.scene_arg`), the fit's resolution and frames, and the
    store ``--references`` chose.

    >>> compare_command({"scene": "studio", "scene_arg": "'my scenes/studio.toml'", "resolution": [64, 48],
    ...                  "frame": 2}, "out/preset.toml")
    "shadowlab compare 'my scenes/studio.toml' --preset out/preset.toml -r 64x48 --frame 2"
    """
    first = (run.get("scenes") or [None])[0]
    scene = first["scene"] if first else run.get("scene_arg", run["scene"])
    w, h = first["resolution"] if first else run["resolution"]
    frames = [f for f in (first["frames"] if first else run.get("frames", [run.get("frame")])) if f is not None]
    words = ["--preset", str(preset), "-r", f"{w}x{h}"]
    if len(frames) == 1:
        words += ["--frame", str(frames[0])]
    elif frames:
        words += ["--frames", f"{min(frames)}:{max(frames)}"]
    if (store := chosen_store()) is not None:
        words += ["--references", str(store)]
    return f"shadowlab compare {scene} {shlex.join(words)}"


def _preset_file(run: dict, preset):
    """The preset file to name: ``preset``, else the report's (``run["out"]`` is its index.html),
    else ``--save-preset``'s; None when the fit wrote none."""
    if preset is not None:
        return preset
    if run.get("out"):
        return Path(run["out"]).parent / "preset.toml"
    return (run.get("preset") or {}).get("path")


def summary_table(run: dict, preset=None) -> str:
    """Markdown: one row per technique (fitted values, loss and shaded penumbra RMSE before → after,
    evaluations, backward passes, kernels compiled / loaded from disk, wall time), then the command
    that compares with the fitted preset (:func:`compare_command`; ``preset``: its file, default
    the report's)."""
    lines = [f"# shadowlab fit: {scenes_text(run)}, loss {run['loss']}, method {run['method']}", "",
             "| technique | parameters (start → fitted) | methods | loss before | loss after | "
             "shaded RMSE penumbra before → after | evaluations | backward | kernels compiled / from disk | wall (s) |",
             "|---|---|---|---:|---:|---|---:|---:|---|---:|"]
    for t, r in run["techniques"].items():
        meth = ", ".join(sorted({d["method"] for d in r["params"].values()}))
        mb, ma = r["metrics_before"].get("rmse_penumbra"), r["metrics_after"].get("rmse_penumbra")
        k = r["kernels"]
        lines.append(f"| {t} | {param_text(r)} | {meth} | {_fmt(r['loss_before'])} | {_fmt(r['loss_after'])} | "
                     f"{_fmt(mb)} → {_fmt(ma)} | {r['evaluations']} | {r['gradient_evaluations']} | "
                     f"{k['compiled']} / {k['loaded_from_disk']} | {r['wall_time_s']:.2f} |")
    for t, why in (run.get("skipped") or {}).items():
        lines.append(f"| {t} | skipped: {why} | | | | | | | | |")
    if run.get("scenes"):
        lines += ["", "Each scene with the joint preset (one preset minimising the mean loss over the scenes):", "",
                  "| technique | scene | frames | loss before | loss after | shaded RMSE penumbra before → after |",
                  "|---|---|---|---:|---:|---|"]
        lines += [
            f"| {t} | {n} | {_frames(e['frames'])} | {_fmt(e['loss_before'])} | {_fmt(e['loss_after'])} | "
            f"{_fmt(e['metrics_before'].get('rmse_penumbra'))} → {_fmt(e['metrics_after'].get('rmse_penumbra'))} |"
            for t, n, e in scene_rows(run)
        ]
    losses = {}
    for t, r in run["techniques"].items():
        losses.setdefault(r["loss"]["description"], []).append(t)
    text = "; ".join(d + (f" ({', '.join(ts)})" if len(losses) > 1 else "") for d, ts in losses.items())
    lines += ["", f"Loss: {text}. "
              "Evaluations = technique renders of the search (cached points not counted); backward = Dr.Jit "
              "reverse-mode passes (one per Adam step)."]
    if (file := _preset_file(run, preset)) is not None:
        lines += ["", f"Compare with the fitted values: `{compare_command(run, file)}`"]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------
# plot


def plot_history(r: dict, path: Path, title: str):
    """Loss (noise-corrected) per evaluation, and each parameter's position in its window."""
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    hist = r["history"]
    x = np.arange(len(hist))
    loss = np.array([np.nan if e["loss"] is None else e["loss"] for e in hist], float)
    stages = [e["stage"] for e in hist]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.2, 5.0), sharex=True, dpi=100,
                                 gridspec_kw={"height_ratios": [3, 2]})
    colours = {"start": "k", "adam": "tab:blue", "golden": "tab:orange", "grid": "tab:green",
               "exhaustive": "tab:purple"}
    best = np.fmin.accumulate(np.where(np.isfinite(loss), loss, np.inf))
    a1.plot(x, loss, color="0.75", lw=1, zorder=1)
    for st in dict.fromkeys(stages):
        m = np.array([s == st for s in stages])
        a1.scatter(x[m], loss[m], s=14, color=colours.get(st, "tab:gray"), label=st, zorder=2)
    a1.step(x, best, where="post", color="tab:red", lw=1.2, label="best so far", zorder=3)
    pos = loss[np.isfinite(loss) & (loss > 0)]
    if pos.size and pos.max() / max(pos.min(), 1e-12) > 20:
        a1.set_yscale("log")
    a1.set_ylabel(f"loss ({r['loss']['name']})")
    a1.set_title("\n".join(textwrap.wrap(title, 95)), fontsize=9)
    a1.legend(fontsize=8, loc="upper right")
    a1.grid(alpha=0.3)
    numeric = [n for n, d in r["params"].items() if d["kind"] in ("float", "int")]
    if len(r["params"]) == 1 and numeric:          # one number: its values, in its units
        n = numeric[0]
        a2.plot(x, [float(e["values"][n]) for e in hist], marker=".", ms=4, lw=1, color="tab:blue")
        a2.axhline(float(r["params"][n]["fitted"]), color="tab:red", lw=0.8, ls="--",
                   label=f"fitted {_fmt(r['params'][n]['fitted'])}")
        a2.set_ylabel(n)
        if r["params"][n].get("scale") == "log":
            a2.set_yscale("log")
    else:                                          # several: each one's position in its window
        _plot_positions(a2, r, hist, x)
    a2.set_xlabel("evaluation")
    a2.legend(fontsize=8, loc="best")
    a2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_positions(a2, r, hist, x):
    for n, d in r["params"].items():
        vals = [e["values"][n] for e in hist]
        if d["kind"] in ("float", "int"):
            lo, hi = d["window"]
            if d.get("scale") == "log":
                y = [math.log(max(float(v), lo) / lo) / math.log(hi / lo) for v in vals]
            else:
                y = [(float(v) - lo) / (hi - lo) if hi > lo else 0.5 for v in vals]
            a2.plot(x, y, marker=".", ms=4, lw=1, label=f"{n} [{_fmt(lo)}, {_fmt(hi)}]"
                    + (" log" if d.get("scale") == "log" else ""))
        else:
            opts = d["values"]
            y = [opts.index(v) / max(len(opts) - 1, 1) if v in opts else np.nan for v in vals]
            a2.plot(x, y, marker=".", ms=4, lw=1, label=f"{n} ({', '.join(map(str, opts))})")
    a2.set_ylim(-0.05, 1.05)
    a2.set_ylabel("position in window")


# ------------------------------------------------------------------------------------------------
# HTML


def _img(fname: str, alt: str, cls: str = "im") -> str:
    return f'<img class="{cls}" src="img/{quote(fname)}" alt="{_e(alt)}" title="{_e(alt)}">'


def _legend(scale: float) -> str:
    s = _fmt(scale, 3)
    return ('<img class="cbar" src="img/colorbar.png" alt="colour scale">'
            f'<div class="ticks"><span>&minus;{s}</span><span>0</span><span>+{s}</span></div>')


def _metrics_table(r: dict) -> str:
    keys = [k for k in ("rmse_penumbra", "vis_rmse_penumbra", "rmse", "vis_rmse", "flip_penumbra", "flip",
                        "ssim", "psnr", "leak_rate", "overdark_rate") if k in r["metrics_before"]]
    rows = "".join(f"<tr><td>{_e(k)}</td><td>{_e(_fmt(r['metrics_before'][k]))}</td>"
                   f"<td>{_e(_fmt(r['metrics_after'][k]))}</td></tr>" for k in keys)
    return ('<table class="t"><thead><tr><th>metric (shaded image unless vis_)</th><th>start</th><th>fitted</th>'
            f"</tr></thead><tbody>{rows}</tbody></table>")


def _section(run: dict, t: str, r: dict, img_dir: Path, exposure: float) -> list[str]:
    put = lambda f, data: ((img_dir / f).write_bytes(data), f)[1]  # noqa: E731
    tag = _slug(t)
    truth = run["truth_images"]
    imgs = r["images"]
    k = r["kernels"]
    p = [f'<h2 id="{_e(tag)}">{_e(t)}</h2>',
         '<table class="t"><thead><tr><th>parameter</th><th>method</th><th>window / values</th><th>start</th>'
         "<th>fitted</th><th>units</th></tr></thead><tbody>"]
    for n, d in r["params"].items():
        win = f"[{_fmt(d['window'][0])}, {_fmt(d['window'][1])}] ({d['window_from']})" if "window" in d \
            else ", ".join(map(str, d["values"]))
        p.append(
            f"<tr><td><code>{_e(n)}</code></td><td>{_e(d['method'])}</td><td>{_e(win)}</td>"
            f"<td>{_e(_fmt(d['start'], 6))}</td><td><b>{_e(_fmt(d['fitted'], 6))}</b></td>"
            f"<td>{_e(d['units'])}</td></tr>"
        )
    p.append("</tbody></table>")
    lo = r["loss"]
    floor = f", noise floor {_fmt(lo['noise_floor_rmse'])} subtracted" if lo.get("noise_floor_subtracted") else ""
    p.append(
        f"<p>Loss <code>{_e(lo['name'])}</code> ({_e(lo['description'])}; {lo['pixels']} pixels{_e(floor)}): "
        f"<b>{_e(_fmt(r['loss_before']))} → {_e(_fmt(r['loss_after']))}</b>. "
        f"{r['iterations']} iterations, {r['evaluations']} technique evaluations, "
        f"{r['gradient_evaluations']} backward passes, {r['wall_time_s']:.2f} s. Kernels: {k['compiled']} compiled, "
        f"{k['loaded_from_disk']} loaded from the disk cache, {k['launched']} launched; "
        f"{k['iterations_with_new_kernels']} of {len(k['new_per_iteration'])} iterations met a kernel not in "
        "the in-memory cache (parameters are opaque: a new value compiles nothing).</p>"
    )
    for note in r.get("notes") or ():
        p.append(f'<p class="note">Note: {_e(note)}</p>')
    if r["fixed"]:
        p.append('<p class="note">Held fixed (non-default): ' + " ".join(
            f"<code>{_e(a)}={_e(json.dumps(to_jsonable(b)))}</code>" for a, b in r["fixed"].items()) + "</p>")
    p.append(_img(f"loss_{tag}.png", f"loss history {t}", "plot"))
    p.append(_metrics_table(r))
    p.append('<table class="grid"><tr><th></th><th>start</th><th>fitted</th><th>truth</th>'
             "<th>error, start</th><th>error, fitted</th></tr>")
    for j, ln in enumerate(run["lights"]):
        tv = truth["vis"][ln]
        eb = _im.luminance(imgs["before"]["vis"][ln]) - tv
        ea = _im.luminance(imgs["after"]["vis"][ln]) - tv
        sc = max(_im.error_scale(eb), _im.error_scale(ea))
        fb = put(f"{tag}_{j}_before.png", _im.visibility_png(imgs["before"]["vis"][ln]))
        fa = put(f"{tag}_{j}_after.png", _im.visibility_png(imgs["after"]["vis"][ln]))
        ft = put(f"truth_{j}.png", _im.visibility_png(tv))
        feb = put(f"{tag}_{j}_err_before.png", encode_png(_im.signed_error_heatmap(eb, sc)))
        fea = put(f"{tag}_{j}_err_after.png", encode_png(_im.signed_error_heatmap(ea, sc)))
        p.append(f"<tr><th>{_e(ln)} visibility</th><td>{_img(fb, 'start')}</td><td>{_img(fa, 'fitted')}</td>"
                 f"<td>{_img(ft, 'truth')}</td><td>{_img(feb, 'error start')}{_legend(sc)}</td>"
                 f"<td>{_img(fea, 'error fitted')}{_legend(sc)}</td></tr>")
    tl = _im.luminance(truth["shaded"])
    eb = _im.luminance(imgs["before"]["shaded"]) - tl
    ea = _im.luminance(imgs["after"]["shaded"]) - tl
    sc = max(_im.error_scale(eb), _im.error_scale(ea))
    fb = put(f"{tag}_shaded_before.png", _im.shaded_png(imgs["before"]["shaded"], exposure))
    fa = put(f"{tag}_shaded_after.png", _im.shaded_png(imgs["after"]["shaded"], exposure))
    ft = put("truth_shaded.png", _im.shaded_png(truth["shaded"], exposure))
    feb = put(f"{tag}_shaded_err_before.png", encode_png(_im.signed_error_heatmap(eb, sc)))
    fea = put(f"{tag}_shaded_err_after.png", encode_png(_im.signed_error_heatmap(ea, sc)))
    p.append(f"<tr><th>shaded</th><td>{_img(fb, 'start')}</td><td>{_img(fa, 'fitted')}</td><td>{_img(ft, 'truth')}</td>"
             f"<td>{_img(feb, 'error start')}{_legend(sc)}</td><td>{_img(fea, 'error fitted')}{_legend(sc)}</td></tr>")
    p.append("</table>")
    return p


def _page(run: dict, img_dir: Path, out: Path) -> str:
    (img_dir / "colorbar.png").write_bytes(_im.colorbar_png())
    exposure = _im.common_exposure(run["truth_images"]["shaded"])
    title = f"shadowlab fit: {scenes_text(run)}"
    p = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{_e(title)}</title>",
         f"<style>{_CSS}</style></head><body>", f"<h1>{_e(title)}</h1>",
         f'<p class="note">Reference {_e(run["reference"]["path"])} (worst standard error '
         f'{_e(_fmt(run["reference"]["max_std_error"]))}). Loss <code>{_e(run["loss"])}</code>, method '
         f'<code>{_e(run["method"])}</code>. Files: <a href="fit.json">fit.json</a>, '
         f'<a href="summary.md">summary.md</a>, <a href="preset.toml">preset.toml</a> '
         f'(<code>{_e(compare_command(run, out / "preset.toml"))}</code>).</p>']
    if run.get("preset_in"):
        p.append(
            f'<p class="note">Started from preset {_e(run["preset_in"]["name"])} ({_e(run["preset_in"]["path"])}).</p>'
        )
    rows = []
    for t, r in run["techniques"].items():
        rows.append(f'<tr><td><a href="#{_e(_slug(t))}">{_e(t)}</a></td><td>{_e(param_text(r))}</td>'
                    f"<td>{_e(_fmt(r['loss_before']))}</td><td>{_e(_fmt(r['loss_after']))}</td>"
                    f"<td>{_e(_fmt(r['metrics_before'].get('rmse_penumbra')))} → "
                    f"{_e(_fmt(r['metrics_after'].get('rmse_penumbra')))}</td>"
                    f"<td>{r['evaluations']}</td><td>{r['gradient_evaluations']}</td>"
                    f"<td>{r['kernels']['compiled']} / {r['kernels']['loaded_from_disk']}</td>"
                    f"<td>{r['wall_time_s']:.2f}</td></tr>")
    for t, why in (run.get("skipped") or {}).items():
        rows.append(f"<tr><td>{_e(t)}</td><td colspan=8>skipped: {_e(why)}</td></tr>")
    p.append('<table class="t"><thead><tr><th>technique</th><th>parameters (start → fitted)</th><th>loss before</th>'
             "<th>loss after</th><th>shaded RMSE penumbra</th><th>evaluations</th><th>backward</th>"
             "<th>kernels compiled / from disk</th><th>wall (s)</th></tr></thead><tbody>" + "".join(rows)
             + "</tbody></table>")
    if run.get("scenes"):
        first = run["scenes"][0]["name"]
        p.append(f"<h2>Scenes</h2><p>One preset for {len(run['scenes'])} scenes: it minimises the mean of the scenes' "
                 "objectives (each the mean over its frames); each scene's loss with it, before and after. The images "
                 f"below are {_e(first)}'s.</p>")
        p.append('<table class="t"><thead><tr><th>technique</th><th>scene</th><th>frames</th><th>loss before</th>'
                 "<th>loss after (joint preset)</th><th>shaded RMSE penumbra</th></tr></thead><tbody>" + "".join(
                     f"<tr><td>{_e(t)}</td><td>{_e(n)}</td><td>{_e(_frames(e['frames']))}</td>"
                     f"<td>{_e(_fmt(e['loss_before']))}</td><td>{_e(_fmt(e['loss_after']))}</td>"
                     f"<td>{_e(_fmt(e['metrics_before'].get('rmse_penumbra')))} → "
                     f"{_e(_fmt(e['metrics_after'].get('rmse_penumbra')))}</td></tr>" for t, n, e in scene_rows(run))
                 + "</tbody></table>")
    p.append('<p class="note">Heat maps: signed error technique − truth (blue: darker than the truth, red: '
             "brighter); start and fitted share one colour scale per row. Visibility: grey level = visibility. "
             f"Shaded images: exposure {_e(_fmt(exposure))}, sRGB.</p>")
    for t, r in run["techniques"].items():
        plot_history(r, img_dir / f"loss_{_slug(t)}.png", f"{t} on {run['scene']}: {param_text(r)}")
        p += _section(run, t, r, img_dir, exposure)
    p.append("</body></html>")
    return "\n".join(p) + "\n"


def to_json(run: dict) -> dict:
    """fit.json: the run without images."""
    techs = {t: {k: v for k, v in r.items() if k != "images"} for t, r in run["techniques"].items()}
    return to_jsonable({**{k: v for k, v in run.items() if k not in ("truth_images", "techniques")},
                        "techniques": techs}, "fit")


def write(out: Path, run: dict, force: bool = False, protected=()) -> Path:
    """Write the report into ``out`` atomically; returns the path of index.html."""
    out = Path(out)
    check_out(out, force, protected)
    data = to_json(run)
    def fill(tmp: Path) -> None:
        text = _page(run, tmp / "img", out)
        (tmp / "fit.json").write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        (tmp / "summary.md").write_text(summary_table(run, out / "preset.toml"), encoding="utf-8")
        (tmp / "preset.toml").write_text(P.to_toml(run["preset"]["name"], run["preset"]["values"],
                                                   P.FIT_DESCRIPTION, P.preset_meta(run)), encoding="utf-8")
        (tmp / "index.html").write_text(text, encoding="utf-8")

    return write_dir(out, "fit", fill, OUTPUT_FILES, ("img",))


