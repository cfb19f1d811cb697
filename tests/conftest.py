"""Shared fixtures. Tests that run Mitsuba ask for ``mitsuba_backend`` (once per session);
tests that do not need Mitsuba never initialise it."""

import pytest


@pytest.fixture(scope="session")
def mitsuba_backend():
    """Select the Mitsuba variant (llvm_ad_rgb unless $SHADOWLAB_VARIANT) once; return its name."""
    from shadowlab import backend
    return backend.init()
