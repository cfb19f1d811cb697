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

import html as _html
import json
import math
import numbers
import os
import re
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import quote

import numpy as np

from ..errors import InputError
from . import charts as _charts
from . import comparator as _cmp
from . import images as _im
from .lights import light_rows
from ..io.outdir import claim_dir, write_dir

__all__ = ["build", "summary_table", "stats_tables", "validate", "run_to_json", "to_jsonable", "higher_is_better"]

OUTPUT_FILES = ("index.html", "summary.md", "metrics.json")
OUTPUT_DIRS = ("img",)
_HIGHER_IS_BETTER_PREFIXES = ("psnr", "ssim")
_IMG_CSS_WIDTH = 256
_NA = "n/a"
#: the metrics of the page's first table (with time_s); the others go to a second table
KEY_METRICS = ("rmse", "rmse_penumbra", "vis_rmse_penumbra", "leak_rate", "overdark_rate", "psnr", "ssim", "flip")


# --------------------------------------------------------------------------------------------
# JSON


def to_jsonable(obj, key: str = "run"):
    """Plain-JSON copy of ``obj``: numpy scalars/arrays -> Python values, tuples -> lists,
    NaN/±inf -> None. Anything else that JSON cannot hold raises ``InputError`` naming ``key``.

    >>> to_jsonable({"a": np.float32(0.5), "b": float("nan"), "c": (np.int64(3),)})
    {'a': 0.5, 'b': None, 'c': [3]}
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, numbers.Integral):
        return int(obj)
    if isinstance(obj, numbers.Real):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise InputError(f"{key}: a numpy array of dtype {obj.dtype} cannot be written to metrics.json")
        return to_jsonable(obj.tolist(), key)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise InputError(f"{key}: dictionary key {k!r} is not a string; metrics.json needs string keys")
            out[str(k)] = to_jsonable(v, f"{key}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, f"{key}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise InputError(f"{key}: a value of type {type(obj).__name__} cannot be written to metrics.json")


def run_to_json(run: Mapping) -> dict:
    """The run without ``"images"``, as plain JSON (what ``metrics.json`` holds).

    >>> run_to_json({"scene": "s", "images": {}, "resolution": (2, 2)})
    {'scene': 's', 'resolution': [2, 2]}
    """
    return to_jsonable({k: v for k, v in run.items() if k != "images"})


# --------------------------------------------------------------------------------------------
# validation


def _number(v, key: str, allow_none: bool = True, finite: bool = False) -> float | None:
    if v is None and allow_none:
        return None
    if isinstance(v, np.ndarray) and v.ndim == 0:
        v = v.item()
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise InputError(f"{key}: expected a number, got {type(v).__name__} {v!r:.60}")
    v = float(v)
    if finite and not math.isfinite(v):
        raise InputError(f"{key}: expected a finite number, got {v}")
    return v


def _mapping(d, key: str) -> Mapping:
    if not isinstance(d, Mapping):
        raise InputError(f"{key}: expected a dict, got {type(d).__name__}")
    return d


def _get(d: Mapping, name: str, where: str):
    if name not in d:
        raise InputError(f"{where}: the key {name!r} is missing (needed: {where}.{name})")
    return d[name]


def _image(a, key: str, hw: tuple[int, int], channels: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(a)
    except Exception as e:  # e.g. a Dr.Jit tensor that fails to convert
        raise InputError(f"{key}: cannot be converted to a numpy array ({e})") from None
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{key}: expected a numeric image, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    ok_shapes = [hw if c == 0 else (*hw, c) for c in channels]
    if arr.shape not in ok_shapes:
        want = " or ".join("×".join(map(str, s)) for s in ok_shapes)
        raise InputError(f"{key}: image shape {arr.shape} does not match the run resolution; expected {want}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise InputError(f"{key}: image contains {int(bad.sum())} NaN or inf values; fix the renderer output first")
    return arr


def _check_metric_dict(d, key: str) -> None:
    for m, v in _mapping(d, key).items():
        if not isinstance(m, str):
            raise InputError(f"{key}: metric name {m!r} is not a string")
        _number(v, f"{key}.{m}")


#: the channels (0: H×W) of a panel's images by the panel's kind (``Technique.panels``: a family's
#: own report rows, whose images ``Technique.report_images`` builds from its AOVs)
_PANEL_CHANNELS = {"colour": (3,), "log2_ratio": (0,), "levels": (0,), "excess_levels": (0,)}


def _panels(d, where: str) -> tuple:
    """The panels of one technique's images (``images.techniques.<name>.panels``), checked."""
    panels = d.get("panels") or ()
    if not isinstance(panels, (list, tuple)):
        raise InputError(f"{where}.panels: expected a list of panels, got {type(panels).__name__}")
    for i, pn in enumerate(panels):
        if not all(hasattr(pn, a) for a in ("kind", "title", "images", "alt", "note", "legend")):
            raise InputError(f"{where}.panels[{i}]: expected a Panel (kind, title, images, alt, note, legend)")
        if pn.kind not in _PANEL_CHANNELS:
            raise InputError(f"{where}.panels[{i}].kind: {pn.kind!r} is not one of {', '.join(_PANEL_CHANNELS)}")
    return tuple(panels)


