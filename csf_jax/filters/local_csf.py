"""The local Conditional Score-based Filter: CSF whose cost is linear in d (Lorenz-96 at d = 10^4).

Each filter step, inside one jitted ``lax.scan`` over the K observations:

    propagate -> inflate the anomalies -> local statistics (``csf_jax.local_prior``: a sparse
      Gaussian prior precision Lambda from local regressions) -> the reverse sampler over L noise
      levels -> posterior ensemble; mean and std out.

Both samplers use the VE SDE's Tweedie estimates with every d x d matrix replaced by a sparse
operator. At noise level sigma, with the sensor linearised at ``u`` (Jacobian J, noise Fisher
weights W; for a point sensor ``J^T W J`` is a diagonal ``kappa``):

    A = Lambda + I / sigma^2 + diag(kappa)                 the precision of x_0 | x_sigma, y
    E[x_0 | x_sigma, y] = A^{-1} (Lambda m + x / sigma^2 + grad log p(y | u) + kappa u)

(one Gauss-Newton step; without y it is the prior's Tweedie ``E[x_0 | x_sigma]``), solved by a
few conjugate-gradient iterations preconditioned by the inverse of A's diagonal blocks.

* ``"flow"`` (default): deterministic. Every prior member goes up the levels along the prior's
  probability-flow ODE ``dx/dsigma = (x - E[x_0 | x]) / sigma`` (Heun steps), is shifted at the
  top by ``E[x_0 | x, y] - E[x_0 | x]`` (the diffused posterior's mean minus the diffused prior's),
  and comes down along the posterior's. For a Gaussian prior and a linear sensor this is the
  square-root transform ``m_a + P_a^{1/2} C^{-1/2} (x - m)``: each posterior member stays tied to its
  prior member, as in deterministic ensemble square-root filters. On chaotic Lorenz-96 with 40
  members this matters: fresh posterior draws lose the ensemble's alignment with the growing
  directions every step (docs/lorenz96_csf.md).
* ``"ancestral"``: the global sampler's (``csf_jax.filters.csf.ancestral_sample``): from the prior
  noised to ``sigma_t(1)``, at each level an exact draw ``x_0 = A^{-1} (r + xi)``, ``xi ~ N(0, A)``
  (``xi = (I - B)^T D^{-1/2} e_1 + e_2 / sigma + sqrt(kappa) e_3``, perturb-then-optimise), then the
  exact VE bridge. Exact for a Gaussian prior and a linear sensor whatever L; stochastic.

A level costs ``O(N d b)`` per CG iteration. Sensors must be point sensors: observation j is
``g_j(x_{s_j}) + noise`` for a site ``s_j`` (identity, every k-th site, arctan); the localisation's
observation positions give ``s_j``, and ``local_filter`` checks the model against them.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from csf_jax import _checks, _linalg, _random
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.letkf import Localization, check_localization, require_localization
from csf_jax.filters.result import FilterResult
from csf_jax.local_prior import (
    LocalStats,
    local_statistics,
    precision_blocks,
    precision_matvec,
    precision_noise,
)
from csf_jax.sde import bridge, marginal_std_host, noise_levels
from csf_jax.ssm import (
    StateSpaceModel,
    check_model,
    is_additive,
    log_likelihood,
    observed,
    process_draws,
    residual,
)

SAMPLERS = ("flow", "ancestral")


@dataclasses.dataclass(frozen=True)
class LocalCSFConfig:
    """Settings of the local CSF; defaults are the best Lorenz-96 values of docs/lorenz96_csf.md.

    Attributes:
      half_width: b, the regressions' reach (sites within ring distance b).
      ridge, floor: regularisation of the local regressions (``csf_jax.local_prior.local_statistics``).
      inflation: multiplicative factor on the propagated ensemble's anomalies (as the LETKF's).
      reverse_steps: L noise levels, geometric from ``sigma_t(1)`` (9.85) to ``sigma_t(t_min)``.
      t_min: the lowest level's time. The flow sampler starts each prior member at that level as if
        it were already diffused, which is accurate only where ``sigma_t(t_min)^2`` is small against
        the prior's smallest conditional variances: 1e-6 (sigma 1e-3) on Lorenz-96, where 1e-3
        (sigma 0.03) left the members measurably off the exact transform.
      sigma_max: the VE SDE's scale (paper: 25).
      cg_iterations: conjugate-gradient iterations per solve, block-preconditioned.
      block: sites per preconditioner block (``d`` must be a multiple of ``2 block``, and
        ``block > 2 half_width``).
      top_iterations: Gauss-Newton steps of the posterior Tweedie estimate at the top level (the flow
        sampler's shift from the diffused prior to the diffused posterior; a nonlinear sensor needs
        several, the other levels warm-start from their neighbour and take one).
      sampler: "flow" (default: deterministic, each posterior member tied to its prior member) or
        "ancestral" (stochastic: fresh draws of the posterior; docs/lorenz96_csf.md measures it).
    """

    half_width: int = 8
    ridge: float = 1e-2
    floor: float = 1e-3
    inflation: float = 1.02
    reverse_steps: int = 20
    t_min: float = 1e-6
    sigma_max: float = 25.0
    cg_iterations: int = 8
    block: int = 20
    top_iterations: int = 5
    sampler: str = "flow"

    def __post_init__(self):
        _checks.check_fields(self)
        for name in ("half_width", "cg_iterations", "block", "top_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"LocalCSFConfig.{name} must be an int >= 1, got {value!r}")
        if self.reverse_steps < 2:
            raise ValueError(f"LocalCSFConfig.reverse_steps must be >= 2, got {self.reverse_steps}")
        if not 0.0 < self.t_min < 1.0 or not self.sigma_max > 1.0:
            raise ValueError(f"LocalCSFConfig needs 0 < t_min < 1 and sigma_max > 1, got "
                             f"{self.t_min}, {self.sigma_max}")
        if self.block <= 2 * self.half_width:
            raise ValueError(f"LocalCSFConfig.block ({self.block}) must exceed 2 half_width "
                             f"({2 * self.half_width}): the precision couples sites 2b apart")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"LocalCSFConfig.sampler must be one of {SAMPLERS}, got "
                             f"{self.sampler!r}")
        if not self.inflation > 0 or not 0 < self.floor < 1 or not self.ridge >= 0:
            raise ValueError(f"LocalCSFConfig needs inflation > 0, 0 < floor < 1, ridge >= 0, got "
                             f"{self.inflation}, {self.floor}, {self.ridge}")


def site_curvature(model: StateSpaceModel, y, u, sites):
    """``(d,)``: the sensor's curvature at every site for one state ``u (d,)``: the observation
    noise's weights (``ObservationNoise.curvature``) times the squared derivative of each point
    sensor, summed onto its site."""
    _, slope = jax.jvp(model.observe, (u,), (jnp.ones_like(u),))
    weight = model.obs_noise.curvature(residual(model, y, u), observed(y)).astype(u.dtype)
    return jnp.zeros_like(u).at[sites].add(weight * slope * slope)


def conjugate_gradient(matvec, rhs, x0, precond, iterations: int):
    """``iterations`` steps of preconditioned CG on ``matvec(x) = rhs``, batched over rows of
    ``rhs (N, d)`` (each row its own system); ``precond(r)`` applies the preconditioner's inverse."""

    def dot(a, b):
        return jnp.sum(a * b, -1, keepdims=True)

    r = rhs - matvec(x0)
    z = precond(r)
    p = z
    rz = dot(r, z)

    def body(carry, _):
        x, r, p, rz = carry
        ap = matvec(p)
        pap = dot(p, ap)
        alpha = rz / jnp.where(pap > 0, pap, 1.0)
        x = x + alpha * p
        r = r - alpha * ap
        z = precond(r)
        rz_new = dot(r, z)
        p = z + rz_new / jnp.where(rz > 0, rz, 1.0) * p
        return (x, r, p, rz_new), None

    (x, _, _, _), _ = jax.lax.scan(body, (x0, r, p, rz), None, length=iterations)
    return x


