"""Where the reference store lives (issue 27, shadowlab/reference/location.py): ``--references``, then
``$SHADOWLAB_REFERENCES``, then the nearest ``shadowlab.toml`` / ``[tool.shadowlab]`` of a
``pyproject.toml`` walking up from the working directory, then ``./references``; never inside the
installed package, whose built-in references are read as a fallback and never written."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from shadowlab.errors import InputError, ReferenceError_
from shadowlab.reference import location, store
from shadowlab.scene import load_spec
from shadowlab.scene.spec import builtin_dir

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def project(tmp_path, monkeypatch):
    """An empty project folder as the working directory, with no store setting from outside."""
    monkeypatch.delenv(location.ROOT_ENV, raising=False)
    location.choose(None)
    d = tmp_path / "proj"
    (d / "tests" / "deep").mkdir(parents=True)
    monkeypatch.chdir(d)
    yield d
    location.choose(None)


def test_default_is_references_in_the_working_directory(project):
    loc = location.locate()
    assert (loc.path, loc.source) == (project / "references", "default")
    assert store.root() == project / "references"


def test_pyproject_table_is_found_walking_up_and_is_relative_to_the_file(project, monkeypatch):
    (project / "pyproject.toml").write_text('[project]\nname = "x"\n\n[tool.shadowlab]\nreferences = "tests/refs"\n')
    monkeypatch.chdir(project / "tests" / "deep")
    loc = location.locate()
    assert loc.path == project / "tests" / "refs" and loc.source == str(project / "pyproject.toml")


def test_a_pyproject_without_the_table_does_not_stop_the_walk(project, monkeypatch):
    (project / "shadowlab.toml").write_text('references = "store"\n')
    (project / "tests" / "pyproject.toml").write_text('[project]\nname = "inner"\n')
    monkeypatch.chdir(project / "tests" / "deep")
    assert location.locate().path == project / "store"


def test_shadowlab_toml_comes_before_pyproject_in_one_folder_and_the_nearest_folder_wins(project, monkeypatch):
    (project / "pyproject.toml").write_text('[tool.shadowlab]\nreferences = "from_pyproject"\n')
    (project / "shadowlab.toml").write_text('references = "from_shadowlab_toml"\n')
    assert location.locate().path == project / "from_shadowlab_toml"
    (project / "tests" / "shadowlab.toml").write_text('references = "../nearer"\n')
    monkeypatch.chdir(project / "tests" / "deep")
    assert location.locate().path.resolve() == project / "nearer"


def test_environment_beats_the_project_file_and_the_option_beats_both(project, monkeypatch, tmp_path):
    (project / "shadowlab.toml").write_text('references = "from_file"\n')
    env, opt = tmp_path / "env_store", tmp_path / "opt_store"
    env.mkdir(), opt.mkdir()
    monkeypatch.setenv(location.ROOT_ENV, str(env))
    assert (location.locate().path, location.locate().source) == (env, "environment")
    location.choose(opt)
    assert (location.locate().path, location.locate().source) == (opt, "option")
    assert store.root() == opt


def test_a_bad_setting_is_a_clear_input_error(project):
    (project / "shadowlab.toml").write_text("references = 3\n")
    with pytest.raises(InputError, match=r"shadowlab.toml: references must be a path"):
        location.locate()
    (project / "shadowlab.toml").write_text("references = [\n")
    with pytest.raises(InputError, match="cannot read it for the reference store"):
        location.locate()


def test_a_missing_store_given_by_option_is_refused_unless_created(project):
    location.choose(project / "nope")
    with pytest.raises(ReferenceError_, match="--references .*nope is not a directory"):
        store.root()
    assert store.root(create=True) == project / "nope"


def test_a_store_inside_the_installed_package_is_refused(project):
    location.choose(location.PACKAGE / "refs")
    with pytest.raises(InputError, match="inside the installed shadowlab package"):
        store.root(create=True)


def test_builtin_references_are_read_where_installed_and_never_written(project):
    committed = location.builtin_references()
    before = {p: p.stat().st_mtime_ns for p in committed.rglob("*")}
    truth, meta = store.load(load_spec(builtin_dir() / "contact.toml"))   # ./references is empty
    assert truth.lights and meta["scene"] == "contact"
    listed = [r for r in store.list_references() if r["scene"] == "contact"]
    assert listed and listed[0]["builtin"] and listed[0]["path"].startswith(str(committed))
    assert {p: p.stat().st_mtime_ns for p in committed.rglob("*")} == before
    assert not (project / "references").exists()


def test_the_fix_for_a_missing_reference_names_the_chosen_store(project):
    location.choose(project)
    with pytest.raises(ReferenceError_, match=f"--resolution 40x40 --references {project}"):
        store.load(load_spec(builtin_dir() / "contact.toml").with_resolution(40, 40))


def _cli(*args, cwd, env=None):
    e = {k: v for k, v in os.environ.items() if k != location.ROOT_ENV}
    return subprocess.run([sys.executable, "-m", "shadowlab.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env={**e, **(env or {})}, timeout=600)


def test_cli_writes_into_the_project_store_and_reads_it_back(project, tmp_path):
    text = (builtin_dir() / "contact.toml").read_text().replace('name = "contact"', 'name = "mine"')
    (project / "tests" / "mine.toml").write_text(text)
    (project / "pyproject.toml").write_text('[tool.shadowlab]\nreferences = "tests/baselines"\n')
    cwd = project / "tests" / "deep"
    args = ("--resolution", "24x24", "--max-rounds", "2", "--spp", "0")
    r = _cli("reference", "../mine.toml", *args, cwd=cwd)
    assert r.returncode == 0, r.stderr
    assert (project / "tests" / "baselines" / "mine" / "24x24" / "truth.exr").is_file()
    r = _cli("references", cwd=cwd)
    assert str(project / "tests" / "baselines" / "mine" / "24x24") in r.stdout
    assert f"reference store: {project / 'tests' / 'baselines'} (from {project / 'pyproject.toml'})" in r.stderr
    other = tmp_path / "other"
    r = _cli("reference", "../mine.toml", *args, "--references", str(other), cwd=cwd)
    assert r.returncode == 0, r.stderr
    assert (other / "mine" / "24x24" / "meta.json").is_file()
    r = _cli("compare", "../mine.toml", "-r", "24x24", "-t", "hard", "-o", str(tmp_path / "rep"),
             "--references", str(other), cwd=cwd)
    assert r.returncode == 0, r.stderr
    assert not list(location.PACKAGE.rglob("truth.exr")) and not (location.PACKAGE / ".locks").exists()


def test_gate_references_option_overrides_the_gate_files_store(project, tmp_path):
    from shadowlab.gate import load_gate_file
    gf = project / "gates.toml"
    gf.write_text('version = 1\nreferences = "baselines"\n\n[[gate]]\nname = "g"\nscene = "contact"\n'
                  'candidate = { technique = "hard" }\nbudget = { rmse = 0.5 }\n')
    assert load_gate_file(gf).references == project / "baselines"
    location.choose(tmp_path / "elsewhere")
    assert load_gate_file(gf).references == tmp_path / "elsewhere"
