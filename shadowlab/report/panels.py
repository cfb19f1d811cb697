"""HTML pieces of a report page: image tags, colour-bar legends, and the rows a technique's family
adds (``Technique.panels``: images built from its AOVs), drawn by the panel's kind, never by family."""

from __future__ import annotations

import html
import re
from urllib.parse import quote

import numpy as np

from . import images as _im
from .tables import fmt_value

__all__ = ["CSS", "slug", "esc", "img_tag", "legend", "panel_rows", "technique_tag", "TRUTH_SHADED",
           "shaded_error_png"]

_IMG_CSS_WIDTH = 256
#: the truth's shaded image in a report's img/
TRUTH_SHADED = "truth_shaded.png"

#: the stylesheet of every report page
CSS = f"""
body {{ font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }}
h1 {{ font-size: 1.5em; margin-bottom: .2em; }}
h2 {{ font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }}
.ref {{ color: #444; margin-top: 0; }}
table.metrics {{ border-collapse: collapse; font-variant-numeric: tabular-nums; }}
table.metrics th, table.metrics td {{ border: 1px solid #ccc; padding: 3px 8px; text-align: right; }}
table.metrics th:first-child, table.metrics td:first-child {{ text-align: left; }}
table.grid {{ border-collapse: collapse; }}
table.grid th, table.grid td {{ padding: 4px 6px; vertical-align: top; text-align: left; }}
table.grid th.row {{ max-width: 14em; font-weight: normal; font-size: .85em; }}
img.im {{ width: {_IMG_CSS_WIDTH}px; height: auto; image-rendering: pixelated; border: 1px solid #bbb; display: block; }}
img.cbar {{ width: {_IMG_CSS_WIDTH}px; height: 10px; image-rendering: pixelated; display: block; margin-top: 3px; }}
.ticks {{ width: {_IMG_CSS_WIDTH}px; display: flex; justify-content: space-between; font-size: .75em; color: #444; }}
.note {{ font-size: .85em; color: #555; }}
code {{ font-size: .9em; }}
.wide {{ max-width: 100%; overflow-x: auto; }}
table.metrics td.text, table.lights td, table.lights th {{ text-align: left; max-width: 40em; }}
.verdict {{ font-size: 1.1em; padding: .5em .8em; margin: .6em 0; border-radius: 4px; max-width: 60em; }}
.verdict .word {{ font-size: 1.5em; font-weight: 700; margin-right: .4em; vertical-align: middle; }}
.verdict.pass {{ background: #e6f4ea; border: 1px solid #1a7f37; color: #1a7f37; }}
.verdict.fail {{ background: #fbe9eb; border: 1px solid #b2182b; color: #b2182b; }}
table.checks th, table.checks td {{ text-align: left; }}
table.checks td:nth-child(4), table.checks td:nth-child(5) {{ text-align: right; white-space: nowrap; }}
td.pass {{ color: #1a7f37; font-weight: 600; }}
td.fail {{ color: #b2182b; font-weight: 600; }}
ul.facts {{ font-size: .9em; color: #333; padding-left: 1.2em; }}
.charts {{ display: flex; flex-wrap: wrap; gap: 1em 2em; }}
figure.chart {{ margin: 0; }}
figure.chart svg {{ display: block; max-width: 100%; height: auto; }}
.chart-legend {{ font-size: .8em; display: flex; flex-wrap: wrap; gap: .2em 1em; }}
.chart-legend i {{ display: inline-block; width: .8em; height: .8em; margin-right: .3em; vertical-align: -1px; }}
a.open {{ font-size: .6em; font-weight: normal; margin-left: .6em; }}
details pre {{ white-space: pre-wrap; word-break: break-all; font-size: .8em; }}
"""  # noqa: E501


def slug(s: str) -> str:
    return (re.sub(r"[^A-Za-z0-9_-]+", "-", s).strip("-") or "x")[:40]


def technique_tag(i: int, name: str) -> str:
    """The prefix of the i-th technique's image files in a report's img/ (and its anchor)."""
    return f"t{i}_{slug(name)}"


def shaded_error_png(i: int, name: str) -> str:
    """The file name of the i-th technique's shaded error heat map in a report's img/."""
    return f"{technique_tag(i, name)}_shaded_err.png"


def esc(s) -> str:
    return html.escape(str(s), quote=True)


def img_tag(fname: str, alt: str) -> str:
    return f'<img class="im" src="img/{quote(fname)}" alt="{esc(alt)}" title="{esc(alt)}">'


