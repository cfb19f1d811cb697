"""The package structure: no import cycle between shadowlab's packages, and no import of a
shadowlab module inside a function (such imports only hide cycles), except in the CLI (below).

The graph is read from the source with ``ast`` (nothing is imported). Its nodes are the
sub-packages (``shadowlab.render``, ``shadowlab.sdf``, ``shadowlab.bench``, …) and the top-level
modules (``shadowlab.pipeline``, ``shadowlab.cli``, …); an edge A → B is an import, anywhere in
A, of a module of B. ``shadowlab/__init__.py`` is a leaf (its names, e.g. ``__version__``,
belong to no sub-package). Inside one package the module graph must be acyclic too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "shadowlab"

# third-party dependencies that are optional (not in the package's install requirements) or slow
# to load and only needed by one command: they may be imported inside the function that uses them
LAZY_OPTIONAL = frozenset({"matplotlib", "flip_evaluator", "colour", "tqdm"})

# the one module whose functions may import anything, shadowlab's own modules included: the CLI is
# the top layer, which no module imports, so an import inside one of its functions cannot hide a
# cycle (the cycle checks still see it as an edge). Each command imports what it runs inside its
# own function, so that `shadowlab --help` and usage errors load no Mitsuba / Dr.Jit / numpy
# (start-up time; tests/test_cli_startup.py)
# The package root (`shadowlab/__init__.py`, a leaf of the graph) is the other: its module
# __getattr__ loads the public API (shadowlab.api) on first use, for the same reason.
LAZY_MODULES = frozenset({"shadowlab.cli", "shadowlab"})


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _targets(node, mod: str, is_pkg: bool, known: set) -> list[str]:
    """Absolute names of the modules an import statement imports."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = mod.split(".") if is_pkg else mod.split(".")[:-1]
        base = base[:len(base) - (node.level - 1)]
        src = ".".join(base + ([node.module] if node.module else []))
    else:
        src = node.module or ""
    # `from pkg import name`: name is a module when such a module exists, else a name of pkg
    return [f"{src}.{a.name}" if f"{src}.{a.name}" in known else src for a in node.names]


def imports(root: Path = ROOT, pkg: Path | None = None):
    """[(module, imported module, line, inside a function?)] of every import in the package."""
    pkg = pkg or root / "shadowlab"
    files = sorted(pkg.rglob("*.py"))
    known = {module_name(f, root) for f in files}
    out = []
    for f in files:
        mod = module_name(f, root)
        tree = ast.parse(f.read_text(), filename=str(f))

        def walk(node, in_function):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.Import, ast.ImportFrom)):
                    for t in _targets(child, mod, f.name == "__init__.py", known):
                        out.append((mod, t, f"{f.relative_to(root)}:{child.lineno}", in_function))
                walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

        walk(tree, False)
    return out


def node_of(mod: str) -> str:
    """The graph node of a module: its sub-package or top-level module (shadowlab.X)."""
    return ".".join(mod.split(".")[:2])


