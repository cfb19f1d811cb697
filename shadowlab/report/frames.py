"""The top-level page of ``compare --frames A:B``: a technique × frame table and the shimmer.

``out/frame_<NNNN>/`` holds each frame's own report (:func:`shadowlab.report.html.build`);
``out/index.html``, ``out/summary.md`` and ``out/metrics.json`` hold, per technique, the chosen
metrics of every frame and, with two frames or more, the temporal stability (shimmer, mean and
99th percentile of |V_t − V_{t−1}| at fixed world points, :mod:`shadowlab.metrics.temporal`) per
light and pooled, beside the truth's own shimmer and the reason for its value.
"""

from __future__ import annotations

import html as _html
import json
import os
from collections.abc import Mapping
from pathlib import Path

from ..io.outdir import MARKER, claim_dir, inside, marker_text
from .charts import frame_charts
from .jsonable import to_jsonable
from .panels import CSS, TRUTH_SHADED, shaded_error_png
from .tables import fmt_value

__all__ = ["build_frames", "frames_summary", "FRAME_METRICS"]

#: the metrics of the technique × frame table
FRAME_METRICS = ("rmse", "rmse_penumbra", "vis_rmse")
FRAME_FILES = ("index.html", "summary.md", "metrics.json")


def _metric(summary, tech, frame, m):
    return summary["per_frame"][str(frame)][tech]["metrics"].get(m)


def _shimmer_rows(summary) -> list[tuple[str, str, str, str]]:
    """(name, light, mean, p99) rows: each technique pooled and per light, then the truth."""
    sh = summary.get("shimmer")
    rows = []
    if not sh:
        return rows
    for n, d in sh["techniques"].items():
        rows.append((n, "all lights", fmt_value(d["pooled"]["mean"]), fmt_value(d["pooled"]["p99"])))
        if len(d["per_light"]) > 1:
            for l, v in d["per_light"].items():
                rows.append((n, l, fmt_value(v["mean"]), fmt_value(v["p99"])))
    t = sh["truth"]
    rows.append(("truth", "all lights", fmt_value(t["pooled"]["mean"]) if t["pooled"] else "n/a",
                 fmt_value(t["pooled"]["p99"]) if t["pooled"] else "n/a"))
    return rows


def frames_summary(summary: Mapping) -> str:
    """Markdown: the technique × frame table per metric and the shimmer table (summary.md)."""
    fr = summary["frames"]
    lines = [f"# shadowlab report: {summary['scene']} ({summary['resolution'][0]}x{summary['resolution'][1]}), "
             f"frames {fr[0]}..{fr[-1]}", ""]
    for m in FRAME_METRICS:
        if not any(_metric(summary, n, fr[0], m) is not None for n in summary["techniques"]):
            continue
        lines += [f"## {m} per frame", "", "| technique | " + " | ".join(f"frame {f}" for f in fr) + " |",
                  "|---|" + "---:|" * len(fr)]
        for n in summary["techniques"]:
            lines.append(f"| {n} | " + " | ".join(fmt_value(_metric(summary, n, f, m)) for f in fr) + " |")
        lines.append("")
    sh = summary.get("shimmer")
    if sh:
        lines += ["## Temporal stability (shimmer)", "",
                  f"|V_t(x) − V_t−1(x)| at fixed world points x ({sh['points']}) with each frame's light views, "
                  f"over {len(sh['frames']) - 1} frame pairs.", "",
                  "| technique | light | mean | p99 |", "|---|---|---:|---:|"]
        lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in _shimmer_rows(summary)]
        lines += ["", f"Truth: {sh['truth']['why']}.", ""]
    else:
        lines += ["Temporal stability (shimmer) needs two frames or more.", ""]
    return "\n".join(lines)


def _image_grid(summary: Mapping) -> list[str]:
    """Thumbnails from the frames' own reports, each linked to its report: the truth's shaded
    image per frame, then each technique's shaded error heat map per frame (one colour scale per
    frame's report: see its legend there)."""
    reports, fr = summary.get("reports") or {}, summary["frames"]
    if not reports:
        return []
    e = _html.escape

    def thumb(f, fname, alt):
        rep = reports[str(f)]
        src = f"{os.path.dirname(rep)}/img/{fname}"
        return f'<td><a href="{e(rep)}"><img class="im thumb" src="{e(src)}" alt="{e(alt)}" title="{e(alt)}"></a></td>'

    p = ['<div class="wide"><table class="grid"><tr><th></th>'
         + "".join(f'<th><a href="{e(reports[str(f)])}">frame {f}</a></th>' for f in fr) + "</tr>",
         '<tr><th class="row">truth (shaded)</th>' + "".join(thumb(f, TRUTH_SHADED, f"truth frame {f}") for f in fr)
         + "</tr>"]
    for i, n in enumerate(summary["techniques"]):
        p.append(f'<tr><th class="row">{e(n)}<br>signed error (shaded)</th>'
                 + "".join(thumb(f, shaded_error_png(i, n), f"{n} error frame {f}") for f in fr) + "</tr>")
    p.append("</table></div>")
    return p


