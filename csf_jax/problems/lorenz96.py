"""Lorenz-96 on a ring of d sites: the data-assimilation standard benchmark.

    dx_i/dt = (x_{i+1} - x_{i-2}) x_{i-1} - x_i + F,      i = 0 .. d-1 (indices mod d)

integrated with RK4 (``substeps`` steps of ``dt / substeps`` per filter step). The standard setup
(Sakov & Oke 2008; DAPPER's benchmark): F = 8, dt = 0.05, every site observed every step with
``R = I``, a perfect model (no process noise). Sensors: ``"identity"``, ``"every"`` (sites
0, k, 2k, ...) and ``"arctan"`` (``y_i = arctan(x_i) + w_i``, the nonlinear sensor of EnSF).

Initial conditions: a point on the attractor, reached by integrating ``spinup_steps`` filter steps
from ``F`` with a small perturbation of site 0 (deterministic, computed once per config); the truth
and the filters' ensemble both start from it plus ``N(0, x0_std^2 I)``. Filters then need a spin-up
of their own before their errors are representative (``Lorenz96Config.burn_in``).

``obs_sites(config)`` gives the site of each observation, for localisation.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.ssm import StateSpaceModel, gaussian_noise

SENSORS = ("identity", "every", "arctan")


@dataclasses.dataclass(frozen=True)
class Lorenz96Config:
    """Parameters of a Lorenz-96 problem; defaults are the standard setup.

    dim: number of sites d.  forcing: F.  dt: time between observations.  substeps: RK4 steps per
    dt.  sensor: "identity", "every" (every ``obs_every``-th site) or "arctan" (every site).
    obs_std: std of the i.i.d. Gaussian observation noise.  process_std: std of the additive
    process noise per step (0: perfect model).  num_steps: K.  burn_in: steps left out of
    time-averaged errors (the filters' own spin-up).  x0_std: spread of truth and ensemble around
    the attractor point at time 0.  spinup_steps: steps integrated to reach that point.
    """

    dim: int = 40
    forcing: float = 8.0
    dt: float = 0.05
    substeps: int = 1
    sensor: str = "identity"
    obs_every: int = 1
    obs_std: float = 1.0
    process_std: float = 0.0
    num_steps: int = 1000
    burn_in: int = 200
    x0_std: float = 1.0
    spinup_steps: int = 1000

    def __post_init__(self):
        _checks.check_fields(self)
        if self.sensor not in SENSORS:
            raise ValueError(f"Lorenz96Config.sensor must be one of {SENSORS}, got {self.sensor!r}")
        if self.dim < 4:
            raise ValueError(f"Lorenz96Config.dim must be >= 4, got {self.dim}")
        for name in ("substeps", "obs_every", "num_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"Lorenz96Config.{name} must be >= 1, got {getattr(self, name)}")
        if self.sensor == "every" and self.dim % self.obs_every:
            raise ValueError(f"Lorenz96Config.obs_every ({self.obs_every}) must divide dim "
                             f"({self.dim})")
        if not 0 <= self.burn_in < self.num_steps:
            raise ValueError(f"Lorenz96Config.burn_in must lie in [0, num_steps), got "
                             f"{self.burn_in}")
        for name in ("dt", "obs_std", "x0_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Lorenz96Config.{name} must be > 0, got {getattr(self, name)}")
        if not self.process_std >= 0:
            raise ValueError(f"Lorenz96Config.process_std must be >= 0, got {self.process_std}")


def tendency(x, forcing: float):
    """``dx/dt`` of Lorenz-96 for ``x (..., d)`` on the ring."""
    return (jnp.roll(x, -1, -1) - jnp.roll(x, 2, -1)) * jnp.roll(x, 1, -1) - x + forcing


def rk4(tendency_fn, x, h: float):
    """One classical Runge-Kutta step of length ``h`` of ``dx/dt = tendency_fn(x)`` (any model)."""
    k1 = tendency_fn(x)
    k2 = tendency_fn(x + 0.5 * h * k1)
    k3 = tendency_fn(x + 0.5 * h * k2)
    k4 = tendency_fn(x + h * k3)
    return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rk4_step(x, h: float, forcing: float):
    """One classical RK4 step of length ``h`` of Lorenz-96."""
    return rk4(lambda y: tendency(y, forcing), x, h)


def obs_sites(config: Lorenz96Config) -> np.ndarray:
    """``(m,)`` int: the site each observation sees."""
    step = config.obs_every if config.sensor == "every" else 1
    return np.arange(0, config.dim, step)


@functools.cache
def attractor_point(config: Lorenz96Config) -> np.ndarray:
    """``(d,)`` float32: ``F`` with site 0 raised by 0.01, integrated ``spinup_steps`` steps."""
    x = np.full(config.dim, config.forcing, np.float64)
    x[0] += 0.01
    h = config.dt / config.substeps
    x = jax.jit(lambda x: jax.lax.fori_loop(
        0, config.spinup_steps * config.substeps, lambda i, x: rk4_step(x, h, config.forcing), x))(
        jnp.asarray(x, jnp.float32))
    out = np.asarray(x, np.float32)
    out.setflags(write=False)
    return out


@functools.cache
def lorenz96_problem(config: Lorenz96Config = Lorenz96Config()) -> StateSpaceModel:
    """The Lorenz-96 ``StateSpaceModel``; cached, so equal configs give the same model."""
    c = config
    h = c.dt / c.substeps
    sites = obs_sites(c)
    x_a = attractor_point(c)

    def drift(x):
        return jax.lax.fori_loop(0, c.substeps, lambda i, x: rk4_step(x, h, c.forcing), x)

    if c.sensor == "identity":
        def observe(x):
            return x
    elif c.sensor == "every":
        def observe(x):
            return x[::c.obs_every]
    else:
        def observe(x):
            return jnp.arctan(x)

    def initial_truth(key):
        return jnp.asarray(x_a) + c.x0_std * jax.random.normal(key, (c.dim,))

    def initial_ensemble(key, n):
        return jnp.asarray(x_a) + c.x0_std * jax.random.normal(key, (n, c.dim))

    suffix = "" if c.sensor == "identity" else f"_{c.sensor}"
    return StateSpaceModel(
        name=f"lorenz96_d{c.dim}{suffix}", dim=c.dim, obs_dim=len(sites), num_steps=c.num_steps,
        dt=c.dt, drift=drift, observe=observe, process_std=c.process_std,
        obs_noise=gaussian_noise(c.obs_std), initial_truth=initial_truth,
        initial_ensemble=initial_ensemble)
