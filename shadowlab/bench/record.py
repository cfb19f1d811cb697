"""A bench run as data: one JSON record per run and part, tagged with the machine and the date.

``shadowlab bench`` writes each part's tables as Markdown (``PART.md``) and its raw figures as JSON
(``PART.json``). :func:`make_record` turns the pair into a *run record*: the part, the date, the
machine (CPU, cores, GPU, variant, versions) and the tables as rows of cells, plus the raw figures.
Records are committed under ``docs/bench/runs/`` and the bench pages of the docs are generated
from them (:mod:`shadowlab.docs`), so a page can always be rebuilt from tracked files.

>>> blocks = parse_markdown("## Cost\\n\\nOne run.\\n\\n| a | b |\\n|---|---|\\n| 1 | 2 |")
>>> [b["type"] for b in blocks]
['heading', 'text', 'table']
>>> blocks[2]["columns"], blocks[2]["rows"]
(['a', 'b'], [['1', '2']])
>>> render_blocks(blocks) == "## Cost\\n\\nOne run.\\n\\n| a | b |\\n| --- | --- |\\n| 1 | 2 |"
True
"""

from __future__ import annotations

import json
import re
from pathlib import Path

#: version of the record format (bump when a key changes meaning)
SCHEMA = 1

_MACHINE = re.compile(
    r"^Machine: (?P<cpu>.+?), (?P<cores>\d+) cores(?:, (?P<gpu>[^,]*(?:NVIDIA|AMD Instinct|GPU)[^,]*))?"
    r", mitsuba (?P<mitsuba>[^,]+), drjit (?P<drjit>[^,]+), variant (?P<variant>[^,.\s]+)"
)


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def parse_markdown(text: str) -> list[dict]:
    """Markdown of a bench part as blocks: ``heading`` (level, text), ``table`` (columns, rows of
    cells) and ``text`` (a paragraph or a list, as written)."""
    blocks, para = [], []

    def flush():
        if para:
            blocks.append({"type": "text", "text": "\n".join(para)})
            para.clear()

    lines = text.strip().split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        m = re.match(r"^(#+) (.*)$", line)
        if m:
            flush()
            blocks.append({"type": "heading", "level": len(m.group(1)), "text": m.group(2).strip()})
        elif line.startswith("|") and i + 1 < len(lines) and re.match(r"^\|[\s:|-]+\|?\s*$", lines[i + 1]):
            flush()
            table = {"type": "table", "columns": _cells(line), "rows": []}
            i += 2
            while i < len(lines) and lines[i].startswith("|"):
                table["rows"].append(_cells(lines[i]))
                i += 1
            blocks.append(table)
            continue
        elif not line.strip():
            flush()
        else:
            para.append(line)
        i += 1
    flush()
    return blocks


def render_blocks(blocks: list[dict], *, shift: int = 0) -> str:
    """Markdown of :func:`parse_markdown`'s blocks; ``shift`` demotes every heading by that many levels."""
    out = []
    for b in blocks:
        if b["type"] == "heading":
            out.append("#" * (b["level"] + shift) + " " + b["text"])
        elif b["type"] == "table":
            rows = [b["columns"], ["---"] * len(b["columns"])] + b["rows"]
            out.append("\n".join("| " + " | ".join(r) + " |" for r in rows))
        else:
            out.append(b["text"])
    return "\n\n".join(out)


def machine_from_text(text: str) -> dict:
    """The machine of a part's ``Machine: …`` line (as :func:`shadowlab.bench.timing.machine_text`
    writes it).

    >>> machine_from_text("Machine: AMD EPYC, 2 cores, mitsuba 3.9.1, drjit 1.5.0, variant llvm_ad_rgb. All")
    {'cpu': 'AMD EPYC', 'cores': 2, 'gpu': None, 'mitsuba': '3.9.1', 'drjit': '1.5.0', 'variant': 'llvm_ad_rgb'}
    """
    for line in text.split("\n"):
        m = _MACHINE.match(line.strip())
        if m:
            d = m.groupdict()
            d["cores"] = int(d["cores"])
            return d
    return {}


def machine_label(machine: dict) -> str:
    """A short name for grouping runs by machine: CPU and cores, or the GPU, and the variant.

    >>> machine_label({"cpu": "AMD EPYC", "cores": 2, "gpu": None, "variant": "llvm_ad_rgb"})
    'AMD EPYC, 2 cores (llvm_ad_rgb)'
    """
    where = machine.get("gpu") or f"{machine.get('cpu', '?')}, {machine.get('cores', '?')} cores"
    return f"{where} ({machine.get('variant', '?')})"


def slug(text: str) -> str:
    """
    >>> slug("Intel(R) Xeon(R) Processor, 16 cores")
    'intel-r-xeon-r-processor-16-cores'
    """
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


def make_record(part: str, markdown: str, *, results: dict | None = None, machine: dict | None = None,
                date: str | None = None) -> dict:
    """The run record of one bench part. The first heading carries the date as ``Title (DATE)``;
    the ``Machine:`` line names the machine unless ``machine`` (``backend.machine_info()``) is given."""
    blocks = parse_markdown(markdown)
    title = next((b["text"] for b in blocks if b["type"] == "heading"), part)
    m = re.match(r"^(.*?) \((\d{4}-\d\d-\d\dT[\d:]+)\)$", title)
    if m:
        title, date = m.group(1), date or m.group(2)
        blocks = blocks[1:]
    results = results or {}
    date = date or results.get("date")
    mach = dict(machine or results.get("machine") or {})
    if not mach.get("cpu"):
        mach.update(machine_from_text(markdown))
    if not date or not mach:
        raise ValueError(f"bench part {part!r}: the record needs a date and a machine (a 'Title (DATE)' "
                         "heading and a 'Machine: …' line, or the part's JSON)")
    keep = {k: mach.get(k) for k in ("cpu", "cores", "gpu", "variant", "mitsuba", "drjit", "libllvm") if mach.get(k)}
    return {"schema": SCHEMA, "part": part, "title": title, "date": date, "machine": keep,
            "blocks": blocks, "results": results}


def record_name(rec: dict) -> str:
    """File name of a record: date, part and machine, unique per run."""
    return f"{rec['date'].replace(':', '')}_{rec['part']}_{slug(machine_label(rec['machine']))}.json"


def write_record(out_dir: Path, part: str, md_path: Path) -> Path:
    """Write the run record of the part whose Markdown is ``md_path`` (raw figures from the ``.json``
    beside it, if any) to ``out_dir/runs/``; return its path."""
    js = md_path.with_suffix(".json")
    results = json.loads(js.read_text()) if js.exists() else {}
    rec = make_record(part, md_path.read_text(), results=results)
    path = Path(out_dir) / "runs" / record_name(rec)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec, indent=1, ensure_ascii=False) + "\n")
    return path


def load_records(folder: Path) -> list[dict]:
    """Every record in ``folder`` (``*.json``), oldest first."""
    recs = []
    for f in sorted(Path(folder).glob("*.json")):
        rec = json.loads(f.read_text())
        if rec.get("schema") != SCHEMA:
            raise ValueError(f"{f}: bench record schema {rec.get('schema')!r}, expected {SCHEMA}")
        rec["file"] = f.name
        recs.append(rec)
    return sorted(recs, key=lambda r: (r["date"], r["part"]))
