"""Fault injection on the reference store: a save killed (SIGKILL) at each of its steps, two
writers at once, and damaged store files. What must hold: the old or the new reference is always
in place and the next reader cleans up; one writer per reference, the loser exits 2 naming the
winner; every damaged file is an exit 2 naming the file and the fix, never a traceback."""

import contextlib
import hashlib
import io
import re
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from shadowlab import cli, pipeline
from shadowlab.errors import ReferenceError_
from shadowlab.io.exr import read_exr, write_exr
from shadowlab.reference import store
from shadowlab.scene import load_spec

ROOT = Path(__file__).resolve().parents[1]
RES = "16x16"

# A writer in its own process: saves the reference of SCENE read from SRC into BASE (V halved, seed 99),
# with store._checkpoint replaced by ACTION at POINT: "kill" (SIGKILL itself), "pause" (touch
# READY, wait for GO), "sleep" (widen a race window). Exit 2 with the message on a ReferenceError_.
WRITER = r"""
import os, signal, sys, time
from pathlib import Path
from shadowlab.errors import ReferenceError_
from shadowlab.reference import store
from shadowlab.scene import load_spec
scene, src, base, point, action, mode, force, sync = sys.argv[1:9]
if mode == "fallback":
    store._exchange = lambda a, b: False
def checkpoint(p):
    if p != point:
        return
    if action == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if action == "pause":
        Path(sync + ".ready").touch()
        while not Path(sync + ".go").exists():
            time.sleep(0.01)
    if action == "sleep":
        time.sleep(0.5)
store._checkpoint = checkpoint
spec = load_spec(scene)
truth, meta = store.load(spec, base=Path(src))
for lt in truth.lights.values():
    lt.V = lt.V * 0.5
meta.update(seed=99, writer=os.getpid())
try:
    store.save(truth, meta, store.path_for(spec.name, spec.camera.resolution, Path(base)), force=force == "1")
except ReferenceError_ as e:
    print(f"error: {e}", file=sys.stderr)
    sys.exit(2)
"""


def _digest(d: Path) -> dict:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def made(tmp_path_factory, mitsuba_backend):
    """A 16×16 reference rendered by `shadowlab reference` into a store that does not exist yet,
    with a target it cannot meet in 8 rounds: (scene file, store, stderr of the run)."""
    d = tmp_path_factory.mktemp("faults")
    text = (ROOT / "scenes" / "contact.toml").read_text().replace("resolution = [128, 128]", "resolution = [16, 16]")
    scene = d / "tiny.toml"
    scene.write_text(text.replace('name = "contact"', 'name = "tiny"'))
    base = d / "refs"
    err = io.StringIO()
    with contextlib.redirect_stderr(err), _env(store.ROOT_ENV, str(base)):
        rc = cli.main(["reference", str(scene), "--max-rounds", "8", "--target-se", "0.002", "--spp", "4"])
    assert rc == 0, err.getvalue()
    return scene, base, err.getvalue()


@contextlib.contextmanager
def _env(key, value):
    old = os.environ.get(key)
    os.environ[key] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(key)
        else:
            os.environ[key] = old


@pytest.fixture
def ref(made, tmp_path):
    """A fresh copy of the made store: (scene, base, reference directory)."""
    scene, base0, _ = made
    base = tmp_path / "refs"
    shutil.copytree(base0, base)
    return scene, base, base / "tiny" / RES


def _writer(scene, base, point="none", action="none", mode="exchange", force=True, sync="", wait=True, src=None):
    args = [sys.executable, "-c", WRITER, str(scene), str(src or base), str(base), point, action, mode,
            "1" if force else "0", str(sync)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    p = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if wait:
        p.communicate(timeout=120)
    return p


def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.parent.iterdir() if p.name != d.name)


# ------------------------------------------------------------------------- killed saves
@pytest.mark.parametrize("mode, point", [
    ("exchange", "tmp-created"), ("exchange", "exr-written"), ("exchange", "meta-written"),
    ("exchange", "exchanged"), ("fallback", "old-moved"), ("fallback", "new-placed"), ("exchange", "done"),
])
def test_sigkill_at_any_step_of_a_save_leaves_old_or_new_and_the_next_read_cleans_up(ref, mode, point):
    scene, base, d = ref
    old = _digest(d)
    p = _writer(scene, base, point, "kill", mode)
    assert p.returncode == -signal.SIGKILL, p.stderr  # the save reached the point and died there
    truth, meta = store.load(load_spec(scene), base=base)  # recovers, then verifies the checksum
    assert _leftovers(d) == []
    now = _digest(d)
    if point in ("tmp-created", "exr-written", "meta-written", "old-moved"):
        assert now == old and meta["seed"] == 0
    else:
        assert now != old and meta["seed"] == 99 and meta["writer"] == p.pid
    assert [r["resolution"] for r in store.list_references(base)] == [RES]


