"""The Dask executor: references on a real LocalCluster (2 worker processes) are the same bits as
in this process, a worker killed mid-job has its job re-run with the store left consistent, and
bad options exit with the documented codes."""

import json
import os
import signal
import threading
import time

import numpy as np
import pytest

from shadowlab import cli
from shadowlab.cluster import executor as ex_mod
from shadowlab.cluster import open_executor
from shadowlab.errors import ReferenceError_
from shadowlab.io.exr import read_exr
from shadowlab.pipeline import load_scene, reference_batch, reference_jobs, render_reference_job
from shadowlab.scene.spec import load_spec, resolve
from shadowlab.reference import store

RES = (40, 40)
OPTS = dict(seed=5, spp=8, target_se=0.01)
JOBS = (["contact", "parallel_planes"], RES)


def _channels(base, scene, res=RES):
    return read_exr(store.path_for(scene, res, base) / "truth.exr")


def _same_bits(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True), k


def test_local_cluster_gives_the_same_bits_as_this_process(tmp_path, dask_workers):
    serial = reference_batch(*JOBS, base=tmp_path / "serial", progress=False, **OPTS)
    dist = reference_batch(*JOBS, base=tmp_path / "dask", progress=False, executor=dask_workers, **OPTS)
    assert dask_workers.describe()["workers"] == 2
    assert [(s, f) for s, f, *_ in serial] == [(s, f) for s, f, *_ in dist] == [("contact", None),
                                                                                 ("parallel_planes", None)]
    for scene in JOBS[0]:
        _same_bits(_channels(tmp_path / "serial", scene), _channels(tmp_path / "dask", scene))
    # the workers really ran them: neither result came from this process's run id
    assert {m["run"] for *_, m in dist} != {m["run"] for *_, m in serial}


def test_frames_all_makes_one_job_per_frame_of_each_path(tmp_path, mitsuba_backend):
    jobs = reference_jobs(["boulevard", "contact"], (16, 16), "all", base=tmp_path)
    n = load_spec(resolve("boulevard")).frames
    assert [j.frame for j in jobs] == list(range(n)) + [None]
    assert len({j.run for j in jobs}) == 1 and all(j.base == str(tmp_path) for j in jobs)


def _held_locks(base):
    """pids of the processes holding a reference lock right now (a held lock file names its holder)."""
    out = []
    for p in (base / store.LOCK_DIR).glob("*.lock") if (base / store.LOCK_DIR).is_dir() else []:
        try:
            txt = p.read_text()
        except OSError:
            continue
        if txt.strip():
            try:
                out.append(json.loads(txt)["pid"])
            except (ValueError, KeyError):
                pass
    return out


def test_a_worker_killed_mid_job_has_its_job_rerun_and_the_store_stays_consistent(tmp_path, mitsuba_backend):
    scenes = ["contact", "parallel_planes", "two_lights", "cornell"]
    opts = dict(seed=2, spp=8, target_se=0.004)
    killed = []
    with open_executor(workers=2) as ex:
        result = {}
        t = threading.Thread(target=lambda: result.update(done=reference_batch(
            scenes, (64, 64), base=tmp_path / "dask", progress=False, executor=ex, **opts)))
        t.start()
        deadline = time.time() + 120
        while t.is_alive() and not killed and time.time() < deadline:
            pids = [p for p in _held_locks(tmp_path / "dask") if p != os.getpid()]
            if pids:
                os.kill(pids[0], signal.SIGKILL)  # the worker dies while it holds the lock: mid-render
                killed.append(pids[0])
            time.sleep(0.005)
        t.join(timeout=300)
    assert killed, "no worker was caught in the middle of a job"
    done = result["done"]
    assert [s for s, *_ in done] == scenes                    # the command's result is complete
    serial = reference_batch(scenes, (64, 64), base=tmp_path / "serial", progress=False, **opts)
    assert len(serial) == len(done)
    for s in scenes:
        d = store.path_for(s, (64, 64), tmp_path / "dask")
        assert sorted(p.name for p in d.parent.iterdir()) == ["64x64"]   # no partial or leftover directory
        store.load(load_scene(s, (64, 64)).spec, (64, 64), tmp_path / "dask")   # complete, checksum verified
        _same_bits(_channels(tmp_path / "dask", s, (64, 64)), _channels(tmp_path / "serial", s, (64, 64)))


def test_a_rerun_job_returns_the_reference_its_first_attempt_stored(tmp_path, mitsuba_backend):
    job = reference_jobs(["contact"], (24, 24), base=tmp_path, **OPTS)[0]
    first = render_reference_job(job)
    again = render_reference_job(job)               # what the scheduler does after the worker died
    assert again[3] == first[3] and again[2] == first[2]
    with pytest.raises(ReferenceError_, match="already exists"):      # another command's job is refused
        reference_jobs(["contact"], (24, 24), base=tmp_path, **OPTS)


@pytest.mark.parametrize("argv, code, words", [
    (["reference", "contact", "--workers", "0"], 2, "--workers 0"),
    (["reference", "contact", "--scheduler", "http://localhost:8786"], 2, "not a Dask scheduler address"),
    (["reference", "contact", "--workers", "2", "--scheduler", "tcp://x:1"], 2, "give one"),
    (["reference", "contact", "--all"], 2, "--all and scene names"),
    (["reference"], 2, "no scene given"),
])
def test_bad_options_exit_2(argv, code, words, capsys, mitsuba_backend):
    assert cli.main(argv) == code
    assert words in capsys.readouterr().err


def test_an_unreachable_scheduler_exits_3_naming_it(monkeypatch, capsys, mitsuba_backend):
    monkeypatch.setattr(ex_mod, "CONNECT_TIMEOUT_S", 2)
    assert cli.main(["reference", "contact", "--scheduler", "tcp://127.0.0.1:9"]) == 3
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err


def test_the_scheduler_comes_from_the_environment(monkeypatch, capsys, mitsuba_backend):
    monkeypatch.setattr(ex_mod, "CONNECT_TIMEOUT_S", 2)
    monkeypatch.setenv(ex_mod.SCHEDULER_ENV, "tcp://127.0.0.1:9")
    assert cli.main(["reference", "contact", "-r", "8x8"]) == 3
    assert "tcp://127.0.0.1:9" in capsys.readouterr().err


def test_threads_per_worker_share_the_cores():
    assert ex_mod.threads_per_worker(2, cores=2) == 1
    assert ex_mod.threads_per_worker(4, cores=16) == 4
    assert ex_mod.threads_per_worker(3, cores=16) == 5
