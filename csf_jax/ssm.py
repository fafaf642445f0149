"""The state-space model: ``x_{k+1} = f(x_k) + v_k + shock_k``, ``y_{k+1} = h(x_{k+1}) + w_k``.

A model is a ``StateSpaceModel``: a NamedTuple of pure single-particle callables and constants.
Filters vmap the callables over particles and close over the model as a static (hashable) argument,
so every field must be hashable: Python callables, numbers, strings, tuples. Matrices live inside
the callables' closures. ``shock`` acts on the truth only (filters never see it).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp

Array = jax.Array


class ObservationNoise(NamedTuple):
    """An additive, coordinate-wise i.i.d. observation noise ``w``.

    log_prob: residual ``(m,)`` -> scalar log-density (up to a constant).
    sample: ``(key, shape)`` -> a draw of that shape.
    gaussian_std: std of the Gaussian that the EnKF uses in its place (the noise's own std if
      Gaussian; for Cauchy the Gaussian with the same central 68% interval).
    fisher: the Fisher information of one coordinate's noise, ``E[(d log p(w) / dw)^2]``.
      None: ``1 / gaussian_std^2``. The curvature of CSF's Kalman guidance when ``weight`` is None.
    weight: optional ``residual (m,) -> (m,)``, the iteratively reweighted least-squares weights
      ``-(d log p / dw) / w`` of a symmetric noise whose log-density decreases in ``|w|``: the
      curvature of the Gaussian that touches ``log p`` from below at the residual. For Cauchy
      ``2 / (scale^2 + w^2)``: an outlier gets a small weight, so the guidance does not chase it
      (with the Fisher information it would). None: the constant ``fisher_information``.
    """

    name: str
    log_prob: Callable[[Array], Array]
    sample: Callable[[Array, tuple], Array]
    gaussian_std: float
    fisher: Optional[float] = None
    weight: Optional[Callable[[Array], Array]] = None

    @property
    def fisher_information(self) -> float:
        """The per-coordinate Fisher information (``fisher``, or ``1 / gaussian_std^2``)."""
        return float(self.fisher) if self.fisher is not None else 1.0 / self.gaussian_std ** 2

    def curvature(self, residual: Array) -> Array:
        """Per-coordinate curvature weights ``(m,)`` of the guidance at ``residual = y - h(x)``."""
        if self.weight is not None:
            return self.weight(residual)
        return jnp.full(residual.shape, self.fisher_information, residual.dtype)


def gaussian_noise(std: float) -> ObservationNoise:
    """i.i.d. ``N(0, std^2)`` noise."""
    inv_var = 1.0 / std**2

    def log_prob(r):
        return -0.5 * inv_var * jnp.sum(r * r)

    def sample(key, shape):
        return std * jax.random.normal(key, shape)

    return ObservationNoise("gaussian", log_prob, sample, float(std))


def cauchy_noise(scale: float) -> ObservationNoise:
    """i.i.d. ``Cauchy(0, scale)`` noise; log-density is the sum of independent Cauchy terms.

    Its Gaussian stand-in (``gaussian_std``) is the Gaussian with the same central 68% interval:
    ``scale = 0.0544`` gives std 0.1 (see ``cauchy_matched_std``).
    """

    def log_prob(r):
        return -jnp.sum(jnp.log1p((r / scale) ** 2))

    def sample(key, shape):
        return scale * jax.random.cauchy(key, shape)

    def weight(r):
        return 2.0 / (scale ** 2 + r * r)

    return ObservationNoise("cauchy", log_prob, sample, cauchy_matched_std(scale),
                            fisher=1.0 / (2.0 * scale ** 2), weight=weight)


def cauchy_matched_std(scale: float) -> float:
    """The Gaussian std whose central interval ``P(|w| < s) = 0.6827`` equals that of Cauchy(0, scale)."""
    p = math.erf(1.0 / math.sqrt(2.0))  # 0.6827, mass within one std of a Gaussian
    return scale * math.tan(0.5 * math.pi * p)


def no_shock_times(key: Array, num_steps: int) -> Array:
    """No shocks: ``(K,)`` all False."""
    del key
    return jnp.zeros((num_steps,), dtype=bool)


def random_shock_times(key: Array, num_steps: int, count: int,
                       window: tuple[float, float] = (0.2, 0.8)) -> Array:
    """``(K,)`` bool, True at ``count`` distinct steps drawn uniformly from ``window`` (fractions of K)."""
    if count == 0:
        return no_shock_times(key, num_steps)
    lo = int(window[0] * num_steps)
    hi = max(int(window[1] * num_steps), lo + count)
    steps = lo + jax.random.choice(key, hi - lo, (count,), replace=False)
    return jnp.zeros((num_steps,), dtype=bool).at[steps].set(True)


def jump_shock(size: float) -> Callable[[Array, Array], Array]:
    """A shock that adds ``size * r`` to the state, ``r`` independent random signs per coordinate."""

    def shock(key, x):
        return x + size * jax.random.rademacher(key, x.shape).astype(x.dtype)

    return shock


def reflect_shock(key: Array, x: Array) -> Array:
    """A shock that sends the state to ``-x``: a jump to the mirror well of a symmetric potential."""
    del key
    return -x


class StateSpaceModel(NamedTuple):
    """A discrete-time state-space model with additive Gaussian process noise.

    Attributes:
      name: identifier.
      dim: state dimension d.  obs_dim: observation dimension m.
      num_steps: default trajectory length K (observations ``y_1 .. y_K``).
      dt: the time step the dynamics were discretised with (informational).
      drift: ``x (d,) -> (d,)``, the deterministic map f (it includes ``x_k`` itself).
      observe: ``x (d,) -> (m,)``, the observation map h.
      process_std: std of the i.i.d. Gaussian process noise v (per coordinate).
      obs_noise: the observation noise w.
      initial_truth: ``key -> (d,)``, draws ``x_0`` of the truth.
      initial_ensemble: ``(key, N) -> (N, d)``, the filters' initial ensemble.
      shock_times: ``(key, K) -> (K,)`` bool, the steps at which the truth is shocked.
      shock: ``(key, x (d,)) -> (d,)``, the truth right after a shock (applied after the dynamics).
    """

    name: str
    dim: int
    obs_dim: int
    num_steps: int
    dt: float
    drift: Callable[[Array], Array]
    observe: Callable[[Array], Array]
    process_std: float
    obs_noise: ObservationNoise
    initial_truth: Callable[[Array], Array]
    initial_ensemble: Callable[[Array, int], Array]
    shock_times: Callable[[Array, int], Array] = no_shock_times
    shock: Callable[[Array, Array], Array] = reflect_shock


def log_likelihood(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """``log p(y | x)`` up to a constant for one particle: ``y: (m,)``, ``x: (d,)`` -> scalar."""
    return model.obs_noise.log_prob(y - model.observe(x))


def propagate(model: StateSpaceModel, key: Array, ensemble: Array) -> Array:
    """Prior ensemble ``f(x_i) + v_i``: ``ensemble (N, d) -> (N, d)``, drift vmapped over particles."""
    mean = jax.vmap(model.drift)(ensemble)
    return mean + model.process_std * jax.random.normal(key, mean.shape, mean.dtype)


def shock_steps(model: StateSpaceModel, key: Array, num_steps: int | None = None) -> Array:
    """``(K,)`` bool: the steps at which ``simulate(model, key)`` shocks the truth (step k is x_{k+1}).

    For figures and post-shock error analyses; same key as the ``simulate`` call.
    """
    K = model.num_steps if num_steps is None else int(num_steps)
    return model.shock_times(jax.random.split(key, 5)[1], K)


def simulate(model: StateSpaceModel, key: Array, num_steps: int | None = None):
    """Simulate the truth and its observations.

    Returns ``truth (K+1, d)`` (``x_0 .. x_K``) and ``obs (K, m)`` (``y_1 .. y_K``), with the model's
    shocks applied to the truth. Same key, same trajectory. Jit- and vmap-friendly.
    """
    K = model.num_steps if num_steps is None else int(num_steps)
    k0, _, k_shock, k_proc, k_obs = jax.random.split(key, 5)
    x0 = model.initial_truth(k0)
    shocked = shock_steps(model, key, K)
    v = model.process_std * jax.random.normal(k_proc, (K, model.dim))

    def step(x, inputs):
        v_k, shocked_k, key_k = inputs
        x_next = model.drift(x) + v_k
        x_next = jnp.where(shocked_k, model.shock(key_k, x_next), x_next)
        return x_next, x_next

    _, xs = jax.lax.scan(step, x0, (v, shocked, jax.random.split(k_shock, K)))
    truth = jnp.concatenate([x0[None], xs], axis=0)
    noise = model.obs_noise.sample(k_obs, (K, model.obs_dim))
    obs = jax.vmap(model.observe)(xs) + noise
    return truth, obs
