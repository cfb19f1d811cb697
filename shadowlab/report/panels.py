"""HTML pieces of a report page: image tags, colour-bar legends, and the rows a technique's family
adds (``Technique.panels``: images built from its AOVs), drawn by the panel's kind, never by family."""

from __future__ import annotations

import html
import re
from urllib.parse import quote

import numpy as np

from . import images as _im
from .tables import fmt_value

__all__ = ["slug", "esc", "img_tag", "legend", "panel_rows"]


def slug(s: str) -> str:
    return (re.sub(r"[^A-Za-z0-9_-]+", "-", s).strip("-") or "x")[:40]


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
