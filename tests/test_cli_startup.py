"""``shadowlab --help`` and usage errors answer without loading Mitsuba or Dr.Jit: the CLI
registers its commands with typer and the standard library only, and each command imports what
it runs inside its own function (shadowlab/cli.py's docstring; tests/test_imports.py allows that
in the CLI only). Speed is not asserted (bench/ measures it); which modules load is a fact."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from shadowlab import cli

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("mitsuba", "drjit", "numpy", "scipy", "distributed")

_PROBE = """
import json, sys
from shadowlab.cli import main
rc = main(sys.argv[1:])
print("@@" + json.dumps({"rc": rc, "heavy": sorted({m.split(".")[0] for m in sys.modules} & set(%r))}))
""" % (HEAVY,)


def _probe(*args):
    """Run the CLI's entry in a fresh interpreter; (exit code, heavy modules loaded, stdout, stderr)."""
    p = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    res = json.loads(lines[-1][2:])
    return res["rc"], res["heavy"], "\n".join(lines[:-1]), p.stderr


def test_constants_shown_in_help_match_their_sources():
    from shadowlab.cluster import SCHEDULER_ENV
    from shadowlab.reference.truth import SEED_MAX
    assert cli.SEED_MAX == SEED_MAX and cli.SCHEDULER_ENV == SCHEDULER_ENV


def test_the_cli_module_top_imports_only_typer_errors_and_the_standard_library():
    tree = ast.parse((ROOT / "shadowlab" / "cli.py").read_text())
    names = []
    for node in tree.body:                                  # module level only, not inside functions
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append("." * node.level + (node.module or ""))
    bad = [n for n in names if n not in ("typer", ".errors", "__future__")
           and n.split(".")[0] not in sys.stdlib_module_names]
    assert not bad, f"shadowlab/cli.py imports at module level (import them in the command that needs them): {bad}"


@pytest.mark.parametrize("args, rc, text", [
    (["--help"], 0, "Real-time shadow techniques"),
    (["compare", "--help"], 0, "--techniques"),
    (["compare", "contact", "--bogus"], 2, "No such option"),
    (["fit"], 2, "Missing argument"),
])
def test_help_and_usage_errors(args, rc, text):
    code, _, out, err = _probe(*args)
    assert code == rc and text in out + err
    assert "Traceback" not in out + err


@pytest.mark.parametrize("args", [["--help"], ["compare", "--help"], ["compare", "contact", "--bogus"]])
def test_help_and_usage_errors_load_no_mitsuba_or_drjit(args):
    _, heavy, _, _ = _probe(*args)
    assert heavy == []
