"""The local ensemble transform Kalman filter (LETKF; Hunt, Kostelich & Szunyogh 2007).

Each step propagates the ensemble, inflates its anomalies by ``inflation`` (multiplicative), and
analyses every state site on its own: the observations near the site enter with their inverse
variances tapered by the Gaspari-Cohn function of their distance (R-localisation, support
``2 radius``), and the site's analysis ensemble is the background mean plus the background
anomalies times the ensemble-space weights ``w_bar + W_a``:

    C = Y'^T R_loc^{-1},   P~ = [(N-1) I + C Y']^{-1},   w_bar = P~ C (y - y_bar),
    W_a = [(N-1) P~]^{1/2}   (the symmetric square root).

Sites are analysed in parallel (vmapped), so a step costs O(d N^2 W + d N^3) for W observations in
reach of a site: linear in d. Geometry comes from a ``Localization``: the positions of the state
sites and of the observations, on a ring (period) or a line. NaN observations are missing (weight
0); a site with none in reach keeps its background.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks, _linalg
from csf_jax.covariance import gaspari_cohn
from csf_jax.evidence import gaussian_log_evidence
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.enkf import check_standin
from csf_jax.filters.result import FilterResult
from csf_jax.ssm import (
    StateSpaceModel,
    check_model,
    gaussian_standin,
    is_additive,
    observed,
    propagate,
)


class Localization(NamedTuple):
    """Where the state sites and the observations sit: hashable tuples of floats.

    Attributes:
      state: (d,) site positions.
      obs: (m,) observation positions.
      period: the ring's length (distances wrap), or None for a line.
    """

    state: tuple
    obs: tuple
    period: float | None = None


def ring_localization(dim: int, obs_sites) -> Localization:
    """Sites ``0 .. d-1`` on a ring of length d; observations at ``obs_sites (m,)``, the site each
    observation reads, in the order of the observation vector."""
    if isinstance(dim, (bool, np.bool_)) or not isinstance(dim, (int, np.integer)) or dim < 1:
        raise ValueError(f"ring_localization: dim must be a positive int, got {dim!r}")
    try:
        sites = np.asarray(list(obs_sites) if isinstance(obs_sites, range) else obs_sites,
                           np.float64)
    except (TypeError, ValueError):
        sites = None
    if sites is None or sites.ndim != 1 or not np.isfinite(sites).all():
        raise ValueError(f"ring_localization: obs_sites must be a 1-D sequence of finite site "
                         f"positions, got {obs_sites!r:.60}")
    return Localization(tuple(float(i) for i in range(dim)), tuple(sites.tolist()), float(dim))


def _probe(model: StateSpaceModel):
    """A concrete state to probe the sensor at (works while the filter's inputs are traced)."""
    with jax.ensure_compile_time_eval():
        return model.initial_ensemble(jax.random.key(0), 1)[0]


def _sensor_slopes(model: StateSpaceModel, probe, direction) -> tuple[np.ndarray, np.ndarray]:
    """``(J 1, J v)`` at ``probe (d,)`` for the sensor's Jacobian J: both ``(m,)``."""
    with jax.ensure_compile_time_eval():
        probe = jnp.asarray(probe, jnp.float32)
        _, slope = jax.jvp(model.observe, (probe,), (jnp.ones_like(probe),))
        _, along = jax.jvp(model.observe, (probe,), (jnp.asarray(direction, jnp.float32),))
    return np.asarray(slope, np.float64), np.asarray(along, np.float64)


def is_point_sensor(model: StateSpaceModel, sites: np.ndarray, probe) -> bool:
    """Whether observation j depends on state site ``sites[j]`` alone at ``probe (d,)``: ``J v =
    (J 1) v[sites]`` for a random ``v`` (two Jacobian-vector products)."""
    v = np.random.default_rng(0).standard_normal(model.dim).astype(np.float32)
    slope, along = _sensor_slopes(model, probe, v)
    return bool(np.allclose(along, slope * v[sites], rtol=1e-4, atol=1e-5))


def sensor_sites(model: StateSpaceModel, probe) -> np.ndarray | None:
    """The state site ``(m,)`` int each observation reads if ``model.observe`` is a point sensor
    (observation j a function of one site), else None (a sensor that mixes sites, or one flat at
    the probe). Found digit by digit in base 1024, one Jacobian-vector product per digit:
    ``J v / J 1`` is ``v`` at the site, and float32 resolves ``v_i = 1 + digit_i / 1024`` exactly,
    where a single ramp ``1 + i / d`` would not beyond d = 2^23."""
    d = model.dim
    slope, _ = _sensor_slopes(model, probe, np.ones(d))
    if slope.shape != (model.obs_dim,) or not (np.abs(slope) > 1e-6).all():
        return None
    index = np.arange(d, dtype=np.int64)
    sites = np.zeros(model.obs_dim, np.int64)
    scale = 1
    while scale < d:
        _, along = _sensor_slopes(model, probe, 1.0 + (index // scale % 1024) / 1024)
        digit = np.rint((along / slope - 1.0) * 1024)
        if np.any(digit < 0) or np.any(digit > 1023):
            return None
        sites += digit.astype(np.int64) * scale
        scale *= 1024
    if np.any(sites >= d) or not is_point_sensor(model, sites, probe):
        return None
    sites = sites.astype(np.int32)
    sites.setflags(write=False)                # cached per model: shared by every call
    return sites


@functools.lru_cache(maxsize=256)
def _model_sensor_sites(model: StateSpaceModel) -> np.ndarray | None:
    """``sensor_sites`` at the model's own probe state, once per model (the probe's
    Jacobian-vector products, repeated on every call, would cost about as much as a small model's
    whole analysis)."""
    return sensor_sites(model, _probe(model))


def check_localization(model: StateSpaceModel, localization, name: str, *,
                       points: bool = False) -> np.ndarray | None:
    """Check ``localization`` against ``model`` at the boundary; returns the observations' sites
    ``(m,)`` where the sensor is a point sensor (else None).

    Always: a ``Localization`` with the model's d sites and m observations. Where
    ``model.observe`` reads one site per observation, each observation's position must be its
    site's (``ring_localization(d, sites)`` in the sensor's order; a reversed or shifted list is
    refused). With ``points`` (the local CSF): the sensor must be such a point sensor, on the ring
    of d sites. A time-varying sensor is not probed."""
    if not isinstance(localization, Localization):
        raise TypeError(f"{name}: localization must be a csf_jax.Localization (e.g. "
                        f"csf_jax.ring_localization(d, sites)), got {type(localization).__name__}")
    d, m = model.dim, model.obs_dim
    if points and (localization.period is None or float(localization.period) != float(d)
                   or tuple(localization.state) != tuple(float(i) for i in range(d))):
        raise ValueError(f"{name}: needs the ring of d={d} sites (csf_jax.ring_localization)")
    if len(localization.state) != d or len(localization.obs) != m:
        raise ValueError(f"{name}: the localization has {len(localization.state)} sites and "
                         f"{len(localization.obs)} observations; the model has d={d}, m={m}")
    placed = np.asarray(localization.obs, np.float64)
    if points and (np.any(placed != np.round(placed)) or np.any(placed < 0)
                   or np.any(placed >= d)):
        raise ValueError(f"{name}: the localization's {m} observation positions must be integer "
                         f"sites in [0, {d}), one per observation")
    if model.time_varying:
        return None
    sites = _model_sensor_sites(model)
    if sites is None:
        if points:
            raise ValueError(f"{name}: model.observe is not a point sensor at the localization's "
                             f"observation sites (observation j must depend on site obs[j] only)")
        return None
    where = np.asarray(localization.state, np.float64)[sites]
    gap = np.abs(where - placed)
    if localization.period is not None:
        gap = np.minimum(gap, float(localization.period) - gap)
    wrong = np.flatnonzero(gap > 1e-6)
    if wrong.size:
        j = int(wrong[0])
        raise ValueError(f"{name}: observation {j} reads state site {int(sites[j])} (position "
                         f"{where[j]:g}), but the localization places it at {placed[j]:g} "
                         f"({wrong.size} of {m} misplaced); give the sites in the sensor's order: "
                         f"ring_localization(d, sites) with sites[j] the site observation j reads")
    return sites


DENSE_MAX = 2 ** 26        # d m above this: local_obs searches sorted positions (no d x m array)


@functools.lru_cache(maxsize=32)
def local_obs(loc: Localization, radius: float):
    """For every state site, the observations in reach: ``index (d, W)`` int32 and taper
    ``weight (d, W)`` float (0 pads sites with fewer than W). In reach means a positive taper;
    they are ordered by decreasing taper, ties by observation index. Above ``DENSE_MAX`` the
    candidates come from a search of the sorted positions, in ``O((d + m) log m + d W)`` memory
    and time, where the dense form would build a d x m distance array (10^10 entries at
    d = m = 10^5)."""
    wraps = loc.period is not None and 4.0 * radius >= float(loc.period)
    if len(loc.state) * len(loc.obs) > DENSE_MAX and not wraps:
        return _sparse_local_obs(loc, radius)
    s = np.asarray(loc.state)[:, None]
    o = np.asarray(loc.obs)[None, :]
    dist = np.abs(s - o)
    if loc.period is not None:
        dist = np.minimum(dist, loc.period - dist)
    taper = gaspari_cohn(dist / radius)
    width = max(1, int((taper > 0).sum(axis=1).max()))
    index = np.argsort(-taper, axis=1, kind="stable")[:, :width].astype(np.int32)
    weight = np.take_along_axis(taper, index, axis=1)
    return index, weight


def _sparse_local_obs(loc: Localization, radius: float):
    """``local_obs`` by binary search: each site's candidates are the observations whose positions
    lie within ``2 radius`` (the taper's support), found in the sorted positions, repeated one
    period to either side on a ring (the taper's support shorter than the ring, so each
    observation is a candidate once)."""
    state = np.asarray(loc.state, np.float64)
    pos = np.asarray(loc.obs, np.float64)
    ids = np.argsort(pos, kind="stable")
    pos_sorted, ids_sorted = pos[ids], ids
    if loc.period is not None:
        period = float(loc.period)
        pos_sorted = np.concatenate([pos_sorted - period, pos_sorted, pos_sorted + period])
        ids_sorted = np.concatenate([ids, ids, ids])
    reach = 2.0 * radius
    lo = np.searchsorted(pos_sorted, state - reach, side="right")
    hi = np.searchsorted(pos_sorted, state + reach, side="left")
    width = max(1, int((hi - lo).max()))
    cand = np.minimum(lo[:, None] + np.arange(width), len(pos_sorted) - 1)
    inside = np.arange(width)[None, :] < (hi - lo)[:, None]
    dist = np.abs(state[:, None] - pos_sorted[cand])
    taper = np.where(inside, gaspari_cohn(dist / radius), 0.0)
    obs_id = ids_sorted[cand]
    order = np.lexsort((obs_id, -taper), axis=1)
    weight = np.take_along_axis(taper, order, axis=1)
    index = np.take_along_axis(obs_id, order, axis=1)
    keep = max(1, int((weight > 0).sum(axis=1).max()))
    return index[:, :keep].astype(np.int32), weight[:, :keep]


@dataclasses.dataclass(frozen=True)
class LETKFConfig:
    """The LETKF's localisation and inflation.

    Attributes:
      radius: Gaspari-Cohn half-width in site units (support 2 radius).
      inflation: multiplicative factor on the background anomalies (>= 1 typically).
      adaptive: 0 (off), or the certainty ``x`` of the finite-size EnKF's hyperprior (EnKF-N,
        Bocquet 2011, 2015; DAPPER's ``xN``): each step's anomalies are further scaled by the
        factor that the EnKF-N's dual cost picks from the step's innovation
        (``enkf_n_inflation``), on top of ``inflation``.
      radii: () (off: ``radius`` throughout), or candidate radii: each step analyses at the one
        whose Gaussian evidence for the observations, accumulated over the steps, is largest
        (``radius_evidence``).
    """

    radius: float = 4.0
    inflation: float = 1.05
    adaptive: float = 0.0
    radii: tuple = ()

    def __post_init__(self):
        _checks.check_fields(self, positive=("radius", "inflation"))
        check_adaptive(self)


def check_adaptive(config) -> None:
    """``config.adaptive`` is a finite number >= 0 and ``config.radii`` (where it has one) a
    tuple of positive numbers."""
    a = config.adaptive
    if isinstance(a, bool) or not isinstance(a, (int, float)) or not (0.0 <= a < float("inf")):
        raise ValueError(f"{type(config).__name__}.adaptive must be a finite number >= 0 (0: "
                         f"off), got {a!r}")
    r = getattr(config, "radii", ())
    if not isinstance(r, tuple) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < float("inf")
            for v in r):
        raise ValueError(f"{type(config).__name__}.radii must be a tuple of positive numbers "
                         f"(empty: the fixed radius), got {r!r}")


def letkf_analysis(forecast, y, model: StateSpaceModel, index, weight):
    """The LETKF analysis of ``forecast (N, d)`` on ``y (m,)``; ``index, weight (d, W)`` from
    ``local_obs``. Returns ``(N, d)``."""
    n = forecast.shape[0]
    mean = forecast.mean(0)
    anom = forecast - mean
    hx, R = gaussian_standin(model, forecast)
    y_mean = hx.mean(0)
    y_anom = hx - y_mean
    mask = observed(y)
    innov = jnp.where(mask, jnp.where(mask, y, 0.0) - y_mean, 0.0)
    r_inv = 1.0 / jnp.diagonal(R)
    obs_w = jnp.where(mask, r_inv, 0.0)
    eye = jnp.eye(n, dtype=forecast.dtype)

    def site(a_i, idx, taper):
        yl = y_anom[:, idx]                      # (N, W)
        c = yl * (taper * obs_w[idx])            # (N, W): Y'^T R^-1 localised
        m = (n - 1) * eye + c @ yl.T
        p, w_a = ensemble_transforms(m, n - 1)
        w_bar = p @ (c @ innov[idx])
        return a_i @ (w_bar[:, None] + w_a)     # (N,)

    local = jax.vmap(site, in_axes=(1, 0, 0))(anom, index, jnp.asarray(weight, forecast.dtype))
    return mean + local.T


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def ensemble_transforms(m, scale):
    """``(m^{-1}, sqrt(scale m^{-1}))`` of a symmetric positive-definite ``m (N, N)``, by one
    eigendecomposition: the LETKF's ensemble-space covariance and its symmetric square-root
    transform. ``scale``: N - 1 (static).

    Its derivative is the Daleckii-Krein formula (``_transforms_jvp``), not the
    eigendecomposition's: ``m`` has N - W equal eigenvalues wherever a site sees W < N
    observations, where ``eigh``'s derivative divides by their zero gaps (NaN), while these
    matrix functions are smooth there."""
    lam, vec = jnp.linalg.eigh(m)
    lam = jnp.maximum(lam, 1e-12)
    return (vec / lam) @ vec.T, (vec * jnp.sqrt(scale / lam)) @ vec.T


@ensemble_transforms.defjvp
def _transforms_jvp(scale, primals, tangents):
    """``d f(m) = V (G o (V^T dm V)) V^T`` for ``f(m) = V g(Lambda) V^T``, with ``G_ij`` the
    divided difference ``(g(l_i) - g(l_j)) / (l_i - l_j)``, and ``g'`` where the two eigenvalues
    (nearly) coincide."""
    (m,), (dm,) = primals, tangents
    lam, vec = jnp.linalg.eigh(m)
    lam = jnp.maximum(lam, 1e-12)
    rotated = vec.T @ dm @ vec
    gap = lam[:, None] - lam[None, :]
    close = jnp.abs(gap) <= 1e-6 * jnp.maximum(lam[:, None], lam[None, :])
    middle = 0.5 * (lam[:, None] + lam[None, :])

    def divided(g, slope):
        values = g(lam)
        return jnp.where(close, slope(middle),
                         (values[:, None] - values[None, :]) / jnp.where(close, 1.0, gap))

    inverse = divided(lambda x: 1.0 / x, lambda x: -1.0 / x ** 2)
    root = divided(lambda x: jnp.sqrt(scale / x), lambda x: -0.5 * jnp.sqrt(scale / x) / x)
    primal = ((vec / lam) @ vec.T, (vec * jnp.sqrt(scale / lam)) @ vec.T)
    return primal, (vec @ (inverse * rotated) @ vec.T, vec @ (root * rotated) @ vec.T)


#: the forgetting of the candidate radii's accumulated log evidence (``radius_evidence``): the
#: evidence of an observed step weighs half after about 14 more
RADIUS_MEMORY = 0.95


def obs_tapers(loc: Localization, radii: tuple) -> np.ndarray:
    """``(R, m, m)``: the Gaspari-Cohn taper of the distances between the observations, for each
    of ``radii``."""
    o = np.asarray(loc.obs, np.float64)
    dist = np.abs(o[:, None] - o[None, :])
    if loc.period is not None:
        dist = np.minimum(dist, loc.period - dist)
    return np.stack([gaspari_cohn(dist / r) for r in radii])


@_linalg.precise
def radius_evidence(forecast, y, model: StateSpaceModel, tapers):
    """``(R,)``: for each taper ``rho_r (m, m)`` of ``tapers``, the log density (without its
    ``-(m / 2) log 2 pi``, the same for every radius) of the observed entries of ``y (m,)``
    under the forecast ``(N, d)``'s localised Gaussian,
    ``N(y; y_bar, rho_r o (Y' Y'^T / (N - 1)) + R)`` (``o``: the elementwise product; ``Y'`` the
    predicted observations' anomalies, ``gaussian_standin``). A radius that explains the
    innovation without spurious long-range covariances has the largest; the cost is one
    ``m x m`` Cholesky factor per radius, so it suits up to a few thousand observations. A taper
    whose matrix is not positive definite there scores below every other radius."""
    n = forecast.shape[0]
    hx, R = gaussian_standin(model, forecast)
    mask = observed(y)
    y_mean = hx.mean(0)
    anom = hx - y_mean
    innov = jnp.where(mask, jnp.where(mask, y, 0.0) - y_mean, 0.0)
    cov = anom.T @ anom / (n - 1)
    both = mask[:, None] & mask[None, :]
    eye = jnp.eye(cov.shape[0], dtype=cov.dtype)

    def one(taper):
        p = jnp.where(both, taper.astype(cov.dtype) * cov + R, eye)
        chol = _linalg.cholesky(p)
        z = _linalg.solve_lower(chol, innov)
        return -0.5 * jnp.sum(z * z) - jnp.sum(jnp.log(jnp.diagonal(chol)))

    ll = jax.vmap(one)(jnp.asarray(tapers))
    ok = jnp.isfinite(ll)
    floor = jnp.min(jnp.where(ok, ll, jnp.inf)) - 1e3
    return jnp.where(ok, ll, jnp.where(jnp.any(ok), floor, 0.0))


def ensemble_state(model, static, inflation, ensemble, key):
    """A transform filter's ``init``: its state is the ensemble itself."""
    return ensemble, key


def radii_state(model, static, inflation, ensemble, key):
    """A local filter's ``init``: the ensemble, and with candidate radii
    (``static.radii``) their accumulated log evidence ``(R,)``, 0 at the start."""
    if not static.radii:
        return ensemble, key
    return (ensemble, jnp.zeros((len(static.radii),), ensemble.dtype)), key


def choose_radius(static, scores, forecast, y, model, localization):
    """The next accumulated scores ``(R,)`` and the index of the radius to analyse at: the
    largest score (ties: the first candidate)."""
    evidence = radius_evidence(forecast, y, model, obs_tapers(localization, static.radii))
    scores = jnp.where(jnp.any(observed(y)), RADIUS_MEMORY * scores + evidence, scores)
    return scores, jnp.argmax(scores)


class LETKFStatic(NamedTuple):
    """The LETKF's static settings for the driver: the half-width, the geometry and the EnKF-N
    hyperprior's certainty (0: no adaptive inflation)."""

    radius: float
    localization: Localization
    adaptive: float = 0.0
    radii: tuple = ()


def inflated_forecast(model: StateSpaceModel, key, ensemble, inflation, y=None,
                      adaptive: float = 0.0):
    """The propagated ``ensemble (N, d)`` with its anomalies scaled by ``inflation`` (traced),
    and with ``adaptive > 0`` by the EnKF-N's factor for ``y (m,)`` (``enkf_n_inflation``).
    Returns ``(forecast (N, d), factor ())``, the EnKF-N's factor (1 with ``adaptive`` 0)."""
    forecast = propagate(model, key, ensemble).astype(ensemble.dtype)
    center = forecast.mean(0)
    scale = inflation.astype(ensemble.dtype)
    factor = jnp.ones((), ensemble.dtype)
    if adaptive > 0:
        factor = enkf_n_inflation(center + scale * (forecast - center), y, model, adaptive)
        scale = scale * factor
    return center + scale * (forecast - center), factor


#: the adaptive inflation's largest factor in one step (``enkf_n_inflation``)
MAX_ADAPTIVE = 2.0


@_linalg.precise
def enkf_n_inflation(forecast, y, model: StateSpaceModel, certainty: float):
    """The finite-size EnKF's inflation of ``forecast (N, d)``'s anomalies for ``y (m,)``: a
    scalar >= 1 (NaN entries of ``y`` left out; 1 where none is observed).

    The EnKF-N (Bocquet 2011; dual form, Bocquet, Raanes & Hannart 2015) treats the forecast
    covariance as unknown, drawn around the ensemble's by a Jeffreys hyperprior, and picks the
    anomalies' factor ``l`` that minimises, with ``S = R^{-1/2} Y'`` ``(N, m)`` the normalised
    observation anomalies ``= V s U^T`` and ``u = U^T R^{-1/2} (y - y_bar)``,

        J(l) = sum_k u_k^2 / (l^2 s_k^2 + N - 1) + e / l^2 + c log l^2,

    ``e = (N + 1) / N``, ``c = N / (N - 1)``, after the mode correction of Bocquet et al.
    (2015, their eq. 36: toward no inflation where the observations barely inform) and both
    scaled by ``certainty`` (DAPPER's ``xN``: above 1 trusts the ensemble's spread more). The
    minimiser is found on ``log l^2`` by bisection of ``J'`` (40 halvings), and the factor is
    kept within ``[1, MAX_ADAPTIVE]``: it only widens the ensemble, and at most doubles it in one
    step (after a jump of the truth the innovation asks for far more, and Lorenz-96's RK4
    overflowed from ensembles widened 50-fold at once; over the next steps the factors compound).
    """
    n = forecast.shape[0]
    n1 = n - 1
    hx, R = gaussian_standin(model, forecast)
    mask = observed(y)
    r_isqrt = jnp.where(mask, 1.0 / jnp.sqrt(jnp.diagonal(R)), 0.0)
    y_mean = hx.mean(0)
    s_mat = (hx - y_mean) * r_isqrt                                   # (N, m)
    innov = jnp.where(mask, jnp.where(mask, y, 0.0) - y_mean, 0.0) * r_isqrt
    s2, vec = jnp.linalg.eigh(s_mat @ s_mat.T)                        # (N,), (N, N)
    s2 = jnp.maximum(s2, 0.0)
    proj = vec.T @ (s_mat @ innov)                                    # s_k u_k
    u2 = jnp.where(s2 > 1e-10 * jnp.max(s2), proj**2 / jnp.maximum(s2, 1e-30), 0.0)
    e = (n + 1.0) / n
    c = n / n1
    mode = e / c
    keep = jnp.mean(n1 / (s2 + n1))                                   # ~ 1 / (1 + HBH/R)
    correction = jnp.sqrt(mode**keep)
    e, c = certainty * e / correction, certainty * c * correction

    def slope(log_l2):                                                # dJ / d log l^2
        l2 = jnp.exp(log_l2)
        return -l2 * jnp.sum(u2 * s2 / (l2 * s2 + n1) ** 2) - e / l2 + c

    def halve(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        up = slope(mid) > 0
        return jnp.where(up, lo, mid), jnp.where(up, mid, hi)

    dtype = forecast.dtype
    bounds = (jnp.asarray(0.0, dtype), jnp.asarray(2.0 * math.log(MAX_ADAPTIVE), dtype))
    lo, hi = jax.lax.fori_loop(0, 40, halve, bounds)
    factor = jnp.exp(0.25 * (lo + hi))
    return jnp.where(jnp.any(mask) & jnp.isfinite(factor), factor, 1.0).astype(dtype)


def _step(model: StateSpaceModel, static: LETKFStatic, inflation, state, y, key, time):
    """Forecast, inflate and analyse every site of the ensemble ``(N, d)`` on ``y (m,)``; with
    candidate radii, at the one ``choose_radius`` picks."""
    ensemble = state[0] if static.radii else state
    forecast, _ = inflated_forecast(model, key, ensemble, inflation, y, static.adaptive)

    def at(radius):
        index, weight = local_obs(static.localization, radius)
        return letkf_analysis(forecast, y, model, jnp.asarray(index), weight)

    log_evidence = gaussian_log_evidence(*gaussian_standin(model, forecast), y)
    if not static.radii:
        post = at(static.radius)
        return post, StepOutput(post.mean(0), post.std(0, ddof=1), post,
                                log_evidence=log_evidence)
    scores, pick = choose_radius(static, state[1], forecast, y, model, static.localization)
    post = jax.lax.switch(pick, [functools.partial(at, r) for r in static.radii])
    info = {"radius": jnp.asarray(static.radii, forecast.dtype)[pick]}
    return (post, scores), StepOutput(post.mean(0), post.std(0, ddof=1), post, info, log_evidence)


def _check(model: StateSpaceModel, static: LETKFStatic) -> None:
    if is_additive(model) and model.obs_noise.covariance is not None:
        raise ValueError("letkf: needs uncorrelated observation noise (R-localisation divides by "
                         "each observation's variance)")
    check_standin("letkf")(model, static)


LETKF = Kernel("letkf", radii_state, _step, _check, label="LETKF")


@_checks.renamed_keywords(problem="model")
def letkf(obs, ensemble, *, model: StateSpaceModel, key, localization: Localization | None = None,
          config: LETKFConfig = LETKFConfig(), inputs=None, return_ensembles: bool = False,
          check_finite: bool = True, progress=None) -> FilterResult:
    """Run the LETKF.

    Args:
      obs: (K, m) observations; NaN marks a missing entry.  ensemble: (N, d) at time 0.
      model: the model (static).  key: a ``jax.random.key`` (process noise only).
      localization: the positions of sites and observations (``ring_localization``).
      config: localisation radius and inflation (``LETKFConfig``); the inflation is traced, so a
        sweep over it compiles once.
      inputs: a time-varying model's per-step inputs (leading axis K), or None.
      return_ensembles: also return the (K, N, d) analysis ensembles.
      check_finite: raise FloatingPointError on a non-finite mean (concrete runs only).
      progress: optional host callback ``k -> None`` at every step (and a line on stderr around
        the first compilation).
    Returns ``FilterResult(mean (K, d), std (K, d), ensembles | None, finite (K,))``.
    """
    return run(method(localization, config), obs, ensemble, model=model, key=key, inputs=inputs,
               return_ensembles=return_ensembles, check_finite=check_finite, progress=progress)


def method(localization: Localization | None = None, config: LETKFConfig = LETKFConfig()) -> Method:
    """The LETKF as a ``Method`` for ``csf_jax.run``.

    Args:
      localization: where the sites and observations sit (``csf_jax.ring_localization(d, sites)``).
      config: ``LETKFConfig``: the localisation radius (static) and the inflation (traced).
    """
    localization = require_localization(localization, "letkf")
    if not isinstance(config, LETKFConfig):
        raise TypeError(f"letkf: config must be a LETKFConfig, got {type(config).__name__}")
    return Method(LETKF._replace(bind=_bind, bind_checks=True),
                  LETKFStatic(float(config.radius), localization, float(config.adaptive),
                              tuple(float(r) for r in config.radii)),
                  jnp.asarray(config.inflation))


def require_localization(localization, name: str) -> Localization:
    """``localization`` if it is a ``Localization``; else a one-line error naming
    ``csf_jax.ring_localization``."""
    if localization is None:
        raise TypeError(f"{name}: needs localization= (where the sites and observations sit): "
                        f"csf_jax.ring_localization(d, obs_sites) for a ring of d sites")
    if not isinstance(localization, Localization):
        raise TypeError(f"{name}: localization must be a Localization (csf_jax.ring_localization"
                        f"(d, obs_sites)), got {type(localization).__name__}")
    return localization


def _bind(model, static: LETKFStatic, params, state0):
    check_model(model, "letkf")
    check_localization(model, static.localization, "letkf")
    return model, static, params, state0
