"""``shadowlab bench --only dpsv``: the quick run once, and what must hold of what it writes
(never its measured speeds, which depend on the machine)."""

import json

import numpy as np
import pytest

from shadowlab.bench import dpsv


@pytest.fixture(scope="module")
def bench(mitsuba_backend, tmp_path_factory):
    out = tmp_path_factory.mktemp("dpsv-bench")
    md = dpsv.run(out, quick=True)
    return {"out": out, "md": md.read_text(encoding="utf-8"),
            "json": json.loads((out / "dpsv.json").read_text(encoding="utf-8"))}


def test_the_json_has_its_sections_and_the_machine(bench):
    j = bench["json"]
    for k in ("date", "machine", "variant", "quick", "config", "hard", "soft", "build", "wall_s"):
        assert k in j, k
    assert j["quick"] is True and j["wall_s"] > 0
    for k in ("cpu", "cores", "variant", "drjit", "mitsuba"):
        assert k in j["machine"], k
    assert j["machine"]["variant"] == j["variant"]


def test_every_hard_case_has_times_ratios_and_stats(bench):
    h = bench["json"]["hard"]
    cases = h["cases"]
    assert {(c["scene"], c["light"]) for c in cases} == {(s, l) for s in dpsv.OCCLUDERS for l in dpsv.LIGHTS}
    assert h["paper"] == dpsv.PAPER
    for c in cases:
        assert set(c["techniques"]) == set(dpsv.HARD)
        assert c["triangles"] >= h["floor_triangles"] > 1000
        assert 0 < c["valid_pixels"] <= c["resolution"][0] * c["resolution"][1]
        assert 0.0 <= c["shadowed_fraction"] <= 1.0
        for row in c["techniques"].values():
            assert row["first_run_s"] > 0 and row["warm_s"] > 0 and len(row["runs_s"]) >= 1
            assert 0 <= row["mismatches"] <= c["valid_pixels"]
        assert c["fused_over_sm"] > 0 and c["fused_over_dpsv"] > 0
        t = c["techniques"]
        assert np.isclose(c["fused_over_sm"], t["sm_dpsv"]["warm_s"] / t["hard"]["warm_s"])
        assert 0.0 < t["sm_dpsv"]["edge_fraction"] < 1.0
        assert t["sm_dpsv"]["nodes_per_query"] > 0 and t["dpsv"]["nodes_per_query"] > 0
        tree = c["tree"]
        assert tree["nodes"] == 4 * tree["triangles"] > 0 and tree["depth"] > 0
        assert tree["triangles"] + tree["dropped"] + tree["degenerate"] == c["triangles"]
        assert c["map_cast_s"] > 0 and tree["build_seconds"] > 0


def test_dpsv_is_exact_and_the_fused_method_at_most_as_wrong_as_the_map(bench):
    """dpsv shares a Mitsuba shadow ray's offset: it matches the centre's exact visibility (a
    vanishing fraction allowed for float rounding). sm_dpsv takes the map's answer or, at edge
    points, the same tree query as dpsv: its wrong pixels are among those of hard and dpsv."""
    for c in bench["json"]["hard"]["cases"]:
        t = c["techniques"]
        assert t["dpsv"]["mismatch_fraction"] <= 1e-3, (c["scene"], c["light"])
        assert t["sm_dpsv"]["mismatches"] <= t["hard"]["mismatches"] + t["dpsv"]["mismatches"], (c["scene"], c["light"])
        assert set(c["orders"]) == set(dpsv.BUILD_ORDERS)
        assert {o["mismatches"] for o in c["orders"].values()} == {t["dpsv"]["mismatches"]}   # order-independent


def test_the_large_shadow_scene_has_the_larger_shadow(bench):
    by = {(c["scene"], c["light"]): c["shadowed_fraction"] for c in bench["json"]["hard"]["cases"]}
    for light in dpsv.LIGHTS:
        assert by[("large shadow", light)] > 0.15 > 0.05 > by[("little shadow", light)] > 0.0


