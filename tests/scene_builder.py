"""Scene building blocks for tests: a scene as a plain dict (the document :func:`shadowlab.scene.spec.parse`
reads), the same scene as TOML text or a file, and its built Scene / FrameContext.

The scene format is shadowlab/scene/spec.py's (README.md, "Scene format"): a top-level ``name``,
a ``[camera]`` table, ``[[lights]]``, ``[[shapes]]`` and ``[[sdf]]`` arrays of tables. Tests that
repeat the same floor, the same ``parse(d, f"{name}.toml")`` + ``build`` + ``make_frame`` or the
same inline TOML use these instead::

    d = scene("edge", camera=CAM, resolution=(64, 64), lights=[SUN], shapes=[floor(2.0), OCC])
    frame = frame_from(d)                       # make_frame(build(parse(d, "edge.toml")), u_strata=1)
    path = write_scene(tmp_path / "edge.toml", d)   # the same scene as a TOML file

Nothing here touches Mitsuba until :func:`build_scene` / :func:`frame_from` (they need the
``mitsuba_backend`` fixture's variant, like ``shadowlab.scene.build``).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path


def floor(scale=4.0, *, name: str = "floor", **extra) -> dict:
    """The usual floor: a rectangle in the y = 0 plane facing up (the unit square rotated −90° about x),
    ``scale`` its half size; ``extra`` keys (albedo, translate, ...) are added."""
    return {"name": name, "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": scale, **extra}


def scene(name: str = "t", *, camera: dict, lights=(), shapes=None, sdf=None, resolution=None, **top) -> dict:
    """A scene document (the dict ``parse`` reads): ``camera`` (copied; ``resolution``, when given, replaces
    its ``resolution``), ``lights``, ``shapes`` and ``sdf`` (left out when None) and further top-level keys
    (``description``, ``truth_allocation``, ...)."""
    cam = dict(camera)
    if resolution is not None:
        cam["resolution"] = list(resolution)
    d = {"name": name, **top, "camera": cam, "lights": list(lights)}
    if shapes is not None:
        d["shapes"] = list(shapes)
    if sdf is not None:
        d["sdf"] = list(sdf)
    return d


# ------------------------------------------------------------------------------------------ TOML
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k) -> str:
    return k if _BARE.match(str(k)) else json.dumps(str(k))


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return repr(v)  # 'inf' / '-inf' are TOML too
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, Path):
        return json.dumps(str(v))
    raise TypeError(f"scene_toml: cannot write {v!r} ({type(v).__name__}) as TOML")


def _is_tables(v) -> bool:
    return isinstance(v, (list, tuple)) and len(v) > 0 and all(isinstance(x, dict) for x in v)


def _table(lines: list, prefix: str, d: dict) -> None:
    # plain keys first (TOML puts every key of a table before its sub-tables), then tables, then arrays of tables
    for k, v in d.items():
        if not isinstance(v, dict) and not _is_tables(v):
            lines.append(f"{_key(k)} = {_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            name = f"{prefix}{_key(k)}"
            lines += ["", f"[{name}]"]
            _table(lines, name + ".", v)
    for k, v in d.items():
        if _is_tables(v):
            name = f"{prefix}{_key(k)}"
            for t in v:
                lines += ["", f"[[{name}]]"]
                _table(lines, name + ".", t)


def scene_toml(d: dict | None = None, **parts) -> str:
    """The scene ``d`` (or ``scene(**parts)``) as TOML text: ``[camera]`` and its sub-tables, ``[[lights]]``,
    ``[[shapes]]``, ``[[sdf]]`` (with ``[[sdf.children]]``) in the order the dict gives them.

    >>> print(scene_toml(scene("s", camera={"position": [0, 1, 4], "target": [0, 0, 0]},
    ...                        lights=[{"name": "key", "kind": "point", "position": [0, 3, 0], "power": 5.0}])))
    name = "s"
    <BLANKLINE>
    [camera]
    position = [0, 1, 4]
    target = [0, 0, 0]
    <BLANKLINE>
    [[lights]]
    name = "key"
    kind = "point"
    position = [0, 3, 0]
    power = 5.0
    <BLANKLINE>
    """
    if d is None:
        d = scene(**parts)
    elif parts:
        raise TypeError("scene_toml: give a scene dict or its parts, not both")
    lines: list = []
    _table(lines, "", d)
    return "\n".join(lines) + "\n"


def write_scene(path, d: dict | None = None, **parts) -> Path:
    """Write the scene ``d`` (or ``scene(**parts)``) as TOML to ``path`` (its folder is made); returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(scene_toml(d, **parts), encoding="utf-8")
    return p


# --------------------------------------------------------------------------- spec, Scene, frame
def spec_of(d: dict, path=None):
    """``parse(d, path)``; ``path`` (relative mesh / texture files are found beside it) defaults to
    ``"<name>.toml"``."""
    from shadowlab.scene.spec import parse
    return parse(d, str(path) if path is not None else f"{d['name']}.toml")


def build_scene(d: dict, path=None):
    """The loaded Scene of the scene document ``d`` (see :func:`spec_of` for ``path``)."""
    from shadowlab.scene import build
    return build(spec_of(d, path))


def frame_from(d: dict, path=None, *, u_strata: int = 1, ss: int = 1, seed: int = 0):
    """``make_frame(build(parse(d, path)), ...)`` with the tests' usual single stratum of U_L (``u_strata=1``)."""
    from shadowlab.render.frame import make_frame
    return make_frame(build_scene(d, path), ss=ss, u_strata=u_strata, seed=seed)
