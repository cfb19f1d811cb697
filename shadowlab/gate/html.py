"""One self-contained HTML page of gate results (images inline as PNG data URIs).

Every gate is listed with its checks; each failed gate also shows four images: the candidate,
the reference, the signed error map (candidate − reference, luminance; blue darker, red brighter,
see :mod:`shadowlab.report.images`) and, when the statistical test ran, the p-value map: grey level
−log10 p of the pixel's smallest p-value, black at p = 1 and white at the Šidák level α_pixel;
pixels that fail the Z-test are red, untested pixels dark blue. Shaded images share one exposure
(the reference's 99th-percentile luminance → 0.9); visibility is shown as grey = visibility.

Every heat map has its colour bar under it, drawn by CSS gradients (no extra image): the error
map's from −scale (blue) through 0 (white) to +scale (red), which is exactly the map's colour ramp
(linear in sRGB between the three colours); the p-value map's from p = 1 (black) to p = α_pixel
(white), with the two special colours.
"""

from __future__ import annotations

import base64
import html as _html
import math
import os

import numpy as np

from ..io.png import encode_png, write_bytes_atomic
from ..report import images as _im

__all__ = ["page_html", "write_page", "pvalue_map"]

_CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 7px;text-align:left;
vertical-align:top;font-size:13px}.pass{color:#1a7f37;font-weight:600}.fail{color:#b2182b;font-weight:600}
img{width:256px;image-rendering:pixelated;display:block}.note{color:#555;font-size:13px;max-width:60em}
code{font-size:12px}.cbar{width:256px;height:10px;margin-top:3px}
.err{background:linear-gradient(to right,rgb(33,102,172),#fff,rgb(178,24,43))}
.pv{background:linear-gradient(to right,#000,#fff)}
.ticks{width:256px;display:flex;justify-content:space-between;font-size:11px;color:#444}
.sw{display:inline-block;width:.8em;height:.8em;vertical-align:-1px;margin-right:.2em}"""


def _e(s) -> str:
    return _html.escape(str(s))


def _uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def pvalue_map(p, failed, alpha_value: float) -> np.ndarray:
    """uint8 H×W×3 picture of a p-value map (see the module docstring).

    >>> pvalue_map(np.array([[1.0, 1e-9, np.nan]]), np.array([[False, True, False]]), 1e-6)[0].tolist()
    [[0, 0, 0], [220, 30, 30], [20, 30, 80]]
    """
    p = np.asarray(p, np.float64)
    tested = np.isfinite(p)
    top = -math.log10(max(alpha_value, 1e-300))
    with np.errstate(divide="ignore"):
        lv = -np.log10(np.clip(np.where(tested, p, 1.0), 1e-300, 1.0))
    g = np.round(255 * np.clip(lv / top, 0, 1)).astype(np.uint8)
    out = np.repeat(g[..., None], 3, axis=2)
    out[~tested] = (20, 30, 80)
    out[np.asarray(failed, bool) & tested] = (220, 30, 30)
    return out


def _err_legend(scale: float) -> str:
    s = f"{scale:.3g}"
    return (f'<div class="cbar err" title="colour scale"></div><div class="ticks"><span>&minus;{s}</span>'
            f"<span>0</span><span>+{s}</span></div>")


def _pvalue_legend(alpha: float) -> str:
    return (
        '<div class="cbar pv" title="colour scale"></div><div class="ticks"><span>p = 1</span>'
        f'<span>p = {alpha:.2g}</span></div><div class="ticks"><span><i class="sw" style="background:rgb(220,30,30)">'
        '</i>fails</span><span><i class="sw" style="background:rgb(20,30,80)"></i>untested</span></div>'
    )


def _images(r) -> list[tuple[str, str, str]]:
    """(title, PNG data URI, legend HTML) of a failed gate's images."""
    im = r.images
    cand, ref, err = im.get("candidate"), im.get("reference"), im.get("error")
    if cand is None or ref is None:
        return []
    out = []
    if np.asarray(ref).ndim == 3:
        exp = _im.common_exposure(ref)
        out += [("candidate", _uri(_im.shaded_png(cand, exp)), ""), ("reference", _uri(_im.shaded_png(ref, exp)), "")]
    else:
        out += [("candidate", _uri(_im.visibility_png(np.clip(cand, 0, 1))), ""),
                ("reference", _uri(_im.visibility_png(np.clip(ref, 0, 1))), "")]
    e = np.where(np.asarray(im.get("valid", True)), _im.luminance(err), 0.0)
    scale = _im.error_scale(e)
    out.append((f"error (candidate − reference), ±{scale:.3g}", _uri(encode_png(_im.signed_error_heatmap(e, scale))),
                _err_legend(scale)))
    if im.get("pvalue") is not None:
        a = float(r.info.get("alpha_value", 1e-6))
        out.append((f"p-value map (white: p = α_pixel {a:.2g}; red: fails)",
                    _uri(encode_png(pvalue_map(im["pvalue"], im["failed_pixels"], a))), _pvalue_legend(a)))
    return out


def page_html(results, title: str = "shadowlab gate") -> str:
    n_fail = sum(not r.passed for r in results)
    p = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{_e(title)}</title>",
         f"<style>{_CSS}</style></head><body>", f"<h1>{_e(title)}</h1>",
         f"<p>{len(results) - n_fail} of {len(results)} gates passed; "
         + (f'<span class="fail">{n_fail} failed</span>' if n_fail else '<span class="pass">no failures</span>')
         + "</p>",
         "<table><tr><th>gate</th><th>result</th><th>target</th><th>candidate</th><th>checks failed</th></tr>"]
    for i, r in enumerate(results):
        cls, word = ("pass", "PASS") if r.passed else ("fail", "FAIL")
        link = f'<a href="#g{i}">{_e(r.name)}</a>' if not r.passed else _e(r.name)
        p.append(f"<tr><td>{link}</td><td class=\"{cls}\">{word}</td><td>{_e(r.target)}</td>"
                 f"<td>{_e(r.info.get('candidate', ''))}</td><td>{_e(', '.join(c.name for c in r.failed))}</td></tr>")
    p.append("</table>")
    p.append('<p class="note">Statistical checks: per-pixel Z-test with Šidák-corrected α (stat.pixels: the '
             "fraction of pixels that pass), and Student t-tests of the mean per-pixel z over all tested pixels "
             "(stat.bias) and over the penumbra (stat.bias_penumbra). Budget checks: the metric against its limit "
             "(≥ for psnr/ssim, ≤ otherwise).</p>")
    for i, r in enumerate(results):
        if r.passed:
            continue
        p.append(f'<h2 id="g{i}">{_e(r.name)} <span class="fail">FAIL</span></h2>')
        facts = [f"{k}: {r.info[k]}" for k in ("description", "scene", "candidate", "reference") if r.info.get(k)]
        facts.append(f"target: {r.target}; {r.info.get('pixels', '?')} pixels tested, "
                     f"{r.info.get('penumbra_pixels')} in the penumbra")
        p.append('<p class="note">' + "<br>".join(_e(f) for f in facts) + "</p>")
        p.append("<table><tr><th>check</th><th>result</th><th>value</th><th>threshold</th><th>details</th></tr>")
        for c in r.checks:
            cls, word = ("pass", "PASS") if c.passed else ("fail", "FAIL")
            p.append(f"<tr><td><code>{_e(c.name)}</code></td><td class=\"{cls}\">{word}</td><td>{c.value:.4g}</td>"
                     f"<td>{_e(c.op)} {c.threshold:.4g}</td><td>{_e(c.text)}</td></tr>")
        p.append("</table>")
        imgs = _images(r)
        if imgs:
            p.append("<table><tr>" + "".join(f"<th>{_e(t)}</th>" for t, _, _ in imgs) + "</tr><tr>"
                     + "".join(f'<td><img src="{u}" alt="{_e(t)}">{lg}</td>' for t, u, lg in imgs) + "</tr></table>")
    p.append("</body></html>")
    return "\n".join(p) + "\n"


def write_page(path, results, title: str = "shadowlab gate"):
    """Write the page atomically; returns its path."""
    p = write_bytes_atomic(path, page_html(results, title).encode("utf-8"))
    os.chmod(p, 0o644)
    return p
