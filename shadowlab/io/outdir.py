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

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

from ..errors import InputError

__all__ = ["MARKER", "claim_dir", "check_out_file", "is_ours", "marker_text", "inside", "write_dir"]

#: the file that marks a directory as a shadowlab report directory
MARKER = ".shadowlab-report"


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
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.{kind}-"))
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
