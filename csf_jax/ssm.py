"""The state-space model: ``x_k = f(x_{k-1}) + v_k + shock_k``, ``y_k ~ p(y | h(x_k))``, k = 1..K.

A model is a ``StateSpaceModel``: a NamedTuple of pure single-particle callables and constants.
Filters vmap the callables over particles and close over the model as a static (hashable) argument,
so every field must be hashable: Python callables, numbers, strings, tuples. Matrices live inside
the callables' closures. ``shock`` acts on the truth only (filters never see it).

The observation is additive, ``y = h(x) + w`` with an ``ObservationNoise`` w, or any density
``p(y | eta)`` of ``eta = h(x)`` with conditionally independent entries (a ``Likelihood``:
Poisson counts, stochastic volatility, ...). A time-varying model (``time_varying=True``) has
``f(x, step)`` and ``h(x, step)``, where ``step`` is a ``Step``: the time index k and the user's
per-step input ``u_k`` (``inputs=`` of the filters and of ``simulate``). ``at_step`` binds a step,
so filter code calls ``f(x)`` and ``h(x)`` either way.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from csf_jax import _checks, _linalg, _random
from csf_jax.parametric import as_float

Array = jax.Array


def observed(y: Array) -> Array:
    """``(m,)`` bool: the entries of ``y (m,)`` that were observed (NaN marks a missing entry)."""
    return ~jnp.isnan(y)


def _masked_cov(cov: Array, mask: Array) -> Array:
    """``cov (m, m)`` with every row and column of a missing entry replaced by the identity's:
    block diagonal in (observed, missing), so solves with it act on the observed block alone."""
    both = mask[:, None] & mask[None, :]
    return jnp.where(both, cov, jnp.eye(cov.shape[-1], dtype=cov.dtype))


class ObservationNoise(NamedTuple):
    """An additive observation noise ``w``: i.i.d. per coordinate, or any user density.

    Attributes:
      log_prob: residual ``(m,)`` -> scalar log-density (up to a constant).
      sample: ``(key, shape)`` -> a draw of that shape (``shape[-1] = m``).
      gaussian_std: std of the Gaussian that the EnKF uses in its place (the noise's own std if
        Gaussian; for Cauchy the Gaussian with the same central 68% interval). Ignored where
        ``covariance`` is given.
      fisher: the Fisher information of one coordinate's noise, ``E[(d log p(w) / dw)^2]``.
        None: ``1 / gaussian_std^2``. The curvature of CSF's Kalman guidance when ``weight`` is None.
      weight: optional ``residual (m,) -> (m,)``, the iteratively reweighted least-squares weights
        ``-(d log p / dw) / w`` of a symmetric noise whose log-density decreases in ``|w|``: the
        curvature of the Gaussian that touches ``log p`` from below at the residual. For Cauchy
        ``2 / (scale^2 + w^2)``: an outlier gets a small weight, so the guidance does not chase it
        (with the Fisher information it would). None: the constant ``fisher_information``.
      covariance: optional ``(m, m)`` covariance as a nested tuple (hashable): correlated noise. The
        EnKF, the Kalman filter and CSF's Kalman guidance use it (its inverse is the guidance's
        curvature); None: ``gaussian_std^2 I``.
      marginal: optional ``(residual (m,), observed (m,) bool) -> scalar``, the log-density of the
        observed entries alone (the others are marginalised out; their residuals are 0). Needed for
        missing observations (NaN in ``obs``). The constructors here give it; a user noise without it
        filters complete observations only.
      tail_df: optional degrees of freedom of the noise's tails (Cauchy: 1): CSF's importance
        proposals are then Student-t with these degrees of freedom (``GuidanceConfig.proposal_df``
        left at None), so that they reach the heavy-tailed posterior's tails.
      log_norm: optional ``observed (m,) bool -> scalar``, the log normalising constant that
        ``log_prob`` leaves out, over the observed entries: ``log_prob + log_norm`` is the
        normalised log-density (``normalized_log_likelihood``). The filters' log evidence
        (``FilterResult.log_evidence``) needs it where it uses this density (the particle
        filter, CSF); without it those filters report no evidence. The constructors here give it.
    """

    name: str
    log_prob: Callable[[Array], Array]
    sample: Callable[[Array, tuple], Array]
    gaussian_std: float
    fisher: float | None = None
    weight: Callable[[Array], Array] | None = None
    covariance: tuple | None = None
    marginal: Callable[[Array, Array], Array] | None = None
    tail_df: int | None = None
    log_norm: Callable[[Array], Array] | None = None

    @property
    def fisher_information(self) -> float:
        """The per-coordinate Fisher information (``fisher``, or ``1 / gaussian_std^2``)."""
        return float(self.fisher) if self.fisher is not None else 1.0 / self.gaussian_std ** 2

    def cov(self, m: int, dtype=jnp.float32) -> Array:
        """The ``(m, m)`` covariance the Gaussian filters use: ``covariance``, or
        ``gaussian_std^2 I``."""
        if self.covariance is not None:
            return jnp.asarray(self.covariance, dtype)
        # squared in Python, then cast: the same R, bit for bit, as the tables' cached EnKF runs
        return jnp.asarray(self.gaussian_std ** 2, dtype) * jnp.eye(m, dtype=dtype)

    def gaussian_draws(self, key: Array, shape: tuple, dtype=jnp.float32) -> Array:
        """Draws ``shape = (..., m)`` of ``N(0, cov)``: the EnKF's observation perturbations."""
        z = _random.normal(key, shape, dtype)
        if self.covariance is None:
            return self.gaussian_std * z
        return z @ _linalg.cholesky(self.cov(shape[-1], dtype)).T

    def masked_log_prob(self, residual: Array, mask: Array) -> Array:
        """``log p`` of the observed entries of ``residual (m,)`` (``mask (m,)`` bool; missing
        residuals must be 0). Without ``marginal``: ``log_prob`` when every entry is observed,
        NaN otherwise (the filter then reports the step as non-finite)."""
        if self.marginal is not None:
            return self.marginal(residual, mask)
        return jnp.where(jnp.all(mask), self.log_prob(residual), jnp.nan)

    def curvature(self, residual: Array, mask: Array | None = None) -> Array:
        """The curvature of the guidance at ``residual = y - h(x)``: per-coordinate weights
        ``(m,)``, or the ``(m, m)`` precision of a noise with ``covariance``; 0 on missing entries
        (``mask (m,)`` bool, default all observed)."""
        m = residual.shape[-1]
        mask = jnp.ones((m,), bool) if mask is None else mask
        if self.covariance is not None and self.weight is None:
            chol = _linalg.cholesky(_masked_cov(self.cov(m, residual.dtype), mask))
            precision = _linalg.cho_solve(chol, jnp.eye(m, dtype=residual.dtype))
            return jnp.where(mask[:, None] & mask[None, :], precision, 0.0)
        if self.weight is not None:
            w = self.weight(residual)
        else:
            w = jnp.full(residual.shape, self.fisher_information, residual.dtype)
        return jnp.where(mask, w, 0.0)


