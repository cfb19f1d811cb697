"""``pip install .`` (not editable) gives a working shadowlab (issue 27): the wheel carries the built-in
scenes, their textures and committed references as package data (setup.py), and an installed
``shadowlab demo`` runs from any working directory without writing into the installed package.

The wheel is built from a copy of the checkout's files (tracked and new, not ignored), with
``pip wheel --no-deps --no-build-isolation`` (the venv's setuptools, nothing downloaded), and installed
with ``--no-deps`` into a temporary venv whose ``.pth`` file lists this venv's site-packages for the
dependencies: a plain path entry, so the checkout's editable install (a finder that only its own
``.pth`` file starts) is not what gets imported.
"""

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("pyproject.toml", "setup.py", "README.md", "shadowlab", "scenes", "references")


def _run(args, **kw):
    r = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=600, **kw)
    assert r.returncode == 0, f"{' '.join(map(str, args))}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


def _source_copy(dest: Path) -> Path:
    """The checkout's files under :data:`PARTS` that git tracks or would track (not ignored) in ``dest``."""
    out = _run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z", "--", *PARTS], cwd=ROOT).stdout
    for rel in filter(None, out.split("\0")):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def _snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(d.rglob("*"))}


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv python, venv bin, installed package dir, built wheel) of a fresh install of the wheel."""
    t = tmp_path_factory.mktemp("wheel")
    src = _source_copy(t / "src")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(src),
                        "-w", str(t / "dist")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, ("building the wheel failed; the venv needs setuptools >= 70.1 (pip install -e "
                               f"'.[test]'):\n{r.stderr[-3000:]}")
    wheel = next((t / "dist").glob("shadowlab-*.whl"))
    venv = t / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv])
    py = venv / "bin" / "python"
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    (site / "_shadowlab_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", py, "install", "-q", "--no-deps", wheel])
    return py, venv / "bin", site / "shadowlab", wheel


def test_the_wheel_carries_the_builtin_scenes_textures_and_references(installed):
    *_, wheel = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    scenes = sorted(p.name for p in (ROOT / "scenes").glob("*.toml"))
    assert scenes and all(f"shadowlab/builtin_scenes/{s}" in names for s in scenes)
    assert "shadowlab/builtin_scenes/textures/leaf.png" in names
    committed = sorted(str(p.relative_to(ROOT / "references")) for p in (ROOT / "references").glob("*/*/truth.exr"))
    assert committed and all(f"shadowlab/builtin_references/{c}" in names for c in committed)
    assert "shadowlab/techniques/engine_pages/three.html" in names


def test_installed_demo_runs_in_a_new_directory_and_writes_nothing_into_the_package(installed, tmp_path):
    py, bin_, pkg, _ = installed
    env = {**{k: v for k, v in os.environ.items() if k not in ("SHADOWLAB_REFERENCES", "PYTHONPATH")},
           "PYTHONDONTWRITEBYTECODE": "1"}
    where = _run([py, "-c", "import shadowlab; print(shadowlab.__file__)"], cwd=tmp_path, env=env).stdout.strip()
    assert Path(where).parent == pkg, where            # the installed copy, not the checkout's editable install
    before = _snapshot(pkg)
    sl = bin_ / "shadowlab"
    assert "contact" in _run([sl, "scenes", "--names"], cwd=tmp_path, env=env).stdout.split()
    # a built-in scene's committed reference is read where the package is installed
    r = _run([sl, "compare", "contact", "-t", "hard", "-o", "hard"], cwd=tmp_path, env=env)
    assert "hard" in r.stdout and (tmp_path / "hard" / "metrics.json").is_file()
    # a reference at another resolution goes into the project's store, ./references
    _run([sl, "reference", "contact", "-r", "24x24", "--max-rounds", "2", "--spp", "0"], cwd=tmp_path, env=env)
    assert (tmp_path / "references" / "contact" / "24x24" / "truth.exr").is_file()
    r = _run([sl, "demo", "-r", "24x24", "-o", "demo"], cwd=tmp_path, env=env)
    assert "contact (24x24)" in r.stdout and "pcss" in r.stdout
    for f in ("index.html", "summary.md", "metrics.json"):
        assert (tmp_path / "demo" / f).stat().st_size > 0, f
    assert _snapshot(pkg) == before
