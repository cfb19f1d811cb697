"""References that measure nothing: found once, from a truth's own images, wherever one is made or read.

A ground truth (Mitsuba 3 [Jakob 2022a]) is only a reference where the camera sees a surface (``mask``)
that a light reaches (``U_L > 0``, the unshadowed radiance) and is not blocked everywhere
(``V_L > 0`` somewhere there). Three ways to have nothing to measure, each a scene mistake:

* ``blind``: the camera sees no surface (it looks away from the geometry);
* ``unreached``: a light reaches no surface the camera sees (its ``range`` or cone ends short of
  them, it faces away);
* ``enclosed``: a light reaches visible surfaces only through geometry that blocks every shadow
  ray (a light inside a closed box): its visibility is 0 wherever it would shine.

:func:`findings` names them; :func:`refuse_empty` raises (exit 2) when nothing at all is measurable
(every metric would be n/a, or "rmse 0, psnr inf" between two black images), so such a reference
is never stored and an old one is never compared with; :func:`warnings` are the lines a reference
with some lights measurable and others not carries into every command that reads it.

>>> import numpy as np
>>> m = np.ones((2, 2), bool)
>>> U = {"key": np.ones((2, 2, 3)), "far": np.zeros((2, 2, 3))}
>>> findings(m, U, {"key": np.ones((2, 2)), "far": np.ones((2, 2))})
{'far': 'unreached'}
>>> findings(m, U, {"key": np.zeros((2, 2)), "far": np.ones((2, 2))})
{'key': 'enclosed', 'far': 'unreached'}
>>> findings(~m, U, {})
{'*': 'blind'}
"""

from __future__ import annotations

import numpy as np

from ..errors import ReferenceError_

__all__ = ["findings", "refuse_empty", "warnings", "WHY"]

#: what each finding means and how to fix the scene
WHY = {
    "blind": ("the camera sees no surface (every pixel misses the geometry)",
              "aim the camera at the geometry (camera.target, camera.fov)"),
    "unreached": ("reaches no surface the camera sees (its range or cone ends short of them, or it faces away)",
                  "move or turn the light, or raise its range / angle"),
    "enclosed": ("is blocked on every surface it reaches (enclosed by geometry: every shadow ray hits something)",
                 "move the light out of the geometry that encloses it, or open that geometry"),
}


def findings(mask: np.ndarray, U: dict, V: dict) -> dict:
    """{light: "unreached" | "enclosed"} for each light with nothing to measure, or
    ``{"*": "blind"}`` when the camera sees no surface; {} for a reference that measures."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return {"*": "blind"}
    out = {}
    for name, u in U.items():
        lit = mask & (np.asarray(u).reshape(mask.shape + (-1,)).sum(-1) > 0)
        if not lit.any():
            out[name] = "unreached"
        elif name in V and not (np.asarray(V[name])[lit] > 0).any():
            out[name] = "enclosed"
    return out


def of_truth(truth) -> dict:
    """:func:`findings` of a :class:`~shadowlab.reference.truth.Truth`."""
    return findings(truth.mask, truth.U, {n: lt.V for n, lt in truth.lights.items()})


def _light_text(name: str, why: str) -> str:
    return f"light {name!r} {WHY[why][0]}"


def refuse_empty(found: dict, lights, *, where: str, fix_tail: str) -> None:
    """Raise :class:`~shadowlab.errors.ReferenceError_` (exit 2) when nothing is measurable: the
    camera is blind, or every light of ``lights`` is unreached or enclosed. ``where``: what is
    refused (e.g. "the reference of scene 'x'"); ``fix_tail``: the command to run after fixing."""
    if found.get("*") == "blind":
        what, fix = WHY["blind"][0], WHY["blind"][1]
    elif lights and all(n in found for n in lights):
        what = "; ".join(_light_text(n, found[n]) for n in lights)
        fix = "; ".join(dict.fromkeys(WHY[found[n]][1] for n in lights))
    else:
        return
    raise ReferenceError_(f"{where} measures nothing: {what}. Every pixel would compare as equal (or n/a), so it "
                          f"is refused; fix the scene ({fix}), then {fix_tail}")


def warnings(found: dict) -> list[str]:
    """One line per light with nothing to measure (the others still measure)."""
    return [f"{_light_text(n, why)}; its metrics are n/a: {WHY[why][1]}" for n, why in found.items() if n != "*"]
