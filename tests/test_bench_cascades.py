"""``shadowlab bench --only cascades``: a configuration's cost row on a small frame, what must hold
of it (wall and kernel times split into shadow pass and lookup), never its speeds."""

import pytest

from shadowlab.bench import cascades


@pytest.fixture(scope="module")
def cost(mitsuba_backend):
    from shadowlab.pipeline import load_scene
    from shadowlab.render.frame import make_frame
    frame = make_frame(load_scene(cascades.SCENE, (64, 36)))
    return cascades.frame_time(frame, {**cascades.BASE, "resolution": 128}, repeats=2, lookups=2)


def test_a_cost_row_splits_wall_and_kernel_time(cost):
    assert cost["frame_s"] == pytest.approx(cost["shadow_pass_s"] + cost["lookup_s"])
    assert cost["frame_kernel_ms"] == pytest.approx(cost["shadow_pass_kernel_ms"] + cost["lookup_kernel_ms"])
    assert len(cost["shadow_pass_runs_s"]) == 2 and len(cost["lookup_runs_s"]) == 2
    # the cascades are cast and looked up by kernels: some kernel time in each part, none beyond the wall
    assert 0.0 < cost["shadow_pass_kernel_ms"] and 0.0 < cost["lookup_kernel_ms"] <= 1e3 * max(cost["lookup_runs_s"])


def test_the_row_puts_kernel_speeds_beside_the_source(cost):
    row = cascades._ratio_row("kernel 1×1", cost, cost, 146, 146)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert len(cells) == 11 and cells[0] == "kernel 1×1"
    assert cells[4] == cells[5] == cells[8] == "1.00" and cells[9] == "146" and cells[10] == "1.00"