def test_leftovers_are_not_listed_and_a_killed_swap_is_restored_by_the_next_writer(ref):
    scene, base, d = ref
    old = _digest(d)
    p = _writer(scene, base, "old-moved", "kill", "fallback")
    assert p.returncode == -signal.SIGKILL
    left = _leftovers(d)
    assert not d.exists() and f".{RES}.old-{p.pid}" in left and any(n.startswith(f".{RES}.tmp-{p.pid}-") for n in left)
    assert [r["path"] for r in store.list_references(base)] == []  # leftovers are no references
    # the next writer (no --force) restores the old reference first, then refuses to replace it
    with pytest.raises(ReferenceError_, match="already exists"):
        with store.writing(d):
            pass
    assert _digest(d) == old and _leftovers(d) == []


def test_an_interrupt_between_the_renames_puts_the_old_reference_back(ref, monkeypatch):
    scene, base, d = ref
    old = _digest(d)
    truth, meta = store.load(load_spec(scene), base=base)

    def stop(point):
        if point == "old-moved":
            raise KeyboardInterrupt

    monkeypatch.setattr(store, "_exchange", lambda a, b: False)
    monkeypatch.setattr(store, "_checkpoint", stop)
    with pytest.raises(KeyboardInterrupt):
        store.save(truth, dict(meta), d, force=True)
    assert _digest(d) == old and _leftovers(d) == []


# --------------------------------------------------------------------- concurrent writers
def test_a_second_writer_exits_2_naming_the_first_and_readers_wait_out_its_swap(ref, tmp_path):
    scene, base, d = ref
    old = _digest(d)
    sync = tmp_path / "sync"
    a = _writer(scene, base, "old-moved", "pause", "fallback", sync=sync, wait=False)  # a --force save, mid-swap
    try:
        t0 = time.monotonic()
        while not Path(f"{sync}.ready").exists():
            assert a.poll() is None and time.monotonic() - t0 < 60, a.stderr and a.stderr.read()
            time.sleep(0.02)
        assert not d.exists()  # the worst instant: the old reference is under .old-PID
        # a no-force `shadowlab reference` now: exit 2 naming the writer, nothing touched
        err = io.StringIO()
        with contextlib.redirect_stderr(err), _env(store.ROOT_ENV, str(base)):
            rc = cli.main(["reference", str(scene), "--max-rounds", "4"])
        msg = err.getvalue()
        assert rc == 2 and f"pid {a.pid} on host {socket.gethostname()}" in msg and "Traceback" not in msg, msg
        assert f".{RES}.old-{a.pid}" in _leftovers(d)  # not cleaned up under a live writer
        # a reader waits for the swap to finish, then reads the new reference
        threading.Timer(0.3, lambda: Path(f"{sync}.go").touch()).start()
        truth, meta = store.load(load_spec(scene), base=base)
        assert meta["writer"] == a.pid
    finally:
        Path(f"{sync}.go").touch()
        a.communicate(timeout=60)
    assert a.returncode == 0, a.stderr
    assert _digest(d) != old and _leftovers(d) == []


def test_two_writers_creating_one_reference_one_wins_the_other_exits_2(ref, tmp_path):
    scene, base, d = ref
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    # both read the made reference and race to create it, without --force, in an empty store;
    # each sleeps inside its save, so the second arrives while the first holds the lock or after it
    ws = [_writer(scene, fresh, "tmp-created", "sleep", force=False, wait=False, src=base) for _ in range(2)]
    errs = [w.communicate(timeout=120)[1] for w in ws]
    assert sorted(w.returncode for w in ws) == [0, 2], errs
    win, lose = sorted(range(2), key=lambda i: ws[i].returncode)
    assert (f"being written by another process (pid {ws[win].pid} on host" in errs[lose]
            or "already exists" in errs[lose]), errs[lose]
    stored = json.loads((fresh / "tiny" / RES / "meta.json").read_text())
    assert stored["writer"] == ws[win].pid
    assert _leftovers(fresh / "tiny" / RES) == []


