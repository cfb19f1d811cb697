"""The fitting objective: a technique's visibility against the stored truth, as a Dr.Jit expression.

Losses (``--loss``), all against the reference of the scene at the fit's resolution:

* ``rmse_penumbra`` (default): visibility RMSE over the truth's penumbra (0.02 < V < 0.98, the
  metrics' mask) of every light, pooled over lights, only where the light reaches (U_L > 0);
* ``rmse``: the same over every pixel a light reaches;
* ``flip``: mean LDR-FLIP (``metrics.flip_map``) of the shaded image Σ U_L·V_L over the penumbra
  (union over lights); computed in numpy, so it has no gradient: ``flip`` fits are derivative-free.

Noise floor. The truth t̂ is a Monte Carlo estimate with per-pixel standard error σ (the
reference's ``V.<light>.se``): E[(x − t̂)²] = (x − t)² + σ², so the expected squared error of even
a perfect technique is mean σ² over the mask. The RMSE losses report √max(MSE − mean σ², 0) (the
error against the noise-free truth); the optimisers minimise the MSE itself (same minimiser,
no flat clamp at 0). FLIP is not quadratic in the error and is reported as is.

The truth, the mask weights and the floor are uploaded once as constant Dr.Jit arrays; the loss
of a render is ``Σ_L Σ_i w_i (v_i − t_i)²`` with v the technique's visibility (averaged over the
s×s sub-pixel shading points of a pixel when the reference was rendered with supersampling, by
``dr.block_sum``), so ``dr.backward`` of it reaches the technique's Dr.Jit parameters.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from ..metrics import flip_map
from ..render.shading import compose

LOSSES = {
    "rmse_penumbra": "visibility RMSE over the truth's penumbra (0.02 < V < 0.98), pooled over lights, "
                     "noise floor subtracted",
    "rmse": "visibility RMSE over every pixel a light reaches, pooled over lights, noise floor subtracted",
    "flip": "mean LDR-FLIP of the shaded image over the penumbra (union over lights); no gradient",
}
DIFFERENTIABLE_LOSSES = ("rmse_penumbra", "rmse")


def check_loss(loss: str) -> str:
    if loss not in LOSSES:
        raise InputError(f"--loss {loss!r}: expected one of {', '.join(LOSSES)}")
    return loss


class KernelCounter:
    """Counts the Dr.Jit JIT kernels launched while active (``dr.kernel_history``): ``take()``
    returns and resets {launched, compiled (built from scratch), disk (loaded from the on-disk
    cache), new (= compiled + disk: not in the in-memory cache)} since the last ``take()``."""

    def __enter__(self):
        self._prev = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history_clear()
        return self

    def __exit__(self, *exc):
        dr.kernel_history_clear()
        dr.set_flag(dr.JitFlag.KernelHistory, self._prev)
        return False

    @staticmethod
    def take() -> dict:
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        # measured on drjit 1.5: a kernel loaded from the disk cache has cache_hit = cache_disk = 1,
        # an in-memory hit cache_hit = 1, cache_disk = 0, a compiled one both 0
        compiled = sum(1 for k in jit if not k.get("cache_hit") and not k.get("cache_disk"))
        disk = sum(1 for k in jit if k.get("cache_disk"))
        return {"launched": len(jit), "compiled": compiled, "disk": disk, "new": compiled + disk}


class Objective:
    """The loss of one technique on one frame against its truth; counts renders.

    ``fixed``: the technique's parameter values that do not change during the fit (validated).
    ``value(values)`` renders forward only and returns the objective (MSE, or mean FLIP);
    ``loss_dr(values)`` returns it as a Dr.Jit Float of width 1 (values may hold Dr.Jit
    Floats with gradients enabled); ``report(obj)`` turns an objective into the reported loss.
    """

    def __init__(self, frame, truth, technique, loss: str = "rmse_penumbra", fixed: dict | None = None):
        self.frame, self.truth, self.tech = frame, truth, technique
        self.loss = check_loss(loss)
        self.fixed = dict(fixed or {})
        self.lights = [l.name for l in frame.lights]
        self.ss2 = int(frame.gbuffer.ss) ** 2
        regions, pen_union = {}, np.zeros(truth.mask.shape, bool)
        for name in self.lights:
            t = truth.lights[name].V
            valid = truth.mask & frame.lit_mask(name)
            pen = valid & (t > 0.02) & (t < 0.98)
            pen_union |= pen
            regions[name] = valid if loss == "rmse" else pen
        self.pixels = int(sum(int(r.sum()) for r in regions.values()))
        if self.pixels == 0:
            what = "pixel any light reaches" if loss == "rmse" else "penumbra pixel (0.02 < V < 0.98)"
            raise InputError(f"the reference has no {what}: nothing to fit; "
                             + ("use --loss rmse" if loss != "rmse" else "check the scene and its reference"))
        self.penumbra = pen_union & truth.mask
        floor = 0.0
        self._T, self._W = {}, {}
        for name in self.lights:
            r = regions[name]
            se = truth.lights[name].V_se.astype(np.float64)
            floor += float(np.sum(se[r] ** 2))
            self._T[name] = mi.Float(np.ascontiguousarray(truth.lights[name].V.ravel(), np.float32))
            self._W[name] = mi.Float(np.ascontiguousarray((r / self.pixels).ravel(), np.float32))
            dr.make_opaque(self._T[name], self._W[name])
        self.noise_floor = floor / self.pixels           # mean σ² over the mask (0 for flip: not used)
        self.evaluations = 0                             # technique renders
        self.gradients = 0                               # backward passes

    # -- rendering ---------------------------------------------------------------------------------
    def render(self, values: dict):
        self.evaluations += 1
        return self.tech.render(self.frame, {**self.fixed, **values})

    def _pixel(self, v):
        if self.ss2 == 1:
            return v
        return dr.block_sum(v, self.ss2) * (1.0 / self.ss2)

    def loss_dr(self, values: dict):
        """The objective as a Dr.Jit Float (width 1); differentiable losses only."""
        if self.loss not in DIFFERENTIABLE_LOSSES:
            raise InputError(f"--loss {self.loss} has no gradient; use --method golden or grid")
        res = self.render(values)
        return self._squared(res), res

    def _squared(self, res):
        out = None
        for name in self.lights:
            d = self._pixel(res.visibility[name]) - self._T[name]
            term = dr.sum(self._W[name] * dr.square(d))
            out = term if out is None else out + term
        return out

    def value(self, values: dict) -> float:
        """Objective of ``values`` (forward only)."""
        return self.value_of(self.render(values))

    def value_of(self, res) -> float:
        """Objective of a render already made (a ShadowResult of this frame and technique)."""
        if self.loss == "flip":
            return self._flip(res)
        return float(self._squared(res)[0])

    def _flip(self, res) -> float:
        shaded = compose(self.frame, res.visibility, res.colour)
        fm = flip_map(shaded, self.truth.shaded)
        return float(fm[self.penumbra].mean()) if self.penumbra.any() else float(fm[self.truth.mask].mean())

    def report(self, objective: float) -> float:
        """The reported loss of an objective value: noise-corrected RMSE, or mean FLIP."""
        if self.loss == "flip":
            return float(objective)
        return float(np.sqrt(max(objective - self.noise_floor, 0.0)))

    def describe(self) -> dict:
        d = {"name": self.loss, "description": LOSSES[self.loss], "pixels": self.pixels}
        if self.loss != "flip":
            d["noise_floor_rmse"] = float(np.sqrt(self.noise_floor))
            d["noise_floor_subtracted"] = True
        else:
            d["noise_floor_subtracted"] = False
        return d


class MeanObjective:
    """The mean of several :class:`Objective` s of one technique (the frames of a camera path):
    one preset for the whole path. The objective is the mean of the frames' objectives (each a
    mean over its own mask), the reported loss √max(mean objective − mean noise floor, 0);
    ``evaluations`` counts every frame's render."""

    def __init__(self, objectives: list):
        if not objectives:
            raise ValueError("MeanObjective needs at least one objective")
        self.parts = list(objectives)
        first = self.parts[0]
        self.frame, self.truth, self.tech, self.loss, self.fixed = (
            first.frame,
            first.truth,
            first.tech,
            first.loss,
            first.fixed,
        )
        self.lights = first.lights
        self.pixels = sum(o.pixels for o in self.parts)
        self.noise_floor = float(np.mean([o.noise_floor for o in self.parts]))
        self.gradients = 0

    @property
    def evaluations(self) -> int:
        return sum(o.evaluations for o in self.parts)

    def loss_dr(self, values: dict):
        """Mean of the frames' Dr.Jit losses (the first frame's render is returned with it)."""
        out, first = None, None
        for o in self.parts:
            loss, res = o.loss_dr(values)
            out, first = (loss, res) if out is None else (out + loss, first)
        return out * (1.0 / len(self.parts)), first

    def value(self, values: dict) -> float:
        return float(np.mean([o.value(values) for o in self.parts]))

    def report(self, objective: float) -> float:
        if self.loss == "flip":
            return float(objective)
        return float(np.sqrt(max(objective - self.noise_floor, 0.0)))

    def describe(self) -> dict:
        d = self.parts[0].describe()
        d.update(pixels=self.pixels, frames=len(self.parts),
                 description=d["description"] + f"; mean over {len(self.parts)} frames")
        if self.loss != "flip":
            d["noise_floor_rmse"] = float(np.sqrt(self.noise_floor))
        return d
