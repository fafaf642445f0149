"""Importing csf_jax gives scipy's OpenBLAS (jaxlib's CPU LAPACK) one thread, unless the user set
OPENBLAS_NUM_THREADS; also when scipy was loaded first."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_THREADS = """
import ctypes
from csf_jax import _threads
libs = _threads._loaded_openblas()
print(ctypes.CDLL(libs[0]).scipy_openblas_get_num_threads() if libs else "none")
"""


def _run(code: str, **env) -> str:
    clean = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_import_sets_one_thread_before_scipy_loads():
    assert _run("import csf_jax, os, sys\nprint('scipy' in sys.modules, "
                "os.environ['OPENBLAS_NUM_THREADS'])") == "False 1"


def test_user_setting_is_kept():
    assert _run("import csf_jax, os\nprint(os.environ['OPENBLAS_NUM_THREADS'])",
                OPENBLAS_NUM_THREADS="2") == "2"


def test_scipy_loaded_first_gets_one_thread():
    code = "import numpy as np, scipy.linalg\nscipy.linalg.cholesky(np.eye(2))\n"
    if _run(code + "import ctypes\nprint('ok')") != "ok":
        pytest.skip("no scipy")
    got = _run(code + "import csf_jax\n" + _THREADS)
    if got == "none":
        pytest.skip("scipy is not linked to a bundled OpenBLAS here")
    assert got == "1"