def _levels(config: LocalCSFConfig, dtype):
    """The geometric noise levels ``(L + 1,)`` from ``sigma_t(1)`` down to ``sigma_t(t_min)``, then 0."""
    return jnp.asarray(noise_levels(config.reverse_steps, marginal_std_host(1.0, config.sigma_max),
                                    marginal_std_host(config.t_min, config.sigma_max)), dtype)


class _Operators(NamedTuple):
    """What every level needs: ``Lambda m (d,)``, the diagonal blocks of ``Lambda``
    ``(d / block, block, block)`` (the CG preconditioner), the likelihood's gradient and per-site
    curvature as functions of ``u (N, d)``."""

    lam_m: jax.Array
    lam_blocks: jax.Array
    grad: Callable
    curvature: Callable


def _operators(model: StateSpaceModel, y, stats: LocalStats, sites, block: int) -> _Operators:
    grad_fn = jax.vmap(jax.grad(functools.partial(log_likelihood, model, y)))
    return _Operators(precision_matvec(stats, stats.mean), precision_blocks(stats, block), grad_fn,
                      jax.vmap(lambda u: site_curvature(model, y, u, sites)))


def _solve(stats: LocalStats, ops: _Operators, rhs, x_init, inv_s2, kappa, config):
    """``(Lambda + I / sigma^2 + diag kappa)^{-1} rhs`` by CG from ``x_init``, preconditioned by the
    inverse of the system's diagonal blocks (one Cholesky per block, and per particle unless
    ``kappa`` is None: the prior's system, shared by all particles); ``(N, d)``."""
    n, d = rhs.shape
    nb, w = ops.lam_blocks.shape[:2]
    eye = jnp.eye(w, dtype=rhs.dtype)
    if kappa is None:
        chol = _linalg.cholesky(ops.lam_blocks + inv_s2 * eye)
        shift = inv_s2
    else:
        diag = (inv_s2 + kappa).reshape(n, nb, w)
        chol = _linalg.cholesky(ops.lam_blocks + diag[..., None] * eye)
        shift = inv_s2 + kappa

    def matvec(v):
        return precision_matvec(stats, v) + shift * v

    def precond(r):
        return _linalg.cho_solve(chol, r.reshape(n, nb, w)).reshape(n, d)

    return conjugate_gradient(matvec, rhs, x_init, precond, config.cg_iterations)


