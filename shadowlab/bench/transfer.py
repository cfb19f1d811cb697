"""Fit in shadowlab, paste into the engine: ``shadowlab bench --only transfer`` (``transfer.json``,
``transfer.md``; not in the full run: it needs Chromium and the engines' npm packages).

For each case (scene, shadowlab technique, engine technique), in one run:

1. shadowlab's technique is fitted to the truth with its default fit parameters
   (:func:`shadowlab.fit.run.plan` / ``execute``, the search ``shadowlab fit`` runs);
2. its fitted values are transferred onto the engine (:mod:`shadowlab.techniques.transfer`: per
   receiver point in world units through the engine's own shadow camera, the median);
3. the engine's error (its own fit loss, :func:`~shadowlab.fit.run.default_loss`) is measured at
   its defaults, with the transferred values, and after its own fit with the same budget;
4. parity (:func:`shadowlab.fit.transfer.parity`): shadowlab's image against the engine's with the
   transferred values, away from the truth's penumbra and inside it.

Every engine render of a case keeps the engine's own map size and (``ENGINE_SETS``) what a user of
that scene sets first: the sun's orthographic frustum on ``street`` (three.js's ±5 m default shadows
nothing in a 400 m scene; 159 m is what fitting ``extent`` found). Parity is measured with the
engine's map as many texels as shadowlab's.
"""

from __future__ import annotations

import datetime
from pathlib import Path

from .. import backend
from ..fit.run import Budget, default_loss, execute, plan, prepare
from ..fit.transfer import transfer
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..techniques import base
from ..techniques.engines import package_version
from .timing import machine_text

#: (scene, shadowlab technique, engine technique)
CASES = (
    ("contact", "pcf", "three:pcf"), ("two_lights", "pcf", "three:pcf"), ("foliage", "pcf", "three:pcf"),
    ("street", "pcf", "three:pcf"),
    ("contact", "hard", "three:basic"), ("two_lights", "hard", "three:basic"), ("foliage", "hard", "three:basic"),
    ("contact", "vsm", "three:vsm"), ("two_lights", "vsm", "three:vsm"), ("foliage", "vsm", "three:vsm"),
    ("contact", "hard", "babylon:basic"), ("two_lights", "hard", "babylon:basic"), ("foliage", "hard", "babylon:basic"),
)
#: engine settings kept through the transfer, per scene
ENGINE_SETS = {"street": {"extent": 159.4}}


def case(scene: str, source: str, target: str, budget: Budget) -> dict:
    """One row: shadowlab's fit of ``source``, its transfer to ``target`` and the engine's own fit."""
    sc, truth, meta, frame = prepare(scene)
    src = base.get(source)
    fitted = execute(plan(source, frame, loss=default_loss(target)), frame, truth, budget)
    values = {k: v["fitted"] for k, v in fitted["params"].items()}
    sets = [f"{source}.{k}={v}" for k, v in values.items()]
    sets += [f"{target}.{k}={v}" for k, v in ENGINE_SETS.get(scene, {}).items()]
    rec = transfer(scene, source, target, sets=sets, fit_engine=True, budget=budget)
    rec["source_fit"] = {"params": list(src.fit_params(src.resolve(values))), "values": values,
                         "loss_before": fitted["loss_before"], "loss_after": fitted["loss_after"]}
    return rec


def _fmt(values: dict) -> str:
    return ", ".join(f"`{k}` {v:.4g}" if isinstance(v, float) else f"`{k}` {v}" for k, v in values.items())


def _parity(p: dict) -> str:
    return "—" if not p["pixels"] else f"{p['mean_abs']:.3f} ({100 * p['within_0.05']:.0f} %)"


def markdown(res: dict) -> str:
    lines = ["# Fit in shadowlab, paste into the engine", "",
             f"Machine: {machine_text(res['machine'])}. Date: {res['date']}. Engines: three.js "
             f"{res['three']} and Babylon.js {res['babylon']} in headless Chromium (SwiftShader). Loss: the "
             "engine's fit loss against the truth "
             "(visibility RMSE over the truth's penumbra, noise floor subtracted) at each scene's stored "
             f"reference; every fit: {res['budget']['evals']} evaluations per parameter, "
             f"{res['budget']['rounds']} round.", "",
             "| scene | shadowlab fit | its loss | engine | engine at defaults | transferred values | "
             "engine with them | engine's own fit | engine after it | parity: interior | parity: penumbra |",
             "|---|---|---:|---|---:|---|---:|---|---:|---:|---:|"]
    for r in res["cases"]:
        kept = f" ({_fmt(r['engine_kept'])})" if r["engine_kept"] else ""
        lines.append(f"| {r['scene']} | `{r['source']}`: {_fmt(r['source_fit']['values'])} | {r['source_loss']:.3f} "
                     f"| `{r['target']}`{kept} | {r['engine_loss_defaults']:.3f} | {_fmt(r['transferred'])} | "
                     f"{r['engine_loss_transferred']:.3f} | {_fmt(r['engine_fit'])} | {r['engine_loss_fit']:.3f} | "
                     f"{_parity(r['parity']['interior'])} | {_parity(r['parity']['penumbra'])} |")
    lines += ["", "Parity: shadowlab's technique at its fitted values against the engine with the values transferred "
              "for a map of as many texels as shadowlab's, "
              "pooled over the lights at the pixels each reaches: mean absolute difference of the visibilities and, "
              "in brackets, the share of pixels within 0.05; interior = the truth's umbra and lit pixels more than 2 "
              "pixels from its penumbra (bias, acne and precision), penumbra = 0.02 < V < 0.98 (the filters).",
              "", "How the values map (per receiver point through the engine's own shadow camera, then the median "
              "over the points): [engines](../engines.md#transfer-fit-in-shadowlab-paste-into-the-engine)."]
    return "\n".join(lines) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Every case of :data:`CASES` (``quick``: the first, with a small budget); write
    ``out/transfer.json`` and ``out/transfer.md``; return the .md path."""
    backend.init()
    budget = Budget(evals=4 if quick else 10, rounds=1)
    cases = CASES[:1] if quick else CASES
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "three": package_version("three"), "babylon": package_version("@babylonjs/core"),
           "budget": {"evals": budget.evals, "rounds": budget.rounds},
           "cases": [case(s, a, b, budget) for s, a, b in cases]}
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "transfer.json", res)
    return write_bytes_atomic(out / "transfer.md", markdown(res).encode())
