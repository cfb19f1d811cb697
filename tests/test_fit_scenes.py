"""``shadowlab fit SCENE...``: one preset over several scenes, evaluated as one job per scene frame.

Two small scenes (``parallel_planes`` and ``contact`` at 48², references rendered into a
temporary store): the joint objective is the mean of the scenes' own objectives (values and
gradients), a grid fit's joint loss is no worse than the joint loss at either scene's own best
grid point, the jobs on the embedded executor reproduce the in-process search bit for bit, a
2-process Dask cluster reproduces the embedded run bit for bit (golden section and Adam), and a
fit over scenes without references exits 2 listing every missing one with the command.
"""

import json
import time

import numpy as np
import pytest

RES = (48, 48)
SCENES = ["parallel_planes", "contact"]


def _cli(*args):
    from shadowlab.cli import main
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def store2(mitsuba_backend, tmp_path_factory):
    from shadowlab.pipeline import reference_batch
    base = tmp_path_factory.mktemp("refs")
    reference_batch(SCENES, RES, base=base, target_se=0.02, max_rounds=8, spp=0, progress=False)
    return base


@pytest.fixture(scope="module")
def prepared(store2):
    from shadowlab.fit import run as R
    return R.prepare_scenes(SCENES, RES, store2)


def _parts(prepared, store2, tech="pcss", loss="rmse_penumbra", fixed=None):
    from shadowlab.fit.objective import Objective
    from shadowlab.fit.parts import Part, PartsObjective
    from shadowlab.techniques import get
    flat = [x for ps in prepared for x in ps]
    objs = [Objective(f, t, get(tech), loss, fixed=fixed or {}) for _, t, _, f in flat]
    parts = [Part.of(sc, store2) for sc, *_ in flat]
    return PartsObjective(None, parts, objs, tech, loss, fixed or {}), objs


def _fit(store2, scenes, tech, executor=None, **kw):
    from shadowlab.fit import run as R
    budget = {k: kw.pop(k) for k in ("steps", "evals", "points") if k in kw}
    return R.fit(scenes, tech, resolution=RES, base=store2, budget=R.Budget(**budget), executor=executor, **kw)


def _trace(r: dict) -> list:
    """What must be the same bits whatever ran the jobs (not the timings or kernel counts)."""
    return [(h["stage"], h["values"], h["objective"], h["loss"], h.get("grad_unit")) for h in r["history"]]


# ------------------------------------------------------------------------------------------------
# the joint objective


def test_joint_objective_and_gradient_are_the_means_of_the_scenes(prepared, store2):
    import drjit as dr
    import mitsuba as mi
    from shadowlab.fit import search as S
    from shadowlab.techniques import get
    joint, objs = _parts(prepared, store2)
    try:
        for x in (0.6, 1.0, 1.7):
            own = [o.value({"light_scale": x}) for o in objs]
            assert joint.value({"light_scale": x}) == float(np.mean(own))
            per = joint.by_scene({"light_scale": x})
            assert list(per) == SCENES
            assert [per[n]["objective"] for n in SCENES] == own
            for n, o in zip(SCENES, objs):          # each scene's loss: its own objective's report
                assert per[n]["loss"] == o.report(per[n]["objective"])
        assert len(set(own)) == 2                     # two different scenes, two different losses
        # the gradient in unit coordinates: the mean of each scene's own dr.backward
        d = S.make_dim(get("pcss").param("light_scale"), "adam", 1.0, 1.0)
        u = d.to_unit(0.8)
        o, xs, g = joint.loss_grad({}, [d], {"light_scale": u})
        grads, losses = [], []
        for ob in objs:
            uu = dr.opaque(mi.Float, u)
            dr.enable_grad(uu)
            loss, _ = ob.loss_dr({"light_scale": d.from_unit_dr(uu)})
            dr.backward(loss)
            grads.append(float(dr.grad(uu)[0]))
            losses.append(float(loss[0]))
        assert g["light_scale"] == float(np.mean(grads)) and o == float(np.mean(losses))
        assert xs["light_scale"] == pytest.approx(0.8, rel=1e-6)
        assert joint.evaluations == 3 * 2 + 2 and joint.pixels == sum(ob.pixels for ob in objs)
    finally:
        joint.close()


