"""shadowlab: a differentiable reference and validation suite for real-time shadows.

Real-time shadow techniques run on Dr.Jit's LLVM backend and are compared with Mitsuba 3
ground truth (area lights, direct illumination only). See README.md and docs/ARCHITECTURE.md.

The public API (:mod:`shadowlab.api`): :func:`load_scene`, :func:`make_frame`, :func:`render_technique`,
:func:`visibility`, :func:`load_reference`, :func:`compare`, :func:`gate_image`, :func:`techniques_for`.
"""

__version__ = "0.1.0"

from .libllvm import point_drjit_at_libllvm

point_drjit_at_libllvm()  # before any module of the package imports Dr.Jit, which reads it on import

from .api import (compare, gate_image, load_reference, load_scene, make_frame, render_technique,  # noqa: E402
                  techniques_for, visibility)

__all__ = ["compare", "gate_image", "load_reference", "load_scene", "make_frame", "render_technique", "techniques_for",
           "visibility", "__version__"]
