"""The one timing helper of every benchmark, and the machine line every bench part prints.

Dr.Jit evaluates lazily and launches kernels asynchronously, so a clock read without a
``dr.sync_thread()`` before it times the tracing, not the work: :func:`timed` synchronises before
starting the clock and before reading it, for every run. ``warmup`` untimed runs first compile
the kernels (a warm run then measures the kernels alone, loaded from Dr.Jit's cache).
"""

from __future__ import annotations

import time

import drjit as dr
import numpy as np


def timed(fn, repeats: int = 1, warmup: int = 0):
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times, each between ``dr.sync_thread()``
    calls; returns (the last result, list of seconds of each timed run)."""
    for _ in range(int(warmup)):
        fn()
    ts, out = [], None
    for _ in range(int(repeats)):
        dr.sync_thread()
        t0 = time.perf_counter()
        out = fn()
        dr.sync_thread()
        ts.append(time.perf_counter() - t0)
    return out, ts


def warm_median(fn, repeats: int = 5, warmup: int = 1):
    """(last result, median seconds) of ``repeats`` warm runs of ``fn`` after ``warmup`` untimed ones."""
    out, ts = timed(fn, repeats, warmup=warmup)
    return out, float(np.median(ts))


def render_evaluated(technique, frame, params):
    """``technique.render(frame, params)`` with its visibilities evaluated (what a timed run waits for)."""
    r = technique.render(frame, params)
    dr.eval(*r.visibility.values())
    return r


def machine_text(m: dict) -> str:
    """The machine a bench part ran on, from ``backend.machine_info()``: CPU, cores, GPU (if any),
    Mitsuba and Dr.Jit versions, variant.

    >>> machine_text({"cpu": "Xeon", "cores": 2, "mitsuba": "3.9.1", "drjit": "1.5.0", "variant": "llvm_ad_rgb"})
    'Xeon, 2 cores, mitsuba 3.9.1, drjit 1.5.0, variant llvm_ad_rgb'
    """
    gpu = f", {m['gpu']}" if m.get("gpu") else ""
    return f"{m['cpu']}, {m['cores']} cores{gpu}, mitsuba {m['mitsuba']}, drjit {m['drjit']}, variant {m['variant']}"
