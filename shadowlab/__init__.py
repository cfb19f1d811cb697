"""shadowlab: a differentiable reference and validation suite for real-time shadows.

Real-time shadow techniques run on Dr.Jit's LLVM backend and are compared with Mitsuba 3
ground truth (area lights, direct illumination only). See README.md and docs/ARCHITECTURE.md.
"""

__version__ = "0.1.0"

from .libllvm import point_drjit_at_libllvm

point_drjit_at_libllvm()  # before any module of the package imports Dr.Jit, which reads it on import