def find_cycle(edges: dict) -> list | None:
    """One cycle of a directed graph {node: set of nodes} as [a, b, …, a], or None."""
    state, stack = {}, []

    def visit(v):
        state[v] = 1
        stack.append(v)
        for w in sorted(edges.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state:
                c = visit(w)
                if c:
                    return c
        stack.pop()
        state[v] = 2
        return None

    for v in sorted(edges):
        if v not in state:
            c = visit(v)
            if c:
                return c
    return None


def package_graph(imps) -> dict:
    edges = {}
    for src, dst, _, _ in imps:
        if not dst.startswith("shadowlab.") or dst == "shadowlab" or src == "shadowlab":
            continue
        a, b = node_of(src), node_of(dst)
        if a != b and b != "shadowlab":
            edges.setdefault(a, set()).add(b)
    return edges


def module_graph(imps) -> dict:
    """Edges between modules of one package (``shadowlab.fit.run`` → ``shadowlab.fit.report``)."""
    edges = {}
    for src, dst, _, _ in imps:
        if dst.startswith("shadowlab.") and src != dst and node_of(src) == node_of(dst):
            edges.setdefault(src, set()).add(dst)
    return edges


def function_level(imps) -> list[str]:
    return [f"{where}: {dst}" for src, dst, where, inside in imps
            if inside and dst.split(".")[0] == "shadowlab" and src not in LAZY_MODULES]


IMPS = imports()


def test_no_import_cycle_between_packages():
    cycle = find_cycle(package_graph(IMPS))
    assert cycle is None, "import cycle between packages: " + " -> ".join(cycle)


def test_no_import_cycle_between_modules_of_a_package():
    cycle = find_cycle(module_graph(IMPS))
    assert cycle is None, "import cycle between modules: " + " -> ".join(cycle)


def test_no_shadowlab_import_inside_a_function():
    bad = function_level(IMPS)
    assert not bad, "imports of shadowlab modules inside functions (move them to the module top):\n" + "\n".join(bad)


def test_only_heavy_optional_dependencies_are_imported_inside_functions():
    """Every import sits at the module top, except the dependencies in LAZY_OPTIONAL: heavy to
    import and needed only by one report or metric (plots, FLIP, ΔE2000, progress bars)."""
    bad = [f"{where}: {dst}" for src, dst, where, inside in IMPS
           if inside and dst.split(".")[0] not in LAZY_OPTIONAL and src not in LAZY_MODULES]
    assert not bad, "imports inside functions (move them to the module top):\n" + "\n".join(bad)


def test_sdf_is_a_geometry_library():
    """``shadowlab.sdf`` imports nothing else of shadowlab."""
    bad = [f"{where}: {dst}" for src, dst, where, _ in IMPS
           if node_of(src) == "shadowlab.sdf" and dst.startswith("shadowlab") and node_of(dst) != "shadowlab.sdf"]
    assert not bad, "\n".join(bad)


def test_the_sdf_seed_hash_is_shadowlabs():
    """``shadowlab.sdf.soft.fnv32`` is the seed hash of render.shading (written twice because
    sdf imports nothing of shadowlab): same bits, so Monte-Carlo streams keep their seeds."""
    from shadowlab.render.shading import seed_hash
    from shadowlab.sdf.soft import fnv32
    for vals in [(0x5DF, 0), (0x5DF, 7), (0xC5, 123456789), (1, 2, 3), ()]:
        assert fnv32(*vals) == seed_hash(*vals)


# --- the checks themselves catch what they are for ------------------------------------------------

def _write(root: Path, files: dict):
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def test_a_package_cycle_is_found_and_printed(tmp_path):
    _write(tmp_path, {"shadowlab/__init__.py": "", "shadowlab/a/__init__.py": "",
                      "shadowlab/a/x.py": "from ..b import y\n", "shadowlab/b/__init__.py": "",
                      "shadowlab/b/y.py": "from shadowlab.c import z\n", "shadowlab/c/__init__.py": "",
                      "shadowlab/c/z.py": "from .. import a\n", "shadowlab/top.py": "from .a import x\n"})
    imps = imports(tmp_path)
    cycle = find_cycle(package_graph(imps))
    assert cycle == ["shadowlab.a", "shadowlab.b", "shadowlab.c", "shadowlab.a"]
    assert find_cycle(module_graph(imps)) is None


def test_a_module_cycle_and_a_function_level_import_are_found(tmp_path):
    _write(tmp_path, {"shadowlab/__init__.py": "__version__ = '1'\n", "shadowlab/fit/__init__.py": "",
                      "shadowlab/fit/run.py": "from .report import r\n",
                      "shadowlab/fit/report.py": "from shadowlab import __version__\n"
                                                 "def r():\n    from .run import x\n    import tqdm\n"})
    imps = imports(tmp_path)
    assert find_cycle(package_graph(imps)) is None          # __version__ is a name of shadowlab, a leaf
    assert find_cycle(module_graph(imps)) == ["shadowlab.fit.report", "shadowlab.fit.run", "shadowlab.fit.report"]
    assert function_level(imps) == ["shadowlab/fit/report.py:3: shadowlab.fit.run"]


def test_only_the_cli_may_import_inside_functions(tmp_path):
    """The CLI's lazy imports are allowed and still edges of the graph; the same import in
    another module is refused."""
    _write(tmp_path, {"shadowlab/__init__.py": "", "shadowlab/pipeline.py": "def f():\n    from .cli import x\n",
                      "shadowlab/cli.py": "def cmd():\n    from .pipeline import f\n"})
    imps = imports(tmp_path)
    assert function_level(imps) == ["shadowlab/pipeline.py:2: shadowlab.cli"]
    assert find_cycle(package_graph(imps)) == ["shadowlab.cli", "shadowlab.pipeline", "shadowlab.cli"]


@pytest.mark.parametrize("src", ["shadowlab/render/frame.py", "shadowlab/sdf/soft.py"])
def test_the_real_package_gets_a_cycle_when_one_is_added(tmp_path, src):
    """Copy of the real package plus one back edge (render → pipeline, sdf → scene): the check fails."""
    import shutil
    shutil.copytree(PKG, tmp_path / "shadowlab", ignore=shutil.ignore_patterns("__pycache__"))
    p = tmp_path / src
    extra = "from .. import pipeline\n" if "render" in src else "from ..scene import spec\n"
    p.write_text(p.read_text() + "\n" + extra)
    cycle = find_cycle(package_graph(imports(tmp_path)))
    assert cycle is not None and cycle[0] == cycle[-1]


def test_the_package_imports_its_own_modules_relatively():
    """One import style inside the package: ``from .x import`` / ``from ..x import``, never
    ``from shadowlab.x import`` (the tests and users import absolutely)."""
    bad = []
    for f in sorted(PKG.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "shadowlab":
                bad.append(f"{f.relative_to(ROOT)}:{node.lineno}")
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "shadowlab" for a in node.names):
                bad.append(f"{f.relative_to(ROOT)}:{node.lineno}")
    assert not bad, bad
