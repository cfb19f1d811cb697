"""The truth's two wavefront layouts (reference/truth.py, "Wavefronts"): a lane per (point, round),
a GPU's, and a lane per point looping over its rounds, the CPU's. They draw the same random numbers
and add the same rounds in the same order; a GPU traces each lane alone, so there they agree to the
bit, while Embree on the CPU traces packets of neighbouring lanes, where a ray's result can depend
on its packet: there they agree on all but a few samples."""

from fractions import Fraction

import numpy as np
import pytest

import mitsuba as mi

from shadowlab import backend
from shadowlab.reference import truth
from conftest import CUDA

backend.init()


def test_lane_rows_give_each_lane_its_row():
    rng = np.random.default_rng(1)
    for n in (1, 7, 5000):
        cnt = rng.integers(0, 13, n)
        cnt[0] = 0  # rows without lanes, at the start too
        off = np.cumsum(cnt) - cnt
        rows = truth._lane_rows(mi.UInt32(off.astype(np.uint32)), int(cnt.sum())).numpy()
        assert np.array_equal(rows, np.repeat(np.arange(n), cnt))


def _fma(a, b, c) -> float:
    """a·b + c rounded once (what CUDA's contraction of a multiply-add computes)."""
    return float(Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c)))


def _same(got, want) -> bool:
    """The fold's sums against the model's: bit for bit; on CUDA, whose compiler contracts
    s + x·x into one fused multiply-add, the squares' sums may instead be that rounding."""
    return all(g == w or (CUDA and g in alt) for g, (w, *alt) in zip(got, want))


def test_fold_rounds_adds_each_points_rounds_in_order():
    rng = np.random.default_rng(2)
    cnt = np.array([3, 0, 5, 1])
    n_dec = np.array([1, 0, 5, 0])
    off = np.cumsum(cnt) - cnt
    V, A = rng.random(cnt.sum()), rng.random(cnt.sum())
    v = np.floor(rng.random(cnt.sum()) * 65)
    start = [rng.random(len(cnt)) for _ in range(5)]
    dec, full = truth._fold_rounds((mi.Float64(V), mi.Float64(A), mi.Float64(v)), mi.UInt32(off.astype(np.uint32)),
                                   mi.UInt32(n_dec.astype(np.uint32)), mi.UInt32(cnt.astype(np.uint32)),
                                   tuple(mi.Float64(x) for x in start))
    for p in range(len(cnt)):
        # each sum as (plain value, fused alternative); the fused one follows the device's own chain
        s = [(x[p], x[p]) for x in start]
        for j in range(cnt[p]):
            if j == n_dec[p]:
                assert _same([x.numpy()[p] for x in dec], s)
            i = off[p] + j
            s = [(s[0][0] + V[i],) * 2, (s[1][0] + V[i] * V[i], _fma(V[i], V[i], s[1][1])), (s[2][0] + A[i],) * 2,
                 (s[3][0] + A[i] * A[i], _fma(A[i], A[i], s[3][1])), (s[4][0] + v[i],) * 2]
        if n_dec[p] == cnt[p]:
            assert _same([x.numpy()[p] for x in dec], s)
        assert _same([x.numpy()[p] for x in full], s)  # float64, added in round order: the same bits


@pytest.mark.parametrize("scene,light", [("contact", "key"), ("parallel_planes", "panel")])
def test_round_lanes_agree_with_point_lanes(monkeypatch, frame_of, scene, light):
    fr = frame_of(scene, (64, 48))
    out = {}
    for per_round in (False, True):
        monkeypatch.setattr(truth, "_lanes_per_round", lambda: per_round)
        out[per_round] = truth.visibility(fr, light, seed=5)
    a, b = out[False], out[True]
    pen = a.V_se > 0
    assert pen.sum() > 50, "the frame must have a penumbra"
    if CUDA:  # each lane traced alone: the same bits
        for f in ("V", "V_se", "A", "A_se", "samples", "bound"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
        assert a.rays == b.rays
        return
    # Embree's packets: a few samples may differ, a pixel's plan with them
    assert (a.samples == b.samples).mean() > 0.99
    assert np.array_equal(a.bound, b.bound)  # the first wavefront is the same kernel
    assert abs(a.rays - b.rays) <= 0.01 * a.rays
    same = a.samples == b.samples
    assert (a.V == b.V).mean() > 0.98
    assert np.abs(a.V - b.V)[same].max() < 0.02


def test_a_gpu_runs_a_lane_per_round_and_the_cpu_a_lane_per_point():
    assert truth._lanes_per_round() is CUDA
