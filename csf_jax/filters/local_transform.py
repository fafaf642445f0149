"""The local CSF in transform form: the LETKF's ensemble space, with a score-based transport.

Each site i is analysed on its own, as in the LETKF (``csf_jax.letkf``): its state is written
``x = x_bar + Z^T w`` with ``Z = (forecast - x_bar) / sqrt(N - 1)`` ``(N, d)``, so the forecast
ensemble's Gaussian is ``w ~ N(0, I_N)``, and the observations in reach enter with their inverse
variances tapered by the Gaspari-Cohn weight of their distance (R-localisation). The local
posterior over ``w`` is sampled by the probability-flow transport of the VE SDE over the noise
levels ``sigma_0 > ... > sigma_L = 0``:

* **Top.** The posterior's mode ``w*`` by ``top_iterations`` Gauss-Newton steps (the iterative
  ensemble Kalman filter's analysis), and the sensor's Jacobian there, ``J (W, N)``, with
  ``P = (I + J^T R~^{-1} J)^{-1}`` from one eigendecomposition. Each member's coordinates
  ``sqrt(N - 1) e_n`` are carried up the prior's flow and across to the diffused posterior:
  ``w_n = mu + (P + sigma_0^2)^{1/2} sqrt(N - 1) e_n``.
* **Each level** ``sigma_l -> sigma_{l+1}``: every member's own Tweedie estimate
  ``u_n = E[w_0 | w_sigma = w_n, y]``, the minimiser of
  ``|u|^2 / 2 + |u - w_n|^2 / (2 sigma^2) - log p(y | u)`` by ``iterations`` Gauss-Newton steps
  (the likelihood's gradient at the member's own point, ``J``'s curvature), then the centre
  ``mu_n = P J^T R~^{-1} (y - h(u_n) + J u_n)`` of the Gaussian linearised there, and the exact
  flow of that Gaussian: ``w_n <- mu_n + (P + sigma_{l+1}^2)^{1/2} (P + sigma_l^2)^{-1/2}
  (w_n - mu_n)``.

With a linear sensor every ``mu_n`` is the same ``mu`` and the maps telescope to
``mu + P^{1/2} sqrt(N - 1) e_n``: the LETKF's analysis with its symmetric square root, whatever
the levels and iterations (tested to float64 round-off). With a nonlinear sensor the mode replaces
the LETKF's single linearisation at the forecast mean, and each member is moved by the sensor's
residual at its own point on the way down, so the ensemble keeps the posterior's skew.

The sensor must be a point sensor (observation j reads one site ``s_j``, as the local CSF needs);
the window's sensor values ``h_j(x_bar_{s_j} + Z_{s_j} . w)`` for all sites at once come from
``model.observe`` on a few full-length states, each observation's copies spread over ``slot``
states (``WindowSensor``). A step costs ``O(d N^2 W)`` per Gauss-Newton iteration and one
``N x N`` eigendecomposition per site: linear in d.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.filters.driver import Method, StepOutput, run
from csf_jax.filters.letkf import (
    Localization,
    check_localization,
    ensemble_state,
    inflated_forecast,
    local_obs,
)
from csf_jax.filters.result import FilterResult
from csf_jax.sde import marginal_std_host, noise_levels
from csf_jax.ssm import StateSpaceModel, check_model, is_additive, observed


@dataclasses.dataclass(frozen=True)
class LocalTransformConfig:
    """Settings of the transform-form local CSF.

    radius: Gaspari-Cohn half-width of the R-localisation, in sites (support ``2 radius``; 1.82x
      DAPPER's ``loc_rad``), as ``LETKFConfig.radius``.
    inflation: multiplicative factor on the forecast anomalies, as ``LETKFConfig.inflation``.
    top_iterations: Gauss-Newton steps to the local posterior's mode (1 is the LETKF's analysis
      linearised at the forecast mean; a saturating sensor such as arctan needs several).
    iterations: Gauss-Newton steps of each member's Tweedie estimate per level, warm-started from
      the level above.
    reverse_steps: L, the noise levels of the transport below the top, geometric from
      ``sigma_t(1)`` to ``sigma_t(t_min)`` (then 0), in units of the forecast's spread.
    t_min, sigma_max: the VE SDE's lowest time and scale (paper: sigma_max 25).
    """

    radius: float = 4.0
    inflation: float = 1.05
    top_iterations: int = 5
    iterations: int = 1
    reverse_steps: int = 10
    t_min: float = 1e-3
    sigma_max: float = 25.0

    def __post_init__(self):
        _checks.check_fields(self, positive=("radius", "inflation"))
        for name in ("top_iterations", "iterations", "reverse_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"LocalTransformConfig.{name} must be an int >= 1, got {value!r}")
        if not 0.0 < self.t_min < 1.0 or not self.sigma_max > 1.0:
            raise ValueError(f"LocalTransformConfig needs 0 < t_min < 1 and sigma_max > 1, got "
                             f"{self.t_min}, {self.sigma_max}")


class WindowSensor(NamedTuple):
    """Where each site's window of observations reads, and how to evaluate them all at once.

    index: (d, W) the observations in reach of each site (``local_obs``).  site: (d, W) the state
    site each of them reads.  gather: (P, d) for each of P evaluation states, the flat window
    entry ``i W + k`` whose value sits at each state site (-1: none).  out: (d, W) the flat
    position ``p m + j`` of each window entry's value in the P stacked observation vectors.
    """

    index: np.ndarray
    site: np.ndarray
    gather: np.ndarray
    out: np.ndarray


def _rank_within(groups: np.ndarray) -> np.ndarray:
    """For each entry of the 1-D int array ``groups``, how many earlier entries share its value."""
    order = np.argsort(groups, kind="stable")
    ranked = groups[order]
    rank = np.empty_like(order)
    rank[order] = np.arange(len(groups)) - np.searchsorted(ranked, ranked, side="left")
    return rank


@functools.lru_cache(maxsize=16)
def window_sensor(loc: Localization, radius: float) -> tuple[WindowSensor, np.ndarray]:
    """The ``WindowSensor`` of a point-sensor ring localization, and the taper ``(d, W)``.

    Window entry ``(i, k)`` holds observation ``j = index[i, k]``, which reads site ``s_j``. The
    entries are spread over P full-length states so that no state holds two values at one site:
    entry ``(i, k)`` goes to state ``p`` = its rank among the entries of sites read by the same
    site's observations. ``model.observe`` of state p then gives, at observation j, ``h_j`` of
    the value placed at ``s_j`` (a point sensor reads nothing else)."""
    index, weight = local_obs(loc, radius)
    sites = np.asarray(loc.obs, np.float64).astype(np.int64)
    d, width = index.shape
    site = sites[index]                                       # (d, W)
    flat_site = site.reshape(-1)
    slot = _rank_within(flat_site)                            # (d W,)
    states = int(slot.max()) + 1
    gather = np.full((states, d), -1, np.int64)
    gather[slot, flat_site] = np.arange(d * width)
    m = len(sites)
    out = slot * m + index.reshape(-1)
    table = WindowSensor(index.astype(np.int32), site.astype(np.int32),
                         gather.astype(np.int32), out.reshape(d, width).astype(np.int32))
    return table, weight


def window_observe(model: StateSpaceModel, table: WindowSensor, values):
    """The sensor at window values ``(B, d, W)``: ``h (B, d, W)`` with entry ``(b, i, k)`` equal to
    ``h_j`` of ``values[b, i, k]`` for ``j = index[i, k]``, and its derivative ``h' (B, d, W)``."""
    b, d, width = values.shape
    flat = values.reshape(b, d * width)
    has = jnp.asarray(table.gather >= 0)
    states = jnp.where(has, jnp.take(flat, jnp.asarray(np.maximum(table.gather, 0)), axis=1),
                       0.0)                                   # (B, P, d)
    obs_fn = jax.vmap(jax.vmap(model.observe))
    h, dh = jax.jvp(obs_fn, (states,), (jnp.ones_like(states),))   # (B, P, m)
    pick = jnp.asarray(table.out)
    return (jnp.take(h.reshape(b, -1), pick, axis=1).astype(values.dtype),
            jnp.take(dh.reshape(b, -1), pick, axis=1).astype(values.dtype))


