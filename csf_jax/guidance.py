"""Likelihood guidance for diffusion posterior sampling.

Two families:

* **Kalman guidance** (the default, with the ancestral sampler of ``csf_jax.filters.csf``): the
  posterior Tweedie estimate ``E[x_0 | x_t, y]`` under ``x_0 | x_t ~ N(x0_hat, P_t)``, found by a few
  Fisher-scoring (Gauss-Newton) steps on ``log N(u; x0_hat, P_t) + log p(y | u)``, with its
  covariance ``A^{-1}``, ``A = P_t^{-1} + J^T F J``. For a Gaussian prior and a linear Gaussian
  likelihood this is exact (the Kalman update of ``x_0`` given ``x_t`` and ``y``), and the step is
  bounded by construction: no clipping, whatever the likelihood's stiffness.
* **DPS** (Chung et al. 2023), the paper's form, with the Euler-Maruyama sampler:

DPS approximates ``grad_x log p(y | x_t)`` by ``grad_x log p(y | x0_hat(x_t))`` with Tweedie's
``x0_hat = x_t + sigma_t^2 s(x_t, t)``; the gradient flows through the score (``jax.vjp``).

The paper's raw form adds ``g^2 dt`` times this gradient to each Euler-Maruyama step. For stiff
likelihoods it is unstable: on the cubic sensor (``y = x^3 + w``, std 0.1) the step ``g^2 dt``
times the curvature ``9 x^4 / 0.01`` exceeds 2 as soon as |x| > 1, and particles overflow to NaN.
The default ``"clipped"`` caps each particle's guidance displacement per step at ``clip`` times the
step's diffusion noise scale ``g sqrt(dt) sqrt(d)``: the same direction, never a jump the noise
could not produce. ``"normalized"`` is Chung et al.'s per-particle normalisation
(``zeta grad / ||y - h(x0_hat)||``, written for any likelihood as ``grad l / sqrt(-2 l)``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from csf_jax import _checks, _linalg, _random

MODES = ("kalman", "raw", "clipped", "normalized", "none")
DPS_MODES = ("raw", "clipped", "normalized", "none")


@dataclasses.dataclass(frozen=True)
class GuidanceConfig:
    """How the likelihood gradient enters the reverse step.

    Attributes:
      mode: "kalman" (default: posterior Tweedie by Fisher scoring, ancestral sampler), or a DPS form
        with the Euler-Maruyama sampler: "clipped", "raw" (the paper's Alg. 2), "normalized" (Chung
        et al.), "none" (prior sampling only).
      scale: multiplies the likelihood gradient (zeta in DPS; ignored by "kalman").
      clip: for "clipped", the cap on a particle's guidance displacement per step, in units of the
        step's noise scale ``g(t) sqrt(dt) sqrt(d)``.
      iterations: for "kalman", Fisher-scoring steps per reverse step, warm-started from the previous
        reverse step's solution (so the sampler as a whole makes L x iterations of them). Default 1:
        against 2, the same RMSE on the double well and cubic10_indep, a better one on Cauchy, and
        less time, each iteration being a (d, d) Cholesky factorisation per particle (measured on
        docs/ablation.md).
      proposals: for "kalman", K draws per particle from the Laplace Gaussian ``N(u, A^{-1})``, of
        which one is kept by importance resampling against ``N(x0_hat, P) p(y | x_0)`` (the exact
        likelihood). The Laplace Gaussian sits at the mode; a skewed posterior (the cubic sensor)
        needs its mean: K = 1 keeps the Laplace draw itself, K = 8 (the default) corrects most of
        the bias (measured on docs/design.md, "The sampler").
      proposal_df: None (default): the K candidates are Laplace draws, Gaussian around the mode,
        unless the model's observation noise declares heavy tails (``ssm.tail_df``: Cauchy noise,
        1), whose degrees of freedom CSF then takes. A positive int: Student-t with these degrees
        of freedom per whitened coordinate, for heavy-tailed likelihoods, whose posteriors have
        tails the Gaussian never proposes: with it the resampled ensemble comes out too narrow
        (docs/ablation.md).
    """

    mode: str = "kalman"
    scale: float = 1.0
    clip: float = 1.0
    iterations: int = 1
    proposals: int = 8
    proposal_df: int | None = None

    def __post_init__(self):
        _checks.check_fields(self)
        if self.mode not in MODES:
            raise ValueError(f"GuidanceConfig.mode must be one of {MODES}, got {self.mode!r}")
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int) \
                or self.iterations < 1:
            raise ValueError(f"GuidanceConfig.iterations must be a positive int, got "
                             f"{self.iterations!r}")
        if isinstance(self.proposals, bool) or not isinstance(self.proposals, int) \
                or self.proposals < 1:
            raise ValueError(f"GuidanceConfig.proposals must be a positive int, got "
                             f"{self.proposals!r}")
        df = self.proposal_df
        if df is not None and (isinstance(df, bool) or not isinstance(df, int) or df < 1):
            raise ValueError(f"GuidanceConfig.proposal_df must be None or a positive int, got "
                             f"{df!r}")
        if not self.scale >= 0 or not self.clip > 0:
            raise ValueError(f"GuidanceConfig needs scale >= 0 and clip > 0, got {self.scale}, "
                             f"{self.clip}")


def dps_gradient(score_fn, loglik_fn, x, t_var):
    """Prior score and DPS likelihood gradient at ``x (N, d)``.

    score_fn: ``x (N, d) -> (N, d)`` prior score at the current time.
    loglik_fn: ``x0 (d,) -> scalar`` log-likelihood of the current observation.
    t_var: ``sigma_t^2``.
    Returns ``(score (N, d), grad (N, d), loglik (N,))``; grad is ``d/dx log p(y | x0_hat(x))``,
    one vjp through the score (particles are independent, so the vjp of the summed log-likelihood
    gives every particle's own gradient).
    """

    def x0_hat(x_):
        return x_ + t_var * score_fn(x_)

    x0, vjp = jax.vjp(x0_hat, x)
    loglik, g0 = jax.vmap(jax.value_and_grad(loglik_fn))(x0)
    (grad,) = vjp(g0)
    return (x0 - x) / t_var, grad, loglik


def guidance_displacement(config: GuidanceConfig, grad, loglik, g2dt, noise_scale):
    """The guidance part of one Euler-Maruyama step, per particle: ``(N, d)``.

    grad: (N, d) DPS gradient.  loglik: (N,) its log-likelihood.  g2dt: ``g(t)^2 dt``.
    noise_scale: ``g(t) sqrt(dt)``, the std of the step's noise per coordinate.
    """
    step = config.scale * g2dt * grad
    if config.mode == "none":
        return jnp.zeros_like(grad)
    if config.mode == "raw":
        return step
    if config.mode == "normalized":
        return step / jnp.sqrt(jnp.maximum(-2.0 * loglik, 1e-12))[:, None]
    cap = config.clip * noise_scale * jnp.sqrt(jnp.asarray(grad.shape[-1], grad.dtype))
    norm = jnp.linalg.norm(step, axis=-1, keepdims=True)
    return step * jnp.minimum(1.0, cap / jnp.maximum(norm, 1e-30))


@_linalg.precise
def kalman_tweedie(x0_hat, prior_precision, loglik_fn, observe_fn, weight_fn, u_init, guide,
                   iterations: int, damped: bool = False):
    """Posterior Tweedie estimate ``E[x_0 | x_t, y]`` and the Cholesky factor of its precision.

    Maximises ``-1/2 (u - x0_hat)^T P^{-1} (u - x0_hat) + log p(y | u)`` per particle by
    Gauss-Newton with curvature weights: ``u <- u + A^{-1} (P^{-1} (x0_hat - u) + grad log p(y | u))``
    with ``A = P^{-1} + J^T diag(W(u)) J``, ``J = dh/du``. ``W`` is the noise's Fisher information
    (Fisher scoring) or its reweighted least-squares weights (``ObservationNoise.curvature``: robust
    to Cauchy outliers). One step is exact for a linear ``h`` and Gaussian noise (the Kalman
    update); ``A^{-1}`` is the Laplace covariance of ``x_0 | x_t, y``.

    x0_hat: (N, d) prior Tweedie estimates.  prior_precision: (d, d) ``P^{-1}``, shared, or
    (N, d, d), one per particle.
    loglik_fn: ``u (d,) -> scalar``.  observe_fn: ``u (d,) -> (m,)``.  weight_fn: ``u (d,) -> (m,)``
    per-coordinate weights, or ``(m, m)`` (a correlated noise's precision).
    u_init: (N, d) starting points (the previous reverse step's solution).  guide: scalar 0 or 1
    (0: no observation, ``u = x0_hat``, ``A = P^{-1}``).
    damped: take the best of the step fractions ``DAMPING`` by the objective instead of the full
      step (a line search: every iteration ascends, also far from the mode of a strongly
      nonlinear sensor); the factor returned is then the one at the final ``u``.
    Returns ``(u (N, d), chol (N, d, d))``, ``chol`` lower-triangular with ``chol chol^T = A`` at the
    last linearisation point.
    """
    def system(x0h, u, precision):
        # where the likelihood over- or underflows (an exp of a far-off state) it gives no
        # direction: the prior term alone moves u there
        jac = jax.jacfwd(observe_fn)(u)
        weight = weight_fn(u)
        grad = jax.grad(loglik_fn)(u)
        chol = _linalg.cholesky(precision + guide * weighted_gram(
            jac, jnp.where(jnp.isfinite(weight), weight, 0.0)))
        return chol, precision @ (x0h - u) + guide * jnp.where(jnp.isfinite(grad), grad, 0.0)

    def update(u, x0h, precision):
        chol, rhs = system(x0h, u, precision)
        step = _linalg.cho_solve(chol, rhs)
        if not damped:
            return u + step, chol
        fractions = jnp.asarray(DAMPING, u.dtype)
        tries = u + fractions[:, None] * step
        values = (-0.5 * quadratic_along(precision, u - x0h, step, fractions)
                  + guide * jax.vmap(loglik_fn)(tries))
        return tries[jnp.argmax(jnp.where(jnp.isnan(values), -jnp.inf, values))], chol

    def one(x0h, u, precision):
        if damped:
            # a loop, not unrolled: the evidence's fits take up to 12 steps (compile time)
            u = jax.lax.fori_loop(0, iterations, lambda _, u: update(u, x0h, precision)[0], u)
            chol, _ = system(x0h, u, precision)
            return u, chol
        for _ in range(iterations):
            u, chol = update(u, x0h, precision)
        return u, chol

    if prior_precision.ndim == 2:
        return particle_map(lambda xs: one(*xs, prior_precision), (x0_hat, u_init))
    return particle_map(lambda xs: one(*xs), (x0_hat, u_init, prior_precision))


PARTICLE_BLOCK = 200


def particle_map(fn, xs):
    """``fn`` over the leading (particle) axis of the pytree ``xs``, ``PARTICLE_BLOCK``
    particles at a time (``lax.map`` of a ``vmap``): the per-particle (d, d) Gauss-Newton
    systems of a block stay in the CPU's caches through a step's factorisations and solves,
    where one ``vmap`` over all N streams every particle's matrices through memory at each of
    them (docs/benchmark.md, "Where CSF's step spends its time"). The results are the
    per-particle ones, up to rounding. On an accelerator, one vmap: there the blocks would run
    one after another."""
    n = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if jax.default_backend() != "cpu" or n <= PARTICLE_BLOCK:
        return jax.vmap(fn)(xs)
    return jax.lax.map(fn, xs, batch_size=PARTICLE_BLOCK)


DAMPING = tuple(0.5 ** k for k in range(13)) + (0.0,)


def quadratic_along(matrix, point, direction, fractions):
    """``(p + a v)^T M (p + a v)`` at each of ``fractions (S,)`` (``a``), for a symmetric
    ``matrix (d, d)`` (M; None: the identity), ``point (d,)`` (p) and ``direction (d,)`` (v):
    a line search's quadratic term as ``p^T M p + 2 a v^T M p + a^2 v^T M v``, two
    matrix-vector products in place of one per fraction (S = 14 to 20 of them, most of the
    search's arithmetic)."""
    mp = point if matrix is None else matrix @ point
    mv = direction if matrix is None else matrix @ direction
    return point @ mp + fractions * (2.0 * (direction @ mp) + fractions * (direction @ mv))


def weighted_gram(jac, weight):
    """``J^T W J`` for ``jac (m, d)`` and weights ``(m,)`` (diagonal W) or ``(m, m)``."""
    if weight.ndim == 1:
        return (jac.T * weight) @ jac
    return jac.T @ weight @ jac


def student_t(key, df: int, shape, dtype):
    """Student-t draws with integer ``df`` as ``g_0 / sqrt(mean(g_1^2 .. g_df^2))`` of standard
    normals: exact, and without ``jax.random.t``'s rejection-sampled gamma (a while loop per
    element, slow inside the sampler's scans); a port draws the same from the same normals."""
    g = _random.normal(key, (df + 1, *shape), dtype)
    return g[0] / jnp.sqrt(jnp.mean(g[1:] * g[1:], 0))


@_linalg.precise
def importance_weights(key, mean, precision, u, chol, loglik_fn, guide, proposals: int,
                       df: int | None = None, normalized: bool = False):
    """K candidates per row from the Laplace Gaussian ``N(u, A^{-1})`` (or its Student-t
    version), and their log importance weights against ``N(c; mean, P) p(y | c)^guide``.

    mean, u: (N, d).  precision: (d, d) ``P^{-1}`` shared, or (N, d, d) one per row.
    chol: (N, d, d) with ``chol chol^T = A``.  Returns ``(cand (K, N, d), log_w (K, N))``.
    normalized: include each row's normalising constants (``1/2 log det P^{-1}`` and
    ``log det chol``), so that ``logmeanexp_k log_w`` estimates the row's evidence
    ``int N(c; mean, P) p(y | c)^guide dc`` up to a constant shared by all rows; without them the
    weights serve to pick among a row's own candidates only.
    """
    n, d = u.shape
    k_draw, _ = jax.random.split(key)
    if df is None:
        z = _random.normal(k_draw, (proposals, n, d), u.dtype)
        log_q = -0.5 * jnp.sum(z * z, -1)
    else:
        z = student_t(k_draw, df, (proposals, n, d), u.dtype)
        log_q = -0.5 * (df + 1.0) * jnp.sum(jnp.log1p(z * z / df), -1)
    def row(zn, un, cn, mn, pn):  # one row's K candidates: (K, d), (K,), (K,)
        cand = un + _linalg.solve_lower_transposed(cn, zn)
        diff = cand - mn
        return cand, jnp.einsum("kd,de,ke->k", diff, pn, diff), jax.vmap(loglik_fn)(cand)

    rows = (jnp.swapaxes(z, 0, 1), u, chol, jnp.broadcast_to(mean, u.shape))
    if precision.ndim == 2:
        cand, quad, loglik = particle_map(lambda xs: row(*xs, precision), rows)
    else:
        cand, quad, loglik = particle_map(lambda xs: row(*xs), rows + (precision,))
    cand, quad, loglik = jnp.swapaxes(cand, 0, 1), quad.T, loglik.T
    log_w = -0.5 * quad + guide * loglik - log_q
    if normalized:  # log N(c; mean, P) and log N(c; u, A^{-1}) in full
        log_w = (log_w + 0.5 * _log_det(precision)
                 - jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), -1))
    return cand, log_w


def _log_det(precision):
    """``log det`` of a symmetric positive-definite ``(..., d, d)`` matrix."""
    chol = _linalg.cholesky(precision)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), -1)


