"""One OpenBLAS thread for jaxlib's CPU LAPACK kernels, unless the user chose a number.

On CPU, ``jnp.linalg`` and ``jax.scipy.linalg`` (the EnKF's Cholesky, the LETKF's eigh) call LAPACK
through scipy's bundled OpenBLAS, which starts its own worker threads beside XLA's. On small
matrices they only contend: the EnKF's analysis at Lorenz-96 d = 40, N = 40 runs several times
slower with OpenBLAS's default threads than with one (measured on docs/bench/history.md,
"Threads"). So importing
csf_jax sets ``OPENBLAS_NUM_THREADS=1`` when the variable is unset and scipy's OpenBLAS is not yet
loaded, or, when it is, sets its thread count through its own ``set_num_threads``. A value the
user put in ``OPENBLAS_NUM_THREADS`` is left alone.
"""

from __future__ import annotations

import ctypes
import os
import sys

_SETTERS = ("scipy_openblas_set_num_threads", "openblas_set_num_threads")


def limit_lapack_threads() -> None:
    """Give scipy's OpenBLAS one thread, unless ``OPENBLAS_NUM_THREADS`` is set (see module)."""
    if "OPENBLAS_NUM_THREADS" in os.environ:
        return
    if "scipy" not in sys.modules:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        return
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter.argtypes = [ctypes.c_int]
                setter(1)
                break


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries mapped into this process that belong to scipy."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line}
    except OSError:
        return []
    return sorted(p for p in paths if "scipy.libs" in p or "/scipy/" in p)


limit_lapack_threads()
