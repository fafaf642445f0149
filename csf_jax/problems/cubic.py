"""Cubic-sensor problems (paper Sec. 3.2, Eqs. exp2 and exp3).

    x_{k+1} = x_k + f(x_k) dt + v_k,   v_k ~ N(0, 0.1^2 I)
    y_{k+1} = x_{k+1}^3 + w_k

with ``f(x) = cos(x)`` (independent) or ``f(x) = A_n x + cos(x)`` (correlated; ``A_n`` has -0.5 on
the diagonal and 0.1 on the superdiagonal). ``w_k`` is N(0, 0.1^2 I), or i.i.d. Cauchy(0, 0.0544)
for the 5-D "cauchy" problem. Shocks and initial conditions are our choices (README).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.ssm import (
    StateSpaceModel,
    cauchy_noise,
    gaussian_noise,
    jump_shock,
    random_shock_times,
)


@dataclasses.dataclass(frozen=True)
class CubicConfig:
    """Parameters of a cubic-sensor problem; defaults reproduce the README's tables.

    dim: state dimension d (= m).  correlated: use ``A_n x + cos(x)`` as the drift.
    noise: "gaussian" (std ``obs_scale``) or "cauchy" (scale ``obs_scale``).
    dt: time step.  process_std: std of v_k.  num_steps: K.
    x0_mean, x0_std: truth x_0 ~ N(x0_mean, x0_std^2 I); the initial ensemble has the same law.
    shock_count, shock_size: jumps of +-shock_size in every coordinate at random steps in
      [0.2 K, 0.8 K) (paper: "two random shocks").
    """

    dim: int = 10
    correlated: bool = False
    noise: str = "gaussian"
    obs_scale: float = 0.1
    dt: float = 0.01
    process_std: float = 0.1
    num_steps: int = 200
    x0_mean: float = 0.0
    x0_std: float = 1.0
    shock_count: int = 2
    shock_size: float = 1.0

    def __post_init__(self):
        _checks.check_fields(self)
        if self.noise not in ("gaussian", "cauchy"):
            raise ValueError(f"CubicConfig.noise must be 'gaussian' or 'cauchy', got {self.noise!r}")
        if self.dim < 1 or self.num_steps < 1 or self.shock_count < 0:
            raise ValueError("CubicConfig.dim and num_steps must be >= 1, shock_count >= 0")
        for name in ("obs_scale", "dt", "process_std", "x0_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CubicConfig.{name} must be > 0, got {getattr(self, name)}")


def coupling_matrix(dim: int) -> np.ndarray:
    """``A_n``: -0.5 on the diagonal, 0.1 at (i, i+1)."""
    return -0.5 * np.eye(dim, dtype=np.float32) + 0.1 * np.eye(dim, k=1, dtype=np.float32)


@functools.cache
def cubic_problem(config: CubicConfig = CubicConfig()) -> StateSpaceModel:
    """The cubic-sensor ``StateSpaceModel``; cached, so equal configs give the same model."""
    c = config
    # a host array: a model first built inside a ``jax.jit`` trace must not keep a tracer
    a = coupling_matrix(c.dim) if c.correlated else None

    def drift(x):
        f = jnp.cos(x) if a is None else jnp.asarray(a) @ x + jnp.cos(x)
        return x + f * c.dt

    def observe(x):
        return x**3

    def initial_truth(key):
        return c.x0_mean + c.x0_std * jax.random.normal(key, (c.dim,))

    def initial_ensemble(key, n):
        return c.x0_mean + c.x0_std * jax.random.normal(key, (n, c.dim))

    def shock_times(key, num_steps):
        return random_shock_times(key, num_steps, c.shock_count)

    noise = gaussian_noise(c.obs_scale) if c.noise == "gaussian" else cauchy_noise(c.obs_scale)
    kind = "corr" if c.correlated else "indep"
    name = "cauchy" if c.noise == "cauchy" else f"cubic{c.dim}_{kind}"
    return StateSpaceModel(
        name=name, dim=c.dim, obs_dim=c.dim, num_steps=c.num_steps, dt=c.dt, drift=drift,
        observe=observe, process_std=c.process_std, obs_noise=noise, initial_truth=initial_truth,
        initial_ensemble=initial_ensemble, shock_times=shock_times,
        shock=jump_shock(c.shock_size))
