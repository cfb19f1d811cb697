"""The reference store: ``references/<scene>/<W>x<H>/truth.exr`` + ``meta.json``.

A scene with a camera path (``[camera.path]``) stores each frame's truth separately, in
``references/<scene>/<W>x<H>-f<NNNN>/`` (frame index, at least four digits: ``96x64-f0003``), beside
and under the same rules as any other reference (its own lock ``.locks/<scene>.<W>x<H>-f<NNNN>.lock``,
atomic exchange, checksum, stale scene hash). A scene without a path keeps ``<W>x<H>/``.

EXR channels (one float32 image each): ``V.<light>``, ``V.<light>.se`` (visibility ratio and
its standard error), ``A.<light>``, ``A.<light>.se`` (plain visible fraction), ``N.<light>``
(shadow rays per pixel), ``B.<light>`` (rule-of-three bound of unanimous pixels),
``U.<light>.R|G|B`` (unshadowed radiance), ``shaded.R|G|B`` and ``shaded.var.R|G|B`` (Σ U·V),
``mitsuba.R|G|B`` and ``mitsuba.var.R|G|B`` (mi.render, direct integrator), ``mask``, ``depth``.

Safety rules (each one tested in tests/test_store_faults.py):

* **One writer per reference.** Writes take an exclusive ``fcntl`` lock on
  ``<store>/.locks/<scene>.<W>x<H>.lock`` for the whole render and save; the lock file names its
  holder (pid, host, time, command). A second writer fails at once (:class:`ReferenceError_`,
  exit 2) naming the holder, so create-if-absent is atomic and a no-force run never meets a
  half-done ``--force`` swap.
* **Never no reference.** A new reference is built in a temporary sibling directory
  ``.<W>x<H>.tmp-*`` and exchanged with the old one in one atomic ``renameat2(RENAME_EXCHANGE)``
  (Linux); where the file system lacks it, the old directory is first renamed to
  ``.<W>x<H>.old-<pid>`` and the new one renamed into place. A process killed at any instant
  leaves the old reference or the new one in place, or (between the two renames of the fallback)
  the old one under ``.old-<pid>``: the next writer, and every reader, restores it and deletes
  the other leftovers (:func:`recover`). Leftovers are never listed as references.
* **Integrity.** ``meta.json`` records ``truth_sha256``, the SHA-256 of ``truth.exr``'s bytes
  (``sha256sum truth.exr``); every read verifies it. References written before the checksum
  existed have no such key and are read unverified (the committed ones have it).
* **Validation.** A reader checks meta.json's keys and types, and that truth.exr holds every
  channel at the stored resolution; a missing file, key or channel is an error that names it and
  the fix (re-render with ``--force``), never a traceback. A reference whose scene hash differs
  from the scene file is reported, never used.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import hashlib
import json
import os
import re
import shlex
import shutil
import socket
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import EnvironmentProblem, ReferenceError_, ShadowlabError
from ..io.exr import read_exr, write_exr
from ..io.jsonio import read_json, write_json_atomic
from ..io.outdir import error_number, write_error
from ..scene.spec import builtin_dir, load_spec, resolve
from . import location
from .location import ROOT_ENV
from . import vacuous
from .truth import LightTruth, Truth

LOCK_DIR = ".locks"
CHECKSUM_KEY = "truth_sha256"
FILES = ("truth.exr", "meta.json")
_RES_DIR = re.compile(r"^([0-9]+)x([0-9]+)(?:-f([0-9]+))?$")
_HELD: dict[str, int] = {}   # lock file path -> fd, locks this process holds (re-entrant)


def _checkpoint(point: str) -> None:
    """Called at each step of :func:`save`; tests replace it to interrupt a save right there.

    Points, in order: ``tmp-created``, ``exr-written``, ``meta-written``, then either
    ``exchanged`` (the atomic swap) or ``old-moved`` and ``new-placed`` (the two-rename fallback),
    then ``done``."""


def root(create: bool = False) -> Path:
    """Where references live: ``--references``, ``$SHADOWLAB_REFERENCES``, a project's
    ``shadowlab.toml`` / ``[tool.shadowlab]``, else ``./references`` (:mod:`.location`); never
    inside the installed package.

    A store given by the option or the variable that does not exist is refused (a misspelt path
    would otherwise start an empty store) unless ``create`` (``shadowlab reference`` creates a new
    store)."""
    loc = location.locate()
    location.check_outside_package(loc.path, loc.source)
    if loc.source in ("option", "environment") and not create and not loc.path.is_dir():
        given = f"--references {loc.path}" if loc.source == "option" else f"{ROOT_ENV}={loc.path}"
        undo = "leave the option out" if loc.source == "option" else f"unset {ROOT_ENV}"
        raise ReferenceError_(f"{given} is not a directory: no reference store there; check the spelling, or "
                              f"{undo} to use the project's store. `shadowlab reference SCENE` creates a new store "
                              "at that path")
    return loc.path


def builtin_copy(scene_spec, resolution, frame: int | None = None) -> Path | None:
    """The committed reference of a built-in scene (package data, read-only:
    :func:`.location.builtin_references`), None for another scene or where none is committed."""
    src = str(getattr(scene_spec, "source", "") or "")
    mine = builtin_dir() / f"{scene_spec.name}.toml"
    if not src or not Path(src).exists() or not mine.exists() or Path(src).resolve() != mine.resolve():
        return None
    d = location.builtin_references() / scene_spec.name / dir_name(resolution, frame)
    return d if d.is_dir() else None


def dir_name(resolution, frame: int | None = None) -> str:
    """``<W>x<H>``, or ``<W>x<H>-f<NNNN>`` for frame ``frame`` of a camera path.

    >>> dir_name((96, 64)), dir_name((96, 64), 3)
    ('96x64', '96x64-f0003')
    """
    W, H = resolution
    return f"{W}x{H}" + ("" if frame is None else f"-f{int(frame):04d}")


def parse_dir_name(name: str):
    """((W, H), frame or None) of a reference directory's name, or None if it is not one."""
    m = _RES_DIR.match(name)
    if not m:
        return None
    return (int(m[1]), int(m[2])), (None if m[3] is None else int(m[3]))