def _iid_noise(name: str, coord_log_prob: Callable[[Array], Array], sample, gaussian_std: float,
               **extra) -> ObservationNoise:
    """An i.i.d. noise from its one-coordinate log-density (elementwise ``(m,) -> (m,)``): the
    joint is the sum, the marginal of the observed entries the sum over them."""

    def log_prob(r):
        return jnp.sum(coord_log_prob(r))

    def marginal(r, mask):
        return jnp.sum(jnp.where(mask, coord_log_prob(r), 0.0))

    return ObservationNoise(name, log_prob, sample, as_float(gaussian_std), marginal=marginal,
                            **extra)


def gaussian_noise(std: float) -> ObservationNoise:
    """i.i.d. ``N(0, std^2)`` noise. ``std`` may be traced (a ``ParametricModel``'s number)."""
    inv_var = 1.0 / std**2

    def sample(key, shape):
        return std * _random.normal(key, shape)

    log = jnp.log if isinstance(std, jax.core.Tracer) else math.log
    const = -0.5 * log(2.0 * math.pi * std ** 2)
    return _iid_noise("gaussian", lambda r: -0.5 * inv_var * r * r, sample, std,
                      log_norm=lambda mask: const * jnp.sum(mask))


def covariance_tuple(cov, name: str, size: int | None = None) -> tuple:
    """A symmetric positive-definite matrix as a nested tuple of floats (hashable); clear errors."""
    arr = np.array(cov, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1] or (size is not None and arr.shape[0] != size):
        want = "square" if size is None else f"({size}, {size})"
        raise ValueError(f"{name}: the covariance must be a {want} matrix, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: the covariance has non-finite entries")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-12 * max(1.0, np.abs(arr).max())):
        raise ValueError(f"{name}: the covariance must be symmetric")
    if np.linalg.eigvalsh(arr).min() <= 0:
        raise ValueError(f"{name}: the covariance must be positive definite (smallest eigenvalue "
                         f"{np.linalg.eigvalsh(arr).min():.3g})")
    return tuple(map(tuple, arr.tolist()))


def gaussian_noise_cov(cov) -> ObservationNoise:
    """Correlated Gaussian noise ``N(0, cov)``, ``cov: (m, m)`` symmetric positive definite.

    Missing entries are marginalised exactly: the observed block of ``cov`` alone enters.
    """
    cov_t = covariance_tuple(cov, "gaussian_noise_cov")
    cov_np = np.array(cov_t)
    chol_np = np.linalg.cholesky(cov_np)
    prec_np = np.linalg.inv(cov_np)

    def log_prob(r):
        return -0.5 * r @ jnp.asarray(prec_np, r.dtype) @ r

    def marginal(r, mask):
        r = jnp.where(mask, r, 0.0)
        chol = _linalg.cholesky(_masked_cov(jnp.asarray(cov_np, r.dtype), mask))
        return -0.5 * r @ _linalg.cho_solve(chol, r)

    def sample(key, shape):
        z = _random.normal(key, shape)
        return z @ jnp.asarray(chol_np, z.dtype).T

    def log_norm(mask):
        chol = _linalg.cholesky(_masked_cov(jnp.asarray(cov_np), mask))
        log_det = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))   # the observed block's alone
        return -0.5 * (log_det + math.log(2.0 * math.pi) * jnp.sum(mask))

    std = float(np.sqrt(np.mean(np.diag(cov_np))))
    return ObservationNoise("gaussian_cov", log_prob, sample, std, covariance=cov_t,
                            marginal=marginal, log_norm=log_norm)


