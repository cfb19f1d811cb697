"""Where the reference store lives: a project-local store, as pytest-mpl keeps baselines beside a
project's tests (issue 27).

The store is the first of:

1. ``--references DIR``, the option of every command that reads or writes references (:func:`choose`);
2. ``$SHADOWLAB_REFERENCES`` (:data:`ROOT_ENV`);
3. ``references = "DIR"`` in a ``shadowlab.toml`` (top level) or in the ``[tool.shadowlab]`` table of a
   ``pyproject.toml``, the nearest one found walking up from the working directory (a ``shadowlab.toml``
   before a ``pyproject.toml`` of the same directory); DIR is relative to that file;
4. ``./references`` in the working directory.

The environment comes before the project's file, as for pip and most tools: the file says where a
project keeps its references, the variable overrides it for one shell or CI job (a cache, a scratch
store) without editing the project.

Never inside the installed package: a store there is refused (:func:`check_outside_package`). The
built-in scenes' committed references are package data (``shadowlab/builtin_references`` in a wheel,
``references/`` of a source checkout): :func:`builtin_references` finds them wherever shadowlab is
installed, and the store reads a built-in scene's reference there when it has none of its own; it
never writes there.

Two projects' scenes of the same name do not meet: each project has its own store (its file, or
``./references`` of its own directory). Within one store (a variable shared by two projects), the
scene hash in every reference's meta.json tells them apart: a reference of the other scene is
reported stale and never used, and writing over it needs ``--force``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from ..errors import InputError

ROOT_ENV = "SHADOWLAB_REFERENCES"
#: the project files that may name the store, in the order they are read in one directory
CONFIG_FILES = ("shadowlab.toml", "pyproject.toml")
PACKAGE = Path(__file__).resolve().parents[1]            # the installed shadowlab/ directory
_CHOSEN: dict = {}                                        # "path": the --references option of this process


@dataclass(frozen=True)
class Location:
    """The store's directory and what chose it: ``option``, ``environment``, the config file's path
    or ``default``."""

    path: Path
    source: str


def choose(path) -> None:
    """The ``--references DIR`` option: the store of this process (None: forget it)."""
    if path is None:
        _CHOSEN.pop("path", None)
    else:
        _CHOSEN["path"] = Path(path).expanduser().absolute()


def chosen() -> Path | None:
    """The store ``--references`` chose in this process, None without the option."""
    return _CHOSEN.get("path")


def _setting(file: Path):
    """The ``references`` value a project file gives (None: it names none)."""
    try:
        data = tomllib.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"{file}: cannot read it for the reference store's location ({e}); fix the file, or give "
                         "--references DIR") from None
    table = data if file.name == "shadowlab.toml" else data.get("tool", {}).get("shadowlab", {})
    value = table.get("references") if isinstance(table, dict) else None
    if value is not None and not (isinstance(value, str) and value.strip()):
        where = "references" if file.name == "shadowlab.toml" else "[tool.shadowlab] references"
        raise InputError(f"{file}: {where} must be a path (relative to the file), got {value!r}")
    return value


def config_file(start=None) -> tuple[Path, str] | None:
    """(file, value) of the nearest project file that names the store, walking up from ``start``
    (default: the working directory); None when none does."""
    d = Path(start or Path.cwd()).absolute()
    for folder in (d, *d.parents):
        for name in CONFIG_FILES:
            f = folder / name
            if f.is_file() and (value := _setting(f)) is not None:
                return f, value
    return None


def locate(cwd=None) -> Location:
    """Where the store is (the order of the module docstring)."""
    if (p := chosen()) is not None:
        return Location(p, "option")
    if env := os.environ.get(ROOT_ENV):
        return Location(Path(env), "environment")
    if found := config_file(cwd):
        f, value = found
        return Location((f.parent / value).absolute(), str(f))
    return Location(Path(cwd or Path.cwd()).absolute() / "references", "default")


def inside_package(path) -> bool:
    """``path`` lies inside the installed shadowlab package (where nothing may be written)."""
    p = Path(path).absolute().resolve()
    return p == PACKAGE or PACKAGE in p.parents


def check_outside_package(path, source: str) -> None:
    """Refuse (exit 2) a store inside the installed package: a reinstall would lose it, and the
    package's files are not the user's."""
    if inside_package(path):
        raise InputError(f"the reference store {path} (from {source}) lies inside the installed shadowlab package "
                         f"({PACKAGE}); keep references in your project: give --references DIR, set {ROOT_ENV}, "
                         "or run from your project's directory (./references)")


def builtin_references() -> Path:
    """The built-in scenes' committed references: package data of an installed shadowlab
    (``shadowlab/builtin_references``), else ``references/`` of the source checkout. Read-only."""
    installed = PACKAGE / "builtin_references"
    return installed if installed.is_dir() else PACKAGE.parent / "references"
