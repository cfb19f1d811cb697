"""The examples in shadowlab's docstrings run and print what they show.

One test per module that holds an example (a line starting with ``>>>``), found by walking the
package's files, so modules that move or appear are picked up without editing this file. The
Mitsuba variant is selected first (``mitsuba_backend``): examples may render. Flags: ELLIPSIS
(``...`` matches anything) and NORMALIZE_WHITESPACE. Examples are small and fast; one that
cannot run here is marked ``# doctest: +SKIP`` and says why.
"""

import doctest
import importlib
import io
from pathlib import Path

import pytest

import shadowlab

PACKAGE = Path(shadowlab.__file__).parent
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _modules_with_examples() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>> " not in path.read_text(encoding="utf-8"):
            continue
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        names.append(".".join(parts))
    return names


MODULES = _modules_with_examples()
DOCS = sorted(p.name for p in (PACKAGE.parent / "docs").glob("*.md") if ">>> " in p.read_text(encoding="utf-8"))


def test_the_package_has_examples_to_run():
    assert len(MODULES) >= 10, MODULES
    assert "ARCHITECTURE.md" in DOCS, DOCS


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name, mitsuba_backend):
    module = importlib.import_module(name)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    out = io.StringIO()
    for test in doctest.DocTestFinder().find(module, name):
        runner.run(test, out=out.write)
    result = runner.summarize(verbose=False)
    assert result.attempted > 0, f"{name}: has '>>> ' lines but no example was found in a docstring"
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed\n{out.getvalue()}"


@pytest.mark.parametrize("name", DOCS)
def test_examples_in_docs(name, mitsuba_backend):
    """The ``>>>`` examples of docs/*.md (the code blocks without prompts are illustrations)."""
    path = PACKAGE.parent / "docs" / name
    test = doctest.DocTestParser().get_doctest(path.read_text(encoding="utf-8"), {}, name, str(path), 0)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    out = io.StringIO()
    runner.run(test, out=out.write)
    assert test.examples and runner.failures == 0, out.getvalue()
