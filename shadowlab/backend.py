"""Variant choice, libLLVM check, thread count and seeds (docs/ARCHITECTURE.md, "backend.py").

Mitsuba 3.9 kernels abort inside libLLVM 14/15 ("LLVM ERROR: Cannot select ... fminimum"),
which would kill the Python process. So before the first kernel runs in this process we
(1) point Dr.Jit at the newest libLLVM >= 16 we can find unless ``DRJIT_LIBLLVM_PATH`` is set
(:mod:`shadowlab.libllvm`, called by the package's ``__init__`` before anything imports Dr.Jit,
which reads the variable on import), and (2) run a real Mitsuba kernel in a *subprocess*: if it dies we raise
:class:`EnvironmentProblem` (exit 3) naming the library and the fix instead of crashing.
"""

from __future__ import annotations

import glob
import hashlib
import importlib.metadata as md
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .errors import EnvironmentProblem, InputError
from .libllvm import LIB_DIRS, FIX, MIN_LLVM, find_libllvm, llvm_version

__all__ = ["init", "probe", "machine_info", "find_libllvm", "llvm_version", "DEFAULT_VARIANT", "SUPPORTED_VARIANTS"]

DEFAULT_VARIANT = "llvm_ad_rgb"
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
_state: dict = {"variant": None}

# A kernel that exercises what broke on libLLVM 15: a ray cast plus min/max reductions.
_PROBE = r"""
import sys, drjit as dr, mitsuba as mi
mi.set_variant(sys.argv[1])
s = mi.load_dict({'type': 'scene', 's': {'type': 'sphere'}, 'r': {'type': 'rectangle'}})
ray = mi.Ray3f(mi.Point3f(dr.linspace(mi.Float, -1, 1, 64), 0, 5), mi.Vector3f(0, 0, -1))
si = s.ray_intersect(ray)
v = dr.minimum(dr.maximum(si.t, 0.5), 10.0)
dr.eval(v); dr.sync_thread()
print('ok', dr.min(v).numpy())
"""


def _cache_file(variant: str, lib: str | None) -> Path:
    try:
        versions = md.version("mitsuba") + md.version("drjit")
    except md.PackageNotFoundError:
        versions = "?"
    key = hashlib.sha1(f"{variant}|{lib}|{versions}|{sys.executable}".encode()).hexdigest()[:16]
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "shadowlab"
    return base / f"backend-ok-{key}.json"


def probe(variant: str, lib: str | None) -> tuple[bool, str]:
    """Run one Mitsuba kernel of ``variant`` in a subprocess; return (ok, stderr tail)."""
    env = dict(os.environ)
    if lib:
        env["DRJIT_LIBLLVM_PATH"] = lib
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE, variant], env=env, capture_output=True,
                           text=True, timeout=300)
    except subprocess.TimeoutExpired:
        return False, "the probe kernel did not finish within 300 s"
    ok = r.returncode == 0 and r.stdout.startswith("ok")
    return ok, (r.stderr or r.stdout)[-600:]


def probe_reason(tail: str) -> str:
    """The one line that says why the probe failed: the exception line that ends a Python
    traceback (the rest is the probe's own frames), else the last line it printed.

    >>> probe_reason('Traceback (most recent call last):\\n  File "<string>", line 3\\nImportError: no CUDA\\n')
    'ImportError: no CUDA'
    >>> probe_reason("")
    'no output'
    """
    lines = [l.strip() for l in (tail or "").splitlines() if l.strip()]
    frames = ("Traceback", "File ", "^", "~")
    useful = [l for l in lines if not l.startswith(frames)]
    return (useful or lines or ["no output"])[-1][:300]


def init(variant: str | None = None, threads: int | None = None, check: bool = True) -> str:
    """Select the Mitsuba variant once per process and make sure its backend works.

    ``variant`` defaults to ``$SHADOWLAB_VARIANT`` or ``llvm_ad_rgb``. Once a variant is chosen,
    ``init()`` (no variant) returns it: ``shadowlab --variant cuda_ad_rgb`` chooses the variant and
    the library code below it calls ``init()``. An explicit different variant raises
    EnvironmentProblem (exit 3): a process runs one variant. Raises EnvironmentProblem too when
    the LLVM backend cannot run a Mitsuba kernel. Returns the variant name.

    >>> init() in SUPPORTED_VARIANTS       # a second call returns the variant already chosen
    True
    """
    if _state["variant"] is not None:
        if variant and variant != _state["variant"]:
            raise EnvironmentProblem(f"variant {variant!r} requested after {_state['variant']!r} was "
                                     "initialised in this process; run a new process to switch")
        if threads:
            dr.set_thread_count(int(threads))
        return _state["variant"]
    variant = variant or os.environ.get("SHADOWLAB_VARIANT") or DEFAULT_VARIANT
    if variant not in SUPPORTED_VARIANTS:
        raise InputError(f"unknown variant {variant!r}; choose one of {', '.join(SUPPORTED_VARIANTS)}")

    lib = None
    if variant.startswith("llvm"):
        lib = os.environ.get("DRJIT_LIBLLVM_PATH")
        if lib:
            v = llvm_version(lib)
            if not os.path.exists(lib):
                raise EnvironmentProblem(f"DRJIT_LIBLLVM_PATH={lib} does not exist; {FIX}")
            if v is not None and v < MIN_LLVM:
                raise EnvironmentProblem(f"DRJIT_LIBLLVM_PATH points at libLLVM {v} ({lib}); Mitsuba 3.9 "
                                         f"kernels abort with libLLVM < {MIN_LLVM}; {FIX}")
        else:
            lib = find_libllvm()
            if lib is None:
                older = [p for d in LIB_DIRS for p in glob.glob(os.path.join(d, "libLLVM*.so*"))]
                have = f" (found only {', '.join(sorted(set(older)))})" if older else ""
                raise EnvironmentProblem(f"no libLLVM >= {MIN_LLVM} found for Dr.Jit's LLVM backend{have}; {FIX}")
    if check:
        cache = _cache_file(variant, lib)
        if not cache.exists():
            ok, tail = probe(variant, lib)
            if not ok:
                raise EnvironmentProblem(
                    f"the {variant} backend cannot run a Mitsuba kernel with {lib or 'the default library'} "
                    f"({probe_reason(tail)}); {FIX}" if variant.startswith("llvm") else
                    f"the {variant} backend does not work here ({probe_reason(tail)}); use --variant llvm_ad_rgb, "
                    "or install a CUDA driver on a machine with an NVIDIA GPU")
            cache.parent.mkdir(parents=True, exist_ok=True)
            cache.write_text(json.dumps({"variant": variant, "lib": lib}))
    mi.set_variant(variant)
    if threads:
        dr.set_thread_count(int(threads))
    _state["variant"] = variant
    return variant


def machine_info() -> dict:
    """What a benchmark or reference ran on: CPU model, cores, library versions."""
    cpu = platform.processor()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform(), "variant": _state["variant"],
            "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH")}
    for pkg in ("mitsuba", "drjit"):
        try:
            info[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            info[pkg] = None
    if str(_state["variant"] or "").startswith("cuda"):
        info["gpu"] = _gpu_name()
    return info


def _gpu_name() -> str | None:
    """The first GPU's name from ``nvidia-smi`` (None where it cannot tell)."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    names = [l.strip() for l in out.stdout.splitlines() if l.strip()]
    return names[0] if out.returncode == 0 and names else None
