"""The README's generated sections match their single sources (scene files, declarations)."""

from pathlib import Path

from shadowlab import docs
from shadowlab.techniques import base


def test_readme_sections_are_current():
    readme = (Path(docs.ROOT) / "README.md").read_text()
    fresh = docs.render(readme, {"scenes": docs.scenes_section(), "techniques": docs.techniques_section()})
    assert fresh == readme, "README.md is stale: run `make docs`"


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

import re

ROOT = Path(docs.ROOT)
KEY = re.compile(r"\[((?:[A-ZÁ-Ž][\w'\-]*(?: [a-z]{1,3})? )+(?:19|20)\d\d[a-z]?)(?=[,\]])")
DEFINED = re.compile(r"^\s*(?:- )?\*\*\[([^\]]+)\]\*\*", re.M)


def _cited_keys() -> dict:
    files = list((ROOT / "shadowlab").rglob("*.py")) + list((ROOT / "scenes").glob("*.toml"))
    files += [ROOT / "README.md", ROOT / "docs" / "ARCHITECTURE.md"]
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
    files = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"] + sorted((ROOT / "shadowlab").rglob("*.py")) \
        + sorted((ROOT / "scenes").glob("*.toml"))
    for f in files:
        hits = bad.findall(f.read_text(encoding="utf-8"))
        assert not hits, (f.name, hits)


def test_readme_points_to_the_architecture_guide():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Adding a technique", 1)[1].split("\n## ", 1)[0]
    assert "docs/ARCHITECTURE.md" in section and (ROOT / "docs" / "ARCHITECTURE.md").is_file()
    guide = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    for heading in ("## The data flow", "## Packages and their contracts", "## Adding a technique family"):
        assert heading in guide, heading