def legend(scale: float) -> str:
    s = fmt_value(scale)
    return (
        '<img class="cbar" src="img/colorbar.png" alt="colour scale">'
        f'<div class="ticks"><span>&minus;{s}</span><span>0</span><span>+{s}</span></div>'
    )


def _ratio_legend(scale: float) -> str:
    s = fmt_value(scale)
    return ('<img class="cbar" src="img/colorbar.png" alt="colour scale">'
            f'<div class="ticks"><span>2<sup>&minus;{s}</sup></span><span>1</span><span>2<sup>{s}</sup></span></div>')


def _level_legend(lo: int, hi: int, what: str) -> str:
    mid = fmt_value((lo + hi) / 2)
    return ('<img class="cbar" src="img/colorbar.png" alt="colour scale">'
            f'<div class="ticks"><span>&le;{lo}</span><span>{mid}</span><span>&ge;{hi}</span></div>'
            f'<div class="ticks"><span>{esc(what)}</span></div>')


def _under_legend(scale: int, what: str) -> str:
    return ('<img class="cbar" src="img/colorbar_pos.png" alt="colour scale">'
            f'<div class="ticks"><span>0 (met)</span><span>{fmt_value(scale / 2)}</span><span>&ge;{scale}</span></div>'
            f'<div class="ticks"><span>{esc(what)}</span></div>')


def _colour_png(rgb) -> bytes:
    """PNG of an H×W×3 colour image in [0, 1] (a panel's colour images)."""
    return _im.encode_png(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))


def _axis_row(head: str, cells: list[str]) -> str:
    """A grid row: the header cell, one cell per axis, empty cells up to the table's three columns."""
    return f'<tr><th class="row">{head}</th>' + "".join(cells) + "<td></td>" * (3 - len(cells)) + "</tr>"


def _panel_image(pn, key: str, label: str, img, scale, ln: str, name: str, fname: str, put) -> str:
    """One image of a panel, drawn as the panel's kind on the panel's shared ``scale``."""
    alt = f"{name} {pn.alt} {label} {ln}" if label else f"{name} {pn.alt} {ln}"
    if pn.kind == "colour":
        png, legend = _colour_png(img), ""
    elif pn.kind == "log2_ratio":
        png = _im.encode_png(_im.signed_error_heatmap(_log2_ratio(img), scale))
        legend = _ratio_legend(scale)
    elif pn.kind == "levels":
        png = _im.encode_png(_im.level_heatmap(img, lo=scale[0], hi=scale[1]))
        legend = _level_legend(*scale, pn.legend)
    else:                                    # excess_levels
        png = _im.encode_png(_im.undersampling_heatmap(np.where(img >= 0, img, np.nan), scale=scale))
        legend = _under_legend(scale, pn.legend)
    f = put(fname.format(key), png)
    return f"<td>{esc(label) + ': ' if label else ''}{img_tag(f, alt)}{legend}</td>"


def _log2_ratio(a) -> np.ndarray:
    """log₂ of a ratio image; NaN (grey) where it is not positive (none)."""
    return np.where(a > 0, np.log2(np.maximum(a, 1e-12)), np.nan)


def _panel_scale(pn, imgs: list):
    """The one colour scale of a panel's images for one light: None (colour), the symmetric
    integer log₂ scale (log2_ratio), the level range (levels) or the excess scale (excess_levels)."""
    if pn.kind == "log2_ratio":
        return max(1.0, float(np.ceil(_im.error_scale(np.concatenate([_log2_ratio(a).reshape(1, -1) for a in imgs],
                                                                     axis=1)))))
    if pn.kind == "levels":
        return _im.level_range(*imgs)
    if pn.kind == "excess_levels":
        return _im.level_range(*imgs, lo=0)[1]
    return None


def panel_rows(ti, ln: str, name: str, fname: str, put) -> list[str]:
    """HTML rows of the technique's panels (its family's images, ``Technique.panels``) for light
    ``ln``, those it has images of; ``fname``: the PNG name with ``{}`` for the image's key;
    ``put`` writes a PNG and returns its name."""
    rows = []
    for pn in ti.panels:
        have = [(k, label) for k, label in pn.images if ln in ti.extra.get(k, {})]
        if not have:
            continue
        scale = _panel_scale(pn, [ti.extra[k][ln] for k, _ in have])
        if pn.kind == "excess_levels":
            put("colorbar_pos.png", _im.colorbar_png(signed=False))
        cells = [_panel_image(pn, k, label, ti.extra[k][ln], scale, ln, name, fname, put) for k, label in have]
        head = f"<b>{esc(ln)}</b> {esc(pn.title)}" + (f"<br>{esc(pn.note)}" if pn.note else "")
        rows.append(_axis_row(head, cells))
    return rows
