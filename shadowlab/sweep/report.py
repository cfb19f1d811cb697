"""The sweep report: ``DIR/sweep.json`` (the parameter, per scene per point the metrics, the
metrics per light and, apart from them, the run times), ``DIR/summary.md`` (a table per scene:
a row per parameter value, a column per metric, the best value of each column in bold) and
``DIR/index.html`` (the tables and, per scene, one inline-SVG line chart per metric against the
parameter, its best point ringed; no JavaScript).

Written like the other reports: built in a temporary sibling directory, then moved into place;
in an existing DIR (ours, or any with ``--force``) only these files are replaced
(:func:`shadowlab.io.outdir.claim_dir`).
"""

from __future__ import annotations

import html as _html
import json
import math
from pathlib import Path

from ..errors import InputError
from ..report.charts import colour, nice_ticks
from ..report.jsonable import to_jsonable
from ..io.outdir import claim_dir, write_dir

__all__ = ["OUTPUT_FILES", "summary_markdown", "sweep_chart", "page", "write_report"]

OUTPUT_FILES = ("sweep.json", "summary.md", "index.html")

_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: .2em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table.t { border-collapse: collapse; font-variant-numeric: tabular-nums; margin: .5em 0; font-size: .9em; }
table.t th, table.t td { border: 1px solid #ccc; padding: 3px 6px; text-align: right; }
table.t th:first-child, table.t td:first-child { text-align: left; }
td.best { font-weight: 700; background: #eef6ee; }
.charts { display: flex; flex-wrap: wrap; gap: 8px; } figure.chart { margin: 0; }
.note { font-size: .85em; color: #555; } code { font-size: .9em; }
"""


def _e(s) -> str:
    return _html.escape(str(s), quote=True)


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, int):
        return str(v)
    v = float(v)
    return "n/a" if math.isnan(v) else f"{v:.4g}"


def _title(rec: dict) -> str:
    p = rec["param"]
    sp = ", log spacing" if p["spacing"] == "log" else ""
    return (f"shadowlab sweep: {rec['technique']}.{p['name']} from {_fmt(p['lo'])} to {_fmt(p['hi'])}, "
            f"{len(p['values'])} points{sp}")


def _fixed_text(rec: dict) -> str:
    return ", ".join(f"{k}={_fmt(v) if not isinstance(v, str) else v}" for k, v in rec["fixed"].items()) or "(none)"


def _scene_head(name: str, s: dict) -> str:
    w, h = s["resolution"]
    return f"{name} ({w}x{h}" + ("" if s.get("frame") is None else f", frame {s['frame']}") + ")"


def scene_table(rec: dict, name: str) -> str:
    """Markdown table of one scene: a row per parameter value, a column per metric and the warm
    run time; the best value of each metric in bold."""
    s, pname, metrics = rec["scenes"][name], rec["param"]["name"], rec["metrics"]
    best = {m: b["index"] for m, b in s["best"].items()}
    lines = ["| " + " | ".join([pname, *metrics, "time_s"]) + " |", "|" + "---:|" * (len(metrics) + 2)]
    for i, pt in enumerate(s["points"]):
        cells = [_fmt(pt["value"])]
        for m in metrics:
            c = _fmt(pt["metrics"].get(m))
            cells.append(f"**{c}**" if best.get(m) == i else c)
        cells.append(_fmt(pt["timing"].get("time_s")))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary_markdown(rec: dict) -> str:
    """What summary.md holds and the CLI prints: the title, the fixed parameters and a table per scene."""
    out = [f"# {_title(rec)}", "", f"Fixed parameters: {_fixed_text(rec)}.", ""]
    for name, s in rec["scenes"].items():
        out += [f"## {_scene_head(name, s)}", "", scene_table(rec, name), ""]
        bests = ", ".join(f"{m} at {rec['param']['name']}={_fmt(b['value'])}" for m, b in s["best"].items())
        out += [f"Best: {bests}.", ""]
    out.append("Best (bold): highest psnr / ssim, lowest for the other metrics; time_s (warm run, seconds) is "
               "measured and differs between runs.")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------------------- charts

def sweep_chart(title: str, xs, ys, *, xlabel: str, ylabel: str, best: int | None = None, log: bool = False,
                width: int = 360, height: int = 220) -> str:
    """An inline-SVG line chart of ``ys`` against the numbers ``xs`` (a linear or log x axis);
    missing values (None, NaN) break the line and are listed as n/a; the point ``best`` (an index)
    is ringed and labelled.

    >>> svg = sweep_chart("rmse", [0, 1, 2], [0.3, 0.1, None], xlabel="bias", ylabel="rmse", best=1)
    >>> svg.count("<circle") == 3 and "best" in svg and "n/a" in svg
    True
    """
    left, right, top, bottom = 56, 14, 26, 38
    pw, ph = width - left - right, height - top - bottom
    ok = [(i, float(x), float(y)) for i, (x, y) in enumerate(zip(xs, ys))
          if y is not None and math.isfinite(float(y))]
    fx_lo, fx_hi = float(min(xs)), float(max(xs))
    if log and fx_lo > 0:
        a, b = math.log10(fx_lo), math.log10(fx_hi)
        fx = lambda v: (math.log10(v) - a) / ((b - a) or 1.0)  # noqa: E731
        xt = [10.0**k for k in range(math.floor(a), math.ceil(b) + 1) if fx_lo <= 10.0**k <= fx_hi] or [fx_lo, fx_hi]
    else:
        xt = [t for t in nice_ticks(fx_lo, fx_hi) if fx_lo - 1e-12 <= t <= fx_hi + 1e-12] or [fx_lo, fx_hi]
        fx = lambda v: (v - fx_lo) / ((fx_hi - fx_lo) or 1.0)  # noqa: E731
    yv = [y for _, _, y in ok] or [0.0]
    y_lo, y_hi = min(yv), max(yv)
    if y_hi - y_lo < 1e-12 * max(1.0, abs(y_hi)):
        y_lo, y_hi = y_lo - 0.5 * (abs(y_lo) or 1.0), y_hi + 0.5 * (abs(y_hi) or 1.0)
    yt = nice_ticks(y_lo, y_hi, 4)
    fy = lambda v: (v - yt[0]) / ((yt[-1] - yt[0]) or 1.0)  # noqa: E731
    X = lambda v: left + pw * fx(v)  # noqa: E731
    Y = lambda v: top + ph * (1 - fy(v))  # noqa: E731
    body = [f'<line x1="{left}" x2="{left + pw}" y1="{Y(t):.1f}" y2="{Y(t):.1f}" stroke="#eee"/>'
            f'<text x="{left - 4}" y="{Y(t) + 4:.1f}" text-anchor="end" fill="#555">{t:g}</text>' for t in yt]
    body += [f'<line x1="{X(t):.1f}" x2="{X(t):.1f}" y1="{top}" y2="{top + ph}" stroke="#eee"/>'
             f'<text x="{X(t):.1f}" y="{top + ph + 13}" text-anchor="middle" fill="#555">{t:g}</text>' for t in xt]
    runs, cur, prev = [], [], None
    for i, x, y in ok:
        if prev is not None and i != prev + 1:
            runs.append(cur)
            cur = []
        cur.append(f"{X(x):.1f},{Y(y):.1f}")
        prev = i
    runs.append(cur)
    c = colour(0)
    body += [
        f'<polyline points="{" ".join(r)}" fill="none" stroke="{c}" stroke-width="2"/>' for r in runs if len(r) > 1
    ]
    for i, x, y in ok:
        body.append(f'<circle cx="{X(x):.1f}" cy="{Y(y):.1f}" r="3" fill="{c}"><title>{_e(xlabel)} {_fmt(xs[i])}: '
                    f"{_e(ylabel)} {_fmt(y)}</title></circle>")
    if best is not None and any(i == best for i, _, _ in ok):
        x, y = float(xs[best]), float(ys[best])
        anchor = "end" if fx(x) > 0.7 else "start"
        dx = -8 if anchor == "end" else 8
        body.append(f'<circle class="best" cx="{X(x):.1f}" cy="{Y(y):.1f}" r="7" fill="none" stroke="{colour(2)}" '
                    f'stroke-width="2"><title>best: {_e(xlabel)} {_fmt(xs[best])}, {_e(ylabel)} {_fmt(y)}</title>'
                    f'</circle><text x="{X(x) + dx:.1f}" y="{Y(y) - 9:.1f}" text-anchor="{anchor}" '
                    f'fill="{colour(2)}">best {_fmt(xs[best])}</text>')
    missing = [_fmt(xs[i]) for i in range(len(xs)) if i not in {j for j, _, _ in ok}]
    if missing:
        body.append(
            f'<text x="{width - 4}" y="16" text-anchor="end" fill="#999">n/a at {_e(", ".join(missing))}</text>'
        )
    body.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>'
                f'<text x="{left + pw / 2:.1f}" y="{height - 6}" text-anchor="middle">{_e(xlabel)}'
                f'{" (log scale)" if log else ""}</text>')
    return (f'<svg class="chart" data-metric="{_e(ylabel)}" xmlns="http://www.w3.org/2000/svg" width="{width}" '
            f'height="{height}" viewBox="0 0 {width} {height}" role="img" aria-label="{_e(title)}" '
            f'font-family="system-ui, sans-serif" font-size="11">'
            f'<text x="4" y="16" font-size="13" font-weight="600">{_e(title)}</text>' + "".join(body) + "</svg>")


def _html_table(rec: dict, name: str) -> str:
    s, pname, metrics = rec["scenes"][name], rec["param"]["name"], rec["metrics"]
    best = {m: b["index"] for m, b in s["best"].items()}
    head = "".join(f"<th>{_e(h)}</th>" for h in [pname, *metrics, "time_s"])
    rows = []
    for i, pt in enumerate(s["points"]):
        cells = [f"<td>{_fmt(pt['value'])}</td>"]
        cells += [f'<td{" class=best" if best.get(m) == i else ""}>{_fmt(pt["metrics"].get(m))}</td>' for m in metrics]
        cells.append(f"<td>{_fmt(pt['timing'].get('time_s'))}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f'<table class="t"><tr>{head}</tr>{"".join(rows)}</table>'


def page(rec: dict) -> str:
    """index.html: per scene, the table and one chart per metric (metric against the parameter)."""
    p = rec["param"]
    xlabel = p["name"] + (f" ({p['units']})" if p.get("units") else "")
    ex = rec.get("executor") or {}
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{_e(_title(rec))}</title>"
             f"<style>{_CSS}</style></head><body><h1>{_e(_title(rec))}</h1>",
             f"<p class=note>Fixed parameters: {_e(_fixed_text(rec))}. Values: "
             f"{_e(', '.join(_fmt(v) for v in p['values']))}. Ran on: {_e(ex.get('kind', '?'))}, "
             f"{_e(ex.get('workers', 1))} worker(s). Best: highest psnr / ssim, lowest for the other metrics "
             "(ringed in the charts, bold in the tables). Data: <a href='sweep.json'>sweep.json</a>.</p>"]
    for name, s in rec["scenes"].items():
        parts.append(f"<h2 id='{_e(name)}'>{_e(_scene_head(name, s))}</h2>{_html_table(rec, name)}")
        figs = []
        for m in rec["metrics"]:
            ys = [pt["metrics"].get(m) for pt in s["points"]]
            b = s["best"].get(m)
            figs.append('<figure class="chart">' + sweep_chart(
                f"{name}: {m}", [pt["value"] for pt in s["points"]], ys, xlabel=xlabel, ylabel=m,
                best=None if b is None else b["index"], log=p["spacing"] == "log") + "</figure>")
        parts.append(f"<div class='charts' data-scene='{_e(name)}'>{''.join(figs)}</div>")
    parts.append("</body></html>\n")
    return "".join(parts)


def write_report(out: Path, rec: dict, *, force: bool = False, protected=()) -> Path:
    """Write sweep.json, summary.md and index.html into ``out`` atomically; returns index.html's path."""
    out = Path(out)
    claim_dir(out, "sweep", force=force, protected=protected, files=OUTPUT_FILES)
    for f in OUTPUT_FILES:
        if (out / f).is_dir():
            raise InputError(f"--out: {out / f} is a directory; remove it or choose another --out")
    data = json.dumps(to_jsonable({k: v for k, v in rec.items() if k != "report"}, "sweep"), indent=2,
                      allow_nan=False) + "\n"
    def fill(tmp: Path) -> None:
        (tmp / "sweep.json").write_text(data, encoding="utf-8")
        (tmp / "summary.md").write_text(summary_markdown(rec), encoding="utf-8")
        (tmp / "index.html").write_text(page(rec), encoding="utf-8")

    return write_dir(out, "sweep", fill, OUTPUT_FILES)
