"""A command shadowlab suggests works when pasted (issue 27): the fit report's ``shadowlab compare ...
--preset`` names the scene as the user gave it (a file's path, not its ``name``), the fit's resolution
and the store ``--references`` chose, and runs as printed."""

import html
import os
import shlex
import subprocess
import sys
from pathlib import Path

from shadowlab.scene.spec import builtin_dir


def _cli(words, cwd):
    env = {k: v for k, v in os.environ.items() if k != "SHADOWLAB_REFERENCES"}
    return subprocess.run([sys.executable, "-m", "shadowlab.cli", *words], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=600)


def test_the_fit_reports_compare_command_runs_as_pasted(tmp_path):
    # a user's scene file whose name differs from the file's, in a folder with a space
    scenes = tmp_path / "my scenes"
    scenes.mkdir()
    text = (builtin_dir() / "contact.toml").read_text().replace('name = "contact"', 'name = "studio"')
    (scenes / "studio_v2.toml").write_text(text)
    store = tmp_path / "refs"
    r = _cli(["reference", "my scenes/studio_v2.toml", "-r", "24x24", "--max-rounds", "2", "--spp", "0",
              "--references", str(store)], tmp_path)
    assert r.returncode == 0, r.stderr
    r = _cli(["fit", "my scenes/studio_v2.toml", "-t", "pcf", "--method", "grid", "--grid-points", "2",
              "--rounds", "1", "-r", "24x24", "-o", "fitted", "--references", str(store)], tmp_path)
    assert r.returncode == 0, r.stderr
    summary = (tmp_path / "fitted" / "summary.md").read_text()
    line = next(x for x in summary.splitlines() if x.startswith("Compare with the fitted values:"))
    command = line.split("`")[1]
    assert "'my scenes/studio_v2.toml'" in command and "-r 24x24" in command and str(store) in command
    assert command in r.stdout                                         # the terminal shows the same command
    assert html.escape(command) in (tmp_path / "fitted" / "index.html").read_text()
    words = shlex.split(command)
    assert words[:2] == ["shadowlab", "compare"]
    r = _cli(words[1:] + ["-o", "pasted"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "pasted" / "metrics.json").is_file()
    assert Path(tmp_path / "fitted" / "preset.toml").is_file()