def posterior_tweedie(stats: LocalStats, ops: _Operators, x, u, sigma, config, guide: bool = True,
                      iterations: int = 1):
    """``E[x_0 | x_sigma, y]`` under the GMRF prior and the sensor linearised at ``u`` (relinearised
    ``iterations`` times: Gauss-Newton); ``(N, d)``. ``guide=False`` gives the prior's Tweedie
    ``E[x_0 | x_sigma]`` (exact in one solve)."""
    inv_s2 = 1.0 / sigma ** 2
    if not guide:
        return _solve(stats, ops, ops.lam_m + x * inv_s2, u, inv_s2, None, config)
    for _ in range(iterations):
        kappa = ops.curvature(u)
        rhs = ops.lam_m + x * inv_s2 + ops.grad(u) + kappa * u
        u = _solve(stats, ops, rhs, u, inv_s2, kappa, config)
    return u


def ancestral_sample(model: StateSpaceModel, y, prior_ens, stats: LocalStats, key,
                     config: LocalCSFConfig, sites):
    """The stochastic sampler: from ``prior_ens + sigma_1 eps`` down the L levels, drawing
    ``x_0 ~ N(u, A^{-1})`` at each and bridging; ``(N, d)``."""
    dtype = prior_ens.dtype
    levels = _levels(config, dtype)
    k_init, k_steps = jax.random.split(key)
    x = prior_ens + levels[0] * _random.normal(k_init, prior_ens.shape, dtype)
    ops = _operators(model, y, stats, sites, config.block)

    def step(carry, inputs):
        x, u = carry
        sigma, sigma_next, l_idx = inputs
        inv_s2 = 1.0 / sigma ** 2
        kappa = ops.curvature(u)
        rhs = ops.lam_m + x * inv_s2 + ops.grad(u) + kappa * u
        k1, k2, k3, k_bridge = jax.random.split(jax.random.fold_in(k_steps, l_idx), 4)
        xi = (precision_noise(stats, k1, x.shape, dtype)
              + _random.normal(k2, x.shape, dtype) / sigma
              + jnp.sqrt(kappa) * _random.normal(k3, x.shape, dtype))
        x0 = _solve(stats, ops, rhs + xi, u, inv_s2, kappa, config)
        rho, var = bridge(sigma, sigma_next)
        x = rho * x + (1.0 - rho) * x0 + jnp.sqrt(var) * _random.normal(k_bridge, x.shape, dtype)
        return (x, x0), None

    inputs = (levels[:-1], levels[1:], jnp.arange(config.reverse_steps))
    (x, _), _ = jax.lax.scan(step, (x, prior_ens), inputs)
    return x


