"""The libLLVM choice reaches Dr.Jit: it reads DRJIT_LIBLLVM_PATH when it is imported, so the
package sets it before any of its modules imports Dr.Jit."""

import json
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


def test_init_without_a_variant_returns_the_variant_already_chosen():
    """``shadowlab --variant X`` chooses X, and the library code under the command calls
    ``backend.init()``: that returns X, whatever $SHADOWLAB_VARIANT says. Only an explicit, different
    variant is refused (exit 3: a process runs one variant). $SHADOWLAB_VARIANT names cuda_ad_rgb
    here, so a default taken from it would conflict with the llvm_ad_rgb chosen first."""
    r = _run("from shadowlab import backend\n"
             "from shadowlab.errors import EnvironmentProblem\n"
             "assert backend.init('llvm_ad_rgb') == 'llvm_ad_rgb'\n"
             "assert backend.init() == 'llvm_ad_rgb' and backend.init(None) == 'llvm_ad_rgb'\n"
             "assert backend.init('llvm_ad_rgb') == 'llvm_ad_rgb'\n"
             "try:\n"
             "    backend.init('cuda_ad_rgb')\n"
             "except EnvironmentProblem as e:\n"
             "    print(e.exit_code, e)\n",
             SHADOWLAB_VARIANT="cuda_ad_rgb")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("3 variant 'cuda_ad_rgb' requested after 'llvm_ad_rgb'"), r.stdout
    assert "new process" in r.stdout


def test_the_cli_variant_option_reaches_the_library(tmp_path):
    """``shadowlab reference --variant llvm_ad_rgb`` with $SHADOWLAB_VARIANT=cuda_ad_rgb runs on
    llvm_ad_rgb: the pipeline's own ``backend.init()`` no longer falls back to the environment."""
    (tmp_path / "store").mkdir()
    r = subprocess.run([sys.executable, "-m", "shadowlab.cli", "reference", "contact", "-r", "16x12", "--spp", "0",
                        "--variant", "llvm_ad_rgb"], capture_output=True, text=True, timeout=300,
                       env={**{k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"},
                            "SHADOWLAB_VARIANT": "cuda_ad_rgb", "SHADOWLAB_REFERENCES": str(tmp_path / "store")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert "requested after" not in r.stderr
    meta = json.loads(next((tmp_path / "store").rglob("meta.json")).read_text())
    assert meta["variant"] == "llvm_ad_rgb"