def validate(run: Mapping, need_images: bool = True) -> dict:
    """Check a run dict; raise ``InputError`` naming the bad key. Returns the images as float64
    arrays: ``{"truth": {...}, "mitsuba": arr|None, "techniques": {...}}`` (empty dict when
    ``need_images`` is false).
    """
    run = _mapping(run, "run")
    scene = _get(run, "scene", "run")
    if not isinstance(scene, str) or not scene:
        raise InputError(f"run.scene: expected a non-empty string, got {scene!r}")
    res = _get(run, "resolution", "run")
    try:
        res = list(res)
    except TypeError:
        raise InputError(f"run.resolution: expected [W, H], got {res!r}") from None
    if len(res) != 2 or not all(
        isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_)) and x > 0 for x in res
    ):
        raise InputError(f"run.resolution: expected [W, H] with positive integers, got {res!r}")
    w, h = int(res[0]), int(res[1])
    ref = _mapping(_get(run, "reference", "run"), "run.reference")
    _number(_get(ref, "spp", "run.reference"), "run.reference.spp", allow_none=False, finite=True)
    _number(_get(ref, "max_std_error", "run.reference"), "run.reference.max_std_error", allow_none=False)
    lights = _get(run, "lights", "run")
    if not isinstance(lights, (list, tuple)) or not all(isinstance(x, str) and x for x in lights):
        raise InputError(f"run.lights: expected a list of light names, got {lights!r}")
    if len(set(lights)) != len(lights):
        raise InputError(f"run.lights: light names must be unique, got {list(lights)}")
    techs = _mapping(_get(run, "techniques", "run"), "run.techniques")
    for name, t in techs.items():
        where = f"run.techniques.{name}"
        if not isinstance(name, str) or not name:
            raise InputError(f"run.techniques: technique name {name!r} is not a non-empty string")
        t = _mapping(t, where)
        _mapping(_get(t, "params", where), f"{where}.params")
        _number(_get(t, "time_s", where), f"{where}.time_s")
        _check_metric_dict(_get(t, "metrics", where), f"{where}.metrics")
        per_light = _mapping(_get(t, "per_light", where), f"{where}.per_light")
        for ln, d in per_light.items():
            if ln not in lights:
                raise InputError(f"{where}.per_light.{ln}: {ln!r} is not in run.lights {list(lights)}")
            _check_metric_dict(d, f"{where}.per_light.{ln}")
    info = run.get("light_info")
    if info is not None:
        for ln, d in _mapping(info, "run.light_info").items():
            _mapping(d, f"run.light_info.{ln}")
    run_to_json(run)  # every non-image value must be JSON-serialisable

    if not need_images:
        return {}
    imgs = _mapping(_get(run, "images", "run"), "run.images")
    hw = (h, w)

    def frame(d, where):
        d = _mapping(d, where)
        shaded = _image(_get(d, "shaded", where), f"{where}.shaded", hw, (3, 0, 1))
        vis_d = _mapping(_get(d, "vis", where), f"{where}.vis")
        extra = [k for k in vis_d if k not in lights]
        if extra:
            raise InputError(f"{where}.vis.{extra[0]}: {extra[0]!r} is not in run.lights {list(lights)}")
        vis = {ln: _image(_get(vis_d, ln, f"{where}.vis"), f"{where}.vis.{ln}", hw, (0, 1, 3)) for ln in lights}
        out = {"shaded": shaded, "vis": vis, "panels": _panels(d, where)}
        for pn in out["panels"]:             # the family's per-light images (see _PANEL_CHANNELS)
            for key in pn.keys:
                if key in d:
                    a = _mapping(d[key], f"{where}.{key}")
                    out[key] = {ln: _image(a[ln], f"{where}.{key}.{ln}", hw, _PANEL_CHANNELS[pn.kind])
                                for ln in lights if ln in a}
        return out

    out = {"truth": frame(_get(imgs, "truth", "run.images"), "run.images.truth")}
    mts = imgs.get("mitsuba")
    out["mitsuba"] = None if mts is None else _image(mts, "run.images.mitsuba", hw, (3, 0, 1))
    em = imgs.get("emitter")  # optional: the pixels on a light (images.emitter_pixels)
    out["emitter"] = None if em is None else _image(em, "run.images.emitter", hw, (0,)) > 0.5
    timgs = _mapping(_get(imgs, "techniques", "run.images"), "run.images.techniques")
    for name in timgs:
        if name not in techs:
            raise InputError(f"run.images.techniques.{name}: there is no run.techniques.{name} entry for it")
    out["techniques"] = {
        name: frame(_get(timgs, name, "run.images.techniques"), f"run.images.techniques.{name}") for name in techs
    }
    return out


