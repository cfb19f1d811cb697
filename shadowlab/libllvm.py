"""Which libLLVM Dr.Jit's LLVM backend loads, decided before Dr.Jit is first imported.

Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` when it is imported, and Mitsuba 3.9 kernels abort inside
libLLVM 14/15 ("LLVM ERROR: Cannot select ... fminimum"). ``shadowlab/__init__.py`` therefore
calls :func:`point_drjit_at_libllvm` before any module imports Dr.Jit: it sets the variable to
the newest libLLVM >= 16 of the usual library directories unless the user set it.
:func:`shadowlab.backend.init` then checks the choice by running a kernel in a subprocess. This
module imports nothing but the standard library.

>>> llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
19
>>> llvm_version("libLLVM.so.19.1")
19
"""

from __future__ import annotations

import glob
import os
import re

MIN_LLVM = 16
FIX = ("install a libLLVM >= 16: on Debian/Ubuntu run `sudo apt-get install libllvm19` "
       "(or `make setup`, which does it), or point DRJIT_LIBLLVM_PATH at a libLLVM.so >= 16")

LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
             "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib")

def llvm_version(path: str) -> int | None:
    """Major version encoded in a libLLVM file name, e.g. ``libLLVM-19.so`` -> 19."""
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(m.group(1)) if m else None


def find_libllvm(min_version: int = MIN_LLVM) -> str | None:
    """Newest libLLVM >= ``min_version`` in the usual library directories, or None."""
    found = []
    for d in LIB_DIRS:
        for p in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(os.path.join(d, "libLLVM*.dylib")):
            v = llvm_version(p)
            if v is not None and v >= min_version:
                found.append((v, len(p), p))
    return sorted(found)[-1][2] if found else None


def point_drjit_at_libllvm() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` to :func:`find_libllvm`'s library unless it is set already;
    return the path in force (None: none found, :func:`shadowlab.backend.init` will say so)."""
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    return os.environ.get("DRJIT_LIBLLVM_PATH")
