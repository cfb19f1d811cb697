"""The memory a frame needs and the memory free on the device: a frame that cannot fit is refused
before any work (exit 3, :func:`check_fits`).

The estimate counts what a frame holds (docs/ARCHITECTURE.md, FrameContext): the G-buffer and
the unshadowed light at every shading point, and the light views each technique asks for, a shadow
map being faces × N² texels per map [Williams 1978, §2] (a point light's cube: six faces), times
its cascades [Buljan 2020, §4.1] and its layers. The sizes come from the technique's resolved
values (``resolution``: the map side, 0 = the light's ``shadow_map``; ``cascades``; ``layers``)
and from the scene's lights; a technique without a ``resolution`` casts no map of the frame
(SDF tracing, shadow volumes). Virtual maps ([Giegl 2007]) cast their tiles in wavefronts of
:func:`shadowlab.render.tiles.chunk_texels`: one wavefront is counted; the tile textures they keep
are not. The bytes per point and per texel below were measured (process RSS on ``contact``, the
LLVM variant); a light view is one kernel (:func:`shadowlab.render.lightview.light_view`), which
holds :data:`BUILD_BYTES` a texel beyond the map while it builds one. The estimate is a floor, so
a refusal is certain, not cautious.

Free memory: on the CPU (LLVM variant) the kernel's ``MemAvailable`` (``/proc/meminfo``; where there
is none, the physical memory); on CUDA the driver's ``cuMemGetInfo`` of the current device (through ctypes on
``libcuda``), which does not count what Dr.Jit's allocator has cached.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from dataclasses import dataclass

import mitsuba as mi

from ..errors import EnvironmentProblem
from .tiles import chunk_texels

#: bytes per shading point of the G-buffer (its SurfaceInteraction, p, n, ng, depth, albedo, mask,
#: shape id; 249 measured at 1024² on ``contact``)
GBUFFER_BYTES = 240
#: bytes per shading point and light: the unshadowed light U_L and the technique's visibility
LIGHT_BYTES = 16
#: bytes per texel a light view keeps: its Dr.Jit arrays (quantised depth, decoded depth and slope as
#: float32, the hit mask; numpy copies are made only where a technique reads them)
VIEW_BYTES = 13
#: bytes per texel beyond the view while one view is built: its one kernel keeps rays and hits in
#: registers (peak 14 B a texel measured at 4096² on ``street``, the view's 13 included)
BUILD_BYTES = 1
#: bytes per texel of a virtual map's wavefront of tiles (one ray and its hit per texel)
TILE_RAY_BYTES = 100

GiB = float(1 << 30)


@dataclass(frozen=True)
class Need:
    """Bytes a frame needs: the G-buffer's, and the light views' of the technique that needs most."""

    gbuffer: int
    views: int
    technique: str | None
    maps: tuple          # (faces, side, count) of that technique's maps

    @property
    def total(self) -> int:
        return self.gbuffer + self.views


def gbuffer_bytes(width: int, height: int, *, ss: int = 1, lights: int = 1) -> int:
    """Bytes of the G-buffer and the per-light arrays of ``width`` × ``height`` pixels of ss² points."""
    return int(width) * int(height) * int(ss) ** 2 * (GBUFFER_BYTES + LIGHT_BYTES * int(lights))


def light_maps(spec, values: dict) -> tuple:
    """(faces, side, count) per light of the maps a technique with resolved ``values`` casts on scene
    ``spec`` (empty: it casts none)."""
    if "resolution" not in values:
        return ()
    count = int(values.get("cascades") or 1) * int(values.get("layers") or 1)
    return tuple((6 if l.kind == "point" else 1, int(values["resolution"] or 0) or int(l.shadow_map), count)
                 for l in spec.lights)


def views_bytes(maps) -> int:
    """Bytes the light views ``maps`` ((faces, side, count) each) keep, plus the building of the largest."""
    texels = [f * s * s for f, s, _ in maps]
    return sum(t * c * VIEW_BYTES for t, (_, _, c) in zip(texels, maps)) + max(texels, default=0) * BUILD_BYTES


def frame_need(spec, techniques: dict, *, ss: int = 1) -> Need:
    """The :class:`Need` of a frame of ``spec`` (at its camera's resolution) rendered by
    ``techniques``: {name: resolved values}."""
    W, H = spec.camera.resolution
    gb = gbuffer_bytes(W, H, ss=ss, lights=len(spec.lights))
    best = (0, None, ())
    for name, values in techniques.items():
        maps = light_maps(spec, values)
        b = views_bytes(maps) + (chunk_texels() * TILE_RAY_BYTES if "t_max" in values else 0)
        if b > best[0]:
            best = (b, name, maps)
    return Need(gb, best[0], best[1], best[2])


def _cuda_free() -> tuple[int, str]:
    """(free bytes, where) of the current CUDA device, from the driver."""
    path = ctypes.util.find_library("cuda") or "libcuda.so.1"
    try:
        cu = ctypes.CDLL(path)
    except OSError as e:
        raise EnvironmentProblem(f"cannot read the GPU's free memory: {path} does not load ({e}); install the NVIDIA "
                                 "driver, or run with --variant llvm_ad_rgb") from None
    dev, ctx = ctypes.c_int(0), ctypes.c_void_p()
    free, total = ctypes.c_size_t(), ctypes.c_size_t()
    if cu.cuInit(0) != 0 or (cu.cuCtxGetDevice(ctypes.byref(dev)) != 0 and cu.cuDeviceGet(ctypes.byref(dev), 0) != 0):
        raise EnvironmentProblem("cannot read the GPU's free memory: the CUDA driver does not start (cuInit); check "
                                 "nvidia-smi, or run with --variant llvm_ad_rgb")
    pushed = cu.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev) == 0 and cu.cuCtxPushCurrent_v2(ctx) == 0
    try:
        err = cu.cuMemGetInfo_v2(ctypes.byref(free), ctypes.byref(total))
    finally:
        if pushed:
            cu.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
            cu.cuDevicePrimaryCtxRelease_v2(dev)
    if err:
        raise EnvironmentProblem(f"cannot read the GPU's free memory: cuMemGetInfo failed (CUDA error {err}); check "
                                 "nvidia-smi, or run with --variant llvm_ad_rgb")
    return int(free.value), f"free on GPU {dev.value} (cuMemGetInfo)"


def free_memory() -> tuple[int, str]:
    """(bytes free, where it was read) on the device the active Mitsuba variant runs on."""
    if str(mi.variant() or "").startswith("cuda"):
        return _cuda_free()
    try:
        with open("/proc/meminfo") as f:
            kb = next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:"))
        return kb * 1024, "available on this machine (MemAvailable)"
    except (OSError, StopIteration, ValueError, IndexError):
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "this machine's physical memory"


def _gib(b: int) -> str:
    return f"{b / GiB:.1f} GiB"


def check_fits(spec, techniques: dict, *, ss: int = 1, what: str = "a frame", free=None,
               size_option: str = "--resolution") -> Need:
    """Refuse (EnvironmentProblem, exit 3) a frame of ``spec`` rendered by ``techniques`` ({name:
    resolved values}) that needs more than the memory free (``free``: (bytes, where); default
    :func:`free_memory`). The message names both and the fix (``size_option``: the option that sets
    the frame's size). Returns the :class:`Need`."""
    need = frame_need(spec, techniques, ss=ss)
    avail, where = free if free is not None else free_memory()
    if need.total <= avail:
        return need
    W, H = spec.camera.resolution
    parts = [f"G-buffer {_gib(need.gbuffer)} for {W}×{H}" + (f" at {ss}×{ss} points a pixel" if ss > 1 else "")]
    fixes = []
    if need.views:
        side = max(s for _, s, _ in need.maps) if need.maps else 0
        maps = f"{sum(c for *_, c in need.maps)} map(s) up to {side}²" if need.maps else "a wavefront of tiles"
        parts.append(f"light views {_gib(need.views)} for {need.technique} ({maps})")
        if side:
            fixes.append(f"a smaller map (--set {need.technique}.resolution={max(64, side // 4)}, or the lights' "
                         "shadow_map)")
    fixes.append(f"a smaller {size_option} (e.g. {max(1, W // 4)}x{max(1, H // 4)})")
    raise EnvironmentProblem(f"{what} needs about {_gib(need.total)} ({', '.join(parts)}) but only {_gib(avail)} is "
                             f"{where}; use {' or '.join(fixes)}")