def _levels(config: LocalTransformConfig):
    """``(L + 1,)`` float64 noise levels: geometric from ``sigma_t(1)`` to ``sigma_t(t_min)``,
    then 0."""
    return np.asarray(noise_levels(config.reverse_steps, marginal_std_host(1.0, config.sigma_max),
                                   marginal_std_host(config.t_min, config.sigma_max)), np.float64)


def transform_analysis(forecast, y, model: StateSpaceModel, table: WindowSensor, taper,
                       config: LocalTransformConfig):
    """The transform-form analysis of ``forecast (N, d)`` on ``y (m,)`` (module docstring);
    ``taper (d, W)``. Returns the posterior ensemble ``(N, d)``."""
    n, d = forecast.shape
    dtype = forecast.dtype
    mean = forecast.mean(0)
    z = (forecast - mean) / jnp.sqrt(jnp.asarray(n - 1, dtype))          # (N, d)
    site = jnp.asarray(table.site)
    zs = jnp.transpose(z[:, site], (1, 2, 0))                             # (d, W, N)
    xs = mean[site]                                                       # (d, W)
    mask = observed(y)
    prec = jnp.where(mask, jnp.asarray(1.0 / model.obs_noise.gaussian_std ** 2, dtype), 0.0)
    index = jnp.asarray(table.index)
    rho = jnp.asarray(taper, dtype) * prec[index]                         # (d, W)
    yw = jnp.where(mask, y, 0.0)[index]                                   # (d, W)
    eye = jnp.eye(n, dtype=dtype)

    def sensor(w):
        """``h, h'`` at the window values of coordinates ``w (B, d, N)``; each ``(B, d, W)``."""
        return window_observe(model, table, xs + jnp.einsum("dwk,bdk->bdw", zs, w))

    def cost(u_b, h_b):
        """The local posterior's negative log-density (up to a constant) ``(B, d)``."""
        return 0.5 * jnp.sum(u_b ** 2, -1) + 0.5 * jnp.sum(rho * (yw - h_b) ** 2, -1)

    def mode_step(carry, _):
        """Levenberg-Marquardt: a Gauss-Newton step damped by ``lm diag(H)``; kept where it
        lowers the site's cost, else the damping grows fourfold (a linear sensor's first step
        is exact and final)."""
        u, h, dh, c, lm = carry
        jac = dh[..., None] * zs                                          # (d, W, N)
        hess = eye + jnp.einsum("dwk,dw,dwl->dkl", jac, rho, jac)
        grad = u - jnp.einsum("dwk,dw->dk", jac, rho * (yw - h))
        damped = hess + (lm[:, None, None] * eye) * jnp.diagonal(hess, axis1=1, axis2=2)[:, None]
        trial = u - jnp.linalg.solve(damped, grad[..., None])[..., 0]
        h_t, dh_t = sensor(trial[None])
        c_t = cost(trial[None], h_t)[0]
        better = (c_t < c)[:, None]
        return (jnp.where(better, trial, u), jnp.where(better, h_t[0], h),
                jnp.where(better, dh_t[0], dh), jnp.where(better[:, 0], c_t, c),
                jnp.where(better[:, 0], lm / 4.0, jnp.maximum(4.0 * lm, 0.25))), None

    u = jnp.zeros((d, n), dtype)
    h, dh = sensor(u[None])
    init = (u, h[0], dh[0], cost(u[None], h)[0], jnp.zeros((d,), dtype))
    (u, _, dh, _, _), _ = jax.lax.scan(mode_step, init, None, length=config.top_iterations)
    jac = dh[..., None] * zs
    lam, vec = jnp.linalg.eigh(jnp.einsum("dwk,dw,dwl->dkl", jac, rho, jac))
    lam = jnp.maximum(lam, 0.0)
    p_eig = 1.0 / (1.0 + lam)                                             # P's eigenvalues (d, N)

    def in_basis(scale, v):
        """``V diag(scale) V^T v`` per site; ``scale (d, N)``, ``v (B, d, N)``."""
        return jnp.einsum("dkl,dl,bdl->bdk", vec, scale, jnp.einsum("dkl,bdk->bdl", vec, v))

    levels = jnp.asarray(_levels(config), dtype)
    mu = u[None]                                                          # (1, d, N)
    top = jnp.sqrt(jnp.asarray(n - 1, dtype)) * jnp.sqrt(p_eig + levels[0] ** 2)
    w = mu + jnp.einsum("dkl,dl,dnl->ndk", vec, top, vec)                 # (N, d, N) members
    uw = jnp.broadcast_to(u, w.shape)

    def level(carry, sig):
        w, uw = carry
        sigma, sigma_next = sig
        inv_s2 = 1.0 / sigma ** 2
        h_b, dh_b = sensor(uw)
        c_b = cost(uw, h_b) + 0.5 * inv_s2 * jnp.sum((uw - w) ** 2, -1)
        for _ in range(config.iterations):
            grad = (uw * (1.0 + inv_s2) - w * inv_s2
                    - jnp.einsum("dwk,bdw->bdk", zs, dh_b * rho * (yw - h_b)))
            trial = uw - in_basis(1.0 / (1.0 + inv_s2 + lam), grad)
            h_t, dh_t = sensor(trial)
            c_t = cost(trial, h_t) + 0.5 * inv_s2 * jnp.sum((trial - w) ** 2, -1)
            better = (c_t < c_b)[..., None]
            uw, h_b, dh_b = (jnp.where(better, trial, uw), jnp.where(better, h_t, h_b),
                             jnp.where(better, dh_t, dh_b))
            c_b = jnp.minimum(c_t, c_b)
        mu_b = uw + in_basis(p_eig, uw - w) * inv_s2
        ratio = jnp.sqrt((p_eig + sigma_next ** 2) / (p_eig + sigma ** 2))
        return (mu_b + in_basis(ratio, w - mu_b), uw), None

    (w, _), _ = jax.lax.scan(level, (w, uw), (levels[:-1], levels[1:]))
    return mean + jnp.einsum("nik,ki->ni", w, z)