def path_for(scene_name: str, resolution, base: Path | None = None, create: bool = False,
             frame: int | None = None) -> Path:
    """The directory of a reference; ``frame``: the camera path frame (``SceneSpec.frame``)."""
    return Path(base or root(create)) / scene_name / dir_name(resolution, frame)


def reference_command(scene_name: str, resolution, frame: int | None = None) -> str:
    """The command that renders this reference (into the store ``--references`` chose, if any)."""
    chosen = location.chosen()
    return (f"shadowlab reference {scene_name} --resolution {resolution[0]}x{resolution[1]}"
            + ("" if frame is None else f" --frame {frame}")
            + ("" if chosen is None else f" --references {shlex.quote(str(chosen))}"))


# ------------------------------------------------------------------------------------- locking
def lock_path(dest: Path) -> Path:
    """The lock file of the reference directory ``dest`` (``<store>/.locks/<scene>.<WxH>.lock``)."""
    dest = Path(dest)
    return dest.parent.parent / LOCK_DIR / f"{dest.parent.name}.{dest.name}.lock"


def _holder_text(fd: int) -> str:
    """Who holds a lock, from the lock file (written right after the holder took it)."""
    for _ in range(40):
        try:
            raw = os.pread(fd, 4096, 0)
        except OSError:
            raw = b""
        if raw.strip():
            try:
                h = json.loads(raw)
                return (f"pid {h.get('pid')} on host {h.get('host')}, since {h.get('time')}"
                        + (f": `{h['command']}`" if h.get("command") else ""))
            except (ValueError, AttributeError):
                pass
        time.sleep(0.025)
    return "a process that has not yet written its name into the lock"


def _unwritable(where: Path, exc: OSError) -> ShadowlabError:
    """A store the machine will not let us write: exit 3 with the fix for its errno (permissions:
    chmod; a full disk: free space); another errno is the path's (outdir.write_error)."""
    code = error_number(exc)
    if code in (errno.EACCES, errno.EPERM, errno.EROFS):
        return EnvironmentProblem(f"cannot write to the reference store at {where}: {exc.strerror or exc}; make it "
                                  f"writable (e.g. `chmod -R u+w {where}`) or point {ROOT_ENV} at a writable "
                                  "directory")
    return write_error(where, exc) or EnvironmentProblem(
        f"cannot write to the reference store at {where}: {exc.strerror or exc}; point {ROOT_ENV} at another directory")