def test_soft_compares_sm_dpsv_soft_with_pcss(bench):
    s = bench["json"]["soft"]
    assert s["scene"] == dpsv.SOFT_SCENE and s["kind"] == "rect"
    assert set(s["techniques"]) == set(dpsv.SOFT)
    for row in s["techniques"].values():
        assert row["warm_s"] > 0 and 0.0 <= row["vis_rmse"] < 0.1
    assert s["soft_over_pcss"] > 0 and 0.0 <= s["rmse_soft_vs_pcss"] < 0.1
    assert s["paper_soft_over_pcss"] == dpsv.PAPER["soft_over_pcss"]
    assert s["tree"]["triangles"] > 0 and s["map_cast_first_s"] > 0


def test_build_rows_cover_each_size_and_mesh(bench):
    b = bench["json"]["build"]
    sizes = bench["json"]["config"]["build_sizes"]
    k = 2 * len(dpsv.BUILD_ORDERS)            # two meshes, each built in every order
    assert len(b["rows"]) == k * len(sizes)
    assert [r["order"] for r in b["rows"][:k]] == list(dpsv.BUILD_ORDERS) * 2
    for T, row in zip(np.repeat(sizes, k), b["rows"]):
        assert abs(row["input_triangles"] - T) <= 0.05 * T
        assert row["nodes"] == 4 * row["triangles"] > 0 and row["depth"] > 0 and row["build_seconds"] > 0
        assert row["triangles"] + row["dropped"] + row["degenerate"] == row["input_triangles"]
    assert b["goal_s"] == dpsv.BUILD_GOAL_S and b["goal_met"] is None      # quick: no 70k mesh


def test_the_markdown_has_the_tables(bench):
    md = bench["md"]
    for head in ("## Hard shadows", "## Soft shadows", "## TOP-tree build time"):
        assert head in md, head
    for word in ("fused/SM", "fused/DPSV", "sm_dpsv_soft", "pcss", "Wang 2022", "large shadow", "little shadow",
                 "Machine:", "--quick"):
        assert word in md, word
    assert md.count("|---|") >= 5 and "Insertion order" in md


def test_generated_meshes_have_the_asked_triangle_counts():
    P, N, UV, F = dpsv.displaced_grid(10)
    assert len(F) == 200 and len(P) == len(N) == len(UV) == 121
    V = P[F]
    n = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    assert (n[:, 1] > 0).all()                          # counter-clockwise seen from above
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0)
    P, F = dpsv.box_field(5)
    assert len(F) == 60 and len(P) == 40


def test_only_dpsv_is_a_bench_part():
    from shadowlab.bench import core
    assert "dpsv" in core.ONLY


def test_the_sources_figures_table_reads_this_runs_ratios(bench):
    """The docs' table of the sources' figures (:mod:`shadowlab.bench.claims`) reads the run's record:
    each ratio of the JSON, to the table's rounding, and the figure each claim quotes is the one the
    run printed beside its own."""
    from shadowlab.bench.claims import CLAIMS, claims_table, measured
    from shadowlab.bench.record import make_record
    rec = make_record("dpsv", bench["md"], results=bench["json"])
    hard, soft = bench["json"]["hard"], bench["json"]["soft"]
    raw = (("fused_over_sm", [c["fused_over_sm"] for c in hard["cases"]]),
           ("fused_over_dpsv", [c["fused_over_dpsv"] for c in hard["cases"]]),
           ("soft_over_pcss", [soft["soft_over_pcss"]]))
    claims = [c for c in CLAIMS if c.part == "dpsv"]
    assert len(claims) == len(raw)
    for c, (key, values) in zip(claims, raw):
        assert float(c.figure.rstrip("×")) == pytest.approx(dpsv.PAPER[key], abs=0.005), (c.figure, key)
        np.testing.assert_allclose(measured(c, rec), values, atol=0.006, err_msg=c.what)
        assert c.figure in bench["md"], c.figure
    table = claims_table([{**rec, "file": "run.json"}])
    assert table.count("](runs/run.json)") == 3 and "not in the record" not in table