# ------------------------------------------------------------------------ damaged files
def _fix_checksum(d: Path):
    m = json.loads((d / "meta.json").read_text())
    m["truth_sha256"] = hashlib.sha256((d / "truth.exr").read_bytes()).hexdigest()
    (d / "meta.json").write_text(json.dumps(m))


def _cli(base, *args):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), _env(store.ROOT_ENV, str(base)):
        rc = cli.main(list(args))
    return rc, err.getvalue()


def test_an_edited_truth_exr_fails_its_checksum(ref):
    scene, base, d = ref
    ch = read_exr(d / "truth.exr")
    ch["V.key"] = np.clip(ch["V.key"] + 0.1, 0, 1)
    write_exr(d / "truth.exr", ch)  # still a valid EXR
    rc, err = _cli(base, "compare", str(scene), "--techniques", "hard", "--out", str(d.parent.parent.parent / "rep"))
    assert rc == 2 and "does not match the checksum" in err and str(d / "truth.exr") in err and "--force" in err, err
    assert "Traceback" not in err
    assert any("checksum mismatch" in s for s in store.list_references(base)[0]["status"])


@pytest.mark.parametrize("damage, msg", [
    (lambda ch: ch.pop("V.key.se"), "has no channel V.key.se"),
    (lambda ch: ch.pop("depth"), "has no channel depth"),
    (lambda ch: [ch.__setitem__(k, v[:8, :12]) for k, v in list(ch.items())], "is 12x8, not 16x16"),
])
def test_a_truth_exr_missing_a_channel_or_of_the_wrong_size_exits_2(ref, damage, msg):
    scene, base, d = ref
    ch = read_exr(d / "truth.exr")
    damage(ch)
    write_exr(d / "truth.exr", ch)
    _fix_checksum(d)
    with pytest.raises(ReferenceError_, match=msg) as e:
        store.load(load_spec(scene), base=base)
    assert "--force" in str(e.value)
    rc, err = _cli(base, "compare", str(scene), "--techniques", "hard", "--out", str(base.parent / "rep"))
    assert rc == 2 and msg in err and "Traceback" not in err, err


@pytest.mark.parametrize("edit, key", [
    (lambda m: m.pop("scene_hash"), "scene_hash"),
    (lambda m: m.update(max_std_error="0.1"), "max_std_error"),
    (lambda m: m.update(resolution=[16]), "resolution"),
    (lambda m: m.update(seed=1.5), "seed"),
    (lambda m: m.update(supersampling=True), "supersampling"),
    (lambda m: m.pop("samples"), "samples"),
    (lambda m: m["samples"].update(mean_rays_per_pixel={"key": "many"}), "samples.mean_rays_per_pixel"),
    (lambda m: m["samples"].pop("shadow_rays"), "samples.shadow_rays"),
    (lambda m: m.update(truth_sha256=42), "truth_sha256"),
    (lambda m: m.update(target_missed={"pixels": 3, "worst_se": "x"}), "target_missed"),
    (lambda m: m.setdefault("stats", {}).update(strata="x"), "stats.strata"),
    (lambda m: m["samples"].update(max_rounds="64"), "samples.max_rounds"),
])
def test_meta_json_keys_missing_or_of_the_wrong_type_exit_2(ref, edit, key):
    scene, base, d = ref
    m = json.loads((d / "meta.json").read_text())
    edit(m)
    (d / "meta.json").write_text(json.dumps(m))
    with pytest.raises(ReferenceError_, match=f"key {key} must be") as e:
        store.load(load_spec(scene), base=base)
    assert str(d / "meta.json") in str(e.value) and "--force" in str(e.value)
    assert any("damaged meta.json" in s for s in store.list_references(base)[0]["status"])


def test_malformed_meta_json_exits_2(ref):
    scene, base, d = ref
    (d / "meta.json").write_text("[1, 2")
    rc, err = _cli(base, "compare", str(scene), "--techniques", "hard", "--out", str(base.parent / "rep"))
    assert rc == 2 and "malformed" in err and str(d / "meta.json") in err, err


