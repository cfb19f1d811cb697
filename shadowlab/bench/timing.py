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


def kernel_summary(entries: list) -> dict:
    """Counts and times of Dr.Jit kernel-history entries: JIT kernels launched (and compiled),
    ``Memcpy`` entries (count, bytes), other entries by type, and their execution time (ms)."""
    jit = [k for k in entries if k.get("type") == dr.KernelType.JIT]
    copies = [k for k in entries if k.get("type") == dr.KernelType.Memcpy]
    other: dict = {}
    for k in entries:
        if k.get("type") not in (dr.KernelType.JIT, dr.KernelType.Memcpy):
            name = str(k.get("type")).rsplit(".", 1)[-1]
            other[name] = other.get(name, 0) + 1
    return {"jit": len(jit), "compiled": sum(1 for k in jit if not k.get("cache_hit") and not k.get("cache_disk")),
            "memcpy": len(copies), "memcpy_bytes": int(sum(k.get("size", 0) for k in copies)), "other": other,
            "execution_ms": float(sum(k.get("execution_time", 0.0) for k in entries))}


def history(on: bool) -> None:
    """Turn Dr.Jit's kernel history on or off, after the device is idle, and forget what it held."""
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, on)
    dr.kernel_history_clear()


def timed_kernels(fn):
    """(result, seconds, ms the device ran kernels) of one run of ``fn`` between ``dr.sync_thread()``
    calls: the wall time and the execution time of every kernel-history entry it caused (JIT kernels,
    reductions, copies, memsets), i.e. the work without the host's tracing, Python and waits."""
    history(True)
    try:
        t0 = time.perf_counter()
        out = fn()
        dr.sync_thread()
        wall = time.perf_counter() - t0
        ms = kernel_summary(dr.kernel_history())["execution_ms"]
    finally:
        history(False)
    return out, wall, ms


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
