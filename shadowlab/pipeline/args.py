"""The options the main jobs share, parsed and range-checked before anything is loaded:
``--resolution``, ``--frame`` / ``--frames`` and the truth's settings (exit 2 naming the option),
and whether a frame of that size fits in the device's memory (exit 3, :func:`check_memory`)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from ..reference.truth import SEED_MAX
from ..render.memory import Need, check_fits
from ..techniques import base as tbase

__all__ = ["parse_resolution", "check_reference_args", "parse_frames", "frame_list", "check_memory"]


def parse_resolution(text) -> tuple | None:
    """'128x96' or '128' -> (128, 96) / (128, 128); None stays None."""
    if text is None or text == "":
        return None
    if isinstance(text, (tuple, list)):
        return tuple(int(x) for x in text)
    t = str(text).lower().replace("×", "x")
    try:
        parts = [int(x) for x in t.split("x")] if "x" in t else [int(t)] * 2
    except ValueError:
        raise InputError(f"--resolution {text!r}: expected WIDTHxHEIGHT such as 128x128") from None
    if len(parts) != 2 or min(parts) < 1 or max(parts) > 8192:
        raise InputError(f"--resolution {text!r}: expected WIDTHxHEIGHT with sizes in 1..8192")
    return tuple(parts)


def check_reference_args(*, seed=0, target_se=0.005, spp=256, ss=1, max_rounds=64) -> None:
    """Refuse out-of-range options of ``shadowlab reference`` (a negative or NaN ``--target-se``
    was accepted once): InputError naming the option and its range."""
    def integer(opt, v, lo, hi):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= int(v) <= hi:
            raise InputError(f"{opt} {v!r}: expected an integer in [{lo}, {hi}]")
    if isinstance(target_se, bool) or not isinstance(target_se, (int, float)) or not math.isfinite(target_se) \
            or not 0 < target_se <= 0.5:
        raise InputError(f"--target-se {target_se!r}: expected a standard error in (0, 0.5] (visibility lies in "
                         "[0, 1]), e.g. 0.005")
    integer("--seed", seed, 0, SEED_MAX)
    integer("--spp", spp, 0, 1 << 20)
    integer("--ss", ss, 1, 8)
    integer("--max-rounds", max_rounds, 1, 1 << 16)


def parse_frames(text) -> tuple[int, int] | None:
    """``--frames A:B`` -> (A, B), both ends included (``0:3`` is frames 0, 1, 2 and 3); a
    (A, B) pair or None passes through. InputError (exit 2) for anything else."""
    if text is None or text == "":
        return None
    if isinstance(text, (tuple, list)):
        a, b = (int(x) for x in text)
    else:
        parts = str(text).split(":")
        try:
            if len(parts) != 2:
                raise ValueError
            a, b = int(parts[0]), int(parts[1])
        except ValueError:
            raise InputError(f"--frames {text!r}: expected A:B, two frame indices with A <= B (both included), "
                             "e.g. 0:3 for frames 0, 1, 2 and 3") from None
    if a < 0 or b < a:
        raise InputError(f"--frames {text!r}: expected A:B with 0 <= A <= B (both included), e.g. 0:3")
    return a, b


def frame_list(spec, frame: int | None = None, frames=None) -> list[int] | None:
    """The frames ``--frame N`` / ``--frames A:B`` select on a scene (None: neither was given),
    each checked against the scene's path (SceneError, exit 2, naming the valid range: 0..frames−1;
    a scene without a camera path has only frame 0)."""
    ab = parse_frames(frames)
    if frame is not None and ab is not None:
        raise InputError("--frame and --frames: give one of them (--frame N for one frame, --frames A:B for a range)")
    if frame is not None:
        return [spec.check_frame(frame)]
    if ab is None:
        return None
    spec.check_frame(ab[0])
    spec.check_frame(ab[1])
    return list(range(ab[0], ab[1] + 1))


def check_memory(spec, techniques: dict, *, ss: int = 1, size_option: str = "--resolution") -> Need:
    """Refuse before any work (EnvironmentProblem, exit 3) a frame of ``spec`` (at its camera's
    resolution) rendered by ``techniques`` ({name: parameter overrides}) that needs more memory than
    the device has free, naming both and the fix (:func:`shadowlab.render.memory.check_fits`)."""
    W, H = spec.camera.resolution
    values = {n: tbase.get(n).resolve(o) for n, o in techniques.items()}
    return check_fits(spec, values, ss=ss, what=f"a frame of scene {spec.name!r} at {W}×{H}", size_option=size_option)