def test_embedded_jobs_reproduce_the_in_process_search(prepared, store2):
    """The job path on the embedded executor evaluates exactly what Search on the Objective
    (one scene) or the MeanObjective (several parts) evaluated before it existed."""
    from shadowlab.fit import run as R
    from shadowlab.fit import search as S
    from shadowlab.fit.objective import KernelCounter, MeanObjective, Objective
    sc, truth, meta, frame = prepared[0][0]
    for tech, params, method, budget, more in (
            ("pcss", ["light_scale"], "adam", R.Budget(steps=3), []),
            ("pcss", ["light_scale"], "golden", R.Budget(evals=6), [(prepared[1][0][3], prepared[1][0][1])])):
        p = R.plan(tech, frame, params=params, method=method, sets={"light_scale": 0.5})
        parts = [R.Part.of(s_, store2) for s_ in (sc, *([prepared[1][0][0]] if more else []))]
        r = R.execute(p, frame, truth, budget, more, parts=parts)
        objs = [Objective(f, t, p.tech, p.loss, fixed=p.fixed) for f, t in [(frame, truth), *more]]
        obj = objs[0] if len(objs) == 1 else MeanObjective(objs)
        with KernelCounter() as kc:
            s = S.Search(obj, kc, tuple(p.names), start=dict(p.start))
            S.optimise(s, p.dims, steps=budget.steps, lr=budget.lr, evals=budget.evals, points=budget.points,
                       rounds=budget.rounds, fallback=False, beta_1=budget.beta_1, decay=budget.decay)
        assert _trace(r) == [(h["stage"], h["values"], h["objective"], h["loss"], h.get("grad_unit"))
                             for h in s.history]


def test_joint_grid_fit_is_no_worse_than_either_scenes_own_preset(prepared, store2):
    """On one grid (same window: the default start and the declared range), the joint search's
    best point minimises the mean over the grid, so the joint loss there is ≤ the joint loss at
    each scene's own best grid point; each scene's reported loss with the joint preset is its
    own objective there."""
    joint_run = _fit(store2, SCENES, "pcss", method="grid", points=9)
    own = [_fit(store2, [s], "pcss", method="grid", points=9) for s in SCENES]
    rj = joint_run["techniques"]["pcss"]
    grid = [h["values"]["light_scale"] for h in rj["history"][1:]]
    for r in own:
        assert [h["values"]["light_scale"] for h in r["techniques"]["pcss"]["history"][1:]] == grid

    def best(r):
        h = min(r["history"], key=lambda e: e["objective"])
        return h["values"]["light_scale"], h["objective"]

    xj, oj = best(rj)
    joint, objs = _parts(prepared, store2)
    try:
        assert joint.value({"light_scale": xj}) == oj
        for r in own:
            xs, _ = best(r["techniques"]["pcss"])
            assert oj <= joint.value({"light_scale": xs})
        # the per-scene results beside the joint preset are each scene's own objective
        x_after = rj["params"]["light_scale"]["fitted"]
        for n, o in zip(SCENES, objs):
            e = rj["scenes"][n]
            assert e["objective_after"] == o.value({"light_scale": x_after})
            assert e["loss_after"] == o.report(e["objective_after"])
            assert e["loss_before"] == own[SCENES.index(n)]["techniques"]["pcss"]["loss_before"]
        assert rj["objective_after"] == float(np.mean([rj["scenes"][n]["objective_after"] for n in SCENES]))
    finally:
        joint.close()
    assert joint_run["scene"] == "parallel_planes+contact"
    assert [e["name"] for e in joint_run["scenes"]] == SCENES
    assert "mean over 2 scenes" in rj["loss"]["description"] and rj["loss"]["scenes"] == 2


# ------------------------------------------------------------------------------------------------
# distributed


def test_two_dask_workers_give_the_same_bits_as_the_embedded_run(store2, dask_workers):
    for tech, kw in (("esm", dict(method="golden", evals=4)), ("pcss", dict(method="adam", steps=3))):
        t0 = time.perf_counter()
        a = _fit(store2, SCENES, tech, **kw)
        t1 = time.perf_counter()
        b = _fit(store2, SCENES, tech, executor=dask_workers, **kw)
        t2 = time.perf_counter()
        ra, rb = a["techniques"][tech], b["techniques"][tech]
        assert _trace(ra) == _trace(rb) and len(ra["history"]) >= 4
        assert ra["preset_values"] == rb["preset_values"] and ra["params"] == rb["params"]
        for k in ("loss_before", "loss_after", "objective_before", "objective_after", "evaluations",
                  "gradient_evaluations", "scenes", "metrics_after"):
            assert ra[k] == rb[k], k
        assert b["executor"]["kind"] == "dask" and b["executor"]["workers"] == 2 and "executor" not in a
        if tech == "pcss":
            assert rb["gradient_evaluations"] == 3 and all("grad_unit" in h for h in rb["history"][:3])
        # the workers' kernels are counted too
        assert rb["kernels"]["launched"] > 0
        print(f"{tech} {kw}: embedded {t1 - t0:.2f} s, 2 workers {t2 - t1:.2f} s")