@_linalg.precise
def resample_posterior(key, x0_hat, prior_precision, u, chol, loglik_fn, guide, proposals: int,
                       df: int | None = None):
    """One draw per particle of ``N(x_0; x0_hat, P) p(y | x_0)`` by importance resampling.

    K candidates ``u + chol^{-T} z`` from the Laplace Gaussian ``N(u, A^{-1})``; weights
    ``N(c; x0_hat, P) p(y | c)^guide / N(c; u, A^{-1})`` (``importance_weights``); one kept per
    particle. Consistent as K grows; K = 1 returns the Laplace draw. df: if given, each whitened
    coordinate ``z_j`` is an independent Student-t with ``df`` degrees of freedom instead of
    N(0, 1): a heavy-tailed proposal that reaches the tails of a heavy-tailed posterior (Cauchy
    noise), which the Laplace Gaussian never proposes.
    x0_hat, u: (N, d).  prior_precision: (d, d), or (N, d, d).  chol: (N, d, d).  Returns (N, d).
    """
    if proposals == 1:
        cand, _ = importance_weights(key, x0_hat, prior_precision, u, chol, lambda c: 0.0, 0.0, 1,
                                     df)
        return cand[0]
    cand, log_w = importance_weights(key, x0_hat, prior_precision, u, chol, loglik_fn, guide,
                                     proposals, df)
    _, k_pick = jax.random.split(key)
    pick = jax.random.categorical(k_pick, log_w, axis=0)
    return jnp.take_along_axis(cand, pick[None, :, None], axis=0)[0]