class TransformStatic(NamedTuple):
    """The static settings for the driver: the config and the geometry."""

    config: LocalTransformConfig
    localization: Localization


def _step(model: StateSpaceModel, static: TransformStatic, inflation, ensemble, y, key, time):
    """Forecast, inflate and analyse every site of ``ensemble (N, d)`` on ``y (m,)``."""
    table, taper = window_sensor(static.localization, float(static.config.radius))
    forecast = inflated_forecast(model, key, ensemble, inflation)
    post = transform_analysis(forecast, y, model, table, taper, static.config)
    return post, StepOutput(post.mean(0), post.std(0, ddof=1), post)


def _check(model: StateSpaceModel, static: TransformStatic) -> None:
    if not is_additive(model) or model.time_varying:
        raise ValueError("local_transform_filter: needs a time-invariant point sensor with "
                         "additive noise (not a Likelihood, not time_varying)")
    if model.obs_noise.covariance is not None:
        raise ValueError("local_transform_filter: needs uncorrelated observation noise "
                         "(R-localisation divides by each observation's variance)")


LOCAL_TRANSFORM = Method("local_transform_filter", ensemble_state, _step, _check,
                         label="local CSF (transform)")


def local_transform_filter(obs, ensemble, *, problem: StateSpaceModel, key,
                           localization: Localization,
                           config: LocalTransformConfig = LocalTransformConfig(),
                           return_ensembles: bool = False, check_finite: bool = True,
                           progress=None) -> FilterResult:
    """Filter ``obs`` with the transform-form local CSF (module docstring).

    Args:
      obs: (K, m) observations; NaN marks a missing entry.  ensemble: (N, d) at time 0.
      problem: the model (static); its sensor must be a point sensor at ``localization.obs``,
        with independent noise (a non-Gaussian noise enters through its Gaussian stand-in
        ``gaussian_std``, as in the LETKF).
      key: a ``jax.random.key`` (process noise only: the analysis is deterministic).
      localization: ``csf_jax.ring_localization(d, obs_sites)``.
      config: ``LocalTransformConfig``; its inflation is traced (a sweep compiles once).
      return_ensembles: also return the (K, N, d) ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every step.
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles | None, finite (K,))``; jit-able
    (bind the keywords statically) and vmap-able over ``(obs, ensemble, key)``.
    """
    check_model(problem, "local_transform_filter")
    static = TransformStatic(dataclasses.replace(config, inflation=1.0), localization)
    _check(problem, static)
    check_localization(problem, localization, "local_transform_filter", points=True)
    return run(LOCAL_TRANSFORM, obs, ensemble, model=problem, key=key, config=static,
               params=jnp.asarray(config.inflation), return_ensembles=return_ensembles,
               check_finite=check_finite, progress=progress)
