"""Charts of a report as inline SVG (no JavaScript, no external files): what people would rather
look at than read in the metrics table.

* :func:`bar_chart`: horizontal grouped bars, one group per technique, one bar per light (the
  report draws the penumbra RMSE and the leak rate of the visibility, per light);
* :func:`scatter_chart`: one point per technique, error against run time (log axis when the
  times span more than a factor 20);
* :func:`line_chart`: one line per technique over ordered categories (the visibility error by
  distance band from the camera, or by a label AOV, :func:`band_kinds`).

Missing values (None, NaN) are left out of a chart and listed as "n/a". Every mark has an SVG
``<title>`` (a tooltip with its exact value). Colours: a fixed categorical palette (Tableau 10),
one colour per series in the order given, the same in every chart of a report.

>>> svg = bar_chart("rmse", ["pcf", "pcss"], ["key"], {"pcf": {"key": 0.02}, "pcss": {"key": None}})
>>> svg.startswith('<svg class="chart"') and "n/a" in svg and "<title>pcf · key: 0.02</title>" in svg
True
"""

from __future__ import annotations

import html as _html
import math

__all__ = ["PALETTE", "colour", "nice_ticks", "bar_chart", "scatter_chart", "line_chart", "legend", "run_charts"]

#: Tableau 10 (sRGB), one colour per series
PALETTE = ("#4e79a7", "#f28e2b", "#e15759", "#76b7b2", "#59a14f", "#edc948", "#b07aa1", "#ff9da7", "#9c755f",
           "#bab0ac")
_FONT = 'font-family="system-ui, sans-serif" font-size="11"'
_W = 560          # chart width in px
_LEFT = 130       # room for category labels
_RIGHT = 70       # room for value labels
_TOP = 26         # title


def colour(i: int) -> str:
    """The ``i``-th series colour (the palette cycles).

    >>> colour(0), colour(10)
    ('#4e79a7', '#4e79a7')
    """
    return PALETTE[i % len(PALETTE)]


def _e(s) -> str:
    return _html.escape(str(s), quote=True)


