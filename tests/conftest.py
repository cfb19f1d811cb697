"""Shared fixtures. Tests that run Mitsuba ask for ``mitsuba_backend`` (once per session);
tests that do not need Mitsuba never initialise it. ``frame_of`` shares the frames of built-in
scenes across the session. Scene documents, TOML and frames of inline scenes: tests/scene_builder.py.

The ``slow`` marker (pyproject.toml) is set per file, ``pytestmark = pytest.mark.slow``, on the
files whose tests took longest (measured with ``pytest --durations=0``); ``make test-fast`` runs
``-m "not slow"`` while editing, ``make test`` runs everything."""

import importlib.metadata
import os

import pytest

#: the variant this session runs (the ``mitsuba_backend`` fixture selects the same one)
VARIANT = os.environ.get("SHADOWLAB_VARIANT") or "llvm_ad_rgb"
CUDA = VARIANT.startswith("cuda")


def llvm_only(reason: str):
    """Skip a test under ``cuda_ad_rgb``, saying why it holds only for the LLVM backend."""
    return pytest.mark.skipif(CUDA, reason=f"llvm_ad_rgb only: {reason}")


#: the gate plugin is found through the package's ``pytest11`` entry point: a checkout on
#: ``PYTHONPATH`` that was never pip-installed (the GPU machine's bundle, DEVELOPERS.md) has none
plugin_installed = pytest.mark.skipif(
    not any(ep.value.startswith("shadowlab") for ep in importlib.metadata.entry_points(group="pytest11")),
    reason="shadowlab is not pip-installed here, so pytest has no shadowlab plugin entry point")


@pytest.fixture(scope="session")
def mitsuba_backend():
    """Select the Mitsuba variant (llvm_ad_rgb unless $SHADOWLAB_VARIANT) once; return its name."""
    from shadowlab import backend
    return backend.init()


@pytest.fixture(scope="session")
def dask_workers(mitsuba_backend):
    """A real Dask LocalCluster of 2 worker processes (one task thread each), shared by the
    distributed tests of a session: an executor from :func:`shadowlab.cluster.open_executor`."""
    from shadowlab.cluster import open_executor
    with open_executor(workers=2) as ex:
        yield ex


@pytest.fixture(scope="session")
def frame_of(mitsuba_backend):
    """A factory ``frame_of(name, resolution=None, *, seed=0, u_strata=16, ss=1)``: the FrameContext of
    built-in scene ``name`` (``make_frame(load(name, resolution), ss=ss, u_strata=u_strata, seed=seed)``),
    made once per session per arguments and then shared by every test that asks for it.

    Only for tests that read the frame: rendering techniques on it is fine (the light views it casts
    on demand are cached in the frame by their full key, so the same map is reused), but a test that
    changes the frame's G-buffer, unshadowed light or caches must make its own with ``make_frame``,
    and so must one that counts the kernels a render launches (another test may have rendered there first).
    The defaults are ``make_frame``'s (16 strata of U_L); most tests of techniques pass ``u_strata=1``."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load

    frames = {}

    def frame_of(name: str, resolution=None, *, seed: int = 0, u_strata: int = 16, ss: int = 1):
        res = None if resolution is None else tuple(int(x) for x in resolution)
        key = (name, res, int(seed), int(u_strata), int(ss))
        if key not in frames:
            frames[key] = make_frame(load(name, resolution=res), ss=int(ss), u_strata=int(u_strata), seed=int(seed))
        return frames[key]

    return frame_of
