"""The local iterative ensemble Kalman smoother with a lag of one step (IEnKS; Sakov, Oliver &
Bertino 2012, Bocquet & Sakov 2014), localised as the LETKF is: the iterative baseline of the
local filters.

Each step takes the analysis ensemble ``E (N, d)`` of the previous step, with mean ``x_bar`` and
(inflated) anomalies ``A = inflation (E - x_bar)``, and looks for each site j's weights ``w_j``
``(N,)`` at the start of the step that explain the observations near the site after the model's
step: the minimiser of

    J_j(w) = (N - 1) |w|^2 / 2 + |y - h(M(x_bar + A^T w))|^2_{R_loc^{-1}} / 2,

with ``R_loc^{-1}`` the inverse variances of the observations in reach tapered by the
Gaspari-Cohn weight of their distance to the site (R-localisation, support ``2 radius``), by
Gauss-Newton in the transform form: the members ``x_bar + A^T (w_j + T_j)`` at every site (its own
weights and transform ``T_j (N, N)``, ``I`` at first) are carried through the model's step, the
sensitivities of the site's observations to ``w`` are the predicted observations' anomalies
``Y'`` with the transform undone (``S_j = T_j^{-1} Y'``), and ``T_j = [(N - 1) H_j^{-1}]^{1/2}``
follows the cost's Gauss-Newton Hessian ``H_j = (N - 1) I + S_j R_loc^{-1} S_j^T`` (the symmetric
square root). Near an observation the members carry the weights of the observation's own site,
so each site's residuals are moved to its own weights to first order,
``r_o - S_o^T (w_j - w_{site(o)})``: each site's cost is its own. Each site's step is damped as Levenberg-Marquardt's, ``(H_j + lm_j (N - 1) I)^{-1}``
times the gradient, and kept where it lowers the site's cost (``lm_j`` quartered), else dropped
(``lm_j`` quadrupled, at least 1/4): from an ensemble far from the truth undamped steps overshoot
and the iterates overflow. Iterations stop when every site's last step ``dw`` has
``dw^T H_j dw <= tol`` (squared units of the site's posterior spread), or after ``iterations``.
The analysis is the kept members carried through the model's step: the model's image of an
ensemble at the start of the step, so the model's nonlinearity enters the analysis, where the
LETKF linearises the sensor after the step, at the forecast mean.

With the identity as the model and a linear sensor the first iteration is the LETKF's analysis
(``tests/test_ienks.py``); with a linear model and one site it is the ensemble Kalman update of the
propagated ensemble. The model must be perfect (no process noise): the smoother's window carries
the members through the model's step, where a noise draw would enter the sensitivities.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.enkf import check_standin
from csf_jax.filters.letkf import (
    Localization,
    check_adaptive,
    check_localization,
    enkf_n_inflation,
    ensemble_state,
    local_obs,
    require_localization,
)
from csf_jax.filters.result import FilterResult
from csf_jax.ssm import StateSpaceModel, check_model, gaussian_standin, is_additive, observed


@dataclasses.dataclass(frozen=True)
class IEnKSConfig:
    """The local iterative smoother's localisation, inflation and iterations.

    Attributes:
      radius: Gaspari-Cohn half-width in site units (support 2 radius).
      inflation: multiplicative factor on the anomalies at the start of the step.
      adaptive: 0 (off), or the EnKF-N hyperprior's certainty (as ``LETKFConfig.adaptive``): the
        anomalies are further scaled by the factor the EnKF-N picks from the first forecast's
        innovation.
      iterations: the most Levenberg-Marquardt iterations per step; each carries the N members
        through the model's step once, as do the start and the analysis (and the EnKF-N's
        forecast with ``adaptive``).
      tol: stop when every site's last step ``dw`` is below ``dw^T H_j dw <= tol``, in squared
        units of the site's posterior spread (``H_j``: the cost's Gauss-Newton Hessian).
    """

    radius: float = 4.0
    inflation: float = 1.05
    adaptive: float = 0.0
    iterations: int = 10
    tol: float = 1.0

    def __post_init__(self):
        _checks.check_fields(self, positive=("radius", "inflation", "iterations"),
                             nonnegative=("tol",))
        check_adaptive(self)


class IEnKSStatic(NamedTuple):
    """The smoother's static settings for the driver."""

    radius: float
    localization: Localization
    adaptive: float
    iterations: int
    tol: float


def _members(x_bar, anom, w, t):
    """``(N, d)``: at each site j, ``x_bar_j + A_j^T (w_j + T_j)``; ``anom (N, d)``, ``w (d, N)``,
    ``t (d, N, N)``."""
    return x_bar + jnp.einsum("jmn,mj->nj", w[:, :, None] + t, anom)