@pytest.mark.parametrize("gone", ["meta.json", "truth.exr"])
def test_a_deleted_file_is_an_incomplete_reference_not_already_exists(ref, gone):
    scene, base, d = ref
    (d / gone).unlink()
    with pytest.raises(ReferenceError_, match=f"incomplete \\({gone} missing\\)") as e:
        store.load(load_spec(scene), base=base)
    assert f"shadowlab reference {scene} --resolution {RES} --force" in str(e.value)   # the path the user gave
    with pytest.raises(ReferenceError_, match="incomplete") as e:
        pipeline.reference(str(scene), base=base, progress=False, max_rounds=4)
    assert "already exists" not in str(e.value) and "--force" in str(e.value)
    assert store.list_references(base)[0]["status"][0].startswith(f"incomplete: {gone} missing")


def test_a_read_only_store_after_a_full_render_exits_2_and_keeps_the_reference(ref, monkeypatch):
    scene, base, d = ref
    old = _digest(d)
    rendered = []
    real = pipeline.references.render_truth

    def render_then_lock_store(*a, **k):
        out = real(*a, **k)
        rendered.append(1)
        monkeypatch.setattr(store.tempfile, "mkdtemp", lambda **kw: (_ for _ in ()).throw(
            PermissionError(13, "Read-only file system")))
        return out

    monkeypatch.setattr(pipeline.references, "render_truth", render_then_lock_store)
    rc, err = _cli(base, "reference", str(scene), "--force", "--max-rounds", "4", "--spp", "0")
    assert rendered and rc == 3 and "cannot write to the reference store" in err and "Read-only" in err, err
    assert "Traceback" not in err and _digest(d) == old and _leftovers(d) == []


# ---------------------------------------------------------------- the store as a whole
def test_a_missing_store_is_refused_except_by_reference(ref, tmp_path, monkeypatch):
    scene, base, d = ref
    typo = tmp_path / "refz"
    for args in (["references"], ["compare", str(scene), "--techniques", "hard", "--out", str(tmp_path / "rep")]):
        rc, err = _cli(typo, *args)
        assert rc == 2 and f"{store.ROOT_ENV}={typo} is not a directory" in err and "shadowlab reference" in err, err
        assert not typo.exists()
    monkeypatch.setenv(store.ROOT_ENV, str(typo))
    assert store.path_for("tiny", (16, 16), create=True) == typo / "tiny" / RES


def test_compare_does_not_render_a_missing_resolution(ref, tmp_path):
    scene, base, d = ref
    with pytest.raises(ReferenceError_, match=re.escape(f"shadowlab reference {scene} --resolution 8x8`")) as e:
        pipeline.compare(str(scene), ["hard"], resolution=(8, 8), base=base, progress=False)
    assert "stored resolutions: 16x16" in str(e.value)
    assert sorted(p.name for p in (base / "tiny").iterdir()) == [RES]


def test_references_marks_stale_and_checks_committed_checksums(ref):
    scene, base, d = ref
    (listed,) = store.list_references(base)
    assert listed["status"] == [s for s in listed["status"] if "above the target" in s]  # fresh
    scene.write_text(scene.read_text().replace("power = 300", "power = 301"))
    try:
        rc, err = _cli(base, "references")
        (listed,) = store.list_references(base)
    finally:
        scene.write_text(scene.read_text().replace("power = 301", "power = 300"))
    assert rc == 0 and any(s.startswith("stale: scene 'tiny' changed") for s in listed["status"])
    for r in store.list_references(ROOT / "references"):  # committed: checksummed and fresh
        assert r["meta"].get("truth_sha256") and not [s for s in r["status"] if "above" not in s], r


def test_a_missed_error_target_is_warned_and_recorded(made):
    scene, base, err = made
    meta = json.loads((base / "tiny" / RES / "meta.json").read_text())
    tm = meta["target_missed"]
    truth, _ = store.load(load_spec(scene), base=base)
    se = truth.lights["key"].V_se[truth.mask]
    assert tm["pixels"] == int((se > 0.002).sum()) > 0 and tm["max_rounds"] == 8
    assert tm["worst_se"] == pytest.approx(float(se.max()))
    x, y, s = tm["lights"]["key"]["worst"][0]
    assert s == pytest.approx(tm["worst_se"]) and truth.lights["key"].V_se[y, x] == pytest.approx(s)
    assert f"warning: {tm['pixels']} pixels" in err and "--max-rounds 32" in err
    assert f"{store.ROOT_ENV}={base} did not exist; created a new reference store" in err
    assert meta["scene_file"] == str(scene.resolve())
