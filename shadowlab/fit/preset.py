"""Presets: named parameter sets ``{technique: {param: value}}`` in a TOML or JSON file.

``shadowlab fit`` writes the fitted values (and the values it held fixed that differ from the
defaults) as ``DIR/preset.toml`` and, with ``--save-preset FILE``, to FILE;
``shadowlab compare --preset FILE`` applies one (``--set`` overrides it). Every value is
validated by its technique's :class:`~shadowlab.techniques.base.Param` when the file is read.

TOML::

    name = "contact-pcss"                # optional; default: the file name without suffix
    description = "fitted by shadowlab fit"
    [meta]                               # optional, free-form (scene, loss, losses before/after)
    scene = "contact"
    [pcss]
    light_scale = 0.7386

JSON: the same keys, ``{"name": ..., "pcss": {"light_scale": 0.7386}}``.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..io.outdir import check_out_file
from ..scene.reader import check_param_values, did_you_mean
from ..techniques import base

RESERVED = ("name", "description", "meta")
#: the description of every preset ``shadowlab fit`` writes: how an existing file is known to be ours
FIT_DESCRIPTION = "fitted by shadowlab fit"


@dataclass
class Preset:
    name: str
    values: dict                   # technique -> {param: parsed value}
    path: str = ""
    description: str = ""
    meta: dict = field(default_factory=dict)

    def info(self) -> dict:
        return {"name": self.name, "path": self.path, "values": self.values}


def _parse_text(path: Path, text: str) -> dict:
    suffix = path.suffix.lower()
    if suffix == ".json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"preset {path}: not valid JSON ({e})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        if suffix == ".toml":
            raise InputError(f"preset {path}: not valid TOML ({e})") from None
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            raise InputError(f"preset {path}: neither valid TOML ({e}) nor JSON") from None


def from_dict(data, path: str = "<preset>") -> Preset:
    """Validate a preset mapping (see the module docstring)."""
    if not isinstance(data, dict):
        raise InputError(f"preset {path}: expected a table of techniques, got {type(data).__name__}")
    name = data.get("name", Path(path).stem if path != "<preset>" else "preset")
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"preset {path}: `name` must be a non-empty string")
    if "camera" in data or "gate" in data:
        what = "a scene file ([camera], [[lights]])" if "camera" in data else "a gate file ([[gate]] tables)"
        raise InputError(f"preset {path}: this is {what}, not a preset; give a preset written by `shadowlab fit` "
                         "(e.g. DIR/preset.toml: [technique] tables of parameter = value)")
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise InputError(f"preset {path}: `description` must be a string, got {desc!r}")
    meta = data.get("meta", {})
    if not isinstance(meta, dict):
        raise InputError(f"preset {path}: `meta` must be a table")
    values = {}
    for tech, params in data.items():
        if tech in RESERVED:
            continue
        if tech not in base.names() and not base.composes(tech):
            known = list(base.names()) + list(RESERVED)
            raise InputError(f"preset {path}: unknown technique {tech!r}{did_you_mean(tech, known)}; a preset's "
                             f"top-level keys are {', '.join(RESERVED)} and technique names: "
                             f"{', '.join(base.names())}")
        t = base.get(tech)
        if not isinstance(params, dict):
            raise InputError(f"preset {path}: [{tech}] must be a table of parameter = value, "
                             f"got {type(params).__name__}")
        check_param_values(f"preset {path}: [{tech}]", t, params)
        vals = {}
        for k, v in params.items():
            try:
                vals[k] = t.param(k).parse(v, tech)
            except InputError as e:
                raise InputError(f"preset {path}: {e}") from None
        values[tech] = vals
    if not values:
        raise InputError(f"preset {path}: it names no technique; expected a table per technique, "
                         "[TECHNIQUE] PARAM = VALUE (`shadowlab techniques` lists them and their parameters)")
    return Preset(name=name.strip(), values=values, path=str(path), description=str(desc), meta=meta)


def load(path) -> Preset:
    """Read and validate a preset file; InputError (exit 2) names the file and the problem."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"preset {p} is a directory; give a preset file such as {p / 'preset.toml'}")
    if not p.is_file():
        raise InputError(f"preset file {p} does not exist (write one with `shadowlab fit ... --save-preset {p}`)")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"preset {p}: cannot read it ({e})") from None
    return from_dict(_parse_text(p, text), str(p))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise InputError(f"preset: cannot store the non-finite value {v}")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise InputError(f"preset: cannot store a value of type {type(v).__name__}")


