"""The docs: generated pages match their single sources (scene files, declarations, bench run
records), the Sphinx site builds with warnings as errors, the README is a short guide whose links
resolve, and every cited key is in the bibliography."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from shadowlab import docs
from shadowlab.bench import record
from shadowlab.techniques import base


def test_generated_pages_are_current():
    assert docs.stale() == [], "generated docs pages are stale: run `make docs`"


def test_every_family_has_a_page_naming_each_technique_and_parameter():
    fams = docs.families()
    assert sum(len(ts) for ts in fams.values()) == len(base.names())
    for fam, ts in fams.items():
        page = (Path(docs.DOCS) / "techniques" / f"{fam}.md").read_text()
        for t in ts:
            assert f"## `{t.name}`" in page
            for p in t.params:
                assert f"`{p.name}`" in page, (fam, t.name, p.name)


def test_docs_site_builds_without_warnings(tmp_path):
    """Sphinx with -W: a broken cross-reference, a page outside every toctree or a malformed
    docstring of the API reference fails the build."""
    p = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                        str(docs.DOCS), str(tmp_path / "html")], capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
    html = (tmp_path / "html" / "techniques" / "pcss.html").read_text()
    assert "light_scale" in html and (tmp_path / "html" / "bench" / "index.html").is_file()
    assert "load_reference" in (tmp_path / "html" / "python-api.html").read_text()   # the API reference


def test_readme_is_a_short_guide_whose_links_resolve():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 200
    assert "make demo" in readme and "make test" in readme
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme)
    assert len(links) > 10
    for link in links:
        if "://" not in link:
            assert (ROOT / link).exists(), link
    for t in base.names():      # every technique is named
        if not t.startswith("sdf_"):
            assert f"`{t}`" in readme, t


# ---------------------------------------------------------------------------------------------
# bench results as data: run records in docs/bench/runs, the pages generated from them

def test_committed_bench_records_name_their_machine_and_date():
    recs = record.load_records(Path(docs.DOCS) / "bench" / "runs")
    assert {r["part"] for r in recs} >= {"core", "truth", "cascades", "virtual", "dpsv", "ssss", "scaling", "sdf"}
    for r in recs:
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d", r["date"]), r["file"]
        assert r["machine"]["cpu"] and r["machine"]["cores"] >= 1 and r["machine"]["variant"], r["file"]
        assert any(b["type"] == "table" and b["rows"] for b in r["blocks"]), r["file"]
        assert r["file"] == record.record_name(r)


def test_bench_page_shows_the_latest_run_per_machine_and_links_older_ones(tmp_path):
    """Two runs of one part on one machine: the page carries the newer one's table and links the
    older one's page; a run of another machine gets its own table."""
    def md(date, cpu, value):
        return (f"# Cascaded shadow maps ({date})\n\nMachine: {cpu}, 2 cores, mitsuba 3.9.1, drjit 1.5.0, "
                f"variant llvm_ad_rgb. All figures from one run.\n\n## Cost\n\n| config | ms |\n|---|---|\n"
                f"| base | {value} |\n")
    recs = []
    for date, cpu, value in (("2026-01-01T00:00:00", "AMD EPYC", "11"), ("2026-02-01T00:00:00", "AMD EPYC", "22"),
                             ("2026-01-15T00:00:00", "Intel Xeon", "33")):
        r = record.make_record("cascades", md(date, cpu, value))
        r["file"] = record.record_name(r)
        recs.append(r)
    pages = docs.bench_pages(sorted(recs, key=lambda r: r["date"]))
    index = pages[Path(docs.DOCS) / "bench" / "index.md"]
    assert "| base | 22 |" in index and "| base | 33 |" in index and "| base | 11 |" not in index
    older = Path(recs[0]["file"]).stem + ".md"
    assert f"(runs/{older})" in index and "| base | 11 |" in pages[Path(docs.DOCS) / "bench" / "runs" / older]
    assert index.index("AMD EPYC, 2 cores") < index.index("Intel Xeon, 2 cores")


