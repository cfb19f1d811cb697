"""The report's numbers as tables: the metrics table (summary.md, the terminal), stats per light and
map, the error by distance band and label, and the gate's verdict in Markdown."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

import numpy as np

from .charts import band_kinds
from .run import Run

__all__ = ["KEY_METRICS", "NA", "higher_is_better", "fmt_value", "metric_columns", "table_cells", "reference_line",
           "md_escape", "summary_table", "terminal_table", "stats_tables", "band_tables", "bands_markdown",
           "gate_markdown", "stats_markdown"]

_HIGHER_IS_BETTER_PREFIXES = ("psnr", "ssim")
NA = "n/a"
#: the metrics of the page's first table (with time_s); the others go to a second table
KEY_METRICS = ("rmse", "rmse_penumbra", "vis_rmse_penumbra", "leak_rate", "overdark_rate", "psnr", "ssim", "flip")


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
        return NA
    v = float(v)
    if math.isnan(v):
        return NA
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.4g}"


def metric_columns(techs: Mapping) -> list[str]:
    cols: list[str] = []
    for t in techs.values():
        for m in t.get("metrics", {}):
            if m not in cols:
                cols.append(m)
    return cols


def table_cells(run: Mapping, cols=None) -> tuple[list[str], list[str], list[list[tuple[str, bool]]]]:
    """(column names, technique names, rows of (formatted value, is_best)); ``cols``: the columns,
    default every metric and time_s."""
    techs = run["techniques"]
    cols = metric_columns(techs) + ["time_s"] if cols is None else list(cols)
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


def reference_line(run: Mapping) -> str:
    ref = run["reference"]
    spp = ref["spp"]
    spp_s = str(int(spp)) if float(spp).is_integer() else fmt_value(spp)
    return (f"Reference: {spp_s} shadow rays per pixel and light (mean; the truth adds rays where a pixel's "
            f"standard error is above its target), max standard error {fmt_value(ref['max_std_error'])}")


def md_escape(s: str) -> str:
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
    Reference: 64 shadow rays per pixel and light (mean; the truth adds rays where a pixel's standard error is above its target), max standard error 0.01
    <BLANKLINE>
    | technique | rmse | psnr | time_s |
    |---|---:|---:|---:|
    | hard | **0.1235** | **18.2** | **0.0012** |
    <BLANKLINE>
    Best value per column in bold (highest for psnr/ssim, lowest otherwise). n/a = not available (NaN/inf are null in metrics.json).
    """  # noqa: E501
    run = Run.from_mapping(run, need_images=False)
    w, h = (int(x) for x in run["resolution"])
    cols, names, rows = table_cells(run)
    lines = [
        f"# shadowlab report: {md_escape(run['scene'])} ({w}x{h})",
        "",
        reference_line(run),
        "",
        "| technique | " + " | ".join(md_escape(c) for c in cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]
    for n, row in zip(names, rows):
        cells = [f"**{s}**" if b else s for s, b in row]
        lines.append(f"| {md_escape(n)} | " + " | ".join(cells) + " |")
    if not names:
        lines.append("| (no techniques) |" + " |" * len(cols))
    lines += [
        "",
        "Best value per column in bold (highest for psnr/ssim, lowest otherwise). "
        f"{NA} = not available (NaN/inf are null in metrics.json).",
    ]
    return "\n".join(lines)


def terminal_table(run: Mapping, width: int = 100) -> str:
    """The summary a command prints: the run's title and reference, then a plain table of the key
    columns (:data:`KEY_METRICS` the run has, and time_s) no wider than ``width`` characters (the
    terminal's); columns that do not fit are left out and named, with where to find them.

    >>> run = {"scene": "s", "resolution": [4, 4], "reference": {"spp": 64, "max_std_error": 0.01},
    ...        "lights": ["key"], "techniques": {"hard": {"params": {}, "time_s": 0.0012,
    ...        "metrics": {"rmse": 0.123456, "psnr": 18.2, "flip": 0.05}, "per_light": {}}}}
    >>> print(terminal_table(run, width=30))
    shadowlab: s (4x4), 1 technique
    technique    rmse  psnr  flip
    hard       0.1235  18.2  0.05
    not shown: time_s (all in summary.md, metrics.json)
    """
    run = Run.from_mapping(run, need_images=False)
    all_cols = metric_columns(run.techniques)
    cols = [c for c in KEY_METRICS if c in all_cols] + ["time_s"]
    names = list(run.techniques)
    _, _, rows = table_cells(run, cols)
    first = max([len("technique")] + [len(n) for n in names])
    widths = [max([len(c)] + [len(r[i][0]) for r in rows]) for i, c in enumerate(cols)]
    shown = 0
    total = first
    while shown < len(cols) and total + 2 + widths[shown] <= max(width, first + 2 + widths[0]):
        total += 2 + widths[shown]
        shown += 1
    n = len(names)
    lines = [f"shadowlab: {run.scene} ({run.resolution[0]}x{run.resolution[1]}), {n} technique{'s' if n != 1 else ''}",
             "technique".ljust(first) + "".join("  " + c.rjust(w) for c, w in zip(cols[:shown], widths))]
    lines += [name.ljust(first) + "".join("  " + v.rjust(w) for (v, _), w in zip(r[:shown], widths))
              for name, r in zip(names, rows)]
    hidden = cols[shown:] + [c for c in all_cols if c not in cols]
    if hidden:
        lines.append(f"not shown: {', '.join(hidden)} (all in summary.md, metrics.json)")
    return "\n".join(lines)


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
        for kind, label, head in band_kinds(d):
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
            parts += [f"### {md_escape(name)}: {md_escape(title)}", "",
                      "| " + " | ".join(md_escape(c) for c in cols) + " |", "|" + "---|" * len(cols)]
            parts += ["| " + " | ".join(md_escape(c) for c in r) + " |" for r in rows]
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
    lines = ["", f"## Gate: {'PASS' if g.get('passed') else 'FAIL'} ({md_escape(str(g.get('file', '')))})", ""]
    lines.append("Failed: " + ", ".join(md_escape(str(f)) for f in failed) if failed else "Every check passed.")
    return "\n".join(lines) + "\n"


def stats_markdown(run: Mapping) -> str:
    """Markdown of :func:`stats_tables` for every technique of the run that has them."""
    parts = []
    for name, t in run["techniques"].items():
        for title, cols, rows in stats_tables(t.get("stats") or {}):
            parts += [f"### {md_escape(name)}: stats per {title[:-1]}", "",
                      "| " + " | ".join(md_escape(c) for c in cols) + " |", "|" + "---|" * len(cols)]
            parts += ["| " + " | ".join(md_escape(c) for c in r) + " |" for r in rows]
            parts.append("")
    return "\n".join(parts)