def _heun(tweedie, x, guess, sigma, sigma_next):
    """One Heun step of the probability-flow ODE ``dx/dsigma = (x - E[x_0 | x]) / sigma`` from
    ``sigma`` to ``sigma_next > 0``; ``tweedie(x, guess, sigma) -> E[x_0 | x]``. Returns the new
    state and the last Tweedie estimate (the next solve's warm start)."""
    x0 = tweedie(x, guess, sigma)
    slope = (x - x0) / sigma
    trial = x + (sigma_next - sigma) * slope
    x0_trial = tweedie(trial, x0, sigma_next)
    return x + 0.5 * (sigma_next - sigma) * (slope + (trial - x0_trial) / sigma_next), x0_trial


def flow_sample(model: StateSpaceModel, y, prior_ens, stats: LocalStats, config: LocalCSFConfig,
                sites):
    """The deterministic sampler: every prior member is carried up the L levels by the prior's
    probability-flow ODE and back down by the posterior's (Heun steps; the prior's Tweedie
    ``E[x_0 | x_sigma]`` replaced by ``E[x_0 | x_sigma, y]``). At the top level the diffused prior and
    posterior differ by a shift of their means, ``E[x_0 | x, y] - E[x_0 | x]`` (up to
    ``O(C / sigma^2)``), applied between the two passes. For a Gaussian prior and a linear sensor
    the exact flows compose to the square-root transform ``m_a + P_a^{1/2} C^{-1/2} (x - m)``: each
    posterior member stays tied to its prior member, as in a deterministic ensemble square-root
    filter. ``(N, d)``."""
    levels = _levels(config, prior_ens.dtype)[:-1][::-1]            # (L,), rising
    ops = _operators(model, y, stats, sites, config.block)

    def prior_tweedie(x, guess, sigma):
        return posterior_tweedie(stats, ops, x, guess, sigma, config, guide=False)

    def post_tweedie(x, guess, sigma):
        return posterior_tweedie(stats, ops, x, guess, sigma, config)

    def up(carry, inputs):
        x, x0 = carry
        return _heun(prior_tweedie, x, x0, *inputs), None

    (x, x0), _ = jax.lax.scan(up, (prior_ens, prior_ens), (levels[:-1], levels[1:]))
    top = levels[-1]
    x0 = prior_tweedie(x, x0, top)
    u = posterior_tweedie(stats, ops, x, x0, top, config, iterations=config.top_iterations)
    x = x + (u - x0)

    def down(carry, inputs):
        x, u = carry
        return _heun(post_tweedie, x, u, *inputs), None

    rev = levels[::-1]
    (x, u), _ = jax.lax.scan(down, (x, u), (rev[:-1], rev[1:]))
    return post_tweedie(x, u, rev[-1])


def _init(model, config: LocalCSFConfig, sites, ensemble, key):
    return ensemble, key


