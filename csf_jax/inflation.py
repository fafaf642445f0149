"""Adaptive prior inflation from the innovation: inflate at a surprise, not otherwise.

CSF's prior inflation ``tau`` convolves the prior with ``N(0, tau^2 I)`` (``csf_jax.sde.inflated_time``;
the score-based form of the ensemble filters' covariance inflation). A fixed ``tau`` trades prior
information for robustness at every step. The adaptive ``tau`` is chosen per filter step from how
improbable the observation is under the prior ensemble (Anderson 2007; Li, Kalnay & Miyoshi 2009):

    e = y - mean_i h(x_i),    v = var_i h(x_i) + r,    g = mean_i sum_d (dh/dx)^2   (all (m,))

``sum_j e_j^2 / v_j`` is about ``m`` when the prior ensemble is consistent with ``y``. When it is
larger by more than ``threshold`` standard deviations of a chi-square with m degrees of freedom,
``s = tau^2`` solves ``sum_j e_j^2 / (v_j + s g_j) = m``: the isotropic state-space spread that makes
the innovation typical again, linearised through the ensemble's mean squared Jacobian rows. Otherwise
``s = 0``. After an unmodelled shock ``s`` is about the squared jump; between shocks it is 0.

Only entries whose stand-in's mean moves with the state (``g > 0``) take part: for the others no
``s`` changes ``v``, so they can neither call for inflation nor be explained by it.

``statistic="median"`` is the form for heavy-tailed noise: one outlying coordinate (a Cauchy draw)
must not read as a shock. It inflates only when more than half of the coordinates are surprised
(``e_j^2 / v_j > 1 + threshold sqrt(2)``, the per-coordinate form of the same trigger; 3.83 at
threshold 2, the 95% point of a chi-square with one degree of freedom), and then takes
``s = median_j max(0, (e_j^2 - v_j) / g_j)``. For m = 1 the two statistics agree.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from csf_jax import _checks, _linalg
from csf_jax.ssm import StateSpaceModel, gaussian_standin, is_additive, observed


@_linalg.precise
def innovation_statistic(prior_ens, y, model: StateSpaceModel, base: float = 0.0):
    """``(e^2 (m,), v (m,), g (m,))`` of the module docstring for ``prior_ens: (N, d)``, ``y: (m,)``.

    ``v`` includes the fixed inflation ``base`` (``base^2 g``) and the noise's variance ``r`` (the
    diagonal of the Gaussian stand-in's R, ``ssm.gaussian_standin``: ``gaussian_std^2`` unless a
    covariance is given). Missing (NaN) entries of ``y`` get ``e^2 = 0``.
    """
    hx, R = gaussian_standin(model, prior_ens)
    if is_additive(model):
        predict = model.observe
    else:
        predict = lambda x: model.obs_noise.mean(model.observe(x))
    jac = jax.vmap(jax.jacfwd(predict))(prior_ens)  # (N, m, d)
    g = jnp.mean(jnp.sum(jac * jac, -1), 0)
    r = jnp.diagonal(R)
    mask = observed(y)
    e2 = jnp.where(mask, jnp.square(jnp.where(mask, y, 0.0) - hx.mean(0)), 0.0)
    v = hx.var(0) + r + base ** 2 * g
    return e2, v, g


STATISTICS = ("chi2", "median")


def adaptive_inflation(prior_ens, y, model: StateSpaceModel, base: float = 0.0,
                       threshold: float = 2.0, max_tau: float = 10.0, iterations: int = 60,
                       statistic: str = "chi2"):
    """The prior inflation ``tau`` (scalar, >= ``base``) for one filter step.

    prior_ens: (N, d) propagated ensemble.  y: (m,) this step's observation.
    base: the fixed inflation, always applied (``tau^2 = base^2 + s``).
    threshold: inflate only when ``sum e^2 / v > m + threshold sqrt(2 m)`` (a chi-square tail).
    max_tau: cap on the adaptive part ``sqrt(s)``.  iterations: bisection steps in ``log s``.
    statistic: "chi2" (the sum) or "median" (robust to single outlying coordinates; module doc).
    """
    if statistic not in STATISTICS:
        raise ValueError(f"adaptive_inflation: statistic must be one of {STATISTICS}, got "
                         f"{statistic!r}")
    e2, v, g = innovation_statistic(prior_ens, y, model, base)
    # the observed entries that inflating the state can move: an entry whose Gaussian stand-in
    # does not depend on the state (g = 0: stochastic volatility's mean 0) cannot be explained by
    # any tau, and counting it would drive tau to its cap at every large observation
    mask = observed(y) & (g > 0)
    m = jnp.sum(mask).astype(v.dtype)  # none: no inflation
    if statistic == "median":
        votes = jnp.sum(mask & (e2 / v > 1.0 + threshold * jnp.sqrt(2.0)))
        s = jnp.nanmedian(jnp.where(mask, jnp.maximum(0.0, (e2 - v) / g), jnp.nan))
        s = jnp.where((votes > m / 2) & (m > 0), jnp.minimum(s, max_tau ** 2), 0.0)
        return jnp.sqrt(base ** 2 + s)
    stat = lambda s: jnp.sum(jnp.where(mask, e2 / (v + s * g), 0.0))
    surprised = stat(0.0) > m + threshold * jnp.sqrt(2.0 * m)
    lo, hi = jnp.log(jnp.asarray(1e-8, v.dtype)), jnp.log(jnp.asarray(max_tau ** 2, v.dtype))

    def bisect(_, bounds):
        a, b = bounds
        mid = 0.5 * (a + b)
        too_small = stat(jnp.exp(mid)) > m
        return jnp.where(too_small, mid, a), jnp.where(too_small, b, mid)

    _, s_hi = jax.lax.fori_loop(0, iterations, bisect, (lo, hi))
    s = jnp.where(surprised, jnp.exp(s_hi), 0.0)
    return jnp.sqrt(base ** 2 + s)


@dataclasses.dataclass(frozen=True)
class InflationConfig:
    """CSF's prior inflation ``tau`` per filter step (``CSFConfig.inflation``; module docstring).

    Attributes:
      base: tau_0 >= 0, the fixed part. The prior score is evaluated at the noise level
        ``sqrt(sigma_t^2 + tau^2)``: the prior convolved with ``N(0, tau^2 I)``, the score-based form
        of the ensemble filters' covariance inflation. 0 is the paper's sampler and the exact Bayes
        update between surprises.
      adaptive: add ``s`` of the module docstring per step (``tau^2 = base^2 + s``): ``s > 0`` only
        when the observation is improbable under the prior ensemble (an unmodelled shock). Off
        by default: the mixture prior's shock components (``csf_jax.mixture``) read a surprise by
        its evidence instead; ``csf_jax.PAPER``, the learned prior alone, turns it on.
      threshold: the trigger, in standard deviations of the chi-square innovation statistic above
        its mean.
      max: cap on the adaptive part of tau.
      statistic: "median" (a majority of coordinates must be surprised; robust to heavy-tailed
        noise, where "chi2" reads one outlier as a shock) or "chi2" (the innovation's chi-square sum).
    """

    base: float = 0.0
    adaptive: bool = False
    threshold: float = 2.0
    max: float = 10.0
    statistic: str = "median"

    def __post_init__(self):
        _checks.check_fields(self, nonnegative=("base",), positive=("max",))
        if self.statistic not in STATISTICS:
            raise ValueError(f"InflationConfig.statistic must be one of {STATISTICS}, got "
                             f"{self.statistic!r}")