def cauchy_noise(scale: float) -> ObservationNoise:
    """i.i.d. ``Cauchy(0, scale)`` noise; log-density is the sum of independent Cauchy terms.

    Its Gaussian stand-in (``gaussian_std``) is the Gaussian with the same central 68% interval:
    ``scale = 0.0544`` gives std 0.1 (see ``cauchy_matched_std``).
    """

    def sample(key, shape):
        return scale * jax.random.cauchy(key, shape)

    def weight(r):
        return 2.0 / (scale ** 2 + r * r)

    return _iid_noise("cauchy", lambda r: -jnp.log1p((r / scale) ** 2), sample,
                      cauchy_matched_std(scale), fisher=1.0 / (2.0 * scale ** 2), weight=weight,
                      tail_df=1, log_norm=lambda mask: -math.log(math.pi * scale) * jnp.sum(mask))


class Likelihood(NamedTuple):
    """A non-additive observation density ``p(y | eta)``, ``eta = h(x) (m,)``, entries of y
    conditionally independent given eta (Poisson counts, stochastic volatility, binary data).

    Attributes:
      log_prob: ``(y (m,), eta (m,)) -> (m,)``, the log-density of each entry (up to constants in y).
      sample: ``(key, eta (m,)) -> y (m,)``, one draw (for ``simulate``).
      fisher: optional ``eta (m,) -> (m,)``, the Fisher information of each ``eta_j``: the curvature
        of CSF's Gauss-Newton guidance (``J^T diag(fisher) J``, ``J = dh/dx``). None: the observed
        information ``-d^2 log_prob / d eta^2``, clipped at 0.
      mean, variance: optional ``eta (m,) -> (m,)``, ``E[y | eta]`` and ``Var[y | eta]``: the Gaussian
        stand-in of the Kalman-type filters (EnKF, LETKF). Without them those filters refuse the model.
      log_norm: optional ``observed (m,) bool -> scalar``, the log normalising constant that
        ``log_prob`` leaves out (one that does not depend on y or eta), over the observed
        entries; as ``ObservationNoise.log_norm``. Poisson: 0 (its ``log_prob`` is normalised).
      discrete: y takes discrete values (counts): the filters then take integer ``obs`` too,
        cast to their float dtype (NaN, for a missing count, needs float ``obs``).
      support: optional elementwise ``y -> bool`` (any shape, numpy or jax arrays), True where y
        is a possible value: a concrete filter call refuses an observation outside it (a negative
        count), naming its step and entry, rather than filtering a density that is not one.
      support_text: what the support is, in words, for that message ("non-negative integer
        counts").
    """

    name: str
    log_prob: Callable[[Array, Array], Array]
    sample: Callable[[Array, Array], Array]
    fisher: Callable[[Array], Array] | None = None
    mean: Callable[[Array], Array] | None = None
    variance: Callable[[Array], Array] | None = None
    log_norm: Callable[[Array], Array] | None = None
    discrete: bool = False
    support: Callable[[Array], Array] | None = None
    support_text: str = ""


