"""Shared fixtures: float64 mode and a linear-Gaussian problem with its exact Kalman solution.

The tests run under the flags a user has: no XLA flags are set here.

The PyTorch tests (``test_torch_equivalence.py``) run in a pytest process of their own
(``test_torch_process.py`` starts it; ``pytest_ignore_collect`` keeps them out of this one): with
torch loaded into the process, later XLA compilations crashed whole runs with a segmentation fault
(in the training step's and in the CSF filter's compilation, with the ``bench`` extra installed),
while the PyTorch file on its own passes.
"""

import gc
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax.filters.kalman import kalman_filter
from csf_jax.filters.result import FilterResult
from csf_jax.problems.linear import LinearGaussian, linear_gaussian, to_model
from csf_jax.ssm import StateSpaceModel, propagate

TORCH_PROCESS = "CSF_TORCH_PROCESS"  # set in the process that runs the PyTorch tests

# Float32 matmuls on a GPU round their operands to TensorFloat-32 (a 10-bit mantissa; JAX's default
# precision there): identities that hold to 1e-6 on a CPU hold to about 1e-3 on a GPU.
MATMUL_ATOL = 1e-6 if jax.default_backend() == "cpu" else 2e-3


# The tests the default run leaves to ``-m slow`` (``slow_tests.txt``, written by ``slow_list.py``)
SLOW_TESTS = frozenset(
    line.strip() for line in open(os.path.join(os.path.dirname(__file__), "slow_tests.txt"))
    if line.strip() and not line.startswith("#"))


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark the tests listed in ``slow_tests.txt`` slow, before ``-m`` selects."""
    for item in items:
        if item.nodeid in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)


def pytest_ignore_collect(collection_path, config):
    """The PyTorch tests only in their own process (module docstring)."""
    if collection_path.name == "test_torch_equivalence.py":
        return os.environ.get(TORCH_PROCESS) != "1"
    return None


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop each test module's compiled executables when the module ends.

    XLA's CPU backend maps every compiled executable into memory; kept for the whole run, the
    suite's thousands of executables approach the kernel's limit on memory mappings
    (``vm.max_map_count``, 65530 by default) and a later compilation aborts the process.
    """
    yield
    jax.clear_caches()
    gc.collect()


def simulate_linear(lg: LinearGaussian, seed: int) -> np.ndarray:
    """Observations ``(K, m)`` of a truth drawn from ``lg``, in plain float64 numpy.

    Numpy rather than ``csf_jax.ssm.simulate`` keeps the tests free of extra compilations (the
    filters do not care where the data come from) and works in either precision mode.
    """
    rng = np.random.default_rng(seed)
    x = lg.m0 + lg.p0_std * rng.standard_normal(lg.dim)
    obs = []
    for _ in range(lg.num_steps):
        x = lg.A @ x + lg.q_std * rng.standard_normal(lg.dim)
        obs.append(lg.H @ x + lg.r_std * rng.standard_normal(lg.obs_dim))
    return np.array(obs)


@pytest.fixture
def linear_obs():
    """``simulate_linear`` as a fixture: ``linear_obs(lg, seed) -> obs (K, m)`` numpy float64."""
    return simulate_linear


@pytest.fixture
def highest_precision():
    """The test's float32 matrix products at full precision, the precision it checks
    (``jax.default_matmul_precision("highest")``): on GPUs the default lets them use TF32."""
    with jax.default_matmul_precision("highest"):
        yield


@pytest.fixture
def x64():
    """Run the test with ``jax_enable_x64`` on; restore the previous setting afterwards."""
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", previous)


class Errors(NamedTuple):
    """Distance of a filter from the Kalman filter over all steps and coordinates.

    Mean errors are in units of the Kalman posterior std; std errors are relative.
    """

    mean_rms: float
    mean_max: float
    std_rms: float
    std_max: float


class LinearCase(NamedTuple):
    """A simulated linear-Gaussian run with its Kalman reference.

    obs: (K, m).  ensemble: (N, d) initial ensemble.  kalman: the exact FilterResult.
    prior_mean: (K, d) mean of the initial ensemble only propagated (observations ignored), or
      None when not asked for.
    """

    lg: LinearGaussian
    model: StateSpaceModel
    obs: jax.Array
    ensemble: jax.Array
    kalman: FilterResult
    prior_mean: jax.Array | None

    def errors(self, mean, std=None) -> Errors:
        """``Errors`` of a filter's ``mean (K, d)`` and ``std (K, d)`` (default: Kalman's std)."""
        z = (mean - self.kalman.mean) / self.kalman.std
        s = (self.kalman.std if std is None else std) / self.kalman.std - 1.0
        return Errors(_rms(z), float(jnp.abs(z).max()), _rms(s), float(jnp.abs(s).max()))


def _rms(x) -> float:
    return float(jnp.sqrt(jnp.mean(jnp.square(x))))


def _prior_only_mean(model: StateSpaceModel, ensemble, num_steps: int, key):
    """``(K, d)`` means of an ensemble that is only propagated: a 'filter' that ignores ``obs``."""

    def step(ens, k):
        ens = propagate(model, k, ens)
        return ens, ens.mean(axis=0)

    _, means = jax.lax.scan(step, ensemble, jax.random.split(key, num_steps))
    return means


def make_linear_case(obs_dim: int, num_particles: int, seed: int = 0,
                     with_prior: bool = False) -> LinearCase:
    """d = 2, K = 20 (default ``linear_gaussian``); everything from fixed seeds."""
    lg = linear_gaussian(dim=2, obs_dim=obs_dim, num_steps=20)
    model = to_model(lg)
    obs = jnp.asarray(simulate_linear(lg, seed))
    ensemble = model.initial_ensemble(jax.random.key(100 + seed), num_particles)
    prior = (_prior_only_mean(model, ensemble, obs.shape[0], jax.random.key(200 + seed))
             if with_prior else None)
    return LinearCase(lg, model, obs, ensemble, kalman_filter(obs, model=lg), prior)


@pytest.fixture(params=[1, 2], ids=["m1", "m2"])
def linear_case(request, x64) -> LinearCase:
    """d = 2 linear-Gaussian case, N = 20000, observing the first or both coordinates; float64."""
    return make_linear_case(request.param, 20000, with_prior=True)


@pytest.fixture
def small_case(x64) -> LinearCase:
    """d = 2, m = 2 linear-Gaussian case with N = 200 for API tests (jit, vmap, keys); float64."""
    return make_linear_case(2, 200)
