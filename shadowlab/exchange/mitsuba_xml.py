"""Mitsuba 3 scene dicts -> Mitsuba XML text, with exact transforms.

Mitsuba 3.9 can write XML itself (``mi.parser.parse_dict`` + ``mi.parser.write_string``), but it
decomposes every ``to_world`` into scale / rotate / translate steps, which moves a floor scaled by
4 to 3.9999998 and cannot express a shear; here every transform is written as its 4×4 matrix
(9 significant digits: the float32 values Mitsuba holds, read back bit for bit), so the file
loads into the same scene as ``mi.load_dict``. Only the plugins shadowlab's scenes use are known
(:data:`PLUGIN_TAG`). ``$name`` string values of ``width``, ``height`` and ``sample_count`` are
written as integer parameters with a ``<default>``, so ``mitsuba scene.xml -Dspp=256 -Dresx=512``
works. Bitmap textures must reference a file (``filename``): the caller writes a tensor texture
(``data``) to a file first (:func:`shadowlab.exchange.export._texture_files`).
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from ..errors import SceneError

__all__ = ["dict_to_xml", "PLUGIN_TAG"]

PLUGIN_TAG = {
    "rectangle": "shape", "disk": "shape", "cube": "shape", "sphere": "shape", "cylinder": "shape",
    "ply": "shape", "obj": "shape",
    "perspective": "sensor", "hdrfilm": "film", "box": "rfilter", "independent": "sampler",
    "diffuse": "bsdf", "twosided": "bsdf", "mask": "bsdf",
    "area": "emitter", "point": "emitter", "spot": "emitter", "directional": "emitter",
    "bitmap": "texture", "direct": "integrator", "path": "integrator",
}
_POINT_KEYS = ("center", "position", "origin", "target")
_VECTOR_KEYS = ("direction", "up")


def _num(v) -> str:
    return format(float(v), ".9g")


def _attr(**kw) -> str:
    return "".join(f" {k}={quoteattr(str(v))}" for k, v in kw.items())


def _is_transform(v) -> bool:
    return hasattr(v, "matrix") and hasattr(v, "inverse")


def _value(key: str, v, ind: str) -> list[str]:
    if isinstance(v, dict):
        return _object(key, v, ind, nested=True)
    if _is_transform(v):
        m = np.array(v.matrix, dtype=np.float64).reshape(4, 4)
        vals = " ".join(_num(x) for x in m.ravel())
        return [f"{ind}<transform{_attr(name=key)}>", f"{ind}    <matrix{_attr(value=vals)}/>", f"{ind}</transform>"]
    if isinstance(v, bool):
        return [f"{ind}<boolean{_attr(name=key, value=str(v).lower())}/>"]
    if isinstance(v, (int, np.integer)):
        return [f"{ind}<integer{_attr(name=key, value=int(v))}/>"]
    if isinstance(v, (float, np.floating)):
        return [f"{ind}<float{_attr(name=key, value=_num(v))}/>"]
    if isinstance(v, str):
        if v.startswith("$") and key in ("width", "height", "sample_count"):
            return [f"{ind}<integer{_attr(name=key, value=v)}/>"]
        return [f"{ind}<string{_attr(name=key, value=v)}/>"]
    if isinstance(v, (list, tuple)) and len(v) == 3 and key in _POINT_KEYS + _VECTOR_KEYS:
        tag = "point" if key in _POINT_KEYS else "vector"
        x, y, z = (_num(c) for c in v)
        return [f"{ind}<{tag}{_attr(name=key, x=x, y=y, z=z)}/>"]
    raise SceneError(f"cannot write the Mitsuba parameter {key!r} = {v!r} to XML")


def _object(key: str, d: dict, ind: str, nested: bool) -> list[str]:
    t = d.get("type")
    if t == "rgb":
        vals = d["value"]
        vals = [vals] * 3 if isinstance(vals, (int, float)) else list(vals)
        return [f"{ind}<rgb{_attr(name=key, value=' '.join(_num(x) for x in vals))}/>"]
    if t not in PLUGIN_TAG:
        raise SceneError(f"cannot write a Mitsuba object of type {t!r} ({key!r}) to XML")
    tag = PLUGIN_TAG[t]
    body = {k: v for k, v in d.items() if k != "type"}
    if t == "bitmap" and "data" in body:
        raise SceneError(f"bitmap {key!r} holds a tensor; write it to a file and reference it with 'filename'")
    head = f"{ind}<{tag}{_attr(type=t, **({'name': key} if nested else {'id': key}))}"
    if not body:
        return [head + "/>"]
    out = [head + ">"]
    for k, v in body.items():
        out += _value(k, v, ind + "    ")
    out.append(f"{ind}</{tag}>")
    return out


def dict_to_xml(scene: dict, defaults: dict | None = None) -> str:
    """XML text of a ``{"type": "scene", key: object, ...}`` dict (top-level keys become ids)."""
    if scene.get("type") != "scene":
        raise SceneError("dict_to_xml needs a dict with type 'scene'")
    lines = ['<?xml version="1.0" encoding="utf-8"?>', '<scene version="3.0.0">']
    for k, v in (defaults or {}).items():
        lines.append(f"    <default{_attr(name=k, value=v)}/>")
    for k, v in scene.items():
        if k == "type":
            continue
        if not isinstance(v, dict):
            raise SceneError(f"top-level scene entry {k!r} is not a plugin dict")
        lines += [""] + _object(k, v, "    ", nested=False)
    lines.append("</scene>")
    return "\n".join(lines) + "\n"