def counts(y):
    """Elementwise: ``y`` a non-negative integer (a Poisson count); numpy or jax arrays."""
    return (y >= 0) & (y == y // 1)


def poisson_likelihood() -> Likelihood:
    """Counts ``y_j ~ Poisson(exp(eta_j))``: ``eta = h(x)`` is the log-rate. Fisher information
    ``exp(eta)``; Gaussian stand-in mean = variance = ``exp(eta)``."""

    def log_prob(y, eta):
        return y * eta - jnp.exp(eta) - gammaln(y + 1.0)

    def sample(key, eta):
        return jax.random.poisson(key, jnp.exp(eta)).astype(eta.dtype)

    return Likelihood("poisson", log_prob, sample, fisher=jnp.exp, mean=jnp.exp, variance=jnp.exp,
                      log_norm=lambda mask: jnp.zeros((), jnp.float32), discrete=True,
                      support=counts, support_text="non-negative integer counts")


def volatility_likelihood() -> Likelihood:
    """``y_j ~ N(0, exp(eta_j))``, i.e. ``y = exp(eta / 2) eps``: the stochastic-volatility
    observation, with ``eta = h(x)`` the log-variance. Fisher information 1/2; Gaussian stand-in
    mean 0, variance ``exp(eta)`` (an EnKF learns nothing from it: y and eta are uncorrelated)."""

    def log_prob(y, eta):
        return -0.5 * (eta + y * y * jnp.exp(-eta))

    def sample(key, eta):
        return jnp.exp(0.5 * eta) * _random.normal(key, eta.shape, eta.dtype)

    const = -0.5 * math.log(2.0 * math.pi)
    return Likelihood("volatility", log_prob, sample, fisher=lambda eta: jnp.full_like(eta, 0.5),
                      mean=jnp.zeros_like, variance=jnp.exp,
                      log_norm=lambda mask: const * jnp.sum(mask))


class ProcessNoise(NamedTuple):
    """An additive process noise ``v`` other than the default i.i.d. ``N(0, process_std^2)``.

    Attributes:
      sample: ``(key, shape (..., d)) -> draws of that shape``.
      covariance: ``(d, d)`` as a nested tuple (hashable), or None if unknown: the Kalman filter needs
        it; the ensemble filters only sample.
      log_prob: optional ``v (d,) -> scalar`` log-density (up to a constant), for users' own methods.
    """

    name: str
    sample: Callable[[Array, tuple], Array]
    covariance: tuple | None = None
    log_prob: Callable[[Array], Array] | None = None


def gaussian_process_noise(cov) -> ProcessNoise:
    """Correlated Gaussian process noise ``N(0, cov)``, ``cov: (d, d)`` symmetric positive definite."""
    cov_t = covariance_tuple(cov, "gaussian_process_noise")
    cov_np = np.array(cov_t)
    chol_np = np.linalg.cholesky(cov_np)
    prec_np = np.linalg.inv(cov_np)

    def sample(key, shape):
        z = _random.normal(key, shape)
        return z @ jnp.asarray(chol_np, z.dtype).T

    def log_prob(v):
        return -0.5 * v @ jnp.asarray(prec_np, v.dtype) @ v

    return ProcessNoise("gaussian_cov", sample, cov_t, log_prob)


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


class Step(NamedTuple):
    """What a time-varying model's ``drift`` and ``observe`` are told at step k.

    Attributes:
      k: int32 scalar, the index of the state being made and observed: ``x_k = f(x_{k-1}, step)``,
        ``y_k`` from ``h(x_k, step)``; k = 1 .. K (``obs[k - 1]``).
      u: the user's input for step k (``inputs`` sliced at ``k - 1``, any pytree), or None.
    """

    k: Array
    u: object = None


@_checks.static_pytree
class StateSpaceModel(NamedTuple):
    """A discrete-time state-space model with additive process noise.

    Attributes:
      name: identifier.
      dim: state dimension d.  obs_dim: observation dimension m.
      num_steps: default trajectory length K (observations ``y_1 .. y_K``).
      dt: the time step the dynamics were discretised with (informational).
      drift: ``x (d,) -> (d,)``, the deterministic map f (it includes ``x_k`` itself); with
        ``time_varying``, ``(x, step: Step) -> (d,)``.
      observe: ``x (d,) -> (m,)``, the observation map h; with ``time_varying``, ``(x, step)``.
      process_std: std of the i.i.d. Gaussian process noise v (per coordinate); ignored where
        ``process_noise`` is given.
      obs_noise: the observation's law given ``h(x)``: an additive ``ObservationNoise`` w
        (``y = h(x) + w``), or a ``Likelihood`` ``p(y | eta = h(x))`` for non-additive data.
      initial_truth: ``key -> (d,)``, draws ``x_0`` of the truth.
      initial_ensemble: ``(key, N) -> (N, d)``, the filters' initial ensemble.
      shock_times: ``(key, K) -> (K,)`` bool, the steps at which the truth is shocked.
      shock: ``(key, x (d,)) -> (d,)``, the truth right after a shock (applied after the dynamics).
      process_noise: optional ``ProcessNoise`` (a full covariance, or any sampler); None: i.i.d.
        ``N(0, process_std^2)``.
      time_varying: drift and observe take the ``Step`` as a second argument (the time index and
        the per-step input).

    A pytree with no leaves (the model itself is its static data), so a function of it goes
    through ``jax.jit`` and ``jax.vmap`` as it is written: ``jax.jit(csf_jax.filter)(None, obs,
    ensemble, model=model, key=key)``; a new model compiles anew.
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
    process_noise: ProcessNoise | None = None
    time_varying: bool = False


def at_step(model: StateSpaceModel, step: Step | None) -> StateSpaceModel:
    """``model`` with ``step`` bound into a time-varying drift and observation map, so that they
    take ``x`` alone; the model itself when it is not time-varying. For use inside a trace: the
    result holds traced values and is not a static argument."""
    if not model.time_varying:
        return model
    if step is None:
        raise ValueError(f"model {model.name!r} is time-varying: its drift and observe need the "
                         f"step (csf_jax.Step(k, u))")
    return model._replace(drift=lambda x: model.drift(x, step),
                          observe=lambda x: model.observe(x, step), time_varying=False)


def steps(num_steps: int, inputs=None) -> Step:
    """The ``Step`` of every time index, stacked: ``k = 1 .. K`` (int32) and ``u = inputs``."""
    return Step(jnp.arange(1, num_steps + 1, dtype=jnp.int32), inputs)


def is_additive(model: StateSpaceModel) -> bool:
    """True if the observation is ``y = h(x) + w`` with an ``ObservationNoise`` w."""
    return isinstance(model.obs_noise, ObservationNoise)


def tail_df(model: StateSpaceModel) -> int | None:
    """The degrees of freedom of the observation noise's heavy tails, or None (light tails)."""
    return model.obs_noise.tail_df if is_additive(model) else None


def process_draws(model: StateSpaceModel, key: Array, shape: tuple, dtype=jnp.float32) -> Array:
    """Draws of the process noise v, ``shape = (..., d)``, in ``dtype``."""
    if model.process_noise is None:
        return model.process_std * _random.normal(key, shape, dtype)
    return model.process_noise.sample(key, shape).astype(dtype)


def process_cov(model: StateSpaceModel, dtype=jnp.float32) -> Array:
    """The ``(d, d)`` process-noise covariance (ValueError if a user sampler did not give one)."""
    if model.process_noise is None:
        return jnp.asarray(model.process_std, dtype) ** 2 * jnp.eye(model.dim, dtype=dtype)
    if model.process_noise.covariance is None:
        raise ValueError(f"model {model.name!r}: its process noise {model.process_noise.name!r} "
                         f"has no covariance; give ProcessNoise(covariance=...)")
    return jnp.asarray(model.process_noise.covariance, dtype)


def is_isotropic(model: StateSpaceModel) -> bool:
    """True if the process noise is the default i.i.d. ``N(0, process_std^2)``."""
    return model.process_noise is None


def check_model(model, name: str = "filter") -> None:
    """Check ``model``'s structure at the API boundary, each failure one line naming the field:
    a ``StateSpaceModel``; positive int ``dim``, ``obs_dim``, ``num_steps``; a finite
    ``process_std >= 0``; its noises (``_check_noises``); callables; covariances of the model's
    sizes (R ``(m, m)``, Q ``(d, d)``); hashable (the filters take it as a static argument)."""
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"{name}: the model must be a csf_jax.StateSpaceModel (e.g. "
                        f"csf_jax.problems.get('pendulum')), got {type(model).__name__}")
    label = f"{name}: model {model.name!r}"
    for field in ("dim", "obs_dim", "num_steps"):
        value = getattr(model, field)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                or value < 1:
            raise ValueError(f"{label}: {field} must be a positive int, got {value!r}")
    if not _is_number(model.process_std) or model.process_std < 0:
        raise ValueError(f"{label}: process_std must be a finite number >= 0, got "
                         f"{model.process_std!r}")
    _check_noises(model, label)
    for field in ("drift", "observe", "initial_truth", "initial_ensemble", "shock_times", "shock"):
        if not callable(getattr(model, field)):
            raise TypeError(f"{label}: {field} must be callable, got "
                            f"{type(getattr(model, field)).__name__}")
    if not isinstance(model.time_varying, (bool, np.bool_)):
        raise TypeError(f"{label}: time_varying must be a bool, got {model.time_varying!r}")
    for which, cov, size in _covariances(model):
        if np.shape(cov) != (size, size):
            raise ValueError(f"{label}: {which} has shape {np.shape(cov)}, but the model needs "
                             f"({size}, {size}) ({_SIZE_OF[which]}={size})")
    _check_hashable(model, label)