# --------------------------------------------------------------------------------------------
# tables


def higher_is_better(metric: str) -> bool:
    """True for metrics where larger is better (psnr*, ssim*); errors, rates and time are lower-better.

    >>> higher_is_better("psnr"), higher_is_better("rmse_penumbra")
    (True, False)
    """
    return metric.lower().startswith(_HIGHER_IS_BETTER_PREFIXES)


def fmt_value(v) -> str:
    """A number as the report prints it: 4 significant digits, "n/a" for None and NaN.

    >>> fmt_value(0.123456), fmt_value(None), fmt_value(float("inf"))
    ('0.1235', 'n/a', 'inf')
    """
    if v is None:
        return _NA
    v = float(v)
    if math.isnan(v):
        return _NA
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.4g}"


def _metric_columns(techs: Mapping) -> list[str]:
    cols: list[str] = []
    for t in techs.values():
        for m in t.get("metrics", {}):
            if m not in cols:
                cols.append(m)
    return cols


def _table_cells(run: Mapping, cols=None) -> tuple[list[str], list[str], list[list[tuple[str, bool]]]]:
    """(column names, technique names, rows of (formatted value, is_best)); ``cols``: the columns,
    default every metric and time_s."""
    techs = run["techniques"]
    cols = _metric_columns(techs) + ["time_s"] if cols is None else list(cols)
    names = list(techs)

    def val(name, col):
        t = techs[name]
        v = t.get("time_s") if col == "time_s" else t["metrics"].get(col)
        v = None if v is None else float(v)
        return None if v is None or math.isnan(v) else v

    best = {}
    for c in cols:
        vs = [v for v in (val(n, c) for n in names) if v is not None]
        if vs:
            best[c] = max(vs) if higher_is_better(c) else min(vs)
    rows = [[(fmt_value(val(n, c)), c in best and val(n, c) == best[c]) for c in cols] for n in names]
    return cols, names, rows


def _reference_line(run: Mapping) -> str:
    ref = run["reference"]
    spp = ref["spp"]
    spp_s = str(int(spp)) if float(spp).is_integer() else fmt_value(spp)
    return f"Reference: {spp_s} spp, max standard error {fmt_value(ref['max_std_error'])}"


def _md_escape(s: str) -> str:
    return s.replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")