def check_name(dest: Path) -> None:
    """Refuse (exit 2) a reference whose scene directory would be one of the store's own files
    (``gates.toml``, a README): a scene ``name`` that clashes with an entry that is not a folder."""
    scene_dir = Path(dest).parent
    if os.path.lexists(scene_dir) and not scene_dir.is_dir():
        raise ReferenceError_(f"scene name {scene_dir.name!r} clashes with the file {scene_dir} of the reference "
                              f"store, where the scene's references would go; give the scene another `name` (its "
                              f"references live in {scene_dir.parent}/NAME/)")


@contextmanager
def locked(dest: Path, role: str = "write"):
    """Hold the exclusive lock of reference directory ``dest`` (re-entrant within a process).

    Raises :class:`ReferenceError_` naming the holder if another process has it, or naming the
    store if the lock file cannot be created (a read-only store)."""
    lp = lock_path(dest)
    key = str(lp.resolve())
    if key in _HELD:
        yield
        return
    try:
        lp.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise _unwritable(lp.parent.parent, e) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ReferenceError_(f"the reference at {dest} is being written by another process ({_holder_text(fd)}); "
                                  f"wait until it has finished and run again (lock file {lp})") from None
        prog = "shadowlab" if sys.argv[0].endswith(("shadowlab", "cli.py")) else os.path.basename(sys.argv[0])
        info = {"pid": os.getpid(), "host": socket.gethostname(), "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "role": role, "command": " ".join([prog, *sys.argv[1:]])[:300]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        _HELD[key] = fd
        try:
            yield
        finally:
            del _HELD[key]
            try:
                os.ftruncate(fd, 0)
            except OSError:
                pass
    finally:
        os.close(fd)  # releases the flock


# ------------------------------------------------------------------------------- crash recovery
def _leftovers(dest: Path) -> list[Path]:
    if not dest.parent.is_dir():
        return []
    pre = f".{dest.name}."
    return sorted(p for p in dest.parent.iterdir()
                  if p.name.startswith(pre) and (".tmp-" in p.name or ".old-" in p.name) and p.is_dir())


def _complete(d: Path) -> bool:
    return all((d / f).is_file() for f in FILES)


def _recover_locked(dest: Path) -> str | None:
    """With the lock held: restore ``dest`` from an ``.old-*`` directory if a save was killed
    between its two renames, then delete every leftover. Returns a note when it restored."""
    note = None
    left = _leftovers(dest)
    if not dest.exists():
        olds = [p for p in left if ".old-" in p.name and _complete(p)]
        if olds:
            src = max(olds, key=lambda p: p.stat().st_mtime)
            os.rename(src, dest)
            left.remove(src)
            note = f"restored the reference at {dest} from {src.name} (left by an interrupted save)"
    for p in left:
        shutil.rmtree(p, ignore_errors=True)
    return note


#: seconds a reader waits for a writer that has moved the old reference away to put the new one in place
SWAP_WAIT_S = 30.0


def _await_swap(dest: Path, wait_s: float = SWAP_WAIT_S) -> None:
    """A reader that finds ``dest`` missing while an ``.old-*`` directory of a save in progress
    exists (the fallback's two renames) waits for the new reference instead of reporting none."""
    deadline = time.monotonic() + wait_s
    while not dest.exists() and any(".old-" in p.name for p in _leftovers(dest)) and time.monotonic() < deadline:
        time.sleep(0.02)


def _read_settled(d: Path, cmd: str):
    """:func:`_read`, once more after a swap in progress settles: a reader whose files were moved
    away mid-read (between the fallback's two renames) reads the new reference instead of failing;
    a damaged reference fails the second read as it did the first."""
    try:
        return _read(d, cmd)
    except ShadowlabError:
        _await_swap(d)
        return _read(d, cmd)


def recover(dest: Path, wait_s: float = 5.0) -> str | None:
    """Clean up after an interrupted save of ``dest`` (see the module docstring); a no-op, with
    no lock taken, when nothing is left over. Readers call it: if a writer holds the lock while
    ``dest`` is missing (between the fallback's two renames), wait up to ``wait_s`` for it."""
    dest = Path(dest)
    deadline = time.monotonic() + wait_s
    while _leftovers(dest):
        try:
            with locked(dest, role="recover"):
                return _recover_locked(dest)
        except EnvironmentProblem:
            return None  # a read-only store: nothing can be cleaned; reading still works
        except ReferenceError_ as e:
            if "being written" not in str(e):
                return None
            if dest.exists() or time.monotonic() > deadline:
                return None  # a live writer owns the leftovers
            time.sleep(0.05)
    return None


def _note(text: str | None) -> None:
    if text:
        print(f"note: {text}", file=sys.stderr)


# ---------------------------------------------------------------------------------- writing
def scene_arg(scene_spec) -> str:
    """How the fix texts name a scene: its built-in name, or the path of its file when it is not a
    built-in (``shadowlab reference NAME`` fails for a scene only known by its path)."""
    src = str(getattr(scene_spec, "source", "") or "")
    builtin = builtin_dir() / f"{scene_spec.name}.toml"
    if not src or (Path(src).exists() and Path(src).resolve() == builtin.resolve()):
        return scene_spec.name
    return shlex.quote(src)


def _channels(truth: Truth) -> dict:
    ch = {}
    for name, lt in truth.lights.items():
        ch[f"V.{name}"], ch[f"V.{name}.se"] = lt.V, lt.V_se
        ch[f"A.{name}"], ch[f"A.{name}.se"] = lt.A, lt.A_se
        ch[f"N.{name}"], ch[f"B.{name}"] = lt.samples, lt.bound
        if getattr(lt, "V_rgb", None) is not None:  # coloured shadows (translucent casters): C.<light>.R/G/B
            for c, ax in zip("RGB", range(3)):
                ch[f"C.{name}.{c}"], ch[f"C.{name}.se.{c}"] = lt.V_rgb[..., ax], lt.V_rgb_se[..., ax]
        for c, ax in zip("RGB", range(3)):
            ch[f"U.{name}.{c}"] = truth.U[name][..., ax]
    for c, ax in zip("RGB", range(3)):
        ch[f"shaded.{c}"] = truth.shaded[..., ax]
        ch[f"shaded.var.{c}"] = truth.shaded_var[..., ax]
        if truth.mitsuba is not None:
            ch[f"mitsuba.{c}"] = truth.mitsuba[..., ax]
            ch[f"mitsuba.var.{c}"] = truth.mitsuba_var[..., ax]
    ch["mask"] = truth.mask.astype(np.float32)
    ch["depth"] = truth.view_depth
    return ch


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_writable(dest: Path, force: bool = False, scene_name: str | None = None, resolution=None) -> None:
    """Raise unless a reference may be written at ``dest``: absent, or ``force``. Call with the lock held."""
    dest = Path(dest)
    check_name(dest)
    if not dest.exists() or force:
        return
    parsed = parse_dir_name(dest.name)
    frame = parsed[1] if parsed else None
    cmd = reference_command(scene_name or dest.parent.name, resolution or (parsed[0] if parsed else ("W", "H")), frame)
    missing = [f for f in FILES if not (dest / f).is_file()]
    if missing:
        raise ReferenceError_(f"the reference at {dest} is incomplete ({' and '.join(missing)} missing); "
                              f"replace it with `{cmd} --force`")
    raise ReferenceError_(f"a reference already exists at {dest}; pass --force to replace it (`{cmd} --force`)")


def stored_by_run(dest: Path, run: str) -> dict | None:
    """The meta of the complete reference at ``dest`` if the job run ``run`` stored it (its
    ``"run"`` key), else None. Call with the lock held: a job re-run after its worker died
    recognises its own earlier save this way (:func:`shadowlab.pipeline.render_reference_job`)."""
    dest = Path(dest)
    if not dest.is_dir() or _problem(dest):
        return None
    try:
        meta = read_json(dest / "meta.json")
    except (OSError, ValueError, ShadowlabError):
        return None
    return meta if isinstance(meta, dict) and meta.get("run") == run else None


@contextmanager
def writing(dest: Path, force: bool = False, scene_name: str | None = None, resolution=None):
    """Lock ``dest`` for a render and save: clean up after an interrupted save, then check that
    a reference may be written there (:func:`check_writable`). The lock is held until the block ends."""
    dest = Path(dest)
    with locked(dest):
        _note(_recover_locked(dest))
        check_writable(dest, force, scene_name, resolution)
        yield dest


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False if unsupported."""
    fn = getattr(_LIBC, "renameat2", None) if _LIBC is not None else None
    if fn is None:
        return False
    if fn(-100, os.fsencode(str(a)), -100, os.fsencode(str(b)), 2) == 0:  # AT_FDCWD, RENAME_EXCHANGE
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


try:
    _LIBC = ctypes.CDLL(None, use_errno=True)
except OSError:  # no C library to load: the two-rename fallback
    _LIBC = None


def save(truth: Truth, meta: dict, dest: Path, force: bool = False) -> Path:
    """Write ``truth`` + ``meta`` to ``dest`` (see the module docstring); adds ``truth_sha256`` to ``meta``."""
    dest = Path(dest)
    with writing(dest, force):
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.tmp-{os.getpid()}-", dir=dest.parent))
        except OSError as e:
            raise _unwritable(dest.parent, e) from None
        old = None
        try:
            _checkpoint("tmp-created")
            write_exr(tmp / "truth.exr", _channels(truth))
            _checkpoint("exr-written")
            meta[CHECKSUM_KEY] = sha256_file(tmp / "truth.exr")
            write_json_atomic(tmp / "meta.json", meta)
            _checkpoint("meta-written")
            try:
                os.chmod(tmp, 0o755)
                for f in tmp.iterdir():
                    os.chmod(f, 0o644)
                if dest.exists() and _exchange(tmp, dest):
                    _checkpoint("exchanged")  # tmp now holds the old reference
                else:
                    if dest.exists():
                        old = dest.parent / f".{dest.name}.old-{os.getpid()}"
                        os.rename(dest, old)
                        _checkpoint("old-moved")
                    os.rename(tmp, dest)
                    _checkpoint("new-placed")
            except OSError as e:
                raise _unwritable(dest.parent, e) from None
        except BaseException:
            if old is not None and not dest.exists() and old.exists():
                os.rename(old, dest)  # put the old reference back
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        shutil.rmtree(old if old is not None else tmp, ignore_errors=True)
        _checkpoint("done")
    return dest


# ---------------------------------------------------------------------------------- reading
_NUM = (int, float)


def _is(v, types) -> bool:
    return isinstance(v, types) and not isinstance(v, bool)


def check_meta(meta, where: Path, cmd: str) -> None:
    """Raise :class:`ReferenceError_` if a reference's meta.json lacks a key a reader uses or has
    one of the wrong type; the message names the file, the key and the fix."""
    def bad(key, want):
        got = "missing" if key not in m else f"{type(m[key]).__name__} {m[key]!r}"[:80]
        return ReferenceError_(f"{where}: key {prefix}{key} must be {want}, got {got}; the reference is damaged, "
                               f"re-render it with `{cmd} --force`")

    m, prefix = meta, ""
    if not isinstance(meta, dict):
        raise ReferenceError_(f"{where} holds a JSON {type(meta).__name__}, not an object; re-render the reference "
                              f"with `{cmd} --force`")
    if not _is(m.get("scene_hash"), str):
        raise bad("scene_hash", "a string")
    r = m.get("resolution")
    if not (isinstance(r, list) and len(r) == 2 and all(_is(x, int) and x > 0 for x in r)):
        raise bad("resolution", "[WIDTH, HEIGHT]")
    if not _is(m.get("max_std_error"), _NUM):
        raise bad("max_std_error", "a number")
    for k in ("seed", "supersampling"):
        if k in m and not _is(m[k], int):
            raise bad(k, "an integer")
    if "supersampling" in m and m["supersampling"] < 1:
        raise bad("supersampling", "an integer ≥ 1")
    if CHECKSUM_KEY in m and not (_is(m[CHECKSUM_KEY], str) and re.fullmatch(r"[0-9a-f]{64}", m[CHECKSUM_KEY])):
        raise bad(CHECKSUM_KEY, "a hex SHA-256")
    if "stats" in m and not isinstance(m["stats"], dict):
        raise bad("stats", "an object")
    tm = m.get("target_missed")
    if tm is not None and not (isinstance(tm, dict) and _is(tm.get("pixels"), int) and _is(tm.get("worst_se"), _NUM)
                               and isinstance(tm.get("lights", {}), dict)):
        raise bad("target_missed", "an object {pixels: integer, worst_se: number, lights: {...}}")
    st = m.get("stats") or {}
    m, prefix = st, "stats."
    for k in ("strata", "max_rounds", "seed", "spp_mitsuba"):   # read back by gates' truth candidates
        if k in st and not _is(st[k], int):
            raise bad(k, "an integer")
    for k in ("target_se",):
        if k in st and not _is(st[k], _NUM):
            raise bad(k, "a number")
    m, prefix = meta, ""
    if not isinstance(m.get("samples"), dict):
        raise bad("samples", "an object")
    m, prefix = meta["samples"], "samples."
    if not _is(m.get("shadow_rays"), int):
        raise bad("shadow_rays", "an integer")
    for k, want in (("target_se", _NUM), ("max_rounds", int), ("mitsuba_spp", int)):
        if k in m and not _is(m[k], want):
            raise bad(k, "a number" if want is _NUM else "an integer")
    rpp = m.get("mean_rays_per_pixel")
    if not (isinstance(rpp, dict) and rpp and all(_is(v, _NUM) for v in rpp.values())):
        raise bad("mean_rays_per_pixel", "an object {light: number}")


def _problem(d: Path) -> str | None:
    missing = [f for f in FILES if not (d / f).is_file()]
    return f"{' and '.join(missing)} missing" if missing else None


def _read(d: Path, cmd: str):
    """(meta, channels) of the reference directory ``d``, validated and checksum-verified."""
    for attempt in range(3):
        meta = read_json(d / "meta.json")
        check_meta(meta, d / "meta.json", cmd)
        want = meta.get(CHECKSUM_KEY)
        if want is not None:
            try:
                have = sha256_file(d / "truth.exr")
            except OSError as e:
                raise ReferenceError_(
                    f"cannot read {d / 'truth.exr'}: {e.strerror}; re-render it with `{cmd} --force`"
                ) from None
            if have != want:
                if attempt < 2 and read_json(d / "meta.json").get(CHECKSUM_KEY) != want:
                    continue  # a writer swapped the reference in between: read the new one
                raise ReferenceError_(f"{d / 'truth.exr'} does not match the checksum in {d / 'meta.json'} "
                                      f"(sha256 {have[:12]}… ≠ {want[:12]}…): it was changed after it was "
                                      f"rendered; re-render it with `{cmd} --force`")
        try:
            ch = read_exr(d / "truth.exr")
        except ShadowlabError as e:
            raise ReferenceError_(f"{e} (re-render with `{cmd} --force`)") from None
        if want is None or read_json(d / "meta.json").get(CHECKSUM_KEY) == want:
            return meta, ch
    raise ReferenceError_(f"the reference at {d} changed three times while it was read; run again when "
                          "the writer has finished")


def load(scene_spec, resolution=None, base: Path | None = None, check_hash: bool = True):
    """(Truth, meta) of a scene's stored reference; raises ReferenceError_ if missing, incomplete,
    damaged (checksum, keys, channels, size) or stale."""
    res = tuple(resolution or scene_spec.camera.resolution)
    frame = scene_spec.frame
    d = path_for(scene_spec.name, res, base, frame=frame)
    cmd = reference_command(scene_arg(scene_spec), res, frame)
    _note(recover(d))
    _await_swap(d)
    if not d.exists() and (committed := builtin_copy(scene_spec, res, frame)) is not None:
        d = committed                        # a built-in scene's committed reference, read where it is installed
    if not d.exists():
        have = sorted(p.name for p in d.parent.iterdir() if _RES_DIR.match(p.name)) if d.parent.is_dir() else []
        at = f"{res[0]}x{res[1]}" + ("" if frame is None else f" frame {frame}")
        raise ReferenceError_(f"no reference for scene {scene_spec.name!r} at {at} (looked in {d})"
                              + (f"; stored resolutions: {', '.join(have)}" if have else "")
                              + f"; render one with `{cmd}`")
    problem = _problem(d)
    if problem:
        raise ReferenceError_(f"the reference at {d} is incomplete ({problem}); re-render it with `{cmd} --force`")
    meta, ch = _read_settled(d, cmd)
    if check_hash and meta.get("scene_hash") != scene_spec.digest():
        raise ReferenceError_(f"the reference at {d} was rendered from a different version of scene "
                              f"{scene_spec.name!r} (scene hash {str(meta.get('scene_hash'))[:12]}… ≠ "
                              f"{scene_spec.digest()[:12]}…); re-render it with `{cmd} --force`")
    exr = d / "truth.exr"
    shapes = {a.shape for a in ch.values()}
    if shapes != {(res[1], res[0])}:
        raise ReferenceError_(f"{exr} is {'/'.join(f'{s[1]}x{s[0]}' for s in sorted(shapes))}, not {res[0]}x{res[1]}: "
                              f"it does not belong in {d}; re-render it with `{cmd} --force`")
    missing = [c for c in required_channels(l.name for l in scene_spec.lights) if c not in ch]
    if missing:
        raise ReferenceError_(f"{exr} has no channel {', '.join(missing[:6])}{' …' if len(missing) > 6 else ''}; "
                              f"re-render with `{cmd} --force`")
    if ("mitsuba.R" in ch) and any(f"{p}.{c}" not in ch for p in ("mitsuba", "mitsuba.var") for c in "RGB"):
        raise ReferenceError_(f"{exr} has an incomplete mitsuba image (mitsuba.R|G|B and mitsuba.var.R|G|B); "
                              f"re-render with `{cmd} --force`")
    lights, U = {}, {}
    for l in scene_spec.lights:
        n = l.name
        coloured = f"C.{n}.R" in ch
        lights[n] = LightTruth(V=ch[f"V.{n}"], V_se=ch[f"V.{n}.se"], A=ch[f"A.{n}"], A_se=ch[f"A.{n}.se"],
                               samples=ch[f"N.{n}"], bound=ch[f"B.{n}"],
                               V_rgb=np.stack([ch[f"C.{n}.{c}"] for c in "RGB"], -1) if coloured else None,
                               V_rgb_se=np.stack([ch[f"C.{n}.se.{c}"] for c in "RGB"], -1) if coloured else None)
        U[n] = np.stack([ch[f"U.{n}.{c}"] for c in "RGB"], -1)
    rgb = lambda p: np.stack([ch[f"{p}.{c}"] for c in "RGB"], -1) if f"{p}.R" in ch else None  # noqa: E731
    truth = Truth(
        lights=lights,
        U=U,
        shaded=rgb("shaded"),
        shaded_var=rgb("shaded.var"),
        mitsuba=rgb("mitsuba"),
        mitsuba_var=rgb("mitsuba.var"),
        mask=ch["mask"] > 0.5,
        view_depth=ch["depth"],
        stats=meta.get("stats", {}),
    )
    _check_measures(truth, d, cmd, [l.name for l in scene_spec.lights])
    return truth, meta


def required_channels(lights) -> list[str]:
    """The EXR channels every reader needs, for the lights named ``lights``."""
    need = ["mask", "depth", *(f"{p}.{c}" for p in ("shaded", "shaded.var") for c in "RGB")]
    for n in lights:
        need += [f"V.{n}", f"V.{n}.se", f"A.{n}", f"A.{n}.se", f"N.{n}", f"B.{n}", *(f"U.{n}.{c}" for c in "RGB")]
    return need


_WARNED: set = set()


def _check_measures(truth: Truth, d: Path, cmd: str, lights) -> None:
    """A reference that measures nothing is refused (exit 2); one with some lights that measure
    nothing is used with a warning, once per process, in every command that reads it (:mod:`.vacuous`)."""
    found = vacuous.of_truth(truth)
    vacuous.refuse_empty(found, lights, where=f"the reference at {d}", fix_tail=f"re-render it with `{cmd} --force`")
    if str(d) not in _WARNED:
        _WARNED.add(str(d))
        for w in vacuous.warnings(found):
            print(f"warning: the reference at {d}: {w}", file=sys.stderr)


def _content_problems(d: Path, meta: dict, cmd: str) -> list[str]:
    """What ``references`` says of truth.exr's content: a channel missing, nothing measured."""
    try:
        ch = read_exr(d / "truth.exr")
    except ShadowlabError:
        return [f"damaged: truth.exr does not read; re-render with `{cmd} --force`"]
    (W, H), _ = parse_dir_name(d.name)
    shapes = {a.shape for a in ch.values()}
    if shapes != {(H, W)}:
        return [f"damaged: truth.exr is {'/'.join(f'{s[1]}x{s[0]}' for s in sorted(shapes))}, not {W}x{H}; "
                f"re-render with `{cmd} --force`"]
    lights = meta.get("lights") if isinstance(meta.get("lights"), list) else sorted(
        {k[2:] for k in ch if k.startswith("V.") and not k.endswith(".se")})
    missing = [c for c in required_channels(lights) if c not in ch]
    if missing:
        return [f"damaged: truth.exr has no channel {', '.join(missing[:6])}{' …' if len(missing) > 6 else ''}; "
                f"re-render with `{cmd} --force`"]
    found = vacuous.findings(ch["mask"] > 0.5, {n: np.stack([ch[f"U.{n}.{c}"] for c in "RGB"], -1) for n in lights},
                             {n: ch[f"V.{n}"] for n in lights})
    try:
        vacuous.refuse_empty(found, lights, where="it", fix_tail=f"re-render with `{cmd} --force`")
    except ReferenceError_ as e:
        return [f"empty: {e}"]
    return vacuous.warnings(found)


# ---------------------------------------------------------------------------------- listing
def _scene_file(scene: str, meta: dict) -> Path | None:
    f = meta.get("scene_file")
    if isinstance(f, str) and Path(f).is_file():
        return Path(f)
    try:
        p = resolve(scene)
    except ShadowlabError:
        return None
    return p if p.is_file() else None


def _status(d: Path, scene: str, meta) -> list[str]:
    """Problems of one listed reference (empty: fine)."""
    res, frame = parse_dir_name(d.name)
    src = meta.get("scene_file") if isinstance(meta, dict) else None   # a scene known only by its path
    cmd = reference_command(shlex.quote(src) if isinstance(src, str) and src else scene, res, frame)
    problem = _problem(d)
    if problem:
        return [f"incomplete: {problem}; re-render with `{cmd} --force`"]
    try:
        check_meta(meta, d / "meta.json", cmd)
    except ReferenceError_:
        return [f"damaged meta.json; re-render with `{cmd} --force`"]
    out = []
    want = meta.get(CHECKSUM_KEY)
    if want is None:
        out.append("no checksum (written before checksums)")
    elif sha256_file(d / "truth.exr") != want:
        out.append(f"checksum mismatch: truth.exr was changed; re-render with `{cmd} --force`")
    out += _content_problems(d, meta, cmd)
    sf = _scene_file(scene, meta)
    if sf is None:
        out.append("scene file not found: freshness not checked")
    else:
        try:
            spec = load_spec(sf).with_resolution(*res)
        except ShadowlabError:
            out.append(f"scene file {sf} does not load: freshness not checked")
        else:
            if frame is not None and frame >= spec.frames:   # the path got shorter (or was removed)
                out.append(f"stale: scene {scene!r} has no frame {frame} now ({spec.frame_range_text()}); delete {d}")
                fresh = True
            else:   # a frame directory of a scene without a path now never matches (its hash has no path)
                fresh = (spec if frame is None else spec.at_frame(frame)).digest() == meta["scene_hash"]
            if not fresh:
                out.append(f"stale: scene {scene!r} changed since; re-render with `{cmd} --force`")
    tm = meta.get("target_missed")
    if isinstance(tm, dict) and tm.get("pixels"):
        out.append(
            f"{tm['pixels']} pixels above the target standard error (worst {tm.get('worst_se', float('nan')):.4f})"
        )
    return out


def list_references(base: Path | None = None) -> list[dict]:
    """Every stored reference: scene, resolution (``"WxH"``), frame (None, or the camera path
    frame), path, meta and ``status`` (a list of problems: incomplete, damaged, stale, checksum
    mismatch, ...; empty when the reference is fine).
    Temporary and leftover directories of interrupted saves are not references and are not listed.
    Without ``base``, the built-in scenes' committed references that the store does not hold follow,
    marked ``builtin`` (read-only, where shadowlab is installed)."""
    out = _listed(Path(base or root()))
    if base is None:
        have = {(x["scene"], x["resolution"], x["frame"]) for x in out}
        out += [dict(x, builtin=True) for x in _listed(location.builtin_references())
                if (x["scene"], x["resolution"], x["frame"]) not in have]
    return out


def _listed(r: Path) -> list[dict]:
    out = []
    if not r.is_dir():
        return out
    for sd in sorted(p for p in r.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for d in sorted(p for p in sd.iterdir() if p.is_dir() and _RES_DIR.match(p.name)):
            try:
                meta = read_json(d / "meta.json") if (d / "meta.json").is_file() else {}
            except ShadowlabError:  # a broken meta is listed as such, not fatal
                meta = {"error": "unreadable meta.json"}
            res, frame = parse_dir_name(d.name)
            out.append({"scene": sd.name, "resolution": f"{res[0]}x{res[1]}", "frame": frame, "path": str(d),
                        "meta": meta, "status": _status(d, sd.name, meta)})
    return out
