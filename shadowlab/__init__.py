"""shadowlab: a differentiable reference and validation suite for real-time shadows.

Real-time shadow techniques run on Dr.Jit's LLVM backend and are compared with Mitsuba 3
ground truth (area lights, direct illumination only). See README.md and docs/ARCHITECTURE.md.
"""

__version__ = "0.1.0"