def _ok(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(float(v))


def _fmt(v) -> str:
    return "n/a" if not _ok(v) else f"{float(v):.3g}"


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering [lo, hi] (steps 1, 2 or 5 × 10^k).

    >>> nice_ticks(0, 0.037)
    [0.0, 0.01, 0.02, 0.03, 0.04]
    >>> nice_ticks(0, 0)
    [0.0, 0.5, 1.0]
    """
    if not hi > lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.floor(lo / step + 1e-9)
    last = math.ceil(hi / step - 1e-9)
    return [round(k * step, 12) for k in range(first, last + 1)]


def _svg(width: int, height: int, title: str, body: list[str]) -> str:
    return (f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" role="img" aria-label="{_e(title)}" {_FONT}>'
            f'<text x="4" y="16" font-size="13" font-weight="600">{_e(title)}</text>' + "".join(body) + "</svg>")


def legend(names, colours=None) -> str:
    """HTML legend: a colour swatch and a name per series."""
    cols = colours or [colour(i) for i in range(len(names))]
    return '<div class="chart-legend">' + "".join(
        f'<span><i style="background:{c}"></i>{_e(n)}</span>' for n, c in zip(names, cols)) + "</div>"


def bar_chart(title: str, categories, series, values, *, width: int = _W, colours=None) -> str:
    """Horizontal grouped bars: a group per category (row label), a bar per series in it.
    ``values[category][series]``: a number, or None / NaN (drawn as "n/a"). Linear axis from 0."""
    categories, series = list(categories), list(series)
    cols = colours or [colour(i) for i in range(len(series))]
    bar_h, gap = 12, 8
    group_h = bar_h * len(series) + gap
    vals = [values.get(c, {}).get(s) for c in categories for s in series]
    top = max([abs(float(v)) for v in vals if _ok(v)] + [0.0])
    ticks = nice_ticks(0.0, top)
    hi = ticks[-1]
    plot_w = width - _LEFT - _RIGHT
    height = _TOP + group_h * len(categories) + 24
    x = lambda v: _LEFT + plot_w * float(v) / hi  # noqa: E731
    body = []
    for t in ticks:
        body.append(f'<line x1="{x(t):.1f}" x2="{x(t):.1f}" y1="{_TOP - 4}" y2="{height - 20}" stroke="#ddd"/>'
                    f'<text x="{x(t):.1f}" y="{height - 6}" text-anchor="middle" fill="#555">{t:g}</text>')
    for gi, c in enumerate(categories):
        y0 = _TOP + gi * group_h
        body.append(f'<text x="{_LEFT - 6}" y="{y0 + (group_h - gap) / 2 + 4:.1f}" text-anchor="end">{_e(c)}</text>')
        for si, s in enumerate(series):
            v = values.get(c, {}).get(s)
            y = y0 + si * bar_h
            tip = f"<title>{_e(c)} · {_e(s)}: {_fmt(v)}</title>"
            if _ok(v):
                w = max(x(abs(float(v))) - _LEFT, 0.5)
                body.append(f'<rect x="{_LEFT}" y="{y}" width="{w:.1f}" height="{bar_h - 2}" fill="{cols[si]}">'
                            f"{tip}</rect><text x=\"{_LEFT + w + 3:.1f}\" y=\"{y + bar_h - 3}\" fill=\"#333\">"
                            f"{_fmt(v)}</text>")
            else:
                body.append(f'<text x="{_LEFT + 3}" y="{y + bar_h - 3}" fill="#999">n/a{tip}</text>')
    body.append(f'<line x1="{_LEFT}" x2="{_LEFT}" y1="{_TOP - 4}" y2="{height - 20}" stroke="#888"/>')
    return _svg(width, height, title, body)


def _axis(lo: float, hi: float, log: bool):
    """(ticks, labels, to_unit) of an axis: ``to_unit`` maps a value to [0, 1]."""
    if log:
        a, b = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
        b = max(b, a + 1)
        ticks = [10.0 ** k for k in range(a, b + 1)]
        return ticks, [f"{t:g}" for t in ticks], lambda v: (math.log10(v) - a) / (b - a)
    ticks = nice_ticks(min(lo, 0.0), hi)
    t0, t1 = ticks[0], ticks[-1]
    return ticks, [f"{t:g}" for t in ticks], lambda v: (v - t0) / (t1 - t0)


#: the box of a label in the charts' 12 px sans-serif: width per character and height (px)
_CHAR_W, _LABEL_H = 7.0, 14.0


def _overlaps(a, b) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def place_labels(points, names, *, bounds, r: float = 5.0) -> list[tuple]:
    """A box (x, y, w, h) for each point's label, placed greedily so that no two labels and no
    label and point overlap: right of the point if free, else left, above, below, then further
    out in growing rings (the chart draws a leader line to a label moved away). ``bounds``:
    (x0, y0, x1, y1) that labels stay inside where they can.

    >>> boxes = place_labels([(100, 100), (101, 101), (102, 100)], ["vsm", "evsm", "msm"], bounds=(0, 0, 400, 300))
    >>> any(_overlaps(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    False
    """
    x0, y0, x1, y1 = bounds
    dots = [(x - r, y - r, 2 * r, 2 * r) for x, y in points]
    placed: list[tuple] = []
    out: list[tuple | None] = [None] * len(points)
    for i in sorted(range(len(points)), key=lambda i: (points[i][1], points[i][0])):
        (x, y), w, h = points[i], _CHAR_W * len(str(names[i])) + 2, _LABEL_H
        cands = [(x + r + 2, y - h / 2), (x - r - 2 - w, y - h / 2), (x - w / 2, y - r - 2 - h), (x - w / 2, y + r + 2)]
        for ring in range(1, 12):
            d = ring * h
            cands += [(x + r + 2, y - h / 2 - d), (x + r + 2, y - h / 2 + d), (x - r - 2 - w, y - h / 2 - d),
                      (x - r - 2 - w, y - h / 2 + d), (x + r + 2 + d, y - h / 2), (x - r - 2 - w - d, y - h / 2)]
        best = None
        for cx, cy in cands:
            box = (cx, cy, w, h)
            inside = x0 <= cx and cx + w <= x1 and y0 <= cy and cy + h <= y1
            if inside and not any(_overlaps(box, o) for o in placed + dots):
                best = box
                break
        if best is None:   # nothing free: the first candidate inside the bounds, else the first
            best = next(((cx, cy, w, h) for cx, cy in cands if x0 <= cx and cx + w <= x1 and y0 <= cy
                         and cy + h <= y1), (cands[0][0], cands[0][1], w, h))
        placed.append(best)
        out[i] = best
    return out


def scatter_chart(title: str, points, *, xlabel: str, ylabel: str, width: int = _W, height: int = 300) -> str:
    """One labelled point per ``(name, x, y, colour)``; points with a missing or (on the log
    axis) non-positive value are listed as "n/a" below the plot. The x axis is logarithmic when
    all x > 0 and they span more than a factor 20."""
    good = [p for p in points if _ok(p[1]) and _ok(p[2])]
    xs = [float(p[1]) for p in good]
    log = bool(xs) and min(xs) > 0 and max(xs) / min(xs) > 20
    left, bottom, right = 60, 40, 20
    pw, ph = width - left - right, height - _TOP - bottom
    body = []
    if good:
        xt, xl, fx = _axis(min(xs), max(xs), log)
        yt, yl, fy = _axis(0.0, max(float(p[2]) for p in good), False)
        X = lambda v: left + pw * fx(v)  # noqa: E731
        Y = lambda v: _TOP + ph * (1 - fy(v))  # noqa: E731
        body += [f'<line x1="{X(t):.1f}" x2="{X(t):.1f}" y1="{_TOP}" y2="{_TOP + ph}" stroke="#eee"/>'
                 f'<text x="{X(t):.1f}" y="{_TOP + ph + 14}" text-anchor="middle" fill="#555">{s}</text>'
                 for t, s in zip(xt, xl)]
        body += [f'<line x1="{left}" x2="{left + pw}" y1="{Y(t):.1f}" y2="{Y(t):.1f}" stroke="#eee"/>'
                 f'<text x="{left - 4}" y="{Y(t) + 4:.1f}" text-anchor="end" fill="#555">{s}</text>'
                 for t, s in zip(yt, yl)]
        centres = [(X(float(xv)), Y(float(yv))) for _, xv, yv, _ in good]
        boxes = place_labels(centres, [p[0] for p in good], bounds=(0, 0, width, height))
        for (name, xv, yv, col), (cx, cy), (bx, by, bw, bh) in zip(good, centres, boxes):
            body.append(f'<circle cx="{cx:.1f}" cy="{cy:.1f}" r="5" fill="{col}" stroke="#333" stroke-width=".5">'
                        f"<title>{_e(name)}: {xlabel} {_fmt(xv)}, {ylabel} {_fmt(yv)}</title></circle>")
            tx, ty = bx + 1, by + bh - 3
            if not (abs(bx - cx - 7) < 1 and abs(by + bh / 2 - cy) < 1):   # moved away: a leader line to the point
                lx, ly = min(max(cx, bx), bx + bw), min(max(cy, by), by + bh)
                body.append(f'<line x1="{cx:.1f}" y1="{cy:.1f}" x2="{lx:.1f}" y2="{ly:.1f}" stroke="#999" '
                            'stroke-width=".7"/>')
            body.append(f'<text x="{tx:.1f}" y="{ty:.1f}">{_e(name)}</text>')
    body.append(
        f'<rect x="{left}" y="{_TOP}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>'
        f'<text x="{left + pw / 2:.1f}" y="{height - 8}" text-anchor="middle">{_e(xlabel)}'
        f'{" (log scale)" if log else ""}</text>'
        f'<text transform="translate(12 {_TOP + ph / 2:.1f}) rotate(-90)" text-anchor="middle">{_e(ylabel)}</text>'
    )
    missing = [p[0] for p in points if p not in good]
    if missing:
        body.append(f'<text x="{width - 4}" y="16" text-anchor="end" fill="#999">n/a: {_e(", ".join(missing))}</text>')
    return _svg(width, height, title, body)


def line_chart(title: str, xlabels, lines, *, xlabel: str, ylabel: str, width: int = _W, height: int = 260,
               colours=None) -> str:
    """One polyline per series over the ordered categories ``xlabels``; ``lines``: {series: [y or
    None per category]} (a missing value breaks the line)."""
    xlabels, names = list(xlabels), list(lines)
    cols = colours or [colour(i) for i in range(len(names))]
    left, bottom, right = 60, 40, 20
    pw, ph = width - left - right, height - _TOP - bottom
    ys = [float(v) for vs in lines.values() for v in vs if _ok(v)]
    yt, yl, fy = _axis(0.0, max(ys + [0.0]), False)
    n = max(len(xlabels), 1)
    X = lambda i: left + pw * (i + 0.5) / n  # noqa: E731
    Y = lambda v: _TOP + ph * (1 - fy(v))  # noqa: E731
    body = [f'<line x1="{left}" x2="{left + pw}" y1="{Y(t):.1f}" y2="{Y(t):.1f}" stroke="#eee"/>'
            f'<text x="{left - 4}" y="{Y(t) + 4:.1f}" text-anchor="end" fill="#555">{s}</text>' for t, s in zip(yt, yl)]
    body += [f'<text x="{X(i):.1f}" y="{_TOP + ph + 14}" text-anchor="middle" fill="#555">{_e(s)}</text>'
             for i, s in enumerate(xlabels)]
    for si, name in enumerate(names):
        pts = [(X(i), Y(float(v)), v) for i, v in enumerate(lines[name]) if _ok(v)]
        runs, cur = [], []
        for i, v in enumerate(lines[name]):
            if _ok(v):
                cur.append(f"{X(i):.1f},{Y(float(v)):.1f}")
            elif cur:
                runs.append(cur)
                cur = []
        runs.append(cur)
        body += [f'<polyline points="{" ".join(r)}" fill="none" stroke="{cols[si]}" stroke-width="2"/>'
                 for r in runs if len(r) > 1]
        body += [f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3" fill="{cols[si]}"><title>{_e(name)}: {_fmt(v)}</title>'
                 "</circle>" for x, y, v in pts]
    body.append(
        f'<rect x="{left}" y="{_TOP}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>'
        f'<text x="{left + pw / 2:.1f}" y="{height - 8}" text-anchor="middle">{_e(xlabel)}</text>'
        f'<text transform="translate(12 {_TOP + ph / 2:.1f}) rotate(-90)" text-anchor="middle">{_e(ylabel)}</text>'
    )
    return _svg(width, height, title, body)


# --------------------------------------------------------------------------------------------
# the charts of one run


def _figure(svg: str, caption: str = "") -> str:
    cap = f"<figcaption>{caption}</figcaption>" if caption else ""
    return f'<figure class="chart">{svg}{cap}</figure>'


def _per_light_bars(techs, lights) -> list[str]:
    """Bars of the visibility's penumbra RMSE and leak rate, a bar per light."""
    out = []
    for key, title in (("rmse_penumbra", "visibility RMSE in the penumbra, per light"),
                       ("leak_rate", "light-leak rate (umbra shown lit), per light")):
        vals = {n: {ln: t.get("per_light", {}).get(ln, {}).get(key) for ln in lights} for n, t in techs.items()}
        out.append(_figure(bar_chart(title, list(techs), lights, vals), legend(lights)))
    return out


def _time_scatter(techs) -> list[str]:
    """Shaded error (penumbra RMSE, else RMSE) against run time, a point per technique."""
    key = next((k for k in ("rmse_penumbra", "rmse") if any(_ok(t["metrics"].get(k)) for t in techs.values())), None)
    if key is None or not any(_ok(t.get("time_s")) for t in techs.values()):
        return []
    pts = [(n, t.get("time_s"), t["metrics"].get(key), colour(i)) for i, (n, t) in enumerate(techs.items())]
    return [_figure(scatter_chart(f"shaded {key} against run time", pts, xlabel="time (s, warm run)", ylabel=key))]


def _band_label(r) -> str:
    if "label" in r:
        return str(r["label"])
    hi = r.get("hi")
    return f"≥{float(r['lo']):g}" if not _ok(hi) else f"{float(r['lo']):g}–{float(hi):g}"


def band_kinds(d) -> list[tuple[str, str, str]]:
    """(kind, label, column head) of one light's error bands ``d`` (see
    :func:`shadowlab.pipeline.error_bands`): "distance" first, then each label AOV a technique
    breaks its error down by, in the order it gives them.

    >>> band_kinds({"distance": [], "split": []})
    [('distance', 'distance from the camera (m)', 'distance (m)'), ('split', 'split (−1: none)', 'split')]
    """
    return [("distance", "distance from the camera (m)", "distance (m)")] + \
        [(k, f"{k} (−1: none)", k) for k in d if k != "distance"]


def _band_lines(techs, lights) -> list[str]:
    """Visibility RMSE by distance band (and by each label AOV a technique breaks its error down
    by), a line per technique, per light."""
    out = []
    names = list(techs)
    for ln in lights:
        kinds = {k: label for n in names for k, label, _ in band_kinds((techs[n].get("bands") or {}).get(ln, {}))}
        for kind, xlabel in ({"distance": "distance from the camera (m)"} | kinds).items():
            rows = {
                n: {_band_label(r): r.get("rmse") for r in ((techs[n].get("bands") or {}).get(ln, {}).get(kind) or [])}
                for n in names
            }
            rows = {n: d for n, d in rows.items() if d}
            if not rows:
                continue
            xs = list(dict.fromkeys(x for d in rows.values() for x in d))
            cols = [colour(names.index(n)) for n in rows]
            svg = line_chart(
                f"{ln}: visibility RMSE by {kind}",
                xs,
                {n: [d.get(x) for x in xs] for n, d in rows.items()},
                xlabel=xlabel,
                ylabel="rmse",
                colours=cols,
            )
            out.append(_figure(svg, legend(list(rows), cols)))
    return out


def run_charts(run) -> str:
    """The charts section of a report (HTML with inline SVG): per-light bars, error against run
    time and, where the techniques report them, the error by distance band and by label.
    Empty for a run without techniques."""
    techs, lights = run["techniques"], list(run["lights"])
    if not techs:
        return ""
    figs = (_per_light_bars(techs, lights) if lights else []) + _time_scatter(techs) + _band_lines(techs, lights)
    return '<div class="charts">' + "".join(figs) + "</div>" if figs else ""


def frame_charts(summary, metrics) -> str:
    """The charts of a multi-frame page: per metric, a line per technique over the frames, and the
    shimmer (mean and p99, pooled over lights) of each technique beside the truth's."""
    fr, names = summary["frames"], list(summary["techniques"])
    figs = []
    for m in metrics:
        lines = {n: [summary["per_frame"][str(f)][n]["metrics"].get(m) for f in fr] for n in names}
        if any(_ok(v) for vs in lines.values() for v in vs):
            figs.append(_figure(line_chart(f"{m} per frame", [str(f) for f in fr], lines, xlabel="frame",
                                           ylabel=m), legend(names)))
    sh = summary.get("shimmer")
    if sh:
        vals = {n: {"mean": d["pooled"]["mean"], "p99": d["pooled"]["p99"]} for n, d in sh["techniques"].items()}
        if sh["truth"]["pooled"]:
            vals["truth"] = {"mean": sh["truth"]["pooled"]["mean"], "p99": sh["truth"]["pooled"]["p99"]}
        figs.append(_figure(bar_chart("shimmer |V_t − V_t−1| at fixed points, all lights", list(vals),
                                      ["mean", "p99"], vals), legend(["mean", "p99"])))
    return '<div class="charts">' + "".join(figs) + "</div>" if figs else ""