def _site_terms(w, t_inv, y_anom, innov, obs_w, w_obs, idx, taper):
    """One site's cost ``J_j``, gradient ``(N,)`` and Gauss-Newton Hessian ``(N, N)`` at the
    members carried through the step: ``w (N,)`` the site's weights, ``t_inv (N, N)`` its
    transform's inverse, ``y_anom (N, m)`` the predicted observations' anomalies, ``innov (m,)``
    the observations minus their mean and ``obs_w (m,)`` their inverse variances (both 0 where
    missing), ``w_obs (m, N)`` the weights of the site each observation sits at; ``idx, taper
    (W,)`` the site's observations in reach. The members near an observation carry that site's
    weights, so its residual is moved to this site's weights to first order,
    ``r_o - S_o^T (w - w_obs[o])``: each site's cost is its own, and a linear problem's first
    step is its minimum."""
    n = w.shape[0]
    s = t_inv @ y_anom[:, idx]                       # (N, W): sensitivities to w
    prec = taper * obs_w[idx]
    r = innov[idx] - jnp.einsum("nw,wn->w", s, w[None, :] - w_obs[idx])
    cost = 0.5 * (n - 1) * (w @ w) + 0.5 * jnp.sum(prec * r * r)
    grad = (n - 1) * w - s @ (prec * r)
    hess = (n - 1) * jnp.eye(n, dtype=w.dtype) + (s * prec) @ s.T
    return cost, grad, hess


def _site_trial(w, grad, hess, lm):
    """One site's Levenberg-Marquardt trial ``w - (H + lm (N - 1) I)^{-1} g`` and the transform
    ``T = [(N - 1) H^{-1}]^{1/2}`` with its inverse (both ``(N, N)``, symmetric), all from one
    eigendecomposition of H (a second batched LAPACK call beside it can stall jaxlib's CPU
    thread pool: docs/lorenz96.md)."""
    n = w.shape[0]
    lam, vec = jnp.linalg.eigh(hess)
    lam = jnp.maximum(lam, 1e-12)
    trial = w - vec @ ((vec.T @ grad) / (lam + lm * (n - 1)))
    t = (vec * jnp.sqrt((n - 1) / lam)) @ vec.T
    t_inv = (vec * jnp.sqrt(lam / (n - 1))) @ vec.T
    return trial, t, t_inv


def smoother_analysis(ensemble, y, model: StateSpaceModel, index, weight, obs_site, inflation,
                      adaptive: float = IEnKSConfig.adaptive,
                      iterations: int = IEnKSConfig.iterations, tol: float = IEnKSConfig.tol):
    """The lag-1 smoother's analysis at the next time: ``ensemble (N, d)`` the analysis of the
    previous step, ``y (m,)`` the next observations (NaN: missing), ``index, weight (d, W)`` from
    ``local_obs``, ``obs_site (m,)`` the state site each observation sits at (``nearest_sites``),
    ``inflation`` a traced scalar; the rest as ``IEnKSConfig``'s fields (its defaults). Returns
    ``(analysis (N, d), iterations run)``."""
    n, d = ensemble.shape
    dtype = ensemble.dtype
    drift = jax.vmap(model.drift)
    x_bar = ensemble.mean(0)
    anom = inflation.astype(dtype) * (ensemble - x_bar)
    if adaptive > 0:
        anom = anom * enkf_n_inflation(drift(x_bar + anom), y, model, adaptive)
    mask = observed(y)
    taper = jnp.asarray(weight, dtype)
    index = jnp.asarray(index)
    sites = jax.vmap(_site_terms, in_axes=(0, 0, None, None, None, None, 0, 0))
    obs_site = jnp.asarray(obs_site)
    trials = jax.vmap(_site_trial)

    def terms(w, t, t_inv):
        """Every site's cost, gradient and Hessian at the members of ``w, t``."""
        hx, R = gaussian_standin(model, drift(_members(x_bar, anom, w, t)))
        y_mean = hx.mean(0)
        innov = jnp.where(mask, jnp.where(mask, y, 0.0) - y_mean, 0.0)
        obs_w = jnp.where(mask, 1.0 / jnp.diagonal(R), 0.0)
        return sites(w, t_inv, hx - y_mean, innov, obs_w, w[obs_site], index, taper)

    def iterate(carry):
        """Each site's trial, kept where it lowers the site's cost (the damping quartered), else
        dropped (the damping quadrupled, at least 1/4): Levenberg-Marquardt."""
        w, t, cost, grad, hess, lm, count, _ = carry
        w_t, t_t, t_inv_t = trials(w, grad, hess, lm)
        cost_t, grad_t, hess_t = terms(w_t, t_t, t_inv_t)
        better = cost_t < cost
        keep = lambda new, old: jnp.where(  # noqa: E731
            better.reshape((d,) + (1,) * (new.ndim - 1)), new, old)
        dw = w_t - w
        step = jnp.max(jnp.einsum("jm,jmn,jn->j", dw, hess, dw))
        return (keep(w_t, w), keep(t_t, t), keep(cost_t, cost), keep(grad_t, grad),
                keep(hess_t, hess), jnp.where(better, lm / 4.0, jnp.maximum(4.0 * lm, 0.25)),
                count + 1, step)

    def going(carry):
        count, step = carry[6], carry[7]
        return (count < iterations) & (step > tol)

    w0 = jnp.zeros((d, n), dtype)
    eye = jnp.broadcast_to(jnp.eye(n, dtype=dtype), (d, n, n))
    start = (w0, eye) + tuple(terms(w0, eye, eye)) + (
        jnp.zeros((d,), dtype), jnp.asarray(0, jnp.int32), jnp.asarray(jnp.inf, dtype))
    w, t, *_, count, _ = jax.lax.while_loop(going, iterate, start)
    return drift(_members(x_bar, anom, w, t)).astype(dtype), count


