"""Ctrl-C of a multi-scene ``reference --workers`` (issue 27, "Wrong or misleading messages" and
"Tracebacks").

A terminal's Ctrl-C signals the whole foreground process group: the command and its Dask worker
processes. What must hold: exit 130 with one line on stderr (no worker's connection traceback,
no start-up line from a worker, no resource-tracker noise) that says which references were stored
before the signal and which were not, and the store holds exactly those. Real processes: a real
``shadowlab`` with a local cluster of two workers, two tiny scenes and one slow one.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import llvm_only
from shadowlab.reference import store

ROOT = Path(__file__).resolve().parents[1]


def _scene(d: Path, name: str, res: int) -> Path:
    text = (ROOT / "scenes" / "contact.toml").read_text()
    p = d / f"{name}.toml"
    p.write_text(text.replace("resolution = [128, 128]", f"resolution = [{res}, {res}]").replace(
        'name = "contact"', f'name = "{name}"'))
    return p


@llvm_only("the batch needs a job still running when the signal lands: on a GPU the 1024² truth ends first")
def test_ctrl_c_of_a_cluster_batch_says_which_references_were_stored(tmp_path):
    scenes = [_scene(tmp_path, "a", 16), _scene(tmp_path, "b", 16), _scene(tmp_path, "slow", 1024)]
    base = tmp_path / "refs"
    base.mkdir()
    env = dict(os.environ, SHADOWLAB_REFERENCES=str(base),
               PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    p = subprocess.Popen([sys.executable, "-m", "shadowlab.cli", "reference", *map(str, scenes), "--workers", "2",
                          "--max-rounds", "64", "--target-se", "0.0002", "--spp", "0"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT,
                         start_new_session=True)          # its own process group, as a terminal's job
    try:
        t = time.monotonic()
        while len(list(base.rglob("meta.json"))) < 2:
            assert p.poll() is None and time.monotonic() - t < 180, p.communicate()
            time.sleep(0.05)
        time.sleep(0.5)
        assert p.poll() is None, "the slow reference finished before the signal"
        os.killpg(p.pid, signal.SIGINT)                   # Ctrl-C: the command and its workers
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, (out, err)
    lines = [l for l in err.splitlines() if l.strip()]
    a, b, slow = (store.path_for(n, (r, r), base) for n, r in (("a", 16), ("b", 16), ("slow", 1024)))
    # the line says what the store holds once the workers have stopped (read after the executor closed)
    stored = {str(m.parent) for m in base.rglob("meta.json")}
    done, rest = [x for x in (a, b, slow) if str(x) in stored], [x for x in (a, b, slow) if str(x) not in stored]
    assert {str(a), str(b)} <= stored and rest == [slow], stored
    want = f"interrupted by SIGINT: stored {len(done)} of 3 references ({', '.join(map(str, done))})"
    if rest:
        want += f"; not stored, each left as it was: {', '.join(map(str, rest))}"
    assert lines == [want], err
    assert slow.exists() == (str(slow) in stored)
