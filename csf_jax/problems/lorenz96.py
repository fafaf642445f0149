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

EnSF's setup (Bao, Zhang & Zhang 2024; the registry's ``lorenz96_ensf``) changes three things,
each a config field that is off by default:

* ``truth_spinup > 0``: the truth starts from ``N(0, x0_std^2 I)`` integrated ``truth_spinup``
  filter steps, a fresh point on the attractor for every key (EnSF: ``3 N(0, I)`` run 1000 RK4
  steps of 0.01);
* ``ensemble_init = "standard"``: the filters' ensemble is ``N(0, I)``, independent of the truth
  and far from it;
* ``shock_probs``, ``shock_sizes``: random relative shocks of the truth. In every RK4 substep a
  shock of kind j happens with probability ``shock_probs[j]``; a filter step whose substeps had
  any ends with ``x <- x + s |x| * xi``, ``xi ~ N(0, I)``, ``s`` the summed sizes of its events
  (EnSF applies the same perturbation right after the substep of the event).

A model with any of them set is named ``lorenz96_d<d>[_<sensor>]_ensf``.

``obs_sites(config)`` gives the site of each observation, for localisation.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.ssm import StateSpaceModel, gaussian_noise

SENSORS = ("identity", "every", "arctan")
ENSEMBLE_INITS = ("attractor", "standard")


@dataclasses.dataclass(frozen=True)
class Lorenz96Config:
    """Parameters of a Lorenz-96 problem; defaults are the standard setup.

    dim: number of sites d.  forcing: F.  dt: time between observations.  substeps: RK4 steps per
    dt.  sensor: "identity", "every" (every ``obs_every``-th site) or "arctan" (every site).
    obs_std: std of the i.i.d. Gaussian observation noise.  process_std: std of the additive
    process noise per step (0: perfect model).  num_steps: K.  burn_in: steps left out of
    time-averaged errors (the filters' own spin-up).  x0_std: spread of truth and ensemble around
    the attractor point at time 0 (with ``truth_spinup``: the truth's spread before its spin-up).
    spinup_steps: steps integrated to reach that point.
    truth_spinup: 0, or the filter steps a random truth ``N(0, x0_std^2 I)`` is integrated to
      reach the attractor (EnSF: 100 steps of 0.1).
    ensemble_init: "attractor" (the ensemble drawn around the attractor point like the truth) or
      "standard" (``N(0, I)``, independent of the truth: EnSF).
    shock_probs, shock_sizes: per RK4 substep, the probability of a relative shock of each kind
      and its size (EnSF: probabilities (0.005, 0.01, 0.02), sizes (0.5, 0.2, 0.05)); () for none.
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
    truth_spinup: int = 0
    ensemble_init: str = "attractor"
    shock_probs: tuple = ()
    shock_sizes: tuple = ()

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
        if self.truth_spinup < 0:
            raise ValueError(f"Lorenz96Config.truth_spinup must be >= 0, got {self.truth_spinup}")
        if self.ensemble_init not in ENSEMBLE_INITS:
            raise ValueError(f"Lorenz96Config.ensemble_init must be one of {ENSEMBLE_INITS}, got "
                             f"{self.ensemble_init!r}")
        probs, sizes = self.shock_probs, self.shock_sizes
        if len(probs) != len(sizes):
            raise ValueError(f"Lorenz96Config.shock_probs and shock_sizes need one entry per "
                             f"kind of shock, got {len(probs)} and {len(sizes)}")
        if not all(_is_number(p) and 0.0 <= p <= 1.0 for p in probs):
            raise ValueError(f"Lorenz96Config.shock_probs must be probabilities in [0, 1], got "
                             f"{probs!r}")
        if not all(_is_number(v) and v > 0 for v in sizes):
            raise ValueError(f"Lorenz96Config.shock_sizes must be finite numbers > 0, got "
                             f"{sizes!r}")

    @property
    def ensf_fields(self) -> bool:
        """Whether any of EnSF's fields (spun-up truth, standard ensemble, shocks) is set."""
        return bool(self.truth_spinup or self.ensemble_init != "attractor" or self.shock_probs)


