"""The ensemble score filter (EnSF; Bao, Zhang & Zhang, CMAME 432, 117447, 2024): a training-free
score-based baseline.

Each step propagates the ensemble (the model's drift vmapped over members, plus process noise),
then draws the analysis ensemble with a reverse-time SDE in a pseudo-time ``t`` in [0, 1] whose
score is built from the forecast members and the likelihood, with no network and no training.

Forward (noising) process, EnSF's linear schedule::

    x_t | x_0 ~ N(alpha_t x_0, beta_t^2 I),
    alpha_t = 1 - (1 - eps_alpha) t,    beta_t^2 = eps_beta + (1 - eps_beta) t,

that is ``dx_t = f(t) x_t dt + g(t) dw`` with ``f = d log(alpha_t)/dt = -(1 - eps_alpha) /
alpha_t`` and ``g^2 = d(beta_t^2)/dt - 2 f beta_t^2``.

Prior score: the forecast members ``x^1 .. x^N`` as a Gaussian mixture, diffused to time t. For a
particle ``z`` and a mini-batch ``B`` of J members (all N by default)::

    s_prior(z, t) = sum_{j in B} w_j(z) (alpha_t x^j - z) / v_t,   v_t = alpha_t^2 kappa + beta_t^2,
    w_j(z) = exp(-|z - alpha_t x^j|^2 / (2 v_t)) / sum_{i in B} exp(-|z - alpha_t x^i|^2 / (2 v_t)),

the Monte-Carlo estimate of ``E[-(z - alpha_t x_0) / v_t | x_t = z]`` with self-normalised Gaussian
kernel weights (``kappa = ENSFConfig.kernel_var``, 0 by default). It costs O(N J d) per evaluation
for the N particles (the (N, J) weights and the (N, J, d) differences), never a (d, d) matrix. With
``J = 1`` particle i is tied to member i alone (``s = (alpha_t x^i - z) / v_t``), the form
EnSF's released Lorenz-96 scripts use.

Posterior score, with the likelihood gradient (``jax.grad`` of ``ssm.log_likelihood``: missing
(NaN) entries drop out) damped by ``h(t) = 1 - t`` (full weight at t = 0, none at t = 1) and the
sum clipped entrywise at ``score_max``::

    s(z, t) = clip(s_prior(z, t) + h(t) grad_z log p(y | z), -score_max, score_max).

Sampler: Euler-Maruyama on the reverse SDE over ``t_l = 1 - l / L``, ``l = 0 .. L-1``, step
``dt = 1 / L``, from ``z ~ N(0, I)`` standardised over the particles (mean 0, std 1 per
coordinate)::

    z <- z - dt (f(t_l) z - g^2(t_l) s(z, t_l)) + sqrt(dt) g(t_l) xi,   xi ~ N(0, I).

How it differs from CSF (``csf_jax.filter``): CSF's prior score is a network conditioned on the
ensemble (or the ensemble's Gaussian / mixture in closed form), and its likelihood enters through
Kalman guidance at Tweedie's estimate of the clean state, which is exact for a Gaussian prior and
a linear-Gaussian observation at any step count. EnSF has no network: the kernel mixture of the
forecast members is the prior, and the raw likelihood gradient at the noisy state, weighted by
the heuristic ``h(t)``, stands in for the diffused likelihood's score. Its analysis is therefore
not exact even in the linear-Gaussian case (it is close when the likelihood is broad against the
prior); its strength is the cost: O(L N J d) per step, linear in d.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from csf_jax import _checks, _random
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.result import FilterResult
from csf_jax.ssm import StateSpaceModel, log_likelihood, propagate


@dataclasses.dataclass(frozen=True)
class ENSFConfig:
    """EnSF's settings; the defaults are those of the authors' Lorenz-96 code (github
    zezhongzhang/EnSF), tuned there at d = 100, N = 20 (``fine_tune_EnSF``, best RMSE).

    Attributes:
      reverse_steps: Euler-Maruyama steps L of the reverse SDE per analysis. 200: the d = 100
        tuning runs (``Nt_SDE``; their d = 10^6 runs use 500, the paper's first script 100).
      eps_alpha: ``alpha_1``, the signal kept at t = 1 (``alpha_t = 1 - (1 - eps_alpha) t``). 0.5:
        their tuned ``eps_a`` (best of 0.001 .. 0.9 at d = 100; the paper's first script 0.05).
      eps_beta: ``beta_0^2``, the noise variance left at t = 0 (``beta_t^2 = eps_beta + (1 -
        eps_beta) t``): the kernel variance of the prior's mixture at t = 0. 0.025: their tuned
        ``eps_b`` (best of 0.001 .. 0.225 at d = 100).
      batch: members J in each particle's Monte-Carlo score (the paper's mini-batch); None: all N
        (the full estimator). Particle i uses members i, i+1, .., i+J-1 (mod N), fixed over the
        reverse steps. 1 reproduces the released scripts, which score particle i against member i.
      kernel_var: extra variance kappa of each mixture component at t = 0 (``v_t = alpha_t^2 kappa +
        beta_t^2``). 0.0: their ``gm_var_ratio`` in every run.
      inflation: multiplicative factor on the forecast anomalies before the analysis. 1.0: their
        ``inflation`` in every run.
      score_max: the posterior score is clipped entrywise to ``[-score_max, score_max]``. 1000: the
        ``score_max`` of their ``post_score``.
      clip: clip the forecast members to ``[-clip, clip]`` (a guard against diverging members), or
        None. None here; their Lorenz-96 scripts clip at 50 (``clip_tol``) after every RK4 step.

    The damping ``h(t) = 1 - t`` is fixed (their ``damp_fn`` in every run).
    """

    reverse_steps: int = 200
    eps_alpha: float = 0.5
    eps_beta: float = 0.025
    batch: int | None = None
    kernel_var: float = 0.0
    inflation: float = 1.0
    score_max: float = 1000.0
    clip: float | None = None

    def __post_init__(self):
        _checks.check_fields(self, positive=("reverse_steps", "inflation", "score_max", "clip",
                                             "batch"),
                             nonnegative=("kernel_var",))
        if not 0.0 < self.eps_alpha <= 1.0:
            raise ValueError(f"ENSFConfig.eps_alpha must lie in (0, 1], got {self.eps_alpha!r}")
        if not 0.0 < self.eps_beta < 1.0:
            raise ValueError(f"ENSFConfig.eps_beta must lie in (0, 1), got {self.eps_beta!r}")


class ENSFStatic(NamedTuple):
    """EnSF's static settings for the driver (they shape the computation)."""

    reverse_steps: int
    batch: int | None
    clip: float | None


class ENSFParams(NamedTuple):
    """EnSF's traced settings (scalars): a sweep over them compiles once."""

    eps_alpha: jax.Array
    eps_beta: jax.Array
    kernel_var: jax.Array
    inflation: jax.Array
    score_max: jax.Array


class Schedule(NamedTuple):
    """The forward process at one pseudo-time t: ``x_t | x_0 ~ N(alpha x_0, beta2 I)``, drift
    coefficient ``f = d log(alpha)/dt`` and squared diffusion ``g2 = d beta2/dt - 2 f beta2``."""

    alpha: jax.Array
    beta2: jax.Array
    f: jax.Array
    g2: jax.Array


def schedule(t, eps_alpha, eps_beta) -> Schedule:
    """EnSF's linear schedule at pseudo-time ``t`` (any shape; ``alpha_0 = 1``, ``alpha_1 =
    eps_alpha``, ``beta2_0 = eps_beta``, ``beta2_1 = 1``)."""
    alpha = 1.0 - (1.0 - eps_alpha) * t
    beta2 = eps_beta + (1.0 - eps_beta) * t
    f = -(1.0 - eps_alpha) / alpha
    return Schedule(alpha, beta2, f, (1.0 - eps_beta) - 2.0 * f * beta2)


def damping(t):
    """``h(t) = 1 - t``: the likelihood's weight in the posterior score."""
    return 1.0 - t


def mixture_score(z, members, alpha, var):
    """The score at ``z (d,)`` of the mixture ``(1/J) sum_j N(alpha members_j, var I)``,
    ``members (J, d)``: ``sum_j w_j (alpha x^j - z) / var`` with softmax weights ``w (J,)`` of
    ``-|z - alpha x^j|^2 / (2 var)``. Returns ``(d,)``."""
    diff = z - alpha * members                                   # (J, d)
    w = jax.nn.softmax(-0.5 * jnp.sum(diff * diff, axis=-1) / var)
    return -(w @ diff) / var


def member_batches(forecast, batch: int | None):
    """Each particle's members: ``forecast (N, d)`` shared by all (``batch`` None), else
    ``(N, J, d)`` with particle i's members i .. i+J-1 (mod N)."""
    if batch is None:
        return forecast
    n = forecast.shape[0]
    index = (jnp.arange(n)[:, None] + jnp.arange(batch)[None, :]) % n
    return forecast[index]


def prior_score(z, members, batch: int | None, alpha, var):
    """``s_prior`` of particles ``z (N, d)``: every particle against all ``members (N, d)``
    (``batch`` None), or each against its own ``members (N, J, d)``. Returns ``(N, d)``."""
    shared = None if batch is None else 0
    return jax.vmap(mixture_score, in_axes=(0, shared, None, None))(z, members, alpha, var)


def likelihood_gradient(model: StateSpaceModel, y, z):
    """``grad_x log p(y | x)`` at particles ``z (N, d)`` for ``y (m,)`` (NaN: missing); ``(N, d)``."""
    return jax.vmap(jax.grad(lambda x: log_likelihood(model, y, x)))(z)


def standard_start(key, shape, dtype):
    """``N(0, I)`` draws ``shape = (N, d)`` standardised per coordinate over the N rows (mean 0,
    std 1 with the N-1 denominator): EnSF's terminal sample."""
    z = _random.normal(key, shape, dtype)
    return (z - z.mean(0)) / z.std(0, ddof=1)


def ensf_analysis(key, forecast, y, model: StateSpaceModel, params: ENSFParams,
                  reverse_steps: int, batch: int | None = None):
    """EnSF's analysis of ``forecast (N, d)`` on ``y (m,)``: the reverse SDE of the module
    docstring from a standardised Gaussian start. Returns ``(N, d)``."""
    dtype = forecast.dtype
    k_start, k_noise = jax.random.split(key)
    members = member_batches(forecast, batch)
    eps_alpha, eps_beta = params.eps_alpha.astype(dtype), params.eps_beta.astype(dtype)
    kappa, smax = params.kernel_var.astype(dtype), params.score_max.astype(dtype)
    dt = jnp.asarray(1.0 / reverse_steps, dtype)
    times = 1.0 - jnp.arange(reverse_steps, dtype=dtype) * dt

    def step(z, xs):
        t, k = xs
        c = schedule(t, eps_alpha, eps_beta)
        score = prior_score(z, members, batch, c.alpha, c.alpha ** 2 * kappa + c.beta2)
        score = score + damping(t) * likelihood_gradient(model, y, z).astype(dtype)
        score = jnp.clip(score, -smax, smax)
        noise = _random.normal(k, z.shape, dtype)
        z = z - dt * (c.f * z - c.g2 * score) + jnp.sqrt(dt * c.g2) * noise
        return z, None

    z0 = standard_start(k_start, forecast.shape, dtype)
    z, _ = jax.lax.scan(step, z0, (times, jax.random.split(k_noise, reverse_steps)))
    return z


def _init(model, static, params, ensemble, key):
    return ensemble, key


def _step(model: StateSpaceModel, static: ENSFStatic, params: ENSFParams, ensemble, y, key,
          time):
    """Forecast (clip, inflate) and analyse ``ensemble (N, d)`` on ``y (m,)``."""
    k_prop, k_post = jax.random.split(key)
    forecast = propagate(model, k_prop, ensemble).astype(ensemble.dtype)
    if static.clip is not None:
        forecast = jnp.clip(forecast, -static.clip, static.clip)
    center = forecast.mean(0)
    forecast = center + params.inflation.astype(ensemble.dtype) * (forecast - center)
    post = ensf_analysis(k_post, forecast, y, model, params, static.reverse_steps, static.batch)
    return post, StepOutput(post.mean(0), post.std(0, ddof=1), post)


ENSF = Kernel("ensf", _init, _step, label="EnSF", discrete=True)


@_checks.renamed_keywords(problem="model")
def ensf(obs, ensemble, *, model: StateSpaceModel, key, config: ENSFConfig = ENSFConfig(),
         inputs=None, return_ensembles: bool = False, check_finite: bool = True,
         progress: Callable[[jax.Array], None] | None = None) -> FilterResult:
    """Run the ensemble score filter (EnSF).

    Args:
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype. NaN marks a missing entry (its likelihood term drops out); inf is an error.
      ensemble: (N, d) ensemble at time 0 (N >= 2; N >= ``config.batch``).
      model: the ``StateSpaceModel`` (static: hashable). Any observation model whose
        ``log_likelihood`` is differentiable in the state (additive noise or a ``Likelihood``).
      key: a ``jax.random.key`` (process noise and the reverse SDE); same key, same result.
      config: ``ENSFConfig`` (defaults: EnSF's). The float settings are traced, so a sweep over
        them compiles once; ``reverse_steps``, ``batch`` and ``clip`` are static.
      inputs: a time-varying model's per-step inputs (leading axis K), or None.
      return_ensembles: also return the (K, N, d) analysis ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every step (and a line on stderr around
        the first compilation).

    Returns:
      ``FilterResult(mean (K, d), std (K, d), ensembles (K, N, d) | None, finite (K,))``: mean and
      std (N-1 denominator) of the analysis ensemble. Works under ``jax.jit`` and ``jax.vmap``
      over ``(obs, ensemble, key)``; there mean and std are NaN and ``finite`` False from a
      non-finite step on (``mark_nonfinite``).
    """
    return run(method(config), obs, ensemble, model=model, key=key, inputs=inputs,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


def method(config: ENSFConfig = ENSFConfig()) -> Method:
    """EnSF as a ``Method`` for ``csf_jax.run``; ``config``: ``ENSFConfig`` (its float settings
    traced, ``reverse_steps``, ``batch`` and ``clip`` static)."""
    if not isinstance(config, ENSFConfig):
        raise TypeError(f"ensf: config must be an ENSFConfig, got {type(config).__name__}")
    params = ENSFParams(*(jnp.asarray(float(getattr(config, f)))
                          for f in ENSFParams._fields))
    static = ENSFStatic(int(config.reverse_steps), config.batch,
                        None if config.clip is None else float(config.clip))
    return Method(ENSF._replace(bind=_bind), static, params)


def _bind(model, static: ENSFStatic, params, ensemble):
    n = jnp.shape(ensemble)[0] if jnp.ndim(ensemble) == 2 else None
    if static.batch is not None and n is not None and static.batch > n:
        raise ValueError(f"ensf: ENSFConfig.batch ({static.batch}) exceeds the ensemble's "
                         f"N={n} members")
    return model, static, params, ensemble
