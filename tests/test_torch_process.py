"""The PyTorch port's tests (``test_torch_equivalence.py``) in a pytest process of their own, so
that torch is never loaded beside the XLA compilations of the rest of the suite
(``tests/conftest.py`` says why); skipped without torch (``pip install -e '.[bench]'``)."""

import os
import pathlib
import subprocess
import sys

import pytest
from conftest import TORCH_PROCESS

HERE = pathlib.Path(__file__).resolve().parent


def _run(marker: str):
    pytest.importorskip("torch", reason="torch not installed: pip install -e '.[bench]'")
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0",
                           "-m",
                           marker, str(HERE / "test_torch_equivalence.py")],
                          env={**os.environ, TORCH_PROCESS: "1"}, capture_output=True, text=True,
                          cwd=HERE.parent)
    assert done.returncode == 0, done.stdout[-8000:] + done.stderr[-3000:]
    assert " passed" in done.stdout.splitlines()[-1], done.stdout[-2000:]


def test_the_pytorch_port_in_its_own_process():
    _run("not slow")


@pytest.mark.slow
def test_the_pytorch_port_compiled_in_its_own_process():
    _run("slow")