def _is_number(value) -> bool:
    """A finite real number (not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)) and math.isfinite(float(value)))


def _check_noises(model: StateSpaceModel, label: str) -> None:
    """``obs_noise``: an ``ObservationNoise`` (callables, a finite ``gaussian_std > 0``) or a
    ``Likelihood`` (callables); ``process_noise``: a ``ProcessNoise`` or None."""
    noise = model.obs_noise
    if not isinstance(noise, (ObservationNoise, Likelihood)):
        raise TypeError(f"{label}: obs_noise must be a csf_jax.ObservationNoise or "
                        f"csf_jax.Likelihood, got {type(noise).__name__}")
    optional = ("weight", "marginal") if is_additive(model) else ("fisher", "mean", "variance")
    for field in ("log_prob", "sample") + optional:
        value = getattr(noise, field)
        if (value is None and field not in optional) or (value is not None
                                                          and not callable(value)):
            raise TypeError(f"{label}: obs_noise.{field} must be callable, got "
                            f"{type(value).__name__}")
    if is_additive(model) and not (_is_number(noise.gaussian_std) and noise.gaussian_std > 0):
        raise ValueError(f"{label}: obs_noise.gaussian_std must be a finite number > 0, got "
                         f"{noise.gaussian_std!r}")
    if model.process_noise is not None and not isinstance(model.process_noise, ProcessNoise):
        raise TypeError(f"{label}: process_noise must be a csf_jax.ProcessNoise or None, got "
                        f"{type(model.process_noise).__name__}")


def _check_hashable(model: StateSpaceModel, label: str) -> None:
    """Every field hashable: the filters take the model as a static argument."""
    for field, value in zip(model._fields, model):
        try:
            hash(value)
        except TypeError:
            raise TypeError(f"{label}: field {field} holds an unhashable "
                            f"{type(value).__name__}; filters take the model as a static "
                            f"argument, so use tuples and put arrays inside the callables' "
                            f"closures") from None


_SIZE_OF = {"the observation-noise covariance R": "obs_dim",
            "the process-noise covariance Q": "dim"}


def _covariances(model: StateSpaceModel):
    """``(label, covariance, size)`` of the model's R and Q where it gives them."""
    out = []
    if is_additive(model) and model.obs_noise.covariance is not None:
        out.append(("the observation-noise covariance R", model.obs_noise.covariance,
                    model.obs_dim))
    if model.process_noise is not None and model.process_noise.covariance is not None:
        out.append(("the process-noise covariance Q", model.process_noise.covariance, model.dim))
    return out


def check_covariances(model: StateSpaceModel, dtype, name: str = "filter") -> None:
    """Refuse an R or Q that is not positive definite in ``dtype``, the precision the filter
    computes in: one that is in float64 can be singular in float32 (``[[1, 1 - 1e-9], [1 - 1e-9,
    1]]``). The test is on the correlation matrix (scale free): its smallest eigenvalue must
    exceed ``10 m eps(dtype)``."""
    for which, cov, size in _covariances(model):
        smallest, tol = _pd_margin(cov, np.dtype(dtype).name)
        if smallest <= tol:
            raise ValueError(
                f"{name}: model {model.name!r}: {which} ({size} x {size}) is not positive "
                f"definite in {np.dtype(dtype).name} (its correlation matrix's smallest "
                f"eigenvalue {smallest:.3g} < {tol:.2g}); condition it better, or filter in "
                f"float64 (jax_enable_x64 and float64 obs)")


@functools.lru_cache(maxsize=256)
def _pd_margin(cov: tuple, dtype: str) -> tuple[float, float]:
    """The smallest eigenvalue of ``cov``'s correlation matrix, and the least it may be in
    ``dtype`` (``10 m eps``)."""
    arr = np.asarray(cov, np.float64)
    tol = 10.0 * arr.shape[0] * float(np.finfo(np.dtype(dtype)).eps)
    diag = np.diag(arr)
    if not np.isfinite(arr).all() or not (diag > 0).all():
        return -math.inf, tol
    corr = arr / np.sqrt(diag)[:, None] / np.sqrt(diag)[None, :]
    return float(np.linalg.eigvalsh(corr).min()), tol


