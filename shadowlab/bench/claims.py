"""The sources' speed figures beside the measured ones, in one table generated from the run records.

[Giegl 2007, §6] and [Wang 2022, §2] state ratios of times; shadowlab measures the same ratios in
``shadowlab bench`` (``--only virtual``, ``--only dpsv``) and never asserts them in a test. A
:class:`Claim` says where the source states a figure and where a run record holds the measured
value: a column of one of the part's tables, or a pattern in its text. The figure itself is
declared once, in the bench part that prints it beside its own tables
(:data:`shadowlab.bench.virtual.CLAIMED_SPEEDUP`, :data:`shadowlab.bench.dpsv.PAPER`).
:func:`claims_table` puts, per claim and machine, the source's figure beside the latest record's
measurement, and :mod:`shadowlab.docs` writes it into the bench page.

>>> rec = {"blocks": [{"type": "table", "columns": ["scene", "fused/SM"],
...                    "rows": [["a", "**2.69×**"], ["b", "2.30×"], ["[Wang 2022]", "1.50×"]]},
...                   {"type": "text", "text": "sm_dpsv_soft / pcss time: **0.92×** (source 1.63×)"}]}
>>> measured(CLAIMS[1], rec)
[2.69, 2.3]
>>> measured(CLAIMS[3], rec)
[0.92]
>>> measured_text([2.69, 2.3]), measured_text([0.92]), measured_text([])
('2.3× … 2.69× (2 rows)', '0.92×', 'not in the record')
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from .dpsv import PAPER
from .record import machine_label
from .virtual import CLAIMED_SPEEDUP

_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


@dataclass(frozen=True)
class Claim:
    """A figure of a source and where a record of bench ``part`` holds its measurement:
    ``column`` of a table (every row but the source's own, whose first cell starts with "["), or
    the first group of ``pattern`` in a text block."""

    part: str
    source: str
    what: str
    figure: str
    column: str = ""
    pattern: str = ""


CLAIMS = (
    Claim("virtual", "[Giegl 2007, §6] (\"at least an order of magnitude\"; §5, Fig. 4: frame times)",
          "brute-force virtual tiled map's time / fitted virtual map's (vtsm / fvsm), per ξ",
          f"≥ {CLAIMED_SPEEDUP:g}×", column="vtsm time / fvsm time"),
    Claim("dpsv", "[Wang 2022, §2], beside Table 1 (\"50 % slower than the shadow map\")",
          "fused hard shadows' time / the shadow map's (sm_dpsv / hard), per scene and light",
          f"{PAPER['fused_over_sm']:.2f}×", column="fused/SM"),
    Claim("dpsv", "[Wang 2022, §2], beside Table 1 (\"29.8 % faster than DPSV\")",
          "fused hard shadows' time / DPSV's (sm_dpsv / dpsv), per scene and light",
          f"{PAPER['fused_over_dpsv']:.3f}×", column="fused/DPSV"),
    Claim("dpsv", "[Wang 2022, §2], beside Table 2 (\"63 % slower than PCSS\")",
          "fused soft shadows' time / PCSS's (sm_dpsv_soft / pcss, parallel_planes)",
          f"{PAPER['soft_over_pcss']:.2f}×", pattern=r"sm_dpsv_soft / pcss time: \**(\d+(?:\.\d+)?)×"),
)


def measured(claim: Claim, record: dict) -> list[float]:
    """The measured values of ``claim`` in ``record`` (a run record of its part), in table order."""
    out: list[float] = []
    for b in record["blocks"]:
        if claim.column and b["type"] == "table" and claim.column in b["columns"]:
            k = b["columns"].index(claim.column)
            for row in b["rows"]:
                m = _NUMBER.search(row[k]) if k < len(row) else None
                if m and not row[0].startswith("["):
                    out.append(float(m.group()))
        elif claim.pattern and b["type"] == "text":
            out += [float(x) for x in re.findall(claim.pattern, b["text"])]
    return out


def measured_text(values: list[float]) -> str:
    if not values:
        return "not in the record"
    if len(values) == 1:
        return f"{values[0]:g}×"
    return f"{min(values):g}× … {max(values):g}× ({len(values)} rows)"


def latest_by_machine(records: list[dict], part: str) -> dict[str, dict]:
    """{machine label: its latest record of ``part``} (``records`` oldest first)."""
    out: dict[str, dict] = {}
    for r in records:
        if r["part"] == part:
            out[machine_label(r["machine"])] = r
    return dict(sorted(out.items()))


def claims_table(records: list[dict], runs_link: str = "runs") -> str:
    """Markdown: per claim and machine, the source's figure beside the latest record's measurement,
    the record linked (``runs_link``: the records' folder relative to the page)."""
    rows = ["| source | ratio | source's figure | measured | machine | run |", "|---|---|---|---|---|---|"]
    for c in CLAIMS:
        for label, rec in latest_by_machine(records, c.part).items():
            run = f"[{rec['date']}]({runs_link}/{Path(rec['file']).name})"
            rows.append(f"| {c.source} | {c.what} | {c.figure} | {measured_text(measured(c, rec))} | {label} | {run} |")
    return "\n".join(rows)
