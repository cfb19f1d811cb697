"""Shared fixtures. Tests that run Mitsuba ask for ``mitsuba_backend`` (once per session);
tests that do not need Mitsuba never initialise it."""

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
