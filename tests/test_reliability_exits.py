"""Exit codes of the machine's and the path's errors (issue 27, "Wrong exit codes" and "Tracebacks").

docs/cli.md's table: 2 input, 3 environment, 4 internal (a bug), 141 a reader that went away.
Each case runs where the user meets it, a real ``shadowlab`` process where it matters:

* a full disk under the store is exit 3 naming the disk (a real tmpfs of 24 KiB, mounted in a
  private mount namespace with ``unshare``), and nothing is left in the store;
* ``--out`` on a mount point of its own (a real tmpfs) is written, not a cross-device rename (4);
* ``--out /proc/...`` is exit 2 and ``/sys/...`` exit 3, before any work;
* ``shadowlab techniques | head -1`` (and ``scenes``) exits 141, silently, never 1 ("gate failed");
* a scene named like one of the store's own files (``gates.toml``) is exit 2 naming the clash;
* Ctrl-C while the command is still importing prints one line, exit 130, no traceback.
"""

import errno
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from shadowlab import cli, pipeline
from shadowlab.io import outdir

ROOT = Path(__file__).resolve().parents[1]


def _scene(d: Path, name="tiny", res=16) -> Path:
    text = (ROOT / "scenes" / "contact.toml").read_text()
    text = text.replace("resolution = [128, 128]", f"resolution = [{res}, {res}]").replace(
        'name = "contact"', f'name = "{name}"')
    p = d / f"{name.replace('.', '_')}.toml"
    p.write_text(text)
    return p


def _env(**extra):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    env.pop(cli.DEBUG_ENV, None)
    env.update({k: str(v) for k, v in extra.items()})
    return env


SHADOWLAB = [sys.executable, "-m", "shadowlab.cli"]


def _can_mount() -> bool:
    """Whether this machine lets us mount a tmpfs in a private user and mount namespace."""
    if shutil.which("unshare") is None:
        return False
    r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                        "mount -t tmpfs -o size=4k tmpfs /mnt && echo ok"], capture_output=True, text=True)
    return r.stdout.strip() == "ok"


needs_mount = pytest.mark.skipif(not _can_mount(), reason="no unshare/tmpfs mount here (user namespaces off)")


def _in_namespace(mounts: dict, args, env) -> subprocess.CompletedProcess:
    """Run ``shadowlab ARGS`` with tmpfs mounts {directory: size} visible to it only."""
    script = "".join(f"mount -t tmpfs -o size={size} tmpfs '{d}' && " for d, size in mounts.items())
    cmd = " ".join(f"'{a}'" for a in (*SHADOWLAB, *map(str, args)))
    return subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script + "exec " + cmd],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)


def _one_line(err: str) -> str:
    lines = [l for l in err.splitlines() if l.strip() and not l.startswith(("warning:", "note:"))]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------ the machine's errors
@needs_mount
def test_a_full_disk_under_the_store_exits_3_and_leaves_nothing(tmp_path):
    scene = _scene(tmp_path, res=64)
    disk = tmp_path / "disk"
    disk.mkdir()
    r = _in_namespace({disk: "24k"}, ["reference", scene, "--max-rounds", "2", "--spp", "0"],
                      _env(SHADOWLAB_REFERENCES=disk / "refs"))
    assert r.returncode == 3, (r.stdout, r.stderr)
    line = _one_line(r.stderr)
    assert "No space left on device" in line and "free disk space" in line and "internal error" not in line, line
    assert "reference written" not in r.stdout


@needs_mount
def test_out_on_a_mount_point_of_its_own_is_written(tmp_path):
    scene = _scene(tmp_path)
    base = tmp_path / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=2, spp=0)
    vol = tmp_path / "volume"           # a container volume: --out is the mount point itself
    vol.mkdir()
    r = _in_namespace({vol: "16m"}, ["compare", scene, "-t", "hard", "--out", vol], _env(SHADOWLAB_REFERENCES=base))
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert f"report: {vol / 'index.html'}" in r.stdout


def test_out_across_devices_in_process(tmp_path, capsys, monkeypatch):
    """The same without mounts, where ``os.rename`` into OUT from outside it fails as across two
    devices would: the report is still written (its temporary directory lies inside OUT), and
    OUT's own files stay."""
    scene = _scene(tmp_path)
    base = tmp_path / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=2, spp=0)
    vol = tmp_path / "volume"
    vol.mkdir()
    rename, replace = os.rename, os.replace

    def across(fn):
        def f(a, b, *args, **kw):
            if outdir.inside(b, vol) and not outdir.inside(a, vol):
                raise OSError(errno.EXDEV, os.strerror(errno.EXDEV), str(a), None, str(b))
            return fn(a, b, *args, **kw)
        return f

    monkeypatch.setattr(os, "rename", across(rename))
    monkeypatch.setattr(os, "replace", across(replace))
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    for _ in range(2):   # new, then a report of ours replaced
        rc = cli.main(["compare", str(scene), "-t", "hard", "--out", str(vol)])
        out, err = capsys.readouterr()
        assert rc == 0, err
    assert (vol / "index.html").is_file() and (vol / outdir.MARKER).is_file()
    assert [p.name for p in vol.iterdir() if p.name.startswith(".volume.")] == []   # no temporary left