def _step(model: StateSpaceModel, config: LocalCSFConfig, sites, ensemble, y, key, time):
    """Propagate, inflate, estimate the local prior and sample the posterior; ``sites (m,)``."""
    k_prop, k_rev = jax.random.split(key)
    prior_ens = jax.vmap(model.drift)(ensemble) + process_draws(model, k_prop, ensemble.shape,
                                                                ensemble.dtype)
    centre = prior_ens.mean(0)
    prior_ens = centre + config.inflation * (prior_ens - centre)
    stats = local_statistics(prior_ens, config.half_width, config.ridge, config.floor)
    if config.sampler == "flow":
        post = flow_sample(model, y, prior_ens, stats, config, sites)
    else:
        post = ancestral_sample(model, y, prior_ens, stats, k_rev, config, sites)
    return post, StepOutput(post.mean(0), post.std(0), post)


def _check(model: StateSpaceModel, config: LocalCSFConfig) -> None:
    if not is_additive(model) or model.time_varying:
        raise ValueError("local_filter: needs a time-invariant point sensor with additive noise "
                         "(not a Likelihood, not time_varying)")
    if model.obs_noise.covariance is not None:
        raise ValueError("local_filter: needs uncorrelated observation noise")
    if 2 * config.half_width + 1 > model.dim:
        raise ValueError(f"local_filter: the neighbourhood of 2 x LocalCSFConfig.half_width + 1 = "
                         f"{2 * config.half_width + 1} sites is wider than the ring (d={model.dim}); "
                         f"use half_width <= {(model.dim - 1) // 2}")
    if model.dim % (2 * config.block):
        raise ValueError(f"local_filter: d={model.dim} must be a multiple of 2 x block "
                         f"(LocalCSFConfig.block={config.block}): the preconditioner's blocks "
                         f"alternate in two colours around the ring")


LOCAL_CSF = Kernel("local_filter", _init, _step, _check, label="local CSF",
                   discrete=True)


@_checks.renamed_keywords(problem="model")
def local_filter(obs, ensemble, *, model: StateSpaceModel, key,
                 localization: Localization, config: LocalCSFConfig = LocalCSFConfig(),
                 return_ensembles: bool = False, check_finite: bool = True,
                 progress: Callable[[jax.Array], None] | None = None) -> FilterResult:
    """Filter ``obs`` with the local CSF.

    Args:
      obs: (K, m) observations; NaN marks a missing entry.  ensemble: (N, d) at time 0.
      model: the model (static); its sensor must be a point sensor at ``localization.obs``.
      key: a ``jax.random.key``; same key, same result.
      localization: ``csf_jax.ring_localization(d, obs_sites)``.
      config: ``LocalCSFConfig``.  return_ensembles: also return the (K, N, d) ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every filter step (and a line on
        stderr around the first compilation).
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles | None, finite (K,))``; jit-able
    (bind the keywords statically) and vmap-able over ``(obs, ensemble, key)``.
    """
    return run(method(localization, config), obs, ensemble, model=model, key=key,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


class LocalStatic(NamedTuple):
    """The local CSF's static settings before the model is known."""

    config: LocalCSFConfig
    localization: Localization


def method(localization: Localization | None = None,
           config: LocalCSFConfig = LocalCSFConfig()) -> Method:
    """The local CSF as a ``Method`` for ``csf_jax.run``.

    Args:
      localization: ``csf_jax.ring_localization(d, obs_sites)``.
      config: ``LocalCSFConfig``.
    """
    localization = require_localization(localization, "local_filter")
    if not isinstance(config, LocalCSFConfig):
        raise TypeError(f"local_filter: config must be a LocalCSFConfig, got "
                        f"{type(config).__name__}")
    return Method(LOCAL_CSF._replace(bind=_bind), LocalStatic(config, localization))


def _bind(model, static: LocalStatic, params, state0):
    check_model(model, "local_filter")
    _check(model, static.config)
    sites = check_localization(model, static.localization, "local_filter", points=True)
    return model, static.config, jnp.asarray(sites), state0