def _html_page(summary: Mapping) -> str:
    e = _html.escape
    fr = summary["frames"]
    title = f"{summary['scene']} ({summary['resolution'][0]}×{summary['resolution'][1]}), frames {fr[0]}..{fr[-1]}"
    p = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
         '<meta name="viewport" content="width=device-width, initial-scale=1">',
         f"<title>shadowlab: {e(title)}</title>",
         f"<style>{CSS}img.thumb {{ width: 160px; }}</style></head><body>",
         f"<h1>shadowlab report: {e(title)}</h1>",
         '<p class="ref">A technique × frame comparison along the camera path; each frame links to its own '
         "report (images, heat maps, the comparator).</p>"]
    reports = summary.get("reports", {})
    charts = frame_charts(summary, FRAME_METRICS)
    if charts:
        p += ["<h2>Charts</h2>", charts]
    grid = _image_grid(summary)
    if grid:
        p += ["<h2>Frames</h2>"] + grid
    for m in FRAME_METRICS:
        if not any(_metric(summary, n, fr[0], m) is not None for n in summary["techniques"]):
            continue
        head = "".join(f"<th><a href='{e(reports[str(f)])}'>frame {f}</a></th>" if str(f) in reports
                       else f"<th>frame {f}</th>" for f in fr)
        p.append(f'<h2>{e(m)} per frame</h2><div class="wide"><table class="metrics"><thead><tr><th>technique</th>'
                 f"{head}</tr></thead><tbody>")
        for n in summary["techniques"]:
            p.append(f"<tr><td>{e(n)}</td>" + "".join(f"<td>{fmt_value(_metric(summary, n, f, m))}</td>" for f in fr)
                     + "</tr>")
        p.append("</tbody></table></div>")
    sh = summary.get("shimmer")
    if sh:
        p.append("<h2>Temporal stability (shimmer)</h2>"
                 f'<p class="note">|V<sub>t</sub>(x) − V<sub>t−1</sub>(x)| at fixed world points x ({e(sh["points"])}) '
                 f"with each frame's light views, over {len(sh['frames']) - 1} frame pairs.</p>"
                 '<table class="metrics"><thead><tr><th>technique</th><th>light</th><th>mean</th><th>p99</th></tr>'
                 "</thead><tbody>")
        p += [
            f"<tr><td>{e(a)}</td><td>{e(b)}</td><td>{c}</td><td>{d}</td></tr>" for a, b, c, d in _shimmer_rows(summary)
        ]
        p.append(f'</tbody></table><p class="note">Truth: {e(sh["truth"]["why"])}.</p>')
    else:
        p.append('<p class="note">Temporal stability (shimmer) needs two frames or more.</p>')
    p.append("</body></html>")
    return "\n".join(p) + "\n"


def build_frames(out_dir, summary: Mapping, *, force: bool = False, protected=()) -> Path:
    """Write ``out_dir/index.html``, ``summary.md`` and ``metrics.json`` of a multi-frame compare
    (each file replaced atomically; the per-frame reports are already in ``frame_<NNNN>/``). The
    caller claims ``out_dir`` (:func:`~shadowlab.io.outdir.claim_dir`) before anything is
    written into it; here only the store is kept out of it (``protected``)."""
    out = Path(out_dir)
    for root in protected or ():
        if root is not None and inside(out, root):
            claim_dir(out, "compare", force=force, protected=protected, files=FRAME_FILES)  # raises
    out.mkdir(parents=True, exist_ok=True)
    texts = {"metrics.json": json.dumps(to_jsonable(dict(summary), "summary"), indent=2, allow_nan=False) + "\n",
             "summary.md": frames_summary(summary) + "\n", "index.html": _html_page(summary),
             MARKER: marker_text("compare", FRAME_FILES + tuple(f"frame_{f:04d}/" for f in summary["frames"]))}
    for name in ("metrics.json", "summary.md", MARKER, "index.html"):   # index.html last: it links the rest
        tmp = out / f".{name}.tmp-{os.getpid()}"
        tmp.write_text(texts[name], encoding="utf-8")
        os.replace(tmp, out / name)
    return out / "index.html"
