"""``shadowlab bench --only virtual``: the quick run once, and what must hold of what it writes
(never its measured speeds or errors, which depend on the machine)."""

import json
import math

import pytest

from shadowlab.bench import virtual
from shadowlab.techniques.virtual_maps import COARSE

XI_KEYS = [str(x) for x in virtual.XIS]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def bench(mitsuba_backend, tmp_path_factory):
    out = tmp_path_factory.mktemp("virtual-bench")
    md = virtual.run(out, quick=True)
    return {"out": out, "md": md.read_text(encoding="utf-8"),
            "json": json.loads((out / "virtual.json").read_text(encoding="utf-8"))}


def _pow2_bound(t_max: int, overlap: int) -> int:
    """Bytes of every texture of the pow2 series t_max/2^k + 2·overlap, k = 0 … log2 t_max."""
    return 4 * sum((t_max // 2 ** k + 2 * overlap) ** 2 for k in range(int(math.log2(t_max)) + 1))


def test_the_report_has_every_section_and_the_json_its_keys(bench):
    j = bench["json"]
    for k in ("date", "machine", "quick", "config", "cost", "xi", "equal_memory", "wall_s", "plot"):
        assert k in j, k
    assert j["quick"] is True
    assert sorted(j["cost"]["fvsm"]) == sorted(XI_KEYS) and sorted(j["xi"]["xi"]) == sorted(XI_KEYS)
    for row in j["cost"]["fvsm"].values():
        for k in ("frame_s", "tiles", "texels", "memory_bytes", "memory_modes", "traversal_depth", "demand",
                  "hard_error_rate", "speedup_over_vtsm", "tiles_fraction_of_vtsm"):
            assert k in row, k
        assert set(row["memory_modes"]) == {"subrect", "pow2", "exact"}
        assert row["frame_s"] > 0 and 0.0 <= row["hard_error_rate"] <= 1.0
    assert j["cost"]["claimed_speedup"] == virtual.CLAIMED_SPEEDUP
    for row in j["xi"]["xi"].values():
        assert len(row["frames"]) == j["config"]["frames"]
        s = row["summary"]
        assert 0.0 <= s["hard_error_rate"] <= 1.0 and 0.0 <= s["rmse_off_penumbra"] <= 1.0
        assert s["tiles"]["mean"] <= s["tiles"]["max"] and s["memory_bytes"]["mean"] <= s["memory_bytes"]["max"]


def test_a_larger_xi_never_makes_more_tiles(bench):
    """ξ only makes the refinement stricter: the tree at ξ = 5 is a prefix of the tree at ξ = 0."""
    j = bench["json"]
    assert j["cost"]["fvsm"]["5"]["tiles"] <= j["cost"]["fvsm"]["0"]["tiles"]
    f0, f5 = j["xi"]["xi"]["0"]["frames"], j["xi"]["xi"]["5"]["frames"]
    assert all(b["tiles"] <= a["tiles"] for a, b in zip(f0, f5))


def test_tile_memory_follows_the_texture_modes(bench):
    j = bench["json"]
    t, ov = j["config"]["t_max"], 1                      # fvsm's default overlap
    coarse = 4 * min(t, COARSE) ** 2                    # the fallback's coarse tile, where one is needed
    for row in j["cost"]["fvsm"].values():
        mm = row["memory_modes"]
        extra = mm["subrect"] - 4 * (t + 2 * ov) ** 2
        assert extra in (0, coarse)
        assert mm["pow2"] - extra <= _pow2_bound(t, ov)
        assert row["memory_bytes"] == mm["pow2"]         # the bench's fvsm uses pow2 textures
        assert row["tiles"] <= j["cost"]["vtsm"]["tiles"] == j["cost"]["grid"] ** 2
    assert j["cost"]["vtsm"]["memory_bytes"] == 4 * t * t


def test_pow2_textures_without_overlap_take_at_most_four_thirds_of_t_max_squared():
    import numpy as np
    from shadowlab.techniques.virtual_maps import memory_texels
    rng = np.random.default_rng(7)
    t = 1024
    for _ in range(20):
        w, h = 2 ** rng.integers(0, 11, 12), 2 ** rng.integers(0, 11, 12)
        assert 4 * memory_texels(w, h, t, overlap=0)["pow2"] <= 4 * t * t * 4 / 3


def test_the_equal_memory_comparison_sizes_every_map_to_the_budget(bench):
    e = bench["json"]["equal_memory"]
    budget = e["budget_bytes"]
    rows = e["rows"]
    assert rows[virtual.FVSM_LABEL]["summary"]["memory_bytes"]["max"] == budget
    for label, row in rows.items():
        assert label in e["shimmer"]["techniques"]
        p = row["params"]
        if row["technique"] in ("csm", "hard"):
            n = p.get("cascades", 1)
            assert row["summary"]["memory_bytes"]["max"] == 4 * n * p["resolution"] ** 2
            assert 4 * n * p["resolution"] ** 2 <= budget < 4 * n * (p["resolution"] + 1) ** 2, label
        if row["technique"] == "vtsm":
            assert row["summary"]["memory_bytes"]["max"] == 4 * p["t_max"] ** 2
    assert {r["technique"] for r in rows.values()} == {"csm", "fvsm", "vtsm", "hard"}


def test_the_markdown_names_every_technique_and_links_the_plot(bench):
    md = bench["md"]
    for label in bench["json"]["equal_memory"]["rows"]:
        assert label in md, label
    for word in ("fvsm", "vtsm", "csm", "hard", "ξ", "Giegl 2007", "virtual.png"):
        assert word in md, word
    assert "Ran: `street`" in md and "Ran: `boulevard`" in md


def test_the_plot_is_a_png(bench):
    data = (bench["out"] / "virtual.png").read_bytes()
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert width > 100 and height > 100
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.image
    assert matplotlib.image.imread(bench["out"] / "virtual.png").shape[:2] == (height, width)


def test_only_virtual_is_a_bench_part():
    from shadowlab.bench import core
    assert "virtual" in core.ONLY


def test_the_sources_figures_table_reads_this_runs_ratios(bench):
    """The docs' table of the sources' figures (:mod:`shadowlab.bench.claims`) reads the speed-up over
    ``vtsm`` of every ξ from the run's record, to the table's rounding, beside [Giegl 2007]'s figure."""
    from shadowlab.bench.claims import CLAIMS, measured
    from shadowlab.bench.record import make_record
    rec = make_record("virtual", bench["md"], results=bench["json"])
    (claim,) = [c for c in CLAIMS if c.part == "virtual"]
    raw = [r["speedup_over_vtsm"] for r in bench["json"]["cost"]["fvsm"].values()]
    got = measured(claim, rec)
    assert len(got) == len(raw) == len(virtual.XIS)
    assert all(abs(a - b) <= 0.051 for a, b in zip(got, raw)), (got, raw)
    assert claim.figure == f"≥ {virtual.CLAIMED_SPEEDUP:g}×"
