"""Where a command may write its output: ``--out`` directories and single output files.

The rules, checked before any work is done (so a bad ``--out`` costs nothing) and again when the
files are installed:

* ``--out`` never points into the reference store (nor at it): the store holds references only,
  and a report there would sit beside (or replace) ``meta.json`` / ``gates.toml``. Exit 2, even
  with ``--force``.
* ``--out`` on an existing file, or below one, is refused (exit 2): a report is a directory.
* A report directory is *ours* when it does not exist, is empty, or holds the marker file
  :data:`MARKER` (``.shadowlab-report``, written into every report directory shadowlab makes). In a
  directory of ours only the report's own files are replaced; any other existing directory is
  refused unless ``--force`` (then, too, only the report's own files are replaced, and the
  directory is marked as ours).
* A single output file (``fit --save-preset FILE``) is replaced only when shadowlab wrote it
  (:func:`check_out_file` with an ``ours`` test) or with ``--force``.
* An ``--out`` where nothing can be created (``/proc/...``, a read-only or full file system) is
  found before any work by making and removing a temporary directory in its nearest existing
  folder. An OS error while writing is classified once, by :func:`write_error`: the machine's
  (full disk, quota, permissions, read-only file system) is an
  :class:`~shadowlab.errors.EnvironmentProblem` (exit 3), a path that cannot hold files is an
  :class:`~shadowlab.errors.InputError` (exit 2), each naming the path and the fix.
* A report is built in a temporary directory on the destination's own file system (beside a new
  ``--out``, inside an existing one), so installing it is a rename there even when ``--out`` is a
  mount point of its own (a container volume, a tmpfs): no cross-device rename.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> (d / "notes.txt").write_text("mine")
4
>>> try:
...     claim_dir(d, "compare")
... except Exception as e:
...     print(type(e).__name__, "--force" in str(e))
InputError True
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

from ..errors import EnvironmentProblem, InputError, ShadowlabError

__all__ = ["MARKER", "claim_dir", "check_out_file", "is_ours", "marker_text", "inside", "write_dir", "write_error",
           "error_number", "check_creatable"]

#: the file that marks a directory as a shadowlab report directory
MARKER = ".shadowlab-report"


#: errno of an OS error that is the machine's, not the input's -> the fix (exit 3)
ENVIRONMENT_ERRNOS = {
    errno.ENOSPC: "free disk space there, or write elsewhere",
    errno.EDQUOT: "free space within your disk quota, or write elsewhere",
    errno.EACCES: "make it writable (chmod / chown), or write elsewhere",
    errno.EPERM: "make it writable (chmod / chown), or write elsewhere",
    errno.EROFS: "it is on a read-only file system: write elsewhere",
    errno.EXDEV: "keep the output on one file system, or write elsewhere",
    errno.EIO: "the device reported an I/O error: check the disk, or write elsewhere",
}
#: errno of a path that cannot hold the output (the input's: exit 2)
PATH_ERRNOS = (errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENAMETOOLONG, errno.ELOOP, errno.EINVAL,
               errno.ENOTEMPTY, errno.EBUSY)


def error_number(exc: BaseException) -> int | None:
    """The errno of an OS error, also of a library's error that only carries its text (OpenEXR's
    ``RuntimeError("... No space left on device.")``); None when there is none.

    >>> error_number(OSError(errno.ENOSPC, "x")) == errno.ENOSPC
    True
    >>> error_number(RuntimeError("Failed to write pixel data. No space left on device.")) == errno.ENOSPC
    True
    """
    if isinstance(exc, OSError) and exc.errno is not None:
        return exc.errno
    text = str(exc)
    for code in (*ENVIRONMENT_ERRNOS, *PATH_ERRNOS):
        if os.strerror(code) in text:
            return code
    return None


def write_error(path, exc: BaseException, *, what: str = "write") -> ShadowlabError | None:
    """The one-line error for ``exc`` met while writing ``path``: an EnvironmentProblem (exit 3)
    for the machine's errors (:data:`ENVIRONMENT_ERRNOS`), an InputError (exit 2) for a path that
    cannot hold files (:data:`PATH_ERRNOS`: ``/proc/...``, a file where a folder is needed), or
    None when ``exc`` is no OS error and carries no errno's text (a bug: let it propagate). Any
    other OS error met while writing is the machine's (exit 3).

    >>> type(write_error("/full/x.json", OSError(errno.ENOSPC, "No space left on device"))).__name__
    'EnvironmentProblem'
    >>> print(write_error("/proc/r", OSError(errno.ENOENT, "No such file or directory")))
    cannot write /proc/r: No such file or directory; choose a path on a writable file system whose folders are \
