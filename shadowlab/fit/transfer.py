"""``shadowlab transfer``: a shadowlab technique's values mapped onto an engine's parameters, and
what the engine's error is with them.

The mapping is :mod:`shadowlab.techniques.transfer` (per receiver point in world units, the median
over the points). This job measures it against the truth with the engine's own loss
(:func:`~shadowlab.fit.run.default_loss`): shadowlab's technique at its values, the engine at its
defaults, the engine with the transferred values and, with ``fit_engine``, the engine after its own
fit (the same search ``shadowlab fit -t ENGINE`` runs), all with the engine settings ``--set`` gives
(its own ``mapSize`` unless set). Parity (:func:`parity`) compares shadowlab's image with the
engine's at the same map size (the values transferred again for that map). It saves the
transferred values as a preset of the engine's own property names.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from ..errors import InputError
from ..reference import store
from ..techniques import base as tbase
from ..techniques import transfer as T
from . import preset as P
from .objective import Objective
from .run import Budget, default_loss, execute, plan, prepare


def transfer(scene: str, source: str, target: str, *, sets=None, preset=None, loss: str | None = None,
             resolution=None, base: Path | None = None, save_preset=None, force: bool = False,
             fit_engine: bool = False, budget: Budget | None = None) -> dict:
    """The ``shadowlab transfer`` job (module docstring). ``sets``: ``TECHNIQUE.PARAM=VALUE`` for the
    source (its values) and the target (the engine settings the transfer keeps, e.g. ``mapSize``);
    ``preset``: a preset file holding the source's values (e.g. the one ``shadowlab fit`` saved)."""
    src, tgt = tbase.get(source), tbase.get(target)
    T.check_pair(src, tgt)
    pre = P.load(preset) if preset else None
    sets_by = tbase.parse_sets(sets or [], [source, target])
    protected = [base or store.root()]
    if save_preset is not None:
        P.check_writable(save_preset, force, protected)
    sc, truth, meta, frame = prepare(scene, resolution, base)
    for t in (src, tgt):
        why = t.unsupported(sc.spec)
        if why:
            raise InputError(why)
    src_values = src.resolve({**(pre.values.get(source, {}) if pre else {}), **sets_by.get(source, {})})
    kept = dict(sets_by.get(target, {}))
    eng_base = tgt.resolve(kept)
    loss = loss or default_loss(target)
    obj_e = Objective(frame, truth, tgt, loss)
    obj_s = Objective(frame, truth, src, loss)
    first = tgt.render(frame, eng_base)                       # the engine's shadow cameras at its settings
    mapped = T.transfer(frame, src, src_values, tgt, eng_base, first.stats)
    eng_t = tgt.resolve({**eng_base, **mapped["values"]})
    res_s, res_t = src.render(frame, src_values), tgt.render(frame, eng_t)
    rec = {"scene": sc.name, "resolution": list(sc.resolution), "source": source, "target": target,
           "loss": obj_e.describe(), "source_values": {k: src_values[k] for k in src.fit_params(src_values)},
           "source_loss": obj_s.report(obj_s.value_of(res_s)),
           "engine_defaults": {k: eng_base[k] for k in mapped["values"]}, "engine_kept": kept,
           "engine_loss_defaults": obj_e.report(obj_e.value_of(first)),
           "transferred": mapped["values"], "spread": mapped["spread"], "points": mapped["points"],
           "engine_loss_transferred": obj_e.report(obj_e.value_of(res_t))}
    # parity: the engine's map as many texels as shadowlab's, the values transferred for that map
    same = {**kept, **T.map_size(frame, src, src_values, tgt)}
    eng_p, res_p = eng_t, res_t
    p_base = tgt.resolve(same)
    if p_base != eng_base:
        p_map = T.transfer(frame, src, src_values, tgt, p_base, tgt.render(frame, p_base).stats)
        eng_p = tgt.resolve({**p_base, **p_map["values"]})
        res_p = tgt.render(frame, eng_p)
    rec["parity"] = {**parity(frame, truth, res_s, res_p),
                     "engine_values": {k: eng_p[k] for k in (*mapped["values"], *same)}}
    if fit_engine:
        own = execute(plan(target, frame, loss=loss, sets=kept), frame, truth, budget or Budget())
        rec["engine_fit"] = {k: v["fitted"] for k, v in own["params"].items()}
        rec["engine_loss_fit"] = own["loss_after"]
        rec["engine_fit_evaluations"] = own["evaluations"]
    if save_preset is not None:
        P.save(save_preset, f"{sc.name}-{target}-from-{source}", {target: mapped["values"]},
               description=f"{source} values transferred to {target} on {sc.name}",
               meta={"scene": sc.name, "source": source, "loss_transferred": rec["engine_loss_transferred"]},
               force=force, protected=protected)
        rec["preset"] = str(save_preset)
    return rec