def check_dynamics(model: StateSpaceModel, dtype, inputs=None, name: str = "filter") -> None:
    """Trace ``drift`` and ``observe`` once (``jax.eval_shape``: nothing is computed) on a state
    ``(d,)`` of ``dtype`` and, for a time-varying model, the step with one slice of ``inputs``;
    refuse outputs of the wrong shape, and turn a failure (a time-varying model's drift that needs
    the inputs it was not given, say) into one line naming the model and the map. The observation
    law's ``log_prob`` and ``sample`` are traced the same way (``_check_noise``)."""
    _checked_noise(model, np.dtype(dtype).name, name)
    if inputs is None:
        _checked_dynamics(model, np.dtype(dtype).name, name)
        return
    u = jax.tree_util.tree_map(
        lambda a: jax.ShapeDtypeStruct(np.shape(a)[1:], jnp.result_type(a)), inputs)
    _check_dynamics(model, np.dtype(dtype).name, u, name)


@functools.lru_cache(maxsize=256)
def _checked_dynamics(model: StateSpaceModel, dtype: str, name: str) -> None:
    """``_check_dynamics`` without inputs, once per model and dtype (a failure is not cached):
    the trace is host work that, repeated on every call, would cost about as much as a whole
    filter step of a small model."""
    _check_dynamics(model, dtype, None, name)


def _check_dynamics(model: StateSpaceModel, dtype: str, u, name: str) -> None:
    x = jax.ShapeDtypeStruct((model.dim,), dtype)
    step = Step(jax.ShapeDtypeStruct((), jnp.int32), u)
    label = f"{name}: model {model.name!r}"
    for field, size in (("drift", model.dim), ("observe", model.obs_dim)):
        try:
            out = jax.eval_shape(lambda x, s, f=field: getattr(at_step(model, s), f)(x), x, step)
        except Exception as e:  # noqa: BLE001  (whatever the user's function raises)
            hint = (" (it is time-varying and got no inputs: pass inputs=, one per step)"
                    if model.time_varying and u is None else "")
            first = (str(e).strip().splitlines() or [""])[0][:160]
            raise ValueError(f"{label}: its {field} fails on a state of shape ({model.dim},)"
                             f"{hint}: {type(e).__name__}: {first}") from None
        shape = getattr(out, "shape", None)
        if shape != (size,):
            raise ValueError(f"{label}: its {field} returns shape {shape} for a state of shape "
                             f"({model.dim},); expected ({size},) "
                             f"({'dim' if field == 'drift' else 'obs_dim'}={size})")


@functools.lru_cache(maxsize=256)
def _checked_noise(model: StateSpaceModel, dtype: str, name: str) -> None:
    """``_check_noise`` once per model and dtype (a failure is not cached)."""
    _check_noise(model, dtype, name)


def _check_noise(model: StateSpaceModel, dtype: str, name: str) -> None:
    """Trace the observation law's ``log_prob`` and ``sample`` once (``jax.eval_shape``) on
    arrays of the model's sizes and refuse outputs of the wrong shape, each in one line naming the
    field. A ``Likelihood``: ``log_prob(y (m,), eta (m,)) -> (m,)`` (a scalar would be broadcast
    over the m entries and counted m times) and ``sample(key, eta (m,)) -> (m,)``. An
    ``ObservationNoise``: ``log_prob(residual (m,)) -> ()`` and ``sample(key, (2, m)) -> (2, m)``."""
    m = model.obs_dim
    vec = jax.ShapeDtypeStruct((m,), dtype)
    key = jax.random.key(0)
    label = f"{name}: model {model.name!r}"
    noise = model.obs_noise
    if is_additive(model):
        kind = "ObservationNoise"
        probes = (("log_prob", noise.log_prob, (vec,), (), f"a residual of shape ({m},)",
                   "a scalar"),
                  ("sample", lambda k: noise.sample(k, (2, m)), (key,), (2, m),
                   f"shape (2, {m})", f"(2, {m})"))
    else:
        kind = "Likelihood"
        probes = (("log_prob", noise.log_prob, (vec, vec), (m,), f"y and eta of shape ({m},)",
                   f"({m},), one log-density per entry (a scalar would be counted {m} times)"),
                  ("sample", noise.sample, (key, vec), (m,), f"eta of shape ({m},)",
                   f"({m},), one draw of y (obs_dim={m})"))
    for field, fn, args, want, given, expected in probes:
        try:
            out = jax.eval_shape(fn, *args)
        except Exception as e:  # noqa: BLE001  (whatever the user's function raises)
            first = (str(e).strip().splitlines() or [""])[0][:160]
            raise ValueError(f"{label}: its {kind}.{field} fails on {given}: "
                             f"{type(e).__name__}: {first}") from None
        shape = getattr(out, "shape", None)
        if shape != want:
            raise ValueError(f"{label}: its {kind}.{field} returns shape {shape} for {given}; "
                             f"expected {expected}")