# ------------------------------------------------------------------------------------------------
# the command


def test_cli_fit_over_two_scenes_writes_the_joint_preset_and_each_scenes_loss(store2, tmp_path, monkeypatch, capsys):
    from shadowlab.fit import preset as P
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store2))
    monkeypatch.chdir(tmp_path)
    assert _cli("fit", *SCENES, "-t", "esm", "-r", "48x48", "--method", "golden", "--evals", "4") == 0
    out = tmp_path / "reports" / "fit" / "parallel_planes+contact-esm"
    data = json.loads((out / "fit.json").read_text())
    r = data["techniques"]["esm"]
    assert set(r["scenes"]) == set(SCENES) and [e["name"] for e in data["scenes"]] == SCENES
    assert data["preset"]["values"]["esm"]["exponent"] == r["params"]["exponent"]["fitted"]
    md = (out / "summary.md").read_text()
    page = (out / "index.html").read_text()
    for n in SCENES:
        assert f"| esm | {n} |" in md and f"<td>{n}</td>" in page
    pre = P.load(out / "preset.toml")
    assert pre.values["esm"]["exponent"] == r["params"]["exponent"]["fitted"]
    assert "parallel_planes 48x48, contact 48x48" in (out / "preset.toml").read_text()
    assert "| esm | contact |" in capsys.readouterr().out


def test_cli_fit_over_scenes_without_references_exits_2_listing_every_one(store2, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store2))
    out = tmp_path / "o"
    assert _cli("fit", "parallel_planes", "two_lights", "cornell", "-t", "pcss", "-r", "48x48", "-o", out) == 2
    err = capsys.readouterr().err
    assert "two_lights 48x48: missing" in err and "cornell 48x48: missing" in err and "parallel_planes 48x48" not in err
    assert "shadowlab reference two_lights cornell -r 48x48" in err
    assert not out.exists()
    # a scene named twice, a bad worker count: exit 2 before anything runs
    assert _cli("fit", "contact", "contact", "-t", "pcss", "-r", "48x48", "-o", out) == 2
    assert "named twice" in capsys.readouterr().err
    assert _cli("fit", *SCENES, "-t", "pcss", "-r", "48x48", "--workers", "0", "-o", out) == 2
    assert "--workers 0" in capsys.readouterr().err and not out.exists()


def test_joint_name_shortens_long_lists():
    from shadowlab.fit.run import default_out, joint_name
    assert default_out(["contact"], "pcss") == "reports/fit/contact-pcss"
    assert default_out(["a.toml", "b"], None, True) == "reports/fit/a+b-all"
    long = [f"scene_number_{i}" for i in range(6)]
    n = joint_name(long)
    assert len(n) <= 48 and n.startswith("scene_number_0+") and n.endswith("-more")
    assert int(n.rsplit("+", 1)[1].split("-")[0]) == 6 - n.count("scene_number_")


def test_a_job_loads_its_part_once_per_process_and_refuses_a_changed_scene(prepared, store2, monkeypatch):
    """Not lent by a fit, a job loads (scene, frame, truth, objective) itself, once: the second job
    of that part hits the process cache and both equal the fitting process's own objective."""
    import dataclasses
    from shadowlab.errors import InputError
    from shadowlab.fit import parts as PT
    from shadowlab.fit.objective import Objective
    from shadowlab.techniques import get
    sc, truth, meta, frame = prepared[1][0]
    part = PT.Part.of(sc, store2)
    loads = []
    real = PT.make_frame
    monkeypatch.setattr(PT, "make_frame", lambda *a, **k: (loads.append(1), real(*a, **k))[1])
    monkeypatch.setattr(PT, "_CACHE", type(PT._CACHE)())
    own = Objective(frame, truth, get("pcss"), "rmse_penumbra").value({"light_scale": 1.3})
    job = PT.PartJob(part, "pcss", "rmse_penumbra", (), (("light_scale", 1.3),))
    a, b = PT.evaluate_part(job), PT.evaluate_part(job)
    assert a["objective"] == b["objective"] == own and len(loads) == 1 and a["kernels"]["launched"] > 0
    stale = dataclasses.replace(job, part=dataclasses.replace(part, digest="0" * 64))
    with pytest.raises(InputError, match="changed while it was being fitted"):
        PT.evaluate_part(stale)