def _key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) else json.dumps(k)


def to_toml(name: str, values: dict, description: str = "", meta: dict | None = None) -> str:
    lines = [f"name = {_toml_value(name)}"]
    if description:
        lines.append(f"description = {_toml_value(description)}")
    if meta:
        lines += ["", "[meta]"] + [f"{_key(k)} = {_toml_value(v)}" for k, v in meta.items() if v is not None]
    for tech, params in values.items():
        lines += ["", f"[{_key(tech)}]"] + [f"{_key(k)} = {_toml_value(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


def written_by_fit(path) -> bool:
    """Whether the file at ``path`` is a preset ``shadowlab fit`` wrote (a valid preset whose
    description is :data:`FIT_DESCRIPTION`); such a file may be replaced without ``--force``."""
    p = Path(path)
    try:
        data = _parse_text(p, p.read_text(encoding="utf-8"))
        return isinstance(data, dict) and data.get("description") == FIT_DESCRIPTION and bool(from_dict(data, str(p)))
    except (OSError, UnicodeDecodeError, InputError):
        return False


def check_writable(path, force: bool = False, protected=()) -> Path:
    """Refuse a preset destination before any fitting is done: a directory, a name not ending in
    .toml / .json, a path inside the reference store (``protected``), or an existing file that
    ``shadowlab fit`` did not write (unless ``force``): it replaced a reference's meta.json and
    the store's gates.toml once."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"--save-preset {p} is a directory; give a file name such as {p / 'preset.toml'}")
    if p.suffix.lower() not in (".toml", ".json"):
        raise InputError(f"--save-preset {p}: the file name must end in .toml or .json")
    return check_out_file(p, "--save-preset", force=force, protected=protected, ours=written_by_fit)


def save(path, name: str, values: dict, description: str = "", meta: dict | None = None, *,
         force: bool = False, protected=()) -> Path:
    """Write a preset atomically (TOML, or JSON for a .json name); it is read back and validated
    first, so a file that is written can be loaded. An existing file is replaced only if
    ``shadowlab fit`` wrote it or with ``force`` (:func:`check_writable`)."""
    p = check_writable(path, force=force, protected=protected)
    if p.suffix.lower() == ".json":
        text = json.dumps({"name": name, **({"description": description} if description else {}),
                           **({"meta": meta} if meta else {}), **values}, indent=2) + "\n"
    else:
        text = to_toml(name, values, description, meta)
    from_dict(_parse_text(p, text), str(p))
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return p


def preset_meta(run) -> dict:
    """The ``[meta]`` table of the preset a fit run saves (``shadowlab fit --save-preset`` and the
    report's preset.toml): scene, resolution, loss and each technique's loss before and after."""
    meta = {"scene": run["scene"], "resolution": f"{run['resolution'][0]}x{run['resolution'][1]}",
            "loss": run["loss"]}
    if run.get("scenes"):                       # a fit over several scenes: each with its resolution
        meta["scenes"] = ", ".join(f"{e['name']} {e['resolution'][0]}x{e['resolution'][1]}" for e in run["scenes"])
    for t, r in run["techniques"].items():
        meta[f"{t}_loss_before"] = r["loss_before"]
        meta[f"{t}_loss_after"] = r["loss_after"]
    return meta