def log_likelihood(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """``log p(y | x)`` up to a constant for one particle: ``y: (m,)``, ``x: (d,)`` -> scalar.

    NaN entries of ``y`` are missing: only the observed entries enter (0 if none is observed).
    """
    if not is_additive(model):
        return jnp.sum(entry_log_likelihood(model, y, x))
    return model.obs_noise.masked_log_prob(residual(model, y, x), observed(y))


def log_normalizer(model: StateSpaceModel, y: Array) -> Array | None:
    """The log normalising constant that ``log_likelihood`` leaves out, over the observed entries
    of ``y (m,)`` (a scalar, 0 when none is observed), or None where the observation law does not
    give it (``log_norm`` None: a user's own noise or likelihood)."""
    log_norm = model.obs_noise.log_norm
    if log_norm is None:
        return None
    return jnp.asarray(log_norm(observed(y)))


def normalized_log_likelihood(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """``log p(y | x)`` normalised, for one particle: ``y (m,)``, ``x (d,)`` -> scalar; the
    observed entries of ``y`` only (0 if none). ValueError where the observation law gives no
    ``log_norm``."""
    const = log_normalizer(model, y)
    if const is None:
        raise ValueError(f"model {model.name!r}: its observation law {model.obs_noise.name!r} "
                         f"gives no log_norm, so its log-density is known up to a constant only")
    return log_likelihood(model, y, x) + const.astype(x.dtype)


def entry_log_likelihood(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """``(m,)``: ``log p(y_j | x)`` of each entry of ``y (m,)`` (0 where missing), for models whose
    entries are conditionally independent (a ``Likelihood``, or i.i.d. additive noise)."""
    mask = observed(y)
    if is_additive(model):
        r = residual(model, y, x)
        return jnp.where(mask, jax.vmap(lambda ri: model.obs_noise.log_prob(ri[None]))(r), 0.0)
    lp = model.obs_noise.log_prob(jnp.where(mask, y, 0.0), model.observe(x))
    return jnp.where(mask, lp, 0.0)


def curvature(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """The Gauss-Newton curvature of ``-log p(y | .)`` in ``eta = h(x)`` at ``x (d,)``: per-entry
    weights ``(m,)`` or an ``(m, m)`` precision; 0 on missing entries. The guidance's curvature in
    x is ``J^T W J`` with ``J = dh/dx``. Additive noise: ``ObservationNoise.curvature``; a
    ``Likelihood``: its Fisher information (or the observed information, clipped at 0)."""
    mask = observed(y)
    if is_additive(model):
        return model.obs_noise.curvature(residual(model, y, x), mask).astype(x.dtype)
    eta = model.observe(x)
    lik = model.obs_noise
    if lik.fisher is not None:
        w = lik.fisher(eta)
    else:
        y0 = jnp.where(mask, y, 0.0)
        grad = jax.grad(lambda e: jnp.sum(lik.log_prob(y0, e)))
        w = jnp.maximum(-jax.grad(lambda e: jnp.sum(grad(e)))(eta), 0.0)
    return jnp.where(mask, w, 0.0).astype(x.dtype)


def gaussian_standin(model: StateSpaceModel, ensemble: Array):
    """What a Kalman-type filter sees of the observation of ``ensemble (N, d)``: the predicted
    observations ``(N, m)`` and the noise covariance ``R (m, m)``. Additive noise: ``h(x_i)`` and
    ``ObservationNoise.cov``; a ``Likelihood``: ``E[y | x_i]`` and the ensemble-mean ``Var[y | x_i]``
    on the diagonal (ValueError if it gives neither)."""
    m = model.obs_dim
    if is_additive(model):
        return (jax.vmap(model.observe)(ensemble).astype(ensemble.dtype),
                model.obs_noise.cov(m, ensemble.dtype))
    lik = model.obs_noise
    if lik.mean is None or lik.variance is None:
        raise ValueError(f"model {model.name!r}: its likelihood {lik.name!r} gives no Gaussian "
                         f"stand-in (Likelihood.mean and .variance), which a Kalman-type filter needs")
    eta = jax.vmap(model.observe)(ensemble)
    var = jnp.mean(jax.vmap(lik.variance)(eta), 0)
    return jax.vmap(lik.mean)(eta).astype(ensemble.dtype), jnp.diag(var).astype(ensemble.dtype)


def residual(model: StateSpaceModel, y: Array, x: Array) -> Array:
    """``y - h(x)`` with 0 at the missing (NaN) entries of ``y (m,)``; ``x: (d,)`` (additive
    observation noise)."""
    mask = observed(y)
    return jnp.where(mask, jnp.where(mask, y, 0.0) - model.observe(x), 0.0)


def propagate(model: StateSpaceModel, key: Array, ensemble: Array) -> Array:
    """Prior ensemble ``f(x_i) + v_i``: ``ensemble (N, d) -> (N, d)``, drift vmapped over particles."""
    mean = jax.vmap(model.drift)(ensemble)
    return mean + process_draws(model, key, mean.shape, mean.dtype)


def shock_steps(model: StateSpaceModel, key: Array, num_steps: int | None = None) -> Array:
    """``(K,)`` bool: the steps at which ``simulate(model, key)`` shocks the truth (step k is x_{k+1}).

    For figures and post-shock error analyses; same key as the ``simulate`` call.
    """
    K = model.num_steps if num_steps is None else int(num_steps)
    return model.shock_times(jax.random.split(key, 5)[1], K)


def simulate(model: StateSpaceModel, key: Array, num_steps: int | None = None, inputs=None, *,
             check_finite: bool = True):
    """Simulate the truth and its observations.

    Returns ``truth (K+1, d)`` (``x_0 .. x_K``) and ``obs (K, m)`` (``y_1 .. y_K``), with the model's
    shocks applied to the truth. ``inputs``: a time-varying model's per-step inputs, a pytree whose
    leaves have leading axis K (K defaults to theirs); a NaN or inf input is refused, as the
    filters refuse it (a concrete call: under jit or vmap the caller owns the values). Same key,
    same trajectory. Jit- and vmap-friendly.

    ``check_finite``: on a concrete call, a trajectory that diverged (an inf or NaN in the truth
    or the observations, e.g. an explicit step too large for a stiff drift) raises a one-line
    FloatingPointError naming the model and the first non-finite step; False returns it as it
    is. Under jit or vmap nothing is raised (the values are traced): check them yourself.
    """
    check_model(model, "simulate")
    _checks.check_key(key, "simulate")
    K = _num_steps(model, num_steps, inputs, "simulate")
    _checks.check_inputs(inputs, K, model, name="simulate")
    check_dynamics(model, jnp.float32, inputs, "simulate")
    k0, _, k_shock, k_proc, k_obs = jax.random.split(key, 5)
    x0 = model.initial_truth(k0)
    shocked = shock_steps(model, key, K)
    v = process_draws(model, k_proc, (K, model.dim))
    stepped = steps(K, inputs)

    def step(x, xs):
        v_k, shocked_k, key_k, step_k = xs
        x_next = at_step(model, step_k).drift(x) + v_k
        x_next = jnp.where(shocked_k, model.shock(key_k, x_next), x_next)
        return x_next, x_next

    _, xs = jax.lax.scan(step, x0, (v, shocked, jax.random.split(k_shock, K), stepped))
    truth = jnp.concatenate([x0[None], xs], axis=0)
    eta = jax.vmap(lambda x, s: at_step(model, s).observe(x))(xs, stepped)
    if is_additive(model):
        obs = eta + model.obs_noise.sample(k_obs, (K, model.obs_dim))
    else:
        obs = jax.vmap(model.obs_noise.sample)(jax.random.split(k_obs, K), eta)
    if check_finite and _checks.is_concrete(truth, obs):
        why = _divergence(truth, obs)
        if why is not None:
            raise FloatingPointError(f"simulate: model {model.name!r} diverged: {why}; use a "
                                     f"smaller dt (step size) or a stable drift, or pass "
                                     f"check_finite=False to get the values anyway")
    return truth, obs


def _divergence(truth, obs) -> str | None:
    """None if ``truth (K+1, d)`` and ``obs (K, m)`` are finite; else the first non-finite step in
    words (``x_k`` or ``y_k``, k of K) and how large the truth grew before it."""
    truth, obs = np.asarray(truth), np.asarray(obs)
    bad_x = ~np.isfinite(truth).all(axis=-1)
    bad_y = np.concatenate([[False], ~np.isfinite(obs).all(axis=-1)])  # y_k sits at row k
    bad = bad_x | bad_y
    if not bad.any():
        return None
    k, K = int(np.argmax(bad)), truth.shape[0] - 1
    what = f"the truth x_{k}" if bad_x[k] else f"the observation y_{k}"
    seen = truth[:k + 1][np.isfinite(truth[:k + 1])]
    size = f"; the truth reached |x| = {np.abs(seen).max():.2g} by then" if seen.size else ""
    return f"{what} is not finite (step {k} of {K}{size})"


def _num_steps(model: StateSpaceModel, num_steps, inputs, name: str) -> int:
    """K: ``num_steps``, else the inputs' leading axis, else ``model.num_steps``; checked."""
    lengths = {int(np.shape(leaf)[0]) if np.ndim(leaf) else -1
               for leaf in jax.tree_util.tree_leaves(inputs)}
    if inputs is not None and not model.time_varying:
        raise ValueError(f"{name}: inputs given, but model {model.name!r} is not time-varying "
                         f"(set time_varying=True and let drift/observe take the step)")
    if -1 in lengths or len(lengths) > 1:
        raise ValueError(f"{name}: every leaf of inputs needs the same leading axis K, got "
                         f"leading sizes {sorted(lengths)} (-1: a scalar)")
    K = model.num_steps if num_steps is None else num_steps
    if num_steps is None and lengths:
        K = lengths.pop()
    elif lengths and lengths != {K}:
        raise ValueError(f"{name}: inputs have {lengths.pop()} steps but num_steps is {K}")
    if isinstance(K, bool) or not isinstance(K, (int, np.integer)) or K < 1:
        raise ValueError(f"{name}: num_steps must be a positive int, got {K!r}")
    return int(K)


def drop_observations(key: Array, obs: Array, rate: float, *, whole_steps: float = 0.0) -> Array:
    """``obs (K, m)`` with entries set to NaN (missing): each entry independently with probability
    ``rate``, and each whole step with probability ``whole_steps`` (a step with no observation)."""
    for label, p in (("rate", rate), ("whole_steps", whole_steps)):
        if isinstance(p, (bool, np.bool_)) or not (
                isinstance(p, (int, float, np.integer, np.floating)) and 0.0 <= float(p) <= 1.0):
            raise ValueError(f"drop_observations: {label} must be a probability in [0, 1], "
                             f"got {p!r}")
    k_entry, k_step = jax.random.split(key)
    drop = jax.random.bernoulli(k_entry, rate, obs.shape)
    drop = drop | jax.random.bernoulli(k_step, whole_steps, obs.shape[:-1] + (1,))
    return jnp.where(drop, jnp.nan, obs)
