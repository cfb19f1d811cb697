"""``shadowlab bench --only frames``: one small run (64×36, ``contact``, two techniques) and what
must hold of what it writes: the record's fields, a split that adds up to the frame, the rays it
counts. Never its speeds."""

import json

import drjit as dr
import mitsuba as mi
import pytest

from conftest import CUDA  # noqa: E402  (tests/ is on the path)
from shadowlab.bench import core, frames, record

PLAN = (("contact", ("hard", "pcf")),)


@pytest.fixture(scope="module")
def bench(mitsuba_backend, tmp_path_factory):
    out = tmp_path_factory.mktemp("frames-bench")
    md = frames.run(out, size=(64, 36), plan=PLAN)
    rec = json.loads(record.write_record(out, "frames", md).read_text(encoding="utf-8"))
    return {"out": out, "md": md.read_text(encoding="utf-8"), "rec": rec}


def test_the_record_has_the_part_machine_and_a_row_per_technique(bench):
    rec = bench["rec"]
    assert rec["part"] == "frames" and rec["machine"]["variant"] and rec["machine"]["cores"] >= 1
    goals, table = [b for b in rec["blocks"] if b["type"] == "table"][:2]
    assert [r[0] for r in goals["rows"]] == [g[0] for g in frames.GOALS]
    for col in ("new frame", "G-buffer", "light views", "technique", "host", "split total", "warm",
                "kernels new / warm", "first sync, new frame", "rays (texels + taps)", "limit"):
        assert col in table["columns"], col
    assert [r[0] for r in table["rows"]] == ["hard", "pcf"]
    res = rec["results"]
    assert res["size"] == [64, 36] and list(res["scenes"]) == ["contact"]
    for r in res["scenes"]["contact"]["techniques"].values():
        for k in ("new_s", "new_runs_s", "new", "warm", "first_sync", "texels", "taps", "rays", "raw", "limit_s",
                  "new_over_limit"):
            assert k in r, k