directories (e.g. under reports/)
    """
    code = error_number(exc)
    reason = os.strerror(code) if code is not None else str(exc)
    if code in ENVIRONMENT_ERRNOS:
        return EnvironmentProblem(f"cannot {what} {path}: {reason}; {ENVIRONMENT_ERRNOS[code]}")
    if code in PATH_ERRNOS:
        return InputError(f"cannot {what} {path}: {reason}; choose a path on a writable file system whose folders are "
                          "directories (e.g. under reports/)")
    if isinstance(exc, OSError):  # another errno of the OS while writing: the machine's
        return EnvironmentProblem(f"cannot {what} {path}: {reason}; check the disk and the path, or write elsewhere")
    return None


def _nearest_existing(path: Path) -> Path:
    p = _resolve(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_creatable(path, option: str = "--out") -> None:
    """Raise the :func:`write_error` of ``path``'s nearest existing folder if nothing can be
    created there (``/proc``, ``/sys``, a read-only or full file system): found before any work."""
    base = _nearest_existing(Path(path))
    if not base.is_dir():
        return  # a file on the way: the callers' own checks name it
    try:
        os.rmdir(tempfile.mkdtemp(dir=base, prefix=".shadowlab-probe-"))
    except OSError as e:
        err = write_error(f"{option} {path}", e, what="create")
        if err is None:
            raise
        raise err from None


def _resolve(p: Path) -> Path:
    return Path(os.path.abspath(Path(p).expanduser())).resolve()


def inside(path, root) -> bool:
    """Whether ``path`` is ``root`` or lies below it (symbolic links resolved)."""
    if root is None:
        return False
    p, r = _resolve(Path(path)), _resolve(Path(root))
    return p == r or r in p.parents


def _check_protected(path: Path, option: str, protected) -> None:
    for root in protected or ():
        if root is not None and inside(path, root):
            raise InputError(f"{option} {path} is inside the reference store {_resolve(Path(root))}; the store holds "
                             "references only: write the output elsewhere (e.g. under reports/)")


def _check_ancestors(path: Path, option: str) -> None:
    for a in _resolve(path).parents:
        if a.exists() and not a.is_dir():
            raise InputError(f"{option} {path}: {a} is a file, not a directory; choose another {option}")


def is_ours(d) -> bool:
    """A directory shadowlab made for a report (it holds :data:`MARKER`)."""
    return (Path(d) / MARKER).is_file()


def marker_text(kind: str, files) -> str:
    """The marker's content: which command wrote the directory and which entries are its own."""
    return json.dumps({"written_by": "shadowlab", "kind": kind, "files": sorted(files)}, indent=1) + "\n"


def claim_dir(out, kind: str, *, force: bool = False, protected=(), files=(), option: str = "--out") -> Path:
    """Check that the report directory ``out`` may be written (see the module docstring); raise
    :class:`~shadowlab.errors.InputError` (exit 2) naming the problem and the fix. ``protected``:
    directories (the reference store) no output may enter; ``files``: the entries the report
    writes, for the message. Nothing is created."""
    out = Path(out)
    _check_protected(out, option, protected)
    if out.exists() and not out.is_dir():
        raise InputError(f"{option} {out} is an existing file; a {kind} report is a directory: choose another "
                         f"{option} (nothing was written)")
    _check_ancestors(out, option)
    check_creatable(out, option)
    if out.is_dir() and not force and not is_ours(out) and any(out.iterdir()):
        what = ", ".join(files) if files else "its report files"
        raise InputError(f"{option} {out} is a directory that shadowlab did not create (no {MARKER} in it); choose "
                         f"another {option}, empty it, or pass --force to write the {kind} report into it (only "
                         f"{what} are replaced)")
    return out


def check_out_file(path, option: str, *, force: bool = False, protected=(), ours=None) -> Path:
    """Check that the single output file ``path`` may be written: not in ``protected``, not a
    directory, not below a file, and, if it exists, written by shadowlab (``ours(path)`` true) or
    ``force``. Raises :class:`~shadowlab.errors.InputError` (exit 2)."""
    p = Path(path)
    _check_protected(p, option, protected)
    if p.is_dir():
        raise InputError(f"{option} {p} is a directory; give a file name such as {p / 'preset.toml'}")
    _check_ancestors(p, option)
    check_creatable(p, option)
    if p.exists() and not force and not (ours is not None and ours(p)):
        raise InputError(f"{option} {p} already exists and was not written by shadowlab; choose another file "
                         "name, or pass --force to replace it")
    return p


def write_dir(out, kind: str, fill: Callable[[Path], None], files, dirs=()) -> Path:
    """Build a report in a temporary sibling of ``out`` (``fill(tmp)`` writes ``files`` and
    ``dirs`` there), mark it, and install it: one rename when ``out`` does not exist, else only the
    report's own directories and then files are replaced, ``index.html`` last (it links the rest),
    so other files in ``out`` stay and a reader never sees a page without its parts. A failure
    leaves ``out`` as it was. Returns ``out / "index.html"``.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "r"
    >>> write_dir(d, "demo", lambda t: (t / "index.html").write_text("hi"), ("index.html",)).read_text()
    'hi'
    """
    out = Path(out)
    try:
        return _write_dir(out, kind, fill, files, dirs)
    except OSError as e:
        err = write_error(out, e)
        if err is None:
            raise
        raise err from None


def _write_dir(out: Path, kind: str, fill: Callable[[Path], None], files, dirs) -> Path:
    # the temporary directory lies on out's own file system: beside a new out, inside an existing one
    # (out may be a mount point: a rename from its parent into it would cross devices)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out if out.is_dir() else out.parent, prefix=f".{out.name}.{kind}-"))
    try:
        for d in dirs:
            (tmp / d).mkdir()
        fill(tmp)
        (tmp / MARKER).write_text(marker_text(kind, tuple(files) + tuple(dirs)), encoding="utf-8")
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700; a report directory should be readable
        if not out.exists():
            try:
                os.rename(tmp, out)  # atomic; fails if out appeared meanwhile and is non-empty
                return out / "index.html"
            except OSError:
                pass
        out.mkdir(parents=True, exist_ok=True)
        for d in dirs:
            old = tmp / f".old-{d}"
            if os.path.lexists(out / d):
                os.rename(out / d, old)
            try:
                os.rename(tmp / d, out / d)
            except BaseException:
                if os.path.lexists(old):
                    os.rename(old, out / d)
                raise
        for f in sorted((MARKER, *files), key=lambda f: f == "index.html"):
            os.replace(tmp / f, out / f)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out / "index.html"
