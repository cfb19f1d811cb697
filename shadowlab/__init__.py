"""shadowlab: a differentiable reference and validation suite for real-time shadows.

Real-time shadow techniques run on Dr.Jit's LLVM backend and are compared with Mitsuba 3
ground truth (area lights, direct illumination only). See README.md and docs/ARCHITECTURE.md.

The public API (:mod:`shadowlab.api`): :func:`load_scene`, :func:`make_frame`, :func:`render_technique`,
:func:`visibility`, :func:`load_reference`, :func:`compare`, :func:`gate_image`, :func:`techniques_for`,
:func:`shaded_image`, :func:`load_preset`.
"""

__version__ = "0.1.0"

from .libllvm import point_drjit_at_libllvm

point_drjit_at_libllvm()  # before any module of the package imports Dr.Jit, which reads it on import

__all__ = ["compare", "gate_image", "load_preset", "load_reference", "load_scene", "make_frame", "render_technique",
           "shaded_image", "techniques_for", "visibility", "__version__"]


def __getattr__(name):
    """The public API's functions, loaded from :mod:`shadowlab.api` on first use (PEP 562): it
    imports Mitsuba, Dr.Jit and numpy, which ``shadowlab --help`` does not need."""
    if name in __all__:
        from . import api
        return getattr(api, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
