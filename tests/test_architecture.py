"""The architecture of docs/ARCHITECTURE.md, kept: what each package may import, which knowledge
stays in the technique families, and which names are private.

1. **Imports.** The table "What each package may import" of docs/ARCHITECTURE.md is read here
   and is the only statement of the rule: every import edge between packages (read with ``ast``,
   :func:`test_imports.imports`) must be allowed by the importing package's row, every package
   must have a row, and no module imports the package root ``shadowlab`` (its ``__init__`` is
   the API, the top).
2. **Family knowledge stays in the families.** ``pipeline/``, ``report/`` and ``fit/`` must
   not name a family: no registered technique name (``csm``, ``vtsm``, ``pcss``, …), no key of
   a family's report images or error bands (``Technique.panels``, ``Technique.band_aovs``: e.g.
   ``cascade``, ``tile``, ``demand_x``), no AOV name those images are built from
   (:data:`FAMILY_AOVS`) and no family module (``techniques.cascades`` …) may appear in their
   *code*. Code means identifiers (names, attributes, function, class, argument and keyword
   names, imported names and modules) and string constants (f-string parts included);
   docstrings are left out (they may say which family does what, as documentation), as are
   comments (``ast`` does not see them). A word is a run of letters, digits and underscores,
   and also each ``_``-separated part of it, so ``cascade_colours`` names ``cascade``. The
   forbidden words come from the registry, so a new family is covered without an edit here;
   :data:`PROSE` lists the few technique names that are also English words where a file uses
   them as such (``hard``).
3. **Private names stay private.** In ``techniques/``, ``report/``, ``fit/``, ``pipeline/``
   and ``exchange/`` no module imports a ``_name`` from another module, and no code reads or
   writes another object's ``_attribute`` (``x._dr``) other than through ``self`` / ``cls``.
   A package's own helper modules (``techniques/_random.py``) may be imported by name.

Each check is also run on a copy of the package with one violation added, and must fail there.
"""

from __future__ import annotations

import ast
import re
import shutil
from pathlib import Path

import pytest
from test_imports import PKG, ROOT, imports, node_of

from shadowlab.techniques import get, names

DOC = ROOT / "docs" / "ARCHITECTURE.md"

#: AOV names the families' report images are built from that are not themselves image keys
#: (the blend weight colours csm's bands, the cell draws fvsm's SMTG grid, provided levels give
#: the undersampling)
FAMILY_AOVS = frozenset({"blend_weight", "cell", "provided_x", "provided_y", "aliasing"})

#: where family names may not appear (paths relative to shadowlab/)
NEUTRAL = ("pipeline", "report", "fit")

#: (file, word): a technique's name that is also an English word, used as that word in prose
#: strings of that file (and nowhere as code)
PROSE = {("shadowlab/report/lights.py", "hard"): "a spot light's hard cone, hard (delta-light) shadows in the truth"}