def parity(frame, truth, a, b, *, margin: int = 2) -> dict:
    """How far two renders' visibilities differ (``a`` shadowlab's, ``b`` the engine's), pooled over
    the lights at the pixels the light reaches: ``interior`` (the truth's umbra and lit pixels more
    than ``margin`` pixels from its penumbra 0.02 < V < 0.98: bias and precision) and ``penumbra``
    (the filter): mean |a − b| and the fraction within 0.05 of each other.

    >>> class F:
    ...     lights = [type("L", (), {"name": "k"})]
    ...     image = staticmethod(lambda x: x)
    ...     lit_mask = staticmethod(lambda n: np.ones((1, 6), bool))
    >>> class T:
    ...     mask = np.ones((1, 6), bool)
    ...     lights = {"k": type("V", (), {"V": np.array([[0.0, 0.0, 0.0, 0.5, 1.0, 1.0]])})}
    >>> res = lambda v: type("R", (), {"visibility": {"k": np.array([v])}})   # noqa: E731
    >>> p = parity(F, T, res([0.0, 0.0, 0.0, 0.5, 1.0, 1.0]), res([0.0, 0.0, 1.0, 0.2, 1.0, 1.0]), margin=0)
    >>> p["interior"], p["penumbra"]
    ({'pixels': 5, 'mean_abs': 0.2, 'within_0.05': 0.8}, {'pixels': 1, 'mean_abs': 0.3, 'within_0.05': 0.0})
    """
    diff, regions = {"interior": [], "penumbra": []}, {}
    for light in frame.lights:
        t = truth.lights[light.name].V
        reach = truth.mask & frame.lit_mask(light.name)
        pen = reach & (t > 0.02) & (t < 0.98)
        near = ndimage.binary_dilation(pen, iterations=margin) if margin else pen
        regions = {"interior": reach & ~near, "penumbra": pen}
        d = np.abs(np.asarray(frame.image(a.visibility[light.name]), np.float64)
                   - np.asarray(frame.image(b.visibility[light.name]), np.float64))
        for k, m in regions.items():
            diff[k].append(d[m])
    out = {}
    for k, parts in diff.items():
        d = np.concatenate(parts) if parts else np.zeros(0)
        out[k] = {"pixels": int(d.size), "mean_abs": round(float(d.mean()), 6) if d.size else None,
                  "within_0.05": round(float((d < 0.05).mean()), 6) if d.size else None}
    return out


def summary(rec: dict) -> str:
    """The terminal lines of a transfer: the values (with their spread over the points) and the losses."""
    kept = ", ".join(f"{k} {v}" for k, v in rec["engine_kept"].items())
    lines = [f"{rec['source']} -> {rec['target']} on {rec['scene']} ({rec['points']} receiver points; "
             f"loss {rec['loss']['name']}; engine settings kept: {kept or 'its defaults'})", "",
             "| parameter | engine default | transferred | 10th-90th percentile over the points |",
             "|---|---:|---:|---|"]
    for k, v in rec["transferred"].items():
        lo, hi = rec["spread"][k]
        lines.append(f"| {k} | {rec['engine_defaults'][k]:.4g} | {v:.4g} | {lo:.4g} … {hi:.4g} |")
    lines += ["", "| | loss |", "|---|---:|",
              f"| {rec['source']} (shadowlab) at its values | {rec['source_loss']:.4f} |",
              f"| {rec['target']} at its defaults | {rec['engine_loss_defaults']:.4f} |",
              f"| {rec['target']} with the transferred values | {rec['engine_loss_transferred']:.4f} |"]
    size = rec["parity"]["engine_values"].get("mapSize")
    for k, what in (("interior", "umbra and lit, away from the penumbra"), ("penumbra", "the truth's penumbra")):
        p = rec["parity"][k]
        if p["pixels"]:
            lines.append(f"| {rec['source']} against {rec['target']}{f' (mapSize {size})' if size else ''}, {what}: "
                         "mean abs. difference "
                         f"(share within 0.05) | {p['mean_abs']:.4f} ({100 * p['within_0.05']:.1f} %) |")
    if "engine_loss_fit" in rec:
        fit = ", ".join(f"{k} {v:.4g}" for k, v in rec["engine_fit"].items())
        lines.append(f"| {rec['target']} after its own fit ({fit}) | {rec['engine_loss_fit']:.4f} |")
    return "\n".join(lines)
