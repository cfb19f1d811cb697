"""Dask worker preload: give each worker process its own Dr.Jit kernel cache [Dask 2024, "Preloading"].

Dr.Jit reads ``$HOME`` once, when it is imported, and keeps compiled kernels in ``$HOME/.drjit``.
A worker that is to keep its own cache must therefore point ``HOME`` elsewhere before anything
imports Dr.Jit, which is why this module imports nothing of shadowlab. Load it by file path::

    dask worker tcp://HOST:8786 --nworkers 2 --nthreads 1 \\
        --preload "$(python -c 'import shadowlab.cluster as c; print(c.PRELOAD)')"

``$SHADOWLAB_KERNEL_CACHE`` (default ``$XDG_CACHE_HOME/shadowlab/kernels``, ``~/.cache/...``)
holds one directory per worker name; the original ``HOME`` stays in ``$SHADOWLAB_USER_HOME`` and
``XDG_CACHE_HOME`` keeps pointing where it pointed.

With ``$SHADOWLAB_WORKER_GPUS`` (a comma-separated list of GPU ids, set by
:func:`shadowlab.cluster.executor.open_executor` for ``cuda_ad_rgb``), worker ``k`` sees only GPU
``k mod len(list)`` through ``CUDA_VISIBLE_DEVICES``: one worker per GPU.

The workers of ``shadowlab ... --workers N`` (``$SHADOWLAB_LOCAL_WORKER`` set) ignore SIGINT: a
Ctrl-C at the terminal signals the whole process group, and the command's own process is the one
that stops the work and closes the cluster; workers that took it too printed their broken
connections' tracebacks. A worker started by ``dask worker`` keeps its Ctrl-C.
"""

from __future__ import annotations

import os
import re
import signal
import sys


def _cache_root() -> str:
    home = os.environ.get("SHADOWLAB_USER_HOME") or os.path.expanduser("~")
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache")
    os.environ.setdefault("XDG_CACHE_HOME", xdg)
    os.environ.setdefault("SHADOWLAB_USER_HOME", home)
    return os.environ.get("SHADOWLAB_KERNEL_CACHE") or os.path.join(xdg, "shadowlab", "kernels")


def gpu_of(name, gpus: str) -> str | None:
    """The GPU of worker ``name`` among the comma-separated ``gpus`` (round robin over integer
    names, which LocalCluster gives its workers 0, 1, …); None without GPUs or a non-integer name.

    >>> [gpu_of(i, "0,1") for i in range(3)], gpu_of("a", "0,1"), gpu_of(0, "")
    (['0', '1', '0'], None, None)
    """
    ids = [g for g in gpus.split(",") if g.strip()]
    if not ids or not str(name).isdigit():
        return None
    return ids[int(name) % len(ids)].strip()


def dask_setup(worker):
    """Called by Dask in the new worker process before it runs a task."""
    if os.environ.get("SHADOWLAB_LOCAL_WORKER"):   # executor.LOCAL_WORKER_ENV
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if "drjit" in sys.modules:  # too late: Dr.Jit already chose its cache and its device
        return
    gpu = gpu_of(worker.name, os.environ.get("SHADOWLAB_WORKER_GPUS", ""))
    if gpu is not None:  # one GPU per worker: the CUDA driver reads this when Dr.Jit initialises it
        os.environ["CUDA_VISIBLE_DEVICES"] = gpu
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", str(worker.name))
    d = os.path.join(_cache_root(), f"worker-{name}")
    os.makedirs(d, exist_ok=True)
    os.environ["HOME"] = d