def summary_table(run: Mapping) -> str:
    """Markdown summary: a title, the reference line and one table row per technique (4 significant
    digits, best value per column in bold). Works on a full run or on a loaded metrics.json.
    This is what summary.md holds and what the CLI prints.

    >>> run = {"scene": "s", "resolution": [4, 4], "reference": {"spp": 64, "max_std_error": 0.01},
    ...        "lights": ["key"], "techniques": {"hard": {"params": {}, "time_s": 0.0012,
    ...        "metrics": {"rmse": 0.123456, "psnr": 18.2}, "per_light": {}}}}
    >>> print(summary_table(run))  # doctest: +NORMALIZE_WHITESPACE
    # shadowlab report: s (4x4)
    <BLANKLINE>
    Reference: 64 spp, max standard error 0.01
    <BLANKLINE>
    | technique | rmse | psnr | time_s |
    |---|---:|---:|---:|
    | hard | **0.1235** | **18.2** | **0.0012** |
    <BLANKLINE>
    Best value per column in bold (highest for psnr/ssim, lowest otherwise). n/a = not available (NaN/inf are null in metrics.json).
    """  # noqa: E501
    validate(run, need_images=False)
    w, h = (int(x) for x in run["resolution"])
    cols, names, rows = _table_cells(run)
    lines = [
        f"# shadowlab report: {_md_escape(run['scene'])} ({w}x{h})",
        "",
        _reference_line(run),
        "",
        "| technique | " + " | ".join(_md_escape(c) for c in cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]
    for n, row in zip(names, rows):
        cells = [f"**{s}**" if b else s for s, b in row]
        lines.append(f"| {_md_escape(n)} | " + " | ".join(cells) + " |")
    if not names:
        lines.append("| (no techniques) |" + " |" * len(cols))
    lines += [
        "",
        "Best value per column in bold (highest for psnr/ssim, lowest otherwise). "
        f"{_NA} = not available (NaN/inf are null in metrics.json).",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# HTML

_CSS = f"""
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


def _scalar_stat(v) -> bool:
    return isinstance(v, (numbers.Number, str, np.generic)) or v is None


def stats_tables(stats) -> list[tuple[str, list[str], list[list[str]]]]:
    """The per-light and per-map stats of one technique as tables ``(title, columns, rows)``:
    "lights" (one row per light, its scalar stats) and, where the technique reports maps
    (``stats["lights"][light]["maps"]``: cascades, tiles, cube maps), "maps" (one row per
    map of each light). Empty for stats without the ``lights`` layout.

    >>> st = {"lights": {"key": {"resolution": 512, "maps": [{"near": 0.5, "far": 4.0}, {"near": 4.0, "far": 9.0}]}}}
    >>> [(t, c, r) for t, c, r in stats_tables(st)]  # doctest: +NORMALIZE_WHITESPACE
    [('lights', ['light', 'resolution', 'maps'], [['key', '512', '2']]),
     ('maps', ['light', 'map', 'near', 'far'], [['key', '0', '0.5', '4'], ['key', '1', '4', '9']])]
    """
    lights = stats.get("lights") if isinstance(stats, Mapping) else None
    if not isinstance(lights, Mapping) or not lights:
        return []
    cols: list[str] = []
    for st in lights.values():
        cols += [k for k, v in st.items() if k != "maps" and _scalar_stat(v) and k not in cols]
    has_maps = any(st.get("maps") for st in lights.values())
    out = [("lights", ["light", *cols] + (["maps"] if has_maps else []),
            [[str(ln), *[fmt_value(st.get(c)) if not isinstance(st.get(c), str) else st[c] for c in cols]]
             + ([str(len(st.get("maps") or ()))] if has_maps else []) for ln, st in lights.items()])]
    if has_maps:
        mcols: list[str] = []
        for st in lights.values():
            for m in st.get("maps") or ():
                mcols += [k for k, v in m.items() if _scalar_stat(v) and k not in mcols]
        rows = [[str(ln), str(i), *[fmt_value(m.get(c)) if not isinstance(m.get(c), str) else m[c] for c in mcols]]
                for ln, st in lights.items() for i, m in enumerate(st.get("maps") or ())]
        out.append(("maps", ["light", "map", *mcols], rows))
    return out


_BAND_KEYS = ("pixels", "rmse", "rmse_penumbra", "leak_rate", "overdark_rate")


def band_tables(t: Mapping) -> list[tuple[str, list[str], list[list[str]]]]:
    """One technique's visibility error by distance band and by each label AOV it declares
    (``t["bands"]``, see :func:`shadowlab.pipeline.error_bands`) as tables ``(title, columns,
    rows)``, per light.

    >>> t = {"bands": {"sun": {"distance": [{"lo": 0.0, "hi": 10.0, "pixels": 4, "rmse": 0.5, "rmse_penumbra": 0.25,
    ...                                      "leak_rate": 0.0, "overdark_rate": 0.5}]}}}
    >>> band_tables(t)  # doctest: +NORMALIZE_WHITESPACE
    [('sun: visibility error by distance from the camera (m)',
      ['distance (m)', 'pixels', 'rmse', 'rmse_penumbra', 'leak_rate', 'overdark_rate'],
      [['0–10', '4', '0.5', '0.25', '0', '0.5']])]
    """
    out = []
    for ln, d in (t.get("bands") or {}).items():
        for kind, label, head in _charts.band_kinds(d):
            rows = d.get(kind) or []
            if rows:
                keyf = (
                    (lambda r: f"{fmt_value(r['lo'])}–{fmt_value(r['hi'])}")
                    if kind == "distance"
                    else (lambda r: str(r["label"]))
                )
                out.append((f"{ln}: visibility error by {label}", [head, *_BAND_KEYS],
                            [[keyf(r), *[fmt_value(r[k]) for k in _BAND_KEYS]] for r in rows]))
    return out


def bands_markdown(run: Mapping) -> str:
    """Markdown of :func:`band_tables` for every technique of the run."""
    parts = []
    for name, t in run["techniques"].items():
        for title, cols, rows in band_tables(t):
            parts += [f"### {_md_escape(name)}: {_md_escape(title)}", "",
                      "| " + " | ".join(_md_escape(c) for c in cols) + " |", "|" + "---|" * len(cols)]
            parts += ["| " + " | ".join(_md_escape(c) for c in r) + " |" for r in rows]
            parts.append("")
    return "\n".join(parts)


def gate_markdown(run: Mapping) -> str:
    """The gate's verdict and failed checks for summary.md (``run["gate"]``); empty without a gate.

    >>> print(gate_markdown({"gate": {"file": "g.toml", "passed": False, "failed": ["g stat.bias"]}}), end="")
    <BLANKLINE>
    ## Gate: FAIL (g.toml)
    <BLANKLINE>
    Failed: g stat.bias
    """
    g = run.get("gate")
    if not isinstance(g, Mapping):
        return ""
    failed = g.get("failed") or []
    lines = ["", f"## Gate: {'PASS' if g.get('passed') else 'FAIL'} ({_md_escape(str(g.get('file', '')))})", ""]
    lines.append("Failed: " + ", ".join(_md_escape(str(f)) for f in failed) if failed else "Every check passed.")
    return "\n".join(lines) + "\n"


def stats_markdown(run: Mapping) -> str:
    """Markdown of :func:`stats_tables` for every technique of the run that has them."""
    parts = []
    for name, t in run["techniques"].items():
        for title, cols, rows in stats_tables(t.get("stats") or {}):
            parts += [f"### {_md_escape(name)}: stats per {title[:-1]}", "",
                      "| " + " | ".join(_md_escape(c) for c in cols) + " |", "|" + "---|" * len(cols)]
            parts += ["| " + " | ".join(_md_escape(c) for c in r) + " |" for r in rows]
            parts.append("")
    return "\n".join(parts)


def _slug(s: str) -> str:
    return (re.sub(r"[^A-Za-z0-9_-]+", "-", s).strip("-") or "x")[:40]


def _e(s) -> str:
    return _html.escape(str(s), quote=True)


def _img_tag(fname: str, alt: str) -> str:
    return f'<img class="im" src="img/{quote(fname)}" alt="{_e(alt)}" title="{_e(alt)}">'


def _legend(scale: float) -> str:
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
            f'<div class="ticks"><span>{_e(what)}</span></div>')


def _under_legend(scale: int, what: str) -> str:
    return ('<img class="cbar" src="img/colorbar_pos.png" alt="colour scale">'
            f'<div class="ticks"><span>0 (met)</span><span>{fmt_value(scale / 2)}</span><span>&ge;{scale}</span></div>'
            f'<div class="ticks"><span>{_e(what)}</span></div>')


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
    return f"<td>{_e(label) + ': ' if label else ''}{_img_tag(f, alt)}{legend}</td>"


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


def _panel_rows(ti: Mapping, ln: str, name: str, fname: str, put) -> list[str]:
    """HTML rows of the technique's panels (its family's images, ``Technique.panels``) for light
    ``ln``, those it has images of; ``fname``: the PNG name with ``{}`` for the image's key;
    ``put`` writes a PNG and returns its name."""
    rows = []
    for pn in ti.get("panels", ()):
        have = [(k, label) for k, label in pn.images if ln in ti.get(k, {})]
        if not have:
            continue
        scale = _panel_scale(pn, [ti[k][ln] for k, _ in have])
        if pn.kind == "excess_levels":
            put("colorbar_pos.png", _im.colorbar_png(signed=False))
        cells = [_panel_image(pn, k, label, ti[k][ln], scale, ln, name, fname, put) for k, label in have]
        head = f"<b>{_e(ln)}</b> {_e(pn.title)}" + (f"<br>{_e(pn.note)}" if pn.note else "")
        rows.append(_axis_row(head, cells))
    return rows


def _metric_line(d: Mapping) -> str:
    return " · ".join(f"{_e(k)} {_e(fmt_value(v))}" for k, v in d.items())


def _table_html(run: Mapping, cols) -> str:
    """One metrics table (technique names link to their sections; best value per column in bold)."""
    cols, names, rows = _table_cells(run, cols)
    p = ['<div class="wide"><table class="metrics"><thead><tr><th>technique</th>']
    p += [f"<th>{_e(c)}</th>" for c in cols]
    p.append("</tr></thead><tbody>")
    for i, (n, row) in enumerate(zip(names, rows)):
        cells = "".join(f"<td><b>{_e(s)}</b></td>" if b else f"<td>{_e(s)}</td>" for s, b in row)
        p.append(f'<tr><td><a href="#t{i}">{_e(n)}</a></td>{cells}</tr>')
    p.append("</tbody></table></div>")
    return "".join(p)


def _metrics_tables(run: Mapping) -> list[str]:
    """The key columns (:data:`KEY_METRICS` that the run has, and time_s), then the others."""
    all_cols = _metric_columns(run["techniques"])
    key = [c for c in KEY_METRICS if c in all_cols] + ["time_s"]
    rest = [c for c in all_cols if c not in key]
    p = [_table_html(run, key)]
    if rest:
        p += ['<p class="note">More metrics (suffix <code>_penumbra</code>: over the penumbra pixels only):</p>',
              _table_html(run, rest)]
    return p


def _verdict(run: Mapping) -> list[str]:
    """The gate's verdict at the top of the page (``run["gate"]``, as ``shadowlab ingest --gate``
    writes it): PASS or FAIL, the gate file, and a row per check."""
    g = run.get("gate")
    if not isinstance(g, Mapping):
        return []
    ok = bool(g.get("passed"))
    word, cls = ("PASS", "pass") if ok else ("FAIL", "fail")
    failed = g.get("failed") or []
    p = [f'<div class="verdict {cls}" id="verdict"><span class="word">{word}</span> gate '
         f"<code>{_e(g.get('file', ''))}</code>"
         + (f": {len(failed)} check{'s' if len(failed) != 1 else ''} failed ({_e(', '.join(failed))})" if failed
            else ": every check passed") + "</div>"]
    checks = [c for c in g.get("checks") or [] if isinstance(c, Mapping)]
    if checks:
        p.append('<div class="wide"><table class="metrics checks"><thead><tr><th>gate</th><th>check</th><th>result</th>'
                 "<th>value</th><th>threshold</th><th>details</th></tr></thead><tbody>")
        for c in sorted(checks, key=lambda c: bool(c.get("passed"))):  # failed checks first
            r, rc = ("PASS", "pass") if c.get("passed") else ("FAIL", "fail")
            p.append(
                f"<tr><td>{_e(c.get('gate', ''))}</td><td><code>{_e(c.get('check', ''))}</code></td>"
                f'<td class="{rc}">{r}</td><td>{_e(fmt_value(c.get("value")))}</td>'
                f"<td>{_e(c.get('op', ''))} "
                f"{_e(fmt_value(c.get('threshold')))}</td><td>{_e(c.get('text', ''))}</td></tr>"
            )
        p.append("</tbody></table></div>")
    return p


def _ingest_facts(run: Mapping) -> list[str]:
    """What ``shadowlab ingest`` compared (``run["ingest"]``), as a short list instead of JSON."""
    ing = run.get("ingest")
    if not isinstance(ing, Mapping):
        return []
    ch = ing.get("channels") or {}
    chs = ", ".join(f"{_e(k)} ← <code>{_e(v if isinstance(v, str) else ', '.join(map(str, v)))}</code>"
                    for k, v in ch.items())
    facts = [f"image <code>{_e(ing.get('image', ''))}</code>",
             f"compared as: {_e(ing.get('mode', ''))}, against the truth's <code>{_e(ing.get('against', ''))}</code>"]
    if chs:
        facts.append(f"channels: {chs}")
    facts += [f"note: {_e(n)}" for n in ing.get("notes") or []]
    return ['<ul class="facts">' + "".join(f"<li>{f}</li>" for f in facts) + "</ul>"]


def _lights_html(run: Mapping) -> list[str]:
    """The light summary: a row per light (kind, size and what its truth is, ``run["light_info"]``)."""
    info = run.get("light_info")
    names = list(info) if isinstance(info, Mapping) and info else list(run["lights"])
    if not names:
        return []
    if not isinstance(info, Mapping):
        return [f'<p class="note">Lights: {_e(", ".join(names))}.</p>']
    rows = light_rows(names, info)
    return ['<table class="metrics lights"><thead><tr><th>light</th><th>kind</th><th>size</th><th>truth</th></tr>'
            "</thead><tbody>" + "".join(f"<tr><td>{_e(n)}</td><td>{_e(k)}</td><td>{_e(sz)}</td>"
                                        f'<td class="text">{_e(nt) or "as named"}</td></tr>' for n, k, sz, nt in rows)
            + "</tbody></table>"]


def _excluded(emitter, truth_shaded, other) -> np.ndarray | None:
    """The pixels left out of a shaded error map's colour scale: those on a light (``emitter``,
    else :func:`images.emitter_guess`) and their neighbours; None when there are none."""
    em = emitter if emitter is not None else _im.emitter_guess(truth_shaded, other)
    return _im.grow(em) if em.any() else None


def _render(run: Mapping, imgs: dict, img_dir: Path) -> str:
    """Write all PNGs into ``img_dir`` and return the HTML text."""
    lights = list(run["lights"])
    techs = run["techniques"]
    w, h = (int(x) for x in run["resolution"])
    truth = imgs["truth"]
    exposure = _im.common_exposure(truth["shaded"])

    def put(fname: str, data: bytes) -> str:
        (img_dir / fname).write_bytes(data)
        return fname

    put("colorbar.png", _im.colorbar_png())
    truth_shaded = put("truth_shaded.png", _im.shaded_png(truth["shaded"], exposure))
    truth_vis = {
        ln: put(f"truth_vis_{j}_{_slug(ln)}.png", _im.visibility_png(truth["vis"][ln])) for j, ln in enumerate(lights)
    }
    truth_lum = _im.luminance(truth["shaded"])

    # Shared colour scale per light and for the shaded image, across techniques; pixels on a light
    # (and their neighbours) do not count.
    emitter = imgs.get("emitter")
    vis_out = None if emitter is None or not emitter.any() else _im.grow(emitter)
    vis_err = {
        name: {
            ln: _im.luminance(imgs["techniques"][name]["vis"][ln]) - _im.luminance(truth["vis"][ln]) for ln in lights
        }
        for name in techs
    }
    shaded_err = {name: _im.luminance(imgs["techniques"][name]["shaded"]) - truth_lum for name in techs}
    vis_scale = {ln: max([_im.error_scale(vis_err[n][ln], exclude=vis_out) for n in techs], default=1e-6)
                 for ln in lights}
    shaded_scale = max([_im.error_scale(e, exclude=_excluded(emitter, truth["shaded"], imgs["techniques"][n]["shaded"]))
                        for n, e in shaded_err.items()], default=1e-6)

    p = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>shadowlab: {_e(run['scene'])} {w}×{h}</title>",
        f"<style>{_CSS}{_cmp.CSS}</style></head><body>",
        f"<h1>shadowlab report: {_e(run['scene'])} — {w}×{h}</h1>",
    ]
    p += _verdict(run)
    p += _ingest_facts(run)
    p.append(f'<p class="ref">{_e(_reference_line(run))}</p>')
    extra_ref = {k: v for k, v in run["reference"].items() if k not in ("spp", "max_std_error")}
    if extra_ref:
        p.append(f'<p class="note">Reference details: {_metric_line_any(extra_ref)}</p>')

    p.append("<h2>Metrics</h2>")
    p += _metrics_tables(run)
    p.append(
        '<p class="note">Best value per column in bold (highest for psnr/ssim, lowest for errors, rates and '
        f"time). {_NA}: not available; NaN/inf are stored as null in metrics.json. Heat maps show the signed "
        "error technique − truth: <span style=\"color:#2166ac\">blue = technique darker</span>, white = equal, "
        "<span style=\"color:#b2182b\">red = technique brighter</span>; three-channel images are compared by "
        "luminance; for each light (and for the shaded image) all techniques share one colour scale, the 99th "
        "percentile of |error| without the pixels on a light seen by the camera and their neighbours. "
        f"Visibility: grey level = visibility. Shaded images: common exposure {_e(fmt_value(exposure))} "
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
    if imgs["mitsuba"] is not None:
        g.append("<th>Mitsuba <code>mi.render</code></th><th>signed error (mi.render − truth)</th>")
    g.append("</tr><tr><th class=\"row\">shaded</th>")
    g.append(f"<td>{_img_tag(truth_shaded, 'truth shaded')}</td>")
    if imgs["mitsuba"] is not None:
        mts = put("mitsuba.png", _im.shaded_png(imgs["mitsuba"], exposure))
        merr = _im.luminance(imgs["mitsuba"]) - truth_lum
        mscale = _im.error_scale(merr, exclude=_excluded(emitter, truth["shaded"], imgs["mitsuba"]))
        merr_f = put("mitsuba_err.png", _im.encode_png(_im.signed_error_heatmap(merr, mscale)))
        g.append(f"<td>{_img_tag(mts, 'Mitsuba mi.render')}</td>")
        g.append(f"<td>{_img_tag(merr_f, 'signed error mi.render - truth')}{_legend(mscale)}</td>")
        cmp_last.append(_cmp.item("mi.render (Mitsuba direct)", [_cmp.layer(
            "shaded", f"img/{mts}", f"img/{truth_shaded}", f"img/{merr_f}", fmt_value(mscale))], a_label="mi.render"))
    g.append("</tr></table>")
    g.append('<p class="note">Pixels on a light the camera sees (and their neighbours) are left out of the '
             "colour scales: mi.render shows the light's radiance there, the truth has no shading point.</p>")

    # per technique
    tp = []
    for i, name in enumerate(techs):
        t = techs[name]
        ti = imgs["techniques"][name]
        tag = f"t{i}_{_slug(name)}"
        cmp_i = len(cmp_items)
        layers = []
        tp.append(f'<h2 id="t{i}">{_e(name)} <a class="open" href="#cmp" data-cmp-item="{cmp_i}" '
                  'data-cmp-layer="0">compare</a></h2>')
        params = " ".join(f"<code>{_e(k)}={_e(json.dumps(to_jsonable(v)))}</code>" for k, v in t["params"].items())
        tp.append(f'<p class="note">time {_e(fmt_value(t["time_s"]))} s. Parameters: {params or "none"}</p>')
        tp.append(
            '<table class="grid"><tr><th></th><th>technique</th><th>truth</th>'
            "<th>signed error (technique − truth)</th></tr>"
        )
        for j, ln in enumerate(lights):
            vf = put(f"{tag}_vis_{j}_{_slug(ln)}.png", _im.visibility_png(ti["vis"][ln]))
            ef = put(
                f"{tag}_vis_{j}_{_slug(ln)}_err.png",
                _im.encode_png(_im.signed_error_heatmap(vis_err[name][ln], vis_scale[ln])),
            )
            layers.append(_cmp.layer(f"{ln} visibility", f"img/{vf}", f"img/{truth_vis[ln]}", f"img/{ef}",
                                     fmt_value(vis_scale[ln])))
            pl = t["per_light"].get(ln, {})
            title = (run.get("ingest") or {}).get("labels", {}).get(ln)    # ingest --label CHANNEL=TEXT
            tp.append(
                f'<tr><th class="row"><b>{_e(ln)}</b> visibility{f" ({_e(title)})" if title else ""}<br>'
                f'{_metric_line(pl)}</th>'
                f"<td>{_img_tag(vf, f'{name} visibility {ln}')}</td>"
                f"<td>{_img_tag(truth_vis[ln], f'truth visibility {ln}')}</td>"
                f"<td>{_img_tag(ef, f'signed error {name} {ln}')}{_legend(vis_scale[ln])}</td></tr>"
            )
            tp += _panel_rows(ti, ln, name, f"{tag}_{{}}_{j}_{_slug(ln)}.png", put)
        sf = put(f"{tag}_shaded.png", _im.shaded_png(ti["shaded"], exposure))
        sef = put(f"{tag}_shaded_err.png", _im.encode_png(_im.signed_error_heatmap(shaded_err[name], shaded_scale)))
        layers.insert(
            0, _cmp.layer("shaded", f"img/{sf}", f"img/{truth_shaded}", f"img/{sef}", fmt_value(shaded_scale))
        )
        cmp_items.append(_cmp.item(name, layers))
        tp.append(
            f'<tr><th class="row"><b>shaded</b><br>{_metric_line(t["metrics"])}</th>'
            f"<td>{_img_tag(sf, f'{name} shaded')}</td>"
            f"<td>{_img_tag(truth_shaded, 'truth shaded')}</td>"
            f"<td>{_img_tag(sef, f'signed error {name} shaded')}{_legend(shaded_scale)}</td></tr>"
        )
        tp.append("</table>")
        for title, cols, rows in band_tables(t):
            tp.append(f'<p class="note">{_e(title)}</p><table class="metrics"><thead><tr>'
                      + "".join(f"<th>{_e(c)}</th>" for c in cols) + "</tr></thead><tbody>"
                      + "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in r) + "</tr>" for r in rows)
                      + "</tbody></table>")
        for title, cols, rows in stats_tables(t.get("stats") or {}):
            tp.append(
                f'<p class="note">stats per {_e(title[:-1])}</p><div class="wide"><table class="metrics"><thead><tr>'
                + "".join(f"<th>{_e(c)}</th>" for c in cols)
                + "</tr></thead><tbody>"
                + "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in r) + "</tr>" for r in rows)
                + "</tbody></table></div>"
            )

    if cmp_items or cmp_last:
        p += ["<h2>Compare images</h2>",
              _cmp.comparator_html({"width": w, "height": h, "items": cmp_items + cmp_last})]
    p += g + tp
    extra = {k: v for k, v in run.items()
             if k not in ("scene", "resolution", "reference", "lights", "techniques", "images", "gate", "ingest",
                          "light_info")}
    if extra:
        p.append("<h2>Run</h2>")
        p.append(f"<details><summary>{_e(', '.join(extra))}</summary>"
                 f"<pre>{_e(json.dumps(to_jsonable(extra), indent=2))}</pre></details>")
    p.append("</body></html>")
    return "\n".join(p) + "\n"


def _metric_line_any(d: Mapping) -> str:
    return " · ".join(f"{_e(k)} {_e(json.dumps(to_jsonable(v)))}" for k, v in d.items())


# --------------------------------------------------------------------------------------------
# build


def build(out_dir, run: Mapping, *, force: bool = False, protected=(), kind: str = "compare") -> Path:
    """Write ``out_dir/index.html``, ``summary.md``, ``metrics.json`` and ``img/*.png`` for one run;
    returns the path of index.html.

    ``out_dir`` must be ours or new (:func:`shadowlab.io.outdir.claim_dir`: an existing
    directory without the ``.shadowlab-report`` marker is refused unless ``force``) and outside
    the ``protected`` directories (the reference store).

    ``run`` = {"scene", "resolution": [W, H], "reference": {"spp", "max_std_error", ...},
    "lights": [names], "images": {"truth": {"shaded": H×W×3, "vis": {light: H×W}},
    "mitsuba": H×W×3 (optional), "techniques": {name: {"shaded", "vis", optional "panels": the
    family's report rows (``Technique.panels``) and, per image key of a panel, {light: image} (see
    ``_PANEL_CHANNELS``; built by ``Technique.report_images``)}}},
    "techniques": {name: {"params", "time_s", "metrics", "per_light"}}, ...extra JSON keys}.
    Bad input raises ``InputError`` naming the key, before anything is written.

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
    imgs = validate(run)
    claim_dir(out, kind, force=force, protected=protected, files=OUTPUT_FILES + ("img/",))
    for f in OUTPUT_FILES:
        if (out / f).is_dir():
            raise InputError(f"report output {out / f} is a directory; remove it or choose another --out")
    json_text = json.dumps(run_to_json(run), indent=2, allow_nan=False) + "\n"
    md_text = summary_table(run) + "\n" + gate_markdown(run)
    st_md = stats_markdown(run)
    if st_md:
        md_text += "\n## Stats per light and map\n\n" + st_md
    b_md = bands_markdown(run)
    if b_md:
        by = list(dict.fromkeys(k for t in run["techniques"].values() for d in (t.get("bands") or {}).values()
                                for k, _, _ in _charts.band_kinds(d)))
        md_text += f"\n## Visibility error by {' and '.join(by)}\n\n" + b_md

    def fill(tmp: Path) -> None:
        html_text = _render(run, imgs, tmp / "img")
        (tmp / "metrics.json").write_text(json_text, encoding="utf-8")
        (tmp / "summary.md").write_text(md_text, encoding="utf-8")
        (tmp / "index.html").write_text(html_text, encoding="utf-8")

    return write_dir(out, kind, fill, OUTPUT_FILES, OUTPUT_DIRS)
