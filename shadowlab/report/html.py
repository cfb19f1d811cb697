"""Build a report directory from one run: index.html, summary.md, metrics.json and img/*.png.

The run dict (see ``build``) holds the numbers and, under ``"images"``, the numpy arrays.
``metrics.json`` is the run without ``"images"``: numpy scalars and arrays become plain JSON
values and **NaN / ±inf are written as null** (JSON has no NaN; a null metric means "not
available", e.g. a PSNR of identical images, which is +inf, or a penumbra metric without penumbra).

Signed error heat maps show technique − truth: blue = technique darker, white = equal, red =
brighter. Three-channel images are compared by luminance. Per light, and for the shaded image,
all techniques share one colour scale (the largest of their 99th percentiles of |error|), so equal
colours mean equal errors across techniques; the report prints each scale next to its colour bar.
Shaded images share one exposure per report (the truth's 99th-percentile luminance -> 0.9).
Pixels on a light the camera sees (``run.images.emitter``, else guessed from the images, see
:mod:`shadowlab.report.images`) and their neighbours are left out of the colour scales: a light in
view shows its radiance in ``mi.render`` and would set the scale.

The page, top to bottom: the gate verdict (PASS/FAIL and its checks, when the run has ``gate``:
``shadowlab ingest --gate``) and what was ingested; the metrics in two tables no wider than a
laptop window (the key columns :data:`KEY_METRICS`, then the others); charts
(:mod:`shadowlab.report.charts`: per-light bars, error against run time, error by distance band
and by a technique's label AOVs); the image comparator (:mod:`shadowlab.report.comparator`); the lights
(``run.light_info``, :mod:`shadowlab.report.lights`) and the ground truth; a section per technique,
with the rows its family adds (``images.techniques.<name>.panels``, ``Technique.panels``: images
built from the family's AOVs, drawn here by their kind, never by family).

Building is atomic and safe: everything is validated first (bad input raises ``InputError`` and
leaves ``out_dir`` untouched), then written into a temporary sibling directory and moved into
place. In an existing ``out_dir`` only index.html, summary.md, metrics.json and img/ are replaced;
other files stay.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.outdir import claim_dir, write_dir
from . import charts as _charts
from . import comparator as _cmp
from . import images as _im
from .jsonable import to_jsonable
from .lights import light_rows
from .panels import CSS, TRUTH_SHADED, esc, img_tag, legend, panel_rows, shaded_error_png, slug, technique_tag
from .run import Run
from .tables import (KEY_METRICS, NA, band_tables, bands_markdown, fmt_value, gate_markdown, metric_columns,
                     reference_line, stats_markdown, stats_tables, summary_table, table_cells)

__all__ = ["build", "OUTPUT_FILES", "OUTPUT_DIRS"]


OUTPUT_FILES = ("index.html", "summary.md", "metrics.json")
OUTPUT_DIRS = ("img",)


# --------------------------------------------------------------------------------------------
# HTML




def _metric_line(d: Mapping) -> str:
    return " · ".join(f"{esc(k)} {esc(fmt_value(v))}" for k, v in d.items())


def _table_html(run: Run, cols) -> str:
    """One metrics table (technique names link to their sections; best value per column in bold)."""
    cols, names, rows = table_cells(run, cols)
    p = ['<div class="wide"><table class="metrics"><thead><tr><th>technique</th>']
    p += [f"<th>{esc(c)}</th>" for c in cols]
    p.append("</tr></thead><tbody>")
    for i, (n, row) in enumerate(zip(names, rows)):
        cells = "".join(f"<td><b>{esc(s)}</b></td>" if b else f"<td>{esc(s)}</td>" for s, b in row)
        p.append(f'<tr><td><a href="#t{i}">{esc(n)}</a></td>{cells}</tr>')
    p.append("</tbody></table></div>")
    return "".join(p)


def _metrics_tables(run: Run) -> list[str]:
    """The key columns (:data:`KEY_METRICS` that the run has, and time_s), then the others."""
    all_cols = metric_columns(run.techniques)
    key = [c for c in KEY_METRICS if c in all_cols] + ["time_s"]
    rest = [c for c in all_cols if c not in key]
    p = [_table_html(run, key)]
    if rest:
        p += ['<p class="note">More metrics (suffix <code>_penumbra</code>: over the penumbra pixels only):</p>',
              _table_html(run, rest)]
    return p


def _verdict(run: Run) -> list[str]:
    """The gate's verdict at the top of the page (``run["gate"]``, as ``shadowlab ingest --gate``
    writes it): PASS or FAIL, the gate file, and a row per check."""
    g = run.extras.get("gate")
    if not isinstance(g, Mapping):
        return []
    ok = bool(g.get("passed"))
    word, cls = ("PASS", "pass") if ok else ("FAIL", "fail")
    failed = g.get("failed") or []
    p = [f'<div class="verdict {cls}" id="verdict"><span class="word">{word}</span> gate '
         f"<code>{esc(g.get('file', ''))}</code>"
         + (f": {len(failed)} check{'s' if len(failed) != 1 else ''} failed ({esc(', '.join(failed))})" if failed
            else ": every check passed") + "</div>"]
    checks = [c for c in g.get("checks") or [] if isinstance(c, Mapping)]
    if checks:
        p.append('<div class="wide"><table class="metrics checks"><thead><tr><th>gate</th><th>check</th><th>result</th>'
                 "<th>value</th><th>threshold</th><th>details</th></tr></thead><tbody>")
        for c in sorted(checks, key=lambda c: bool(c.get("passed"))):  # failed checks first
            r, rc = ("PASS", "pass") if c.get("passed") else ("FAIL", "fail")
            p.append(
                f"<tr><td>{esc(c.get('gate', ''))}</td><td><code>{esc(c.get('check', ''))}</code></td>"
                f'<td class="{rc}">{r}</td><td>{esc(fmt_value(c.get("value")))}</td>'
                f"<td>{esc(c.get('op', ''))} "
                f"{esc(fmt_value(c.get('threshold')))}</td><td>{esc(c.get('text', ''))}</td></tr>"
            )
        p.append("</tbody></table></div>")
    return p


def _ingest_facts(run: Run) -> list[str]:
    """What ``shadowlab ingest`` compared (``run["ingest"]``), as a short list instead of JSON."""
    ing = run.extras.get("ingest")
    if not isinstance(ing, Mapping):
        return []
    ch = ing.get("channels") or {}
    chs = ", ".join(f"{esc(k)} ← <code>{esc(v if isinstance(v, str) else ', '.join(map(str, v)))}</code>"
                    for k, v in ch.items())
    facts = [f"image <code>{esc(ing.get('image', ''))}</code>",
             f"compared as: {esc(ing.get('mode', ''))}, against the truth's <code>{esc(ing.get('against', ''))}</code>"]
    if chs:
        facts.append(f"channels: {chs}")
    facts += [f"note: {esc(n)}" for n in ing.get("notes") or []]
    return ['<ul class="facts">' + "".join(f"<li>{f}</li>" for f in facts) + "</ul>"]


def _lights_html(run: Run) -> list[str]:
    """The light summary: a row per light (kind, size and what its truth is, ``run["light_info"]``)."""
    info = run.light_info
    names = list(info) if info else list(run.lights)
    if not names:
        return []
    if not isinstance(info, Mapping):
        return [f'<p class="note">Lights: {esc(", ".join(names))}.</p>']
    rows = light_rows(names, info)
    return ['<table class="metrics lights"><thead><tr><th>light</th><th>kind</th><th>size</th><th>truth</th></tr>'
            "</thead><tbody>" + "".join(f"<tr><td>{esc(n)}</td><td>{esc(k)}</td><td>{esc(sz)}</td>"
                                        f'<td class="text">{esc(nt) or "as named"}</td></tr>' for n, k, sz, nt in rows)
            + "</tbody></table>"]


def _excluded(emitter, truth_shaded, other) -> np.ndarray | None:
    """The pixels left out of a shaded error map's colour scale: those on a light (``emitter``,
    else :func:`images.emitter_guess`) and their neighbours; None when there are none."""
    em = emitter if emitter is not None else _im.emitter_guess(truth_shaded, other)
    return _im.grow(em) if em.any() else None


def _render(run: Run, img_dir: Path) -> str:
    """Write all PNGs into ``img_dir`` and return the HTML text."""
    lights, techs, imgs = list(run.lights), run.techniques, run.images
    w, h = run.resolution
    truth = imgs.truth
    exposure = _im.common_exposure(truth.shaded)

    def put(fname: str, data: bytes) -> str:
        (img_dir / fname).write_bytes(data)
        return fname

    put("colorbar.png", _im.colorbar_png())
    truth_shaded = put(TRUTH_SHADED, _im.shaded_png(truth.shaded, exposure))
    truth_vis = {
        ln: put(f"truth_vis_{j}_{slug(ln)}.png", _im.visibility_png(truth.vis[ln])) for j, ln in enumerate(lights)
    }
    truth_lum = _im.luminance(truth.shaded)

    # Shared colour scale per light and for the shaded image, across techniques; pixels on a light
    # (and their neighbours) do not count.
    emitter = imgs.emitter
    vis_out = None if emitter is None or not emitter.any() else _im.grow(emitter)
    vis_err = {
        name: {
            ln: _im.luminance(imgs.techniques[name].vis[ln]) - _im.luminance(truth.vis[ln]) for ln in lights
        }
        for name in techs
    }
    shaded_err = {name: _im.luminance(imgs.techniques[name].shaded) - truth_lum for name in techs}
    vis_scale = {ln: max([_im.error_scale(vis_err[n][ln], exclude=vis_out) for n in techs], default=1e-6)
                 for ln in lights}
    shaded_scale = max([_im.error_scale(e, exclude=_excluded(emitter, truth.shaded, imgs.techniques[n].shaded))
                        for n, e in shaded_err.items()], default=1e-6)

    p = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>shadowlab: {esc(run.scene)} {w}×{h}</title>",
        f"<style>{CSS}{_cmp.CSS}</style></head><body>",
        f"<h1>shadowlab report: {esc(run.scene)} — {w}×{h}</h1>",
    ]
    p += _verdict(run)
    p += _ingest_facts(run)
    p.append(f'<p class="ref">{esc(reference_line(run))}</p>')
    extra_ref = run.reference.details
    if extra_ref:
        p.append(f'<p class="note">Reference details: {_metric_line_any(extra_ref)}</p>')

    p.append("<h2>Metrics</h2>")
    p += _metrics_tables(run)
    p.append(
        '<p class="note">Best value per column in bold (highest for psnr/ssim, lowest for errors, rates and '
        f"time). {NA}: not available; NaN/inf are stored as null in metrics.json. Heat maps show the signed "
        "error technique − truth: <span style=\"color:#2166ac\">blue = technique darker</span>, white = equal, "
        "<span style=\"color:#b2182b\">red = technique brighter</span>; three-channel images are compared by "
        "luminance; for each light (and for the shaded image) all techniques share one colour scale, the 99th "
        "percentile of |error| without the pixels on a light seen by the camera and their neighbours. "
        f"Visibility: grey level = visibility. Shaded images: common exposure {esc(fmt_value(exposure))} "
        "(truth 99th-percentile luminance → 0.9), sRGB.</p>"
    )
    charts = _charts.run_charts(run)
    if charts:
        p += ["<h2>Charts</h2>", charts]

    # ground truth
    g = ["<h2>Lights and ground truth</h2>"]
    g += _lights_html(run)
    g.append('<table class="grid"><tr><th></th><th>truth (shaded)</th>')
    cmp_items, cmp_last = [], []
    if imgs.mitsuba is not None:
        g.append("<th>Mitsuba <code>mi.render</code></th><th>signed error (mi.render − truth)</th>")
    g.append("</tr><tr><th class=\"row\">shaded</th>")
    g.append(f"<td>{img_tag(truth_shaded, 'truth shaded')}</td>")
    if imgs.mitsuba is not None:
        mts = put("mitsuba.png", _im.shaded_png(imgs.mitsuba, exposure))
        merr = _im.luminance(imgs.mitsuba) - truth_lum
        mscale = _im.error_scale(merr, exclude=_excluded(emitter, truth.shaded, imgs.mitsuba))
        merr_f = put("mitsuba_err.png", _im.encode_png(_im.signed_error_heatmap(merr, mscale)))
        g.append(f"<td>{img_tag(mts, 'Mitsuba mi.render')}</td>")
        g.append(f"<td>{img_tag(merr_f, 'signed error mi.render - truth')}{legend(mscale)}</td>")
        cmp_last.append(_cmp.item("mi.render (Mitsuba direct)", [_cmp.layer(
            "shaded", f"img/{mts}", f"img/{truth_shaded}", f"img/{merr_f}", fmt_value(mscale))], a_label="mi.render"))
    g.append("</tr></table>")
    g.append('<p class="note">Pixels on a light the camera sees (and their neighbours) are left out of the '
             "colour scales: mi.render shows the light's radiance there, the truth has no shading point.</p>")

    # per technique
    tp = []
    for i, name in enumerate(techs):
        t = techs[name]
        ti = imgs.techniques[name]
        tag = technique_tag(i, name)
        cmp_i = len(cmp_items)
        layers = []
        tp.append(f'<h2 id="t{i}">{esc(name)} <a class="open" href="#cmp" data-cmp-item="{cmp_i}" '
                  'data-cmp-layer="0">compare</a></h2>')
        params = " ".join(f"<code>{esc(k)}={esc(json.dumps(to_jsonable(v)))}</code>" for k, v in t.params.items())
        tp.append(f'<p class="note">time {esc(fmt_value(t.time_s))} s. Parameters: {params or "none"}</p>')
        tp.append(
            '<table class="grid"><tr><th></th><th>technique</th><th>truth</th>'
            "<th>signed error (technique − truth)</th></tr>"
        )
        for j, ln in enumerate(lights):
            vf = put(f"{tag}_vis_{j}_{slug(ln)}.png", _im.visibility_png(ti.vis[ln]))
            ef = put(
                f"{tag}_vis_{j}_{slug(ln)}_err.png",
                _im.encode_png(_im.signed_error_heatmap(vis_err[name][ln], vis_scale[ln])),
            )
            layers.append(_cmp.layer(f"{ln} visibility", f"img/{vf}", f"img/{truth_vis[ln]}", f"img/{ef}",
                                     fmt_value(vis_scale[ln])))
            pl = t.per_light.get(ln, {})
            title = (run.extras.get("ingest") or {}).get("labels", {}).get(ln)    # ingest --label CHANNEL=TEXT
            tp.append(
                f'<tr><th class="row"><b>{esc(ln)}</b> visibility{f" ({esc(title)})" if title else ""}<br>'
                f'{_metric_line(pl)}</th>'
                f"<td>{img_tag(vf, f'{name} visibility {ln}')}</td>"
                f"<td>{img_tag(truth_vis[ln], f'truth visibility {ln}')}</td>"
                f"<td>{img_tag(ef, f'signed error {name} {ln}')}{legend(vis_scale[ln])}</td></tr>"
            )
            tp += panel_rows(ti, ln, name, f"{tag}_{{}}_{j}_{slug(ln)}.png", put)
        sf = put(f"{tag}_shaded.png", _im.shaded_png(ti.shaded, exposure))
        sef = put(shaded_error_png(i, name), _im.encode_png(_im.signed_error_heatmap(shaded_err[name], shaded_scale)))
        layers.insert(
            0, _cmp.layer("shaded", f"img/{sf}", f"img/{truth_shaded}", f"img/{sef}", fmt_value(shaded_scale))
        )
        cmp_items.append(_cmp.item(name, layers))
        tp.append(
            f'<tr><th class="row"><b>shaded</b><br>{_metric_line(t.metrics)}</th>'
            f"<td>{img_tag(sf, f'{name} shaded')}</td>"
            f"<td>{img_tag(truth_shaded, 'truth shaded')}</td>"
            f"<td>{img_tag(sef, f'signed error {name} shaded')}{legend(shaded_scale)}</td></tr>"
        )
        tp.append("</table>")
        for title, cols, rows in band_tables(t):
            tp.append(f'<p class="note">{esc(title)}</p><table class="metrics"><thead><tr>'
                      + "".join(f"<th>{esc(c)}</th>" for c in cols) + "</tr></thead><tbody>"
                      + "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows)
                      + "</tbody></table>")
        for title, cols, rows in stats_tables(t.stats or {}):
            tp.append(
                f'<p class="note">stats per {esc(title[:-1])}</p><div class="wide"><table class="metrics"><thead><tr>'
                + "".join(f"<th>{esc(c)}</th>" for c in cols)
                + "</tr></thead><tbody>"
                + "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows)
                + "</tbody></table></div>"
            )

    if cmp_items or cmp_last:
        p += ["<h2>Compare images</h2>",
              _cmp.comparator_html({"width": w, "height": h, "items": cmp_items + cmp_last})]
    p += g + tp
    extra = {k: v for k, v in run.extras.items() if k not in ("gate", "ingest")}
    if extra:
        p.append("<h2>Run</h2>")
        p.append(f"<details><summary>{esc(', '.join(extra))}</summary>"
                 f"<pre>{esc(json.dumps(to_jsonable(extra), indent=2))}</pre></details>")
    p.append("</body></html>")
    return "\n".join(p) + "\n"


def _metric_line_any(d: Mapping) -> str:
    return " · ".join(f"{esc(k)} {esc(json.dumps(to_jsonable(v)))}" for k, v in d.items())


# --------------------------------------------------------------------------------------------
# build


def build(out_dir, run: Mapping, *, force: bool = False, protected=(), kind: str = "compare") -> Path:
    """Write ``out_dir/index.html``, ``summary.md``, ``metrics.json`` and ``img/*.png`` for one run;
    returns the path of index.html.

    ``out_dir`` must be ours or new (:func:`shadowlab.io.outdir.claim_dir`: an existing
    directory without the ``.shadowlab-report`` marker is refused unless ``force``) and outside
    the ``protected`` directories (the reference store).

    ``run``: a :class:`~shadowlab.report.run.Run` with images, or its mapping (checked by
    :meth:`Run.from_mapping <shadowlab.report.run.Run.from_mapping>`): {"scene", "resolution": [W, H],
    "reference": {"spp", "max_std_error", ...}, "lights": [names], "images": {"truth": {"shaded":
    H×W×3, "vis": {light: H×W}}, "mitsuba": H×W×3 (optional), "techniques": {name: {"shaded", "vis",
    optional "panels" and their images}}}, "techniques": {name: {"params", "time_s", "metrics",
    "per_light"}}, ...extra JSON keys}. Bad input raises ``InputError`` naming the key, before
    anything is written.

    >>> import numpy as np, tempfile
    >>> z = np.zeros((8, 8)); s = np.full((8, 8, 3), .5)
    >>> run = {"scene": "demo", "resolution": [8, 8], "reference": {"spp": 16, "max_std_error": .01},
    ...        "lights": ["key"], "techniques": {"hard": {"params": {"bias": .001}, "time_s": .002,
    ...        "metrics": {"rmse": .1}, "per_light": {"key": {"rmse": .1}}}},
    ...        "images": {"truth": {"shaded": s, "vis": {"key": z}},
    ...                   "techniques": {"hard": {"shaded": s, "vis": {"key": z}}}}}
    >>> build(tempfile.mkdtemp() + "/r", run).name
    'index.html'
    """
    out = Path(out_dir)
    run = Run.from_mapping(run)
    claim_dir(out, kind, force=force, protected=protected, files=OUTPUT_FILES + ("img/",))
    for f in OUTPUT_FILES:
        if (out / f).is_dir():
            raise InputError(f"report output {out / f} is a directory; remove it or choose another --out")
    json_text = json.dumps(run.to_json(), indent=2, allow_nan=False) + "\n"
    md_text = summary_table(run) + "\n" + gate_markdown(run)
    st_md = stats_markdown(run)
    if st_md:
        md_text += "\n## Stats per light and map\n\n" + st_md
    b_md = bands_markdown(run)
    if b_md:
        by = list(dict.fromkeys(k for t in run.techniques.values() for d in (t.bands or {}).values()
                                for k, _, _ in _charts.band_kinds(d)))
        md_text += f"\n## Visibility error by {' and '.join(by)}\n\n" + b_md

    def fill(tmp: Path) -> None:
        html_text = _render(run, tmp / "img")
        (tmp / "metrics.json").write_text(json_text, encoding="utf-8")
        (tmp / "summary.md").write_text(md_text, encoding="utf-8")
        (tmp / "index.html").write_text(html_text, encoding="utf-8")

    return write_dir(out, kind, fill, OUTPUT_FILES, OUTPUT_DIRS)
