"""The reference store: ``references/<scene>/<W>x<H>/truth.exr`` + ``meta.json``.

EXR channels (one float32 image each): ``V.<light>``, ``V.<light>.se`` (visibility ratio and
its standard error), ``A.<light>``, ``A.<light>.se`` (plain visible fraction), ``N.<light>``
(shadow rays per pixel), ``B.<light>`` (rule-of-three bound of unanimous pixels),
``U.<light>.R|G|B`` (unshadowed radiance), ``shaded.R|G|B`` and ``shaded.var.R|G|B`` (Σ U·V),
``mitsuba.R|G|B`` and ``mitsuba.var.R|G|B`` (mi.render, direct integrator), ``mask``, ``depth``.

Writes are atomic: a new reference is built in a temporary sibling directory and renamed into
place; an existing reference is only replaced with ``force=True``; an interrupted render
leaves the previous reference as it was. A reference whose scene hash differs from the scene
file is reported (:class:`ReferenceError_`), never used silently.
"""

from __future__ import annotations

import os
import shlex
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..errors import ReferenceError_
from ..io.exr import read_exr, write_exr
from ..io.jsonio import read_json, write_json_atomic
from .truth import LightTruth, Truth

ROOT_ENV = "SHADOWLAB_REFERENCES"


def root() -> Path:
    """Where references live: ``$SHADOWLAB_REFERENCES`` or ``references/`` at the repository top."""
    env = os.environ.get(ROOT_ENV)
    return Path(env) if env else Path(__file__).resolve().parents[2] / "references"


def path_for(scene_name: str, resolution, base: Path | None = None) -> Path:
    W, H = resolution
    return (base or root()) / scene_name / f"{W}x{H}"


def scene_arg(scene_spec) -> str:
    """How the fix texts name a scene: its built-in name, or the path of its file when it is not a
    built-in (``shadowlab reference NAME`` fails for a scene only known by its path)."""
    src = str(getattr(scene_spec, "source", "") or "")
    builtin = Path(__file__).resolve().parents[2] / "scenes" / f"{scene_spec.name}.toml"
    if not src or (Path(src).exists() and Path(src).resolve() == builtin.resolve()):
        return scene_spec.name
    return shlex.quote(src)


def _channels(truth: Truth) -> dict:
    ch = {}
    for name, lt in truth.lights.items():
        ch[f"V.{name}"], ch[f"V.{name}.se"] = lt.V, lt.V_se
        ch[f"A.{name}"], ch[f"A.{name}.se"] = lt.A, lt.A_se
        ch[f"N.{name}"], ch[f"B.{name}"] = lt.samples, lt.bound
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


def save(truth: Truth, meta: dict, dest: Path, force: bool = False) -> Path:
    """Write ``truth`` + ``meta`` to ``dest`` atomically (see module docstring)."""
    dest = Path(dest)
    if dest.exists() and not force:
        raise ReferenceError_(f"a reference already exists at {dest}; pass --force to replace it")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.tmp-", dir=dest.parent))
    try:
        write_exr(tmp / "truth.exr", _channels(truth))
        write_json_atomic(tmp / "meta.json", meta)
        os.chmod(tmp, 0o755)
        for f in tmp.iterdir():
            os.chmod(f, 0o644)
        old = None
        if dest.exists():
            old = dest.parent / f".{dest.name}.old-{os.getpid()}"
            os.replace(dest, old)
        os.replace(tmp, dest)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def load(scene_spec, resolution=None, base: Path | None = None, check_hash: bool = True):
    """(Truth, meta) of a scene's stored reference; raises ReferenceError_ if missing or stale."""
    res = tuple(resolution or scene_spec.camera.resolution)
    d = path_for(scene_spec.name, res, base)
    cmd = f"shadowlab reference {scene_arg(scene_spec)} --resolution {res[0]}x{res[1]}"
    if not (d / "truth.exr").exists() or not (d / "meta.json").exists():
        have = sorted(p.name for p in d.parent.glob("*x*")) if d.parent.exists() else []
        raise ReferenceError_(f"no reference for scene {scene_spec.name!r} at {res[0]}x{res[1]} (looked in {d})"
                              + (f"; stored resolutions: {', '.join(have)}" if have else "")
                              + f"; render one with `{cmd}`")
    meta = read_json(d / "meta.json")
    if check_hash and meta.get("scene_hash") != scene_spec.digest():
        raise ReferenceError_(f"the reference at {d} was rendered from a different version of scene "
                              f"{scene_spec.name!r} (scene hash {str(meta.get('scene_hash'))[:12]}… ≠ "
                              f"{scene_spec.digest()[:12]}…); re-render it with `{cmd} --force`")
    ch = read_exr(d / "truth.exr")
    lights, U = {}, {}
    for l in scene_spec.lights:
        n = l.name
        if f"V.{n}" not in ch:
            raise ReferenceError_(f"{d / 'truth.exr'} has no channel V.{n}; re-render with `{cmd} --force`")
        lights[n] = LightTruth(V=ch[f"V.{n}"], V_se=ch[f"V.{n}.se"], A=ch[f"A.{n}"], A_se=ch[f"A.{n}.se"],
                               samples=ch[f"N.{n}"], bound=ch[f"B.{n}"])
        U[n] = np.stack([ch[f"U.{n}.{c}"] for c in "RGB"], -1)
    rgb = lambda p: np.stack([ch[f"{p}.{c}"] for c in "RGB"], -1) if f"{p}.R" in ch else None  # noqa: E731
    truth = Truth(lights=lights, U=U, shaded=rgb("shaded"), shaded_var=rgb("shaded.var"), mitsuba=rgb("mitsuba"),
                  mitsuba_var=rgb("mitsuba.var"), mask=ch["mask"] > 0.5, view_depth=ch["depth"], stats=meta.get("stats", {}))
    return truth, meta


def list_references(base: Path | None = None) -> list[dict]:
    """Every stored reference: scene, resolution, path, meta."""
    out = []
    r = base or root()
    for m in sorted(r.glob("*/*x*/meta.json")):
        try:
            meta = read_json(m)
        except Exception:  # a broken meta is listed as such, not fatal
            meta = {"error": "unreadable meta.json"}
        out.append({"scene": m.parent.parent.name, "resolution": m.parent.name, "path": str(m.parent), "meta": meta})
    return out