@pytest.mark.parametrize("out, code, words", [
    ("/proc/shadowlab-report", 2, "No such file or directory"),
    ("/sys/shadowlab-report", 3, "Operation not permitted"),
])
def test_out_where_nothing_can_be_created_is_refused_before_any_work(out, code, words, tmp_path, capsys):
    scene = _scene(tmp_path, name="unrendered")      # no reference: the --out error must come first
    rc = cli.main(["compare", str(scene), "-t", "hard", "--out", out])
    err = capsys.readouterr().err
    assert rc == code, err
    assert f"cannot create --out {out}: {words}" in _one_line(err)


def test_save_preset_where_nothing_can_be_created_is_refused_before_fitting(tmp_path, capsys):
    scene = _scene(tmp_path, name="unrendered")
    rc = cli.main(["fit", str(scene), "-t", "pcss", "--save-preset", "/proc/p.toml", "--out", str(tmp_path / "f")])
    assert rc == 2 and "cannot create --save-preset /proc/p.toml" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "f").exists()


def test_write_errors_are_classified_once():
    """The one classification (io.outdir.write_error) the writers and the CLI share."""
    E = outdir.write_error
    assert E("x", OSError(errno.ENOSPC, "No space left on device")).exit_code == 3
    assert E("x", OSError(errno.EDQUOT, "Disk quota exceeded")).exit_code == 3
    assert E("x", OSError(errno.EXDEV, "Invalid cross-device link")).exit_code == 3
    assert E("x", OSError(errno.ENOENT, "No such file or directory")).exit_code == 2
    assert E("x", RuntimeError('Failed to write "x.exr". No space left on device.')).exit_code == 3
    assert E("x", RuntimeError("a bug")) is None and E("x", ValueError("no")) is None


# ------------------------------------------------------------------------------ pipes and signals
@pytest.mark.parametrize("command", ["techniques", "scenes"])
def test_a_reader_that_goes_away_is_exit_141_silently(command):
    """``shadowlab techniques | head -1``: the reader closes the pipe; exit 141 (128 + SIGPIPE, as
    a program killed by SIGPIPE), nothing on stderr; never 1, which means a gate failed."""
    p = subprocess.Popen([*SHADOWLAB, command], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=ROOT)
    p.stdout.close()                               # closed before the first line is written
    err = p.stderr.read().decode()
    p.wait(timeout=120)
    assert p.returncode == 141 == cli.PIPE_CLOSED, err
    assert err == ""
    r = subprocess.run(f"{' '.join(SHADOWLAB)} {command} | head -1", shell=True, capture_output=True, text=True,
                       env=_env(), cwd=ROOT, executable="/bin/bash")
    assert r.returncode == 0 and len(r.stdout.splitlines()) == 1 and r.stderr == "", r.stderr


# an import hook that announces the import of typer (the bulk of start-up) and holds it for 30 s
_SLOW_TYPER = '''
import importlib.abc, os, sys, time
class Slow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "typer":
            sys.meta_path.remove(self)
            open(os.environ["SHADOWLAB_TEST_READY"], "w").close()
            time.sleep(30)
        return None
sys.meta_path.insert(0, Slow())
'''


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_start_up_imports_is_one_line(sig, tmp_path):
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_SLOW_TYPER)
    ready = tmp_path / "ready"
    env = _env(SHADOWLAB_TEST_READY=ready)
    env["PYTHONPATH"] = os.pathsep.join((str(hook), env["PYTHONPATH"]))
    p = subprocess.Popen([*SHADOWLAB, "scenes", "--names"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env, cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert p.poll() is None and time.monotonic() < deadline, p.communicate()
            time.sleep(0.02)
        p.send_signal(sig)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 128 + sig, err
    assert _one_line(err) == f"interrupted by {signal.Signals(sig).name} while starting; nothing was done"


# ------------------------------------------------------------------------------ input errors
def test_a_scene_named_like_a_store_file_is_exit_2_naming_the_clash(tmp_path, capsys, monkeypatch):
    base = tmp_path / "refs"
    base.mkdir()
    (base / "gates.toml").write_text("version = 1\n")
    scene = _scene(tmp_path, name="gates.toml")
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    rc = cli.main(["reference", str(scene), "--max-rounds", "2", "--spp", "0"])
    line = _one_line(capsys.readouterr().err)
    assert rc == 2 and "clashes with the file" in line and str(base / "gates.toml") in line, line
    assert "chmod" not in line and (base / "gates.toml").read_text() == "version = 1\n"


@needs_mount
def test_a_report_on_a_full_disk_exits_3(tmp_path):
    scene = _scene(tmp_path)
    base = tmp_path / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=2, spp=0)
    disk = tmp_path / "disk"
    disk.mkdir()
    r = _in_namespace({disk: "16k"}, ["compare", scene, "-t", "hard", "--out", disk / "report"],
                      _env(SHADOWLAB_REFERENCES=base))
    assert r.returncode == 3, (r.stdout, r.stderr)
    line = _one_line(r.stderr)
    assert "No space left on device" in line and "free disk space" in line, line