def test_a_bench_part_writes_its_run_record(tmp_path):
    """What ``shadowlab bench`` does after each part: the part's Markdown and JSON become a record
    named by date, part and machine, whose tables are the Markdown's cells."""
    machine = {"cpu": "AMD EPYC", "cores": 2, "gpu": None, "mitsuba": "3.9.1", "drjit": "1.5.0",
               "variant": "llvm_ad_rgb", "libllvm": "/usr/lib/libLLVM.so.19"}
    (tmp_path / "ssss.json").write_text(json.dumps({"date": "2026-12-03T10:00:00", "machine": machine, "x": 1}))
    (tmp_path / "ssss.md").write_text("# Layered screen-space soft shadows (2026-12-03T10:00:00)\n\n"
                                      "## Cost\n\n| kernel | ms |\n|---|---|\n| 5 | 1.5 |\n")
    path = record.write_record(tmp_path, "ssss", tmp_path / "ssss.md")
    assert path.parent == tmp_path / "runs" and path.name == "2026-12-03T100000_ssss_amd-epyc-2-cores-llvm-ad-rgb.json"
    rec = json.loads(path.read_text())
    assert rec["machine"]["libllvm"] == machine["libllvm"] and rec["results"]["x"] == 1
    assert rec["blocks"][-1] == {"type": "table", "columns": ["kernel", "ms"], "rows": [["5", "1.5"]]}
    (tmp_path / "bad.md").write_text("## Cost\n\nno date, no machine\n")
    with pytest.raises(ValueError, match="date and a machine"):
        record.write_record(tmp_path, "bad", tmp_path / "bad.md")


def test_every_parameter_is_documented_with_units_range_and_source():
    for n in base.names():
        t = base.get(n)
        assert t.title and t.source and t.summary
        for p in t.params:
            assert p.doc and p.source, f"{n}.{p.name} lacks a description or source"
            if p.kind in ("float", "int"):
                assert p.lo is not None and p.hi is not None and p.lo <= p.default <= p.hi
            assert p.parse(p.default, n) == p.default


# ---------------------------------------------------------------------------------------------
# docs/: the architecture guide, the bibliography and the keys that cite it


ROOT = Path(docs.ROOT)
KEY = re.compile(r"\[((?:[A-ZÁ-Ž][\w'\-]*(?: [a-z]{1,3})? )+(?:19|20)\d\d[a-z]?)(?=[,\]])")
DEFINED = re.compile(r"^\s*(?:- )?\*\*\[([^\]]+)\]\*\*", re.M)


def _cited_keys() -> dict:
    files = list((ROOT / "shadowlab").rglob("*.py")) + list((ROOT / "scenes").glob("*.toml"))
    files += [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
    cited = {}
    for f in files:
        for k in KEY.findall(f.read_text(encoding="utf-8")):
            cited.setdefault(k, str(f.relative_to(ROOT)))
    return cited


def test_bibliography_defines_the_source_documents_once():
    text = (ROOT / "docs" / "references.md").read_text(encoding="utf-8")
    keys = DEFINED.findall(text)
    assert len(keys) == len(set(keys)), sorted(k for k in keys if keys.count(k) > 1)
    for k in ("Buljan 2020", "Bán 2019", "Giegl 2007", "Wang 2022", "Tamás 2015"):
        assert k in keys, k


def test_every_cited_key_is_in_the_bibliography():
    defined = set(DEFINED.findall((ROOT / "docs" / "references.md").read_text(encoding="utf-8")))
    missing = {k: f for k, f in _cited_keys().items() if k not in defined}
    assert not missing, f"cited but not in docs/references.md: {missing}"


def test_key_pattern_finds_citations():
    assert KEY.findall("see [Buljan 2020, §3.6] and [Bán 2019]; not [1, 2] or [x 2020") == \
        ["Buljan 2020", "Bán 2019"]


def test_repository_docs_name_no_file_outside_the_repository():
    """docs/, the README, the package and the scene files cite by key only: they name no file the
    repository does not hold."""
    bad = re.compile(r"DESIGN\.md|TECHNIQUES\.md|\.\./shared|\b\d{3}_[0-9a-f]{16}\.txt")
    files = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"] + sorted((ROOT / "shadowlab").rglob("*.py")) \
        + sorted((ROOT / "scenes").glob("*.toml"))
    for f in files:
        hits = bad.findall(f.read_text(encoding="utf-8"))
        assert not hits, (f.name, hits)


def test_readme_points_to_the_architecture_guide():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "(docs/ARCHITECTURE.md)" in readme and (ROOT / "docs" / "ARCHITECTURE.md").is_file()
    guide = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    for heading in ("## The data flow", "## Packages and their contracts", "## Adding a technique family"):
        assert heading in guide, heading