def test_the_new_frame_is_the_median_plain_frame_and_sets_the_ratio(bench):
    """The new frame (the goals' figure) is the median of the plain frames; new / limit is over it."""
    for name, r in bench["rec"]["results"]["scenes"]["contact"]["techniques"].items():
        runs = sorted(r["new_runs_s"])
        assert len(runs) == frames.PLAIN_FRAMES and r["new_s"] == runs[len(runs) // 2], name
        assert r["new_s"] > 0 and r["new_over_limit"] == pytest.approx(r["new_s"] / r["limit_s"], rel=1e-12), name


def test_the_split_adds_up_to_the_new_frame(bench):
    for name, r in bench["rec"]["results"]["scenes"]["contact"]["techniques"].items():
        n = r["new"]
        parts = (n["gbuffer_s"], n["light_views_s"], n["technique_s"])
        assert all(p >= 0 for p in parts), (name, parts)
        assert sum(parts) <= n["total_s"] * (1 + 1e-9), (name, parts, n["total_s"])
        assert sum(parts) >= n["total_s"] * (1 - 1e-9), (name, parts, n["total_s"])
        assert 0 <= n["host_s"] <= n["total_s"]
        assert n["light_views_s"] > 0 and n["casts"] == 1, name      # contact: one light, one map cast
        by = n["kernels_by_part"]
        assert n["kernels"]["jit"] == sum(by[p]["jit"] for p in ("gbuffer", "light_views", "technique")) >= 1
        assert r["warm"]["kernels"]["jit"] >= 1


def test_the_rays_are_the_texels_cast_and_one_tap_per_point(bench, mitsuba_backend):
    from shadowlab.pipeline import load_scene
    from shadowlab.render.frame import make_frame
    sc = load_scene("contact", (64, 36))
    points = int(dr.count(make_frame(sc).gbuffer.valid)[0])
    side = sc.spec.lights[0].shadow_map
    for r in bench["rec"]["results"]["scenes"]["contact"]["techniques"].values():
        assert r["texels"] == side * side and r["taps"] == points
        assert r["rays"] == r["texels"] + r["taps"]
        assert r["raw"]["rays"] >= r["rays"] and r["raw"]["points"] == points


def test_first_sync_names_the_readback_and_none_without_one(mitsuba_backend):
    from shadowlab.pipeline import load_scene
    from shadowlab.render.frame import make_frame
    fr = make_frame(load_scene("contact", (16, 12)))
    x = fr.gbuffer.p.x + 1.0
    assert frames.first_sync(lambda: dr.eval(x * 2.0)) is None
    where = frames.first_sync(lambda: fr.gbuffer.to_image(x * 3.0))
    assert where is not None and where.startswith("shadowlab/render/gbuffer.py:") and "(to_image)" in where
    assert not dr.flag(dr.JitFlag.ForbidSynchronization)


def test_first_sync_collects_garbage_before_and_none_during(mitsuba_backend):
    """A scene of an earlier measurement freed by the garbage collector while synchronisation is
    forbidden waits for the device in its destructor, which ends the process: garbage is collected
    before ``fn`` (a cycle's finaliser has run when it starts) and the collector is off while it runs."""
    import gc
    import weakref

    class Cycle:
        pass

    events = []
    c = Cycle()
    c.me = c
    weakref.finalize(c, events.append, "freed")
    del c
    assert gc.isenabled()
    assert frames.first_sync(lambda: events.append(gc.isenabled())) is None
    assert events == ["freed", False] and gc.isenabled()


def test_kernel_summary_counts_kernels_and_one_element_reads(mitsuba_backend):
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        a = dr.arange(mi.Float, 1000) * dr.opaque(mi.Float, 2.0)
        dr.eval(a)
        b = a + dr.opaque(mi.Float, 1.0)
        dr.eval(b)
        _ = dr.sum(b)[0]
        dr.sync_thread()
        k = frames.kernel_summary(dr.kernel_history())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert k["jit"] == 2 and k["execution_ms"] >= 0
    if not CUDA:                      # the CUDA backend logs no copies in the kernel history
        assert k["memcpy"] >= 1 and k["memcpy_bytes"] >= 4


def test_timed_kernels_times_the_kernels_of_its_run(mitsuba_backend):
    from shadowlab.bench.timing import timed_kernels
    big = lambda: dr.eval(dr.sin(dr.arange(mi.Float, 1 << 22) * dr.opaque(mi.Float, 2.0)))  # noqa: E731
    small = lambda: dr.eval(dr.arange(mi.Float, 1000) * dr.opaque(mi.Float, 2.0))      # noqa: E731
    _, wall_big, ms_big = timed_kernels(big)
    _, wall_small, ms_small = timed_kernels(small)
    assert wall_big > 0 and wall_small > 0 and ms_big > 0 and ms_small > 0
    assert ms_small < ms_big                  # 1000 products against 4 M sines
    assert not dr.flag(dr.JitFlag.KernelHistory)


def test_frames_is_a_part_and_size_belongs_to_it(tmp_path, capsys):
    from shadowlab import cli
    assert "frames" in core.ONLY
    assert cli.main(["bench", "--only", "truth", "--size", "64x36", "--out", str(tmp_path / "b")]) == 2
    assert "--only frames" in capsys.readouterr().err
    assert cli.main(["bench", "--only", "frames", "--size", "64by36", "--out", str(tmp_path / "c")]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_goals_take_the_worst_technique_and_count_those_within():
    def tech(total, gbuffer, over, views=0.001):
        return {"new_s": total, "new": {"total_s": 2 * total, "gbuffer_s": gbuffer, "light_views_s": views},
                "new_over_limit": over,
                "limit_s": 0.001}
    res = {"scenes": {"contact": {"techniques": {"a": tech(0.008, 0.004, 3.0), "b": tech(0.012, 0.006, 6.0),
                                                 "c": tech(0.009, 0.005, 4.0), "sdf": tech(0.5, 0.004, 90.0, 0.0)}}}}
    rows = {r[0]: r[1:] for r in frames.goal_rows(res)}
    new, over, many, gbuffer = (rows[g[0]] for g in frames.GOALS)
    assert (round(new[1], 9), new[2], new[3]) == (12.0, 2, 3)                  # b's 12 ms; a and c within
    assert (over[1], over[2], over[3]) == (6.0, 2, 3)
    # street's families count in the one-light goals too, a virtual map (its tiles cast inside the
    # technique: no light-view time, but texels) among them
    res["scenes"]["street"] = {"techniques": {"vt": {**tech(0.2, 0.01, 40.0, 0.0), "texels": 10}}}
    rows = {r[0]: r[1:] for r in frames.goal_rows(res)}
    new, over = (rows[g[0]] for g in frames.GOALS[:2])
    assert (round(new[1], 9), new[2], new[3]) == (200.0, 2, 4) and (over[1], over[3]) == (40.0, 4)
    assert (round(gbuffer[1], 9), gbuffer[2], gbuffer[3]) == (5.0, 2, 3)          # the median; 4 and 5 ms within
    assert many == (50.0, None, 0, 0)                                            # no many_lights in this run


def test_the_replay_floor_is_a_replayed_stage_over_the_scene(bench, mitsuba_backend):
    """Each scene's floor: a stage replayed (recorded once) with the scene's Mitsuba scene as its
    input, over all of its shapes; shown in the scene's section."""
    from shadowlab.pipeline import load_scene
    from shadowlab.render import replay
    floor = bench["rec"]["results"]["scenes"]["contact"]["replay_floor"]
    sc = load_scene("contact", (64, 36))
    assert floor["shapes"] == len(sc.mi_scene.shapes()) and floor["ms"] > 0
    assert f"the scene's {floor['shapes']} shapes" in bench["md"]
    frames.replay_floor(sc, repeats=2)
    assert replay.recordings("replay_floor", (), sc) == 1


def test_a_new_frame_replays_the_g_buffer_and_the_cast_over_the_scene(bench):
    """contact's shadow-map frame: two stages over the scene (the G-buffer, the light view's cast),
    replayed after the warm-up; the row shows them with their floors' share of the new frame."""
    d = bench["rec"]["results"]["scenes"]["contact"]
    table = [b for b in bench["rec"]["blocks"] if b["type"] == "table"][1]
    col = table["columns"].index("scene replays (floors' share)")
    for row in table["rows"]:
        r = d["techniques"][row[0]]
        assert r["new"]["scene_replays"] == 2, row[0]
        share = 100.0 * 2 * d["replay_floor"]["ms"] / (1e3 * r["new_s"])
        assert row[col] == f"2 ({share:.0f} %)", row