def nearest_sites(loc: Localization) -> np.ndarray:
    """``(m,)`` int32: the state site nearest each observation (distances wrap on a ring), by a
    search of the sorted site positions (no d x m array)."""
    state = np.asarray(loc.state, np.float64)
    order = np.argsort(state, kind="stable")
    pos, ids = state[order], order
    if loc.period is not None:
        pos = np.concatenate([pos - loc.period, pos, pos + loc.period])
        ids = np.concatenate([order, order, order])
    obs = np.asarray(loc.obs, np.float64)
    right = np.searchsorted(pos, obs)
    cand = np.clip(np.stack([right - 1, right], axis=1), 0, len(pos) - 1)
    pick = np.take_along_axis(cand, np.argmin(np.abs(pos[cand] - obs[:, None]), axis=1)[:, None],
                              axis=1)[:, 0]
    return ids[pick].astype(np.int32)


def _step(model: StateSpaceModel, static: IEnKSStatic, inflation, ensemble, y, key, time):
    index, weight = local_obs(static.localization, static.radius)
    post, count = smoother_analysis(ensemble, y, model, index, weight,
                                    nearest_sites(static.localization), inflation, static.adaptive,
                                    static.iterations, static.tol)
    return post, StepOutput(post.mean(0), post.std(0, ddof=1), post, {"iterations": count})


def _check(model: StateSpaceModel, static: IEnKSStatic) -> None:
    if model.process_noise is not None or model.process_std != 0:
        raise ValueError("ienks: needs a perfect model (process_std 0, no process_noise): the "
                         "smoother carries the members through the model's step; use "
                         "csf_jax.letkf or csf_jax.local_transform_filter for a noisy model")
    if is_additive(model) and model.obs_noise.covariance is not None:
        raise ValueError("ienks: needs uncorrelated observation noise (R-localisation divides by "
                         "each observation's variance)")
    check_standin("ienks")(model, static)


IENKS = Kernel("ienks", ensemble_state, _step, _check, label="IEnKS")


def ienks(obs, ensemble, *, model: StateSpaceModel, key, localization: Localization | None = None,
          config: IEnKSConfig = IEnKSConfig(), inputs=None, return_ensembles: bool = False,
          check_finite: bool = True, progress=None) -> FilterResult:
    """Run the local iterative ensemble Kalman smoother (lag 1) as a filter.

    Args:
      obs: (K, m) observations; NaN marks a missing entry.  ensemble: (N, d) at time 0.
      model: a perfect model (no process noise; static).  key: a ``jax.random.key`` (unused by a
        perfect model; kept for the common signature).
      localization: the positions of sites and observations (``ring_localization``).
      config: ``IEnKSConfig``; the inflation is traced, so a sweep over it compiles once.
      inputs: a time-varying model's per-step inputs (leading axis K), or None.
      return_ensembles: also return the (K, N, d) analysis ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every step.
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles | None, finite (K,))``, with
    ``info["iterations"] (K,)``, the Gauss-Newton iterations of each step.
    """
    return run(method(localization, config), obs, ensemble, model=model, key=key, inputs=inputs,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


def method(localization: Localization | None = None, config: IEnKSConfig = IEnKSConfig()) -> Method:
    """The local iterative smoother as a ``Method`` for ``csf_jax.run``.

    Args:
      localization: where the sites and observations sit (``csf_jax.ring_localization(d, sites)``).
      config: ``IEnKSConfig`` (the inflation traced, the rest static).
    """
    localization = require_localization(localization, "ienks")
    if not isinstance(config, IEnKSConfig):
        raise TypeError(f"ienks: config must be an IEnKSConfig, got {type(config).__name__}")
    static = IEnKSStatic(float(config.radius), localization, float(config.adaptive),
                         int(config.iterations), float(config.tol))
    return Method(IENKS._replace(bind=_bind), static, jnp.asarray(config.inflation))


def _bind(model, static: IEnKSStatic, params, state0):
    check_model(model, "ienks")
    check_localization(model, static.localization, "ienks")
    return model, static, params, state0
