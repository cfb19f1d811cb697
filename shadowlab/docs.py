"""README sections generated from their single sources: scene files and technique declarations.

``python -m shadowlab.docs`` rewrites the marked sections of README.md in place
(``<!-- NAME:begin -->`` … ``<!-- NAME:end -->``); ``--check`` exits 1 if they are stale.
The bench section is copied from reports/bench/bench.md (and sdf.md, cascades.md and cascades-cuda.md, a GPU run of the cascades part, after it) when that file exists;
the virtual shadow maps' section (``bench-virtual``) from reports/bench/virtual.md and virtual-cuda.md
(``shadowlab bench --only virtual`` on the CPU and on a GPU) when either exists, so that part can be
measured and regenerated alone; the DPSV family's (``bench-dpsv``) layered SSSS's (``bench-ssss``), the truth's throughput (``bench-truth``) and the Dask executor's scaling (``bench-scaling``) likewise from dpsv.md, ssss.md, truth.md and scaling.md. A part's plot stays beside it in reports/: the README keeps its tables.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from .scene.spec import builtin_names, load_spec, resolve
from .techniques import base

ROOT = Path(__file__).resolve().parents[1]


def scenes_section() -> str:
    rows = ["| scene | lights | description |", "|---|---|---|"]
    for n in builtin_names():
        s = load_spec(resolve(n))
        lights = ", ".join(f"`{l.name}` ({l.kind})" for l in s.lights)
        rows.append(f"| `{n}` | {lights} | {s.description} |")
    return "\n".join(rows)


def techniques_section() -> str:
    parts = []
    for n in base.names():
        t = base.get(n)
        parts.append(f"### `{t.name}`: {t.title}\n\n{t.summary.strip()}\n\nSource: {t.source}.\n\n"
                     f"{base.param_table_markdown(t)}\n")
    return "\n".join(parts).rstrip()


def bench_section() -> str | None:
    p = ROOT / "reports" / "bench" / "bench.md"
    if not p.exists():
        return None
    text = p.read_text().strip()
    for part in ("sdf.md", "cascades.md", "cascades-cuda.md"):
        f = p.with_name(part)
        if f.exists():
            text += "\n\n" + _part(f)
    return _demote(text)


def bench_part_section(part: str) -> str | None:
    """A bench part's own README section: reports/bench/PART.md then PART-cuda.md, where they exist."""
    parts = [ROOT / "reports" / "bench" / n for n in (f"{part}.md", f"{part}-cuda.md")]
    parts = [_part(f) for f in parts if f.exists()]
    return _demote("\n\n".join(parts)) if parts else None


#: bench parts with a README section of their own (``<!-- bench-PART:begin -->``)
OWN_SECTIONS = ("virtual", "dpsv", "ssss", "truth", "scaling")


def _part(f: Path) -> str:
    """A bench part's Markdown without its plots (they stay beside it in reports/, not in the repository)."""
    return re.sub(r"^!\[[^\]]*\]\([^)]*\)\n?", "", f.read_text().strip(), flags=re.M).strip()


def _demote(text: str) -> str:
    """The README's section is "## Benchmarks": a part's title one level below, its tables two."""
    return re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + 2) + " ", text, flags=re.M)


def render(readme: str, sections: dict) -> str:
    for name, body in sections.items():
        if body is None:
            continue
        pat = re.compile(rf"(<!-- {name}:begin -->\n).*?(<!-- {name}:end -->)", re.S)
        if not pat.search(readme):
            raise ValueError(f"README.md has no <!-- {name}:begin --> … <!-- {name}:end --> markers")
        readme = pat.sub(lambda m: m.group(1) + body + "\n" + m.group(2), readme)
    return readme


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    path = ROOT / "README.md"
    old = path.read_text()
    sections = {"scenes": scenes_section(), "techniques": techniques_section()}
    if "--check" in argv:
        return 0 if render(old, sections) == old else 1
    sections["bench"] = bench_section()
    for part in OWN_SECTIONS:
        sections[f"bench-{part}"] = bench_part_section(part)
    new = render(old, sections)
    if new != old:
        path.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