def _is_number(value) -> bool:
    """A finite real number (not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)) and math.isfinite(float(value)))


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
    """``(d,)`` float32: ``F`` with site 0 raised by 0.01, integrated ``spinup_steps`` steps
    (computed at once, also when the model is first built inside a ``jax.jit`` trace)."""
    x = np.full(config.dim, config.forcing, np.float64)
    x[0] += 0.01
    h = config.dt / config.substeps
    with jax.ensure_compile_time_eval():
        x = jax.jit(lambda x: jax.lax.fori_loop(
            0, config.spinup_steps * config.substeps, lambda i, x: rk4_step(x, h, config.forcing),
            x))(jnp.asarray(x, jnp.float32))
    out = np.asarray(x, np.float32)
    out.setflags(write=False)
    return out


class ShockLaw(NamedTuple):
    """The relative shocks of one filter step, from per-substep events: ``probs (M,)`` and
    ``sizes (M,)`` list every (substep, kind) event in order; ``any_prob`` is the probability that
    a step has at least one (``shock_times``); ``first (M,)`` the law of the first event's index
    given that it has (so that ``relative_shock`` draws the step's events given at least one)."""

    probs: np.ndarray
    sizes: np.ndarray
    any_prob: float
    first: np.ndarray


@functools.cache
def shock_law(config: Lorenz96Config) -> ShockLaw | None:
    """``ShockLaw`` of ``config``'s shocks over its ``substeps`` RK4 substeps, or None without."""
    if not config.shock_probs or not any(config.shock_probs):
        return None
    probs = np.tile(np.asarray(config.shock_probs, np.float64), config.substeps)
    sizes = np.tile(np.asarray(config.shock_sizes, np.float64), config.substeps)
    none_before = np.concatenate([[1.0], np.cumprod(1.0 - probs)[:-1]])
    any_prob = 1.0 - float(np.prod(1.0 - probs))
    return ShockLaw(probs, sizes, any_prob, probs * none_before / any_prob)


def relative_shock(law: ShockLaw):
    """The truth's shock of a step known to have at least one event: ``x + s |x| xi``, ``xi ~
    N(0, I)``, ``s`` the summed sizes of the step's events, drawn exactly given at least one (the
    first event's index from ``law.first``, every later one independently)."""
    probs, sizes, first = (jnp.asarray(a, jnp.float32) for a in (law.probs, law.sizes,
                                                                  law.first))

    def shock(key, x):
        k_first, k_rest, k_dir = jax.random.split(key, 3)
        lead = jax.random.choice(k_first, probs.shape[0], p=first)
        later = jax.random.bernoulli(k_rest, probs) & (jnp.arange(probs.shape[0]) > lead)
        size = sizes[lead] + jnp.sum(jnp.where(later, sizes, 0.0))
        xi = jax.random.normal(k_dir, x.shape, x.dtype)
        return x + size.astype(x.dtype) * jnp.abs(x) * xi

    return shock


@functools.cache
def lorenz96_problem(config: Lorenz96Config = Lorenz96Config()) -> StateSpaceModel:
    """The Lorenz-96 ``StateSpaceModel``; cached, so equal configs give the same model."""
    c = config
    h = c.dt / c.substeps
    sites = obs_sites(c)
    needs_attractor = c.truth_spinup == 0 or c.ensemble_init == "attractor"
    x_a = attractor_point(c) if needs_attractor else None

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

    if c.truth_spinup:
        def initial_truth(key):
            x = c.x0_std * jax.random.normal(key, (c.dim,))
            return jax.lax.fori_loop(0, c.truth_spinup * c.substeps,
                                     lambda i, x: rk4_step(x, h, c.forcing), x)
    else:
        def initial_truth(key):
            return jnp.asarray(x_a) + c.x0_std * jax.random.normal(key, (c.dim,))

    if c.ensemble_init == "standard":
        def initial_ensemble(key, n):
            return jax.random.normal(key, (n, c.dim))
    else:
        def initial_ensemble(key, n):
            return jnp.asarray(x_a) + c.x0_std * jax.random.normal(key, (n, c.dim))

    law = shock_law(c)
    shocks = {}
    if law is not None:
        def shock_times(key, num_steps):
            return jax.random.bernoulli(key, law.any_prob, (num_steps,))

        shocks = {"shock_times": shock_times, "shock": relative_shock(law)}

    suffix = "" if c.sensor == "identity" else f"_{c.sensor}"
    suffix += "_ensf" if c.ensf_fields else ""
    return StateSpaceModel(
        name=f"lorenz96_d{c.dim}{suffix}", dim=c.dim, obs_dim=len(sites), num_steps=c.num_steps,
        dt=c.dt, drift=drift, observe=observe, process_std=c.process_std,
        obs_noise=gaussian_noise(c.obs_std), initial_truth=initial_truth,
        initial_ensemble=initial_ensemble, **shocks)