#: where private names may not cross modules: every package and module of shadowlab
PRIVATE_SCOPE = tuple(sorted(p.name for p in PKG.iterdir()
                             if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py")))

#: public names of other APIs that start with "_": namedtuple's methods (so as not to clash with
#: field names), the standard library's ``os._exit`` (leave at once, after a signal) and Dr.Jit's
#: traversal protocol on a bound C++ object, ``_traverse_1_cb_ro`` (it has no other name)
NAMEDTUPLE_API = frozenset({"_asdict", "_replace", "_fields", "_make", "_field_defaults", "_exit",
                            "_traverse_1_cb_ro"})


# --- 1. imports --------------------------------------------------------------------------------

def allowed_imports(doc: Path = DOC) -> dict:
    """{package: set of packages it may import, or None for any} from ARCHITECTURE.md's table."""
    text = doc.read_text(encoding="utf-8")
    m = re.search(r"\| package \| may import \|\n\|[-| ]+\|\n((?:\|.*\|\n)+)", text)
    assert m, f"{doc}: no table with the header '| package | may import |'"
    out = {}
    for row in m.group(1).splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        pkgs = re.findall(r"`([^`]+)`", cells[0])
        may = cells[1]
        allowed = None if may.startswith("anything") else {
            "shadowlab." + x.rstrip("/").removesuffix(".py") for x in re.findall(r"`([^`]+)`", may)}
        for p in pkgs:
            out["shadowlab." + p.rstrip("/").removesuffix(".py")] = allowed
    return out


def import_violations(imps, allowed: dict, pkg: Path = PKG) -> list[str]:
    nodes = {node_of(".".join(["shadowlab", *f.relative_to(pkg).with_suffix("").parts]))
             for f in pkg.rglob("*.py") if f.relative_to(pkg).parts[0] != "__init__.py"}
    bad = [f"{n}: no row in docs/ARCHITECTURE.md's table 'What each package may import'"
           for n in sorted(nodes - set(allowed))]
    for src, dst, where, _ in imps:
        if src == "shadowlab" or not (dst == "shadowlab" or dst.startswith("shadowlab.")):
            continue
        if dst == "shadowlab":
            bad.append(f"{where}: imports the package root `shadowlab` (the API, the top layer)")
            continue
        a, b = node_of(src), node_of(dst)
        if a == b:
            continue
        may = allowed.get(a, set())
        if may is not None and b not in may:
            bad.append(f"{where}: {a} imports {b}, which its row does not allow")
    return bad


def test_every_package_imports_only_what_architecture_md_allows():
    bad = import_violations(imports(), allowed_imports())
    assert not bad, "\n".join(bad)


# --- 2. family names ---------------------------------------------------------------------------

def family_words() -> set[str]:
    """Technique names, the families' report-image and band keys, FAMILY_AOVS and the family
    modules (from the registry)."""
    words = set(FAMILY_AOVS)
    for n in names():
        t = get(n)
        words.add(n)
        words.update(k for p in t.panels for k in p.keys)
        words.update(t.band_aovs)
        words.add(type(t).__module__.rsplit(".", 1)[-1])
    return words


def _docstrings(tree) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                ids.add(id(body[0].value))
    return ids


def code_words(source: str) -> list[tuple[int, str]]:
    """(line, word) of the identifiers and string constants of ``source``, docstrings left out."""
    tree = ast.parse(source)
    skip = _docstrings(tree)
    out = []

    def add(line, text):
        for w in re.findall(r"\w+", text):
            out.append((line, w))
            out.extend((line, part) for part in w.split("_") if part and part != w)

    for node in ast.walk(tree):
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            add(line, node.value)
        elif isinstance(node, ast.Name):
            add(line, node.id)
        elif isinstance(node, ast.Attribute):
            add(line, node.attr)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            add(line, node.name)
        elif isinstance(node, ast.arg):
            add(line, node.arg)
        elif isinstance(node, ast.keyword) and node.arg:
            add(line, node.arg)
        elif isinstance(node, ast.alias):
            add(line, node.name + " " + (node.asname or ""))
        elif isinstance(node, ast.ImportFrom) and node.module:
            add(line, node.module)
    return out


def neutral_files(pkg: Path = PKG) -> list[Path]:
    files = []
    for n in NEUTRAL:
        p = pkg / n
        files += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    return files


def family_mentions(pkg: Path = PKG, words: set | None = None) -> list[str]:
    words = family_words() if words is None else words
    bad = []
    for f in neutral_files(pkg):
        for line, w in code_words(f.read_text(encoding="utf-8")):
            if w in words and (str(f.relative_to(pkg.parent)), w) not in PROSE:
                bad.append(f"{f.relative_to(pkg.parent)}:{line}: {w!r}")
    return sorted(set(bad))


def test_the_forbidden_words_come_from_the_families():
    w = family_words()
    assert {"csm", "vtsm", "fvsm", "pcss", "ssss", "dpsv", "hard"} <= w
    assert {"cascade", "tile", "demand_x", "demand_y", "aliasing", "blend_weight", "cell"} <= w
    assert {"cascades", "virtual_maps"} <= w                     # family modules


def test_pipeline_report_and_fit_name_no_family():
    bad = family_mentions()
    assert not bad, ("family knowledge in pipeline/, report/ or fit/ (declare it on the family's Technique: "
                     "panels / report_images, band_aovs, fit_params, fit_loss, Param.from_scene):\n" + "\n".join(bad))


def test_docstrings_and_comments_may_name_families():
    src = '"""The csm cascades."""\n# vtsm tiles\ndef f(x):\n    """pcss."""\n    return x\n'
    assert not [w for _, w in code_words(src) if w in {"csm", "cascades", "vtsm", "pcss"}]
    assert ("cascade" in {w for _, w in code_words("y = cascade_colours(a)\n")})
    assert ("tile" in {w for _, w in code_words('k = f"{l}.tile"\n')})


# --- 3. private names --------------------------------------------------------------------------

def private_crossings(pkg: Path = PKG) -> list[str]:
    bad = []
    for scope in PRIVATE_SCOPE:
        p = pkg / scope
        for f in (sorted(p.rglob("*.py")) if p.is_dir() else [p]):
            tree = ast.parse(f.read_text(encoding="utf-8"))
            here = f.relative_to(pkg.parent)
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom):
                    for a in node.names:
                        private = a.name.startswith("_") and not a.name.startswith("__")
                        own_module = node.module is None and node.level == 1 and (f.parent / f"{a.name}.py").exists()
                        if private and not own_module:
                            bad.append(f"{here}:{node.lineno}: imports {a.name} from {node.module or '.'}")
                elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__") \
                        and node.attr not in NAMEDTUPLE_API:
                    if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                        bad.append(f"{here}:{node.lineno}: reaches {ast.unparse(node)}")
    return bad


def test_no_private_name_crosses_a_module():
    bad = private_crossings()
    assert not bad, "\n".join(bad)


# --- each check fails on a copy with one violation added ---------------------------------------

@pytest.fixture()
def copy(tmp_path):
    shutil.copytree(PKG, tmp_path / "shadowlab", ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path / "shadowlab"


def _append(p: Path, text: str):
    p.write_text(p.read_text(encoding="utf-8") + "\n" + text, encoding="utf-8")


@pytest.mark.parametrize("target, line, word", [
    ("pipeline/compare.py", 'CASCADE_KEY = "cascade"\n', "cascade"),
    ("report/html.py", "def _csm_rows(ti):\n    return ti\n", "csm"),
    ("fit/run.py", 'LOSSES_BY_TECHNIQUE = {"vtsm": "rmse"}\n', "vtsm"),
    ("report/images.py", "def f(a):\n    return a.tile\n", "tile"),
    ("fit/search.py", "def f(aovs, ln):\n    return aovs[f'{ln}.demand_x']\n", "demand_x"),
])
def test_a_family_name_in_neutral_code_is_found(copy, target, line, word):
    assert family_mentions(copy) == []
    _append(copy / target, line)
    bad = family_mentions(copy)
    assert bad and all(target in b for b in bad) and any(repr(word) in b for b in bad), bad


def test_a_forbidden_import_is_found(copy):
    root = copy.parent
    assert import_violations(imports(root), allowed_imports()) == []
    _append(copy / "report" / "images.py", "from ..techniques import base\n")
    assert any("shadowlab.report imports shadowlab.techniques" in b
               for b in import_violations(imports(root), allowed_imports()))
    _append(copy / "exchange" / "ply.py", "from .. import __version__\n")
    assert any("package root" in b for b in import_violations(imports(root), allowed_imports()))
    (copy / "newpkg").mkdir()
    (copy / "newpkg" / "__init__.py").write_text("")
    assert any("shadowlab.newpkg: no row" in b for b in import_violations(imports(root), allowed_imports(), copy))


def test_a_private_name_crossing_is_found(copy):
    assert private_crossings(copy) == []
    _append(copy / "techniques" / "ssss.py", "from .pcss import _tap\n")
    _append(copy / "pipeline" / "compare.py", "def f(view):\n    return view._dr\n")
    bad = private_crossings(copy)
    assert any("ssss.py" in b and "_tap" in b for b in bad) and any("view._dr" in b for b in bad), bad
