"""The libLLVM choice reaches Dr.Jit: it reads DRJIT_LIBLLVM_PATH when it is imported, so the
package sets it before any of its modules imports Dr.Jit."""

import os
import subprocess
import sys

from shadowlab.libllvm import find_libllvm, llvm_version


def _run(code: str, **env):
    e = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    e.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=120)


def test_the_package_points_drjit_at_the_newest_libllvm_before_drjit_is_imported():
    lib = find_libllvm()
    assert lib is not None and llvm_version(lib) >= 16
    r = _run("import sys, os, shadowlab.backend; print(os.environ['DRJIT_LIBLLVM_PATH']); "
             "print('drjit' in sys.modules)")
    assert r.returncode == 0, r.stderr
    path, imported = r.stdout.split()
    assert path == lib and imported == "True"


def test_a_path_the_user_set_is_kept():
    r = _run("import os, shadowlab; print(os.environ['DRJIT_LIBLLVM_PATH'])", DRJIT_LIBLLVM_PATH="/x/libLLVM-18.so")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "/x/libLLVM-18.so"

