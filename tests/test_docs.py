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
