"""The 1-D double- and triple-well problems (paper Sec. 3.2, Eq. exp1).

    x_{k+1} = x_k - V'(x_k) dt + sqrt(dt) v_k,   v_k ~ N(0, 0.2^2)
    y_{k+1} = x_{k+1}^3 + w_k,                   w_k ~ N(0, 0.1^2)

    V_double(x) = C (x - 1)^2 (x + 1)^2,   V_triple(x) = C (x - 1)^2 (x + 1)^2 (x - 0.5)^2

The paper's Eq. exp1 drops ``x_k`` from the right-hand side (``x_{k+1} = -V'(x_k) dt + ...``), which
would pin the state near 0 and contradicts "two stable minima near +-1": we keep ``x_k``
(``include_state=True``). The paper leaves C, the shocks and the initial conditions open; the
defaults below are our choices (see the README, "Choices where the paper is silent").
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax

from csf_jax import _checks
from csf_jax.ssm import (
    StateSpaceModel,
    gaussian_noise,
    jump_shock,
    random_shock_times,
    reflect_shock,
)


@dataclasses.dataclass(frozen=True)
class WellConfig:
    """Parameters of a well problem; defaults reproduce the README's tables.

    wells: "double" or "triple".
    C: potential scale. Default 1.5 (double well): deep enough that a 1000-particle PF stays in the
      old well after a shock in most runs, as the paper's PF column shows. The triple well uses 0.5
      (its quintic drift makes the Euler map escape to infinity beyond |x| ~ 1.5 for C >= 1, which
      EnKF updates reach).
    dt: time step.  process_std: std of v_k (the noise added is ``sqrt(dt) * v_k``).
    obs_std: std of w_k.  num_steps: K.
    include_state: keep ``x_k`` in the update (see module docstring); False is the paper's literal form.
    x0_mean, x0_std: truth x_0 ~ N(x0_mean, x0_std^2); the filters' initial ensemble has the same law.
    shock_count: number of shocks to the truth, at random steps in [0.2 K, 0.8 K).
    shock_size: None (default) reflects the truth, ``x -> -x``: a jump to the mirror well (for the
      triple well, 0.5 goes to -0.5 and falls into -1). A float adds +-shock_size instead; beware
      that the Euler map escapes to infinity beyond |x| ~ 2.1 (double, C = 1.5) or ~ 1.8 (triple,
      C = 0.5).
    """

    wells: str = "double"
    C: float = 1.5
    dt: float = 0.1
    process_std: float = 0.2
    obs_std: float = 0.1
    num_steps: int = 100
    include_state: bool = True
    x0_mean: float = 1.0
    x0_std: float = 0.1
    shock_count: int = 1
    shock_size: float | None = None

    def __post_init__(self):
        _checks.check_fields(self)
        if self.wells not in ("double", "triple"):
            raise ValueError(f"WellConfig.wells must be 'double' or 'triple', got {self.wells!r}")
        for name in ("dt", "process_std", "obs_std", "x0_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"WellConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.num_steps < 1 or self.shock_count < 0:
            raise ValueError("WellConfig.num_steps must be >= 1 and shock_count >= 0")


def potential(x, wells: str, C: float):
    """V(x) for ``wells`` in {"double", "triple"}; any shape."""
    v = C * (x - 1.0) ** 2 * (x + 1.0) ** 2
    return v * (x - 0.5) ** 2 if wells == "triple" else v


@functools.cache
def well_problem(config: WellConfig = WellConfig()) -> StateSpaceModel:
    """The double- or triple-well ``StateSpaceModel`` (d = m = 1); cached, so equal configs give the
    same (hashable) model and jit caches are reused."""
    c = config
    grad_v = jax.grad(lambda x: potential(x, c.wells, c.C))

    def drift(x):
        step = -jax.vmap(grad_v)(x) * c.dt
        return x + step if c.include_state else step

    def observe(x):
        return x**3

    def initial_truth(key):
        return c.x0_mean + c.x0_std * jax.random.normal(key, (1,))

    def initial_ensemble(key, n):
        return c.x0_mean + c.x0_std * jax.random.normal(key, (n, 1))

    def shock_times(key, num_steps):
        return random_shock_times(key, num_steps, c.shock_count)

    return StateSpaceModel(
        name=f"{c.wells}_well", dim=1, obs_dim=1, num_steps=c.num_steps, dt=c.dt, drift=drift,
        observe=observe, process_std=math.sqrt(c.dt) * c.process_std,
        obs_noise=gaussian_noise(c.obs_std), initial_truth=initial_truth,
        initial_ensemble=initial_ensemble, shock_times=shock_times,
        shock=reflect_shock if c.shock_size is None else jump_shock(c.shock_size))
