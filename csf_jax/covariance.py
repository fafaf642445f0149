"""Covariance estimators for the prior ensemble's Gaussian, for small ensembles.

With N members and d coordinates the sample covariance has d(d+1)/2 entries estimated from N
draws: at N = 20-50 its spurious off-diagonal correlations and its too-small eigenvalues cost the
Gaussian-based samplers much of their accuracy (docs/small_ensembles.md). The classical remedies,
what a data-assimilation user tries first:

* ``"sample"``: the unbiased sample covariance (N - 1 denominator).
* ``"ledoit_wolf"``: shrinkage towards ``mu I`` (``mu`` the mean variance) with the intensity of
  Ledoit and Wolf (2004), which minimises the expected Frobenius error; no tuning.
* ``"localised"``: the Schur product with the Gaspari-Cohn taper of the index distance ``|i - j|``
  (half-width ``radius``; on a ring with ``periodic``), which keeps the covariance positive
  semi-definite and removes correlations between far coordinates.

Every estimator adds the same small diagonal floor as the sample one, so a collapsed ensemble
still gives a positive-definite matrix.
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np

from csf_jax import _checks, _linalg

ESTIMATORS = ("sample", "ledoit_wolf", "localised")


@dataclasses.dataclass(frozen=True)
class CovarianceConfig:
    """How the prior ensemble's covariance is estimated (module docstring).

    Attributes:
      estimator: one of ``ESTIMATORS``.
      radius: the Gaspari-Cohn half-width ``c`` in index units for ``"localised"`` (correlations
        vanish from ``|i - j| = 2c`` on); unused otherwise.
      periodic: ``"localised"`` measures ``|i - j|`` on a ring of length d (Lorenz-96-like states).
    """

    estimator: str = "sample"
    radius: float = 2.0
    periodic: bool = False

    def __post_init__(self):
        _checks.check_fields(self)
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"CovarianceConfig.estimator must be one of {', '.join(ESTIMATORS)}, "
                             f"got {self.estimator!r}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"CovarianceConfig.radius must be positive and finite, got "
                             f"{self.radius}")


SAMPLE = CovarianceConfig()


@_linalg.precise
def ledoit_wolf_intensity(centred):
    """Ledoit-Wolf (2004) shrinkage intensity in ``[0, 1]`` of ``centred (N, d)`` (mean removed).

    With ``S = X^T X / N``, ``mu = tr S / d`` and the normalised Frobenius norm ``|A|^2 = tr(A A^T) / d``:
    ``delta^2 = |S - mu I|^2``, ``beta^2 = min(delta^2, sum_k |x_k x_k^T - S|^2 / N^2)``, intensity
    ``beta^2 / delta^2`` (1 when ``delta = 0``). ``sum_k |x_k x_k^T - S|^2 = sum_k |x_k|^4 - N |S|^2``
    avoids the N outer products.
    """
    n, d = centred.shape
    s = centred.T @ centred / n
    mu = jnp.trace(s) / d
    s_sq = jnp.sum(s * s)
    delta2 = (s_sq - 2.0 * mu * jnp.trace(s) + mu * mu * d) / d
    norms = jnp.sum(centred * centred, axis=-1)
    beta_bar2 = (jnp.sum(norms * norms) - n * s_sq) / (n * n * d)
    beta2 = jnp.clip(beta_bar2, 0.0, delta2)
    return jnp.where(delta2 > 0, beta2 / jnp.where(delta2 > 0, delta2, 1.0), 1.0)


def gaspari_cohn(r):
    """The Gaspari-Cohn fifth-order taper of ``r = distance / half-width`` (1 at 0, 0 from 2 on)."""
    r = np.abs(np.asarray(r, np.float64))
    out = np.zeros_like(r)
    a = r <= 1
    b = (r > 1) & (r < 2)
    ra, rb = r[a], r[b]
    out[a] = -0.25 * ra**5 + 0.5 * ra**4 + 0.625 * ra**3 - 5 / 3 * ra**2 + 1
    out[b] = (rb**5 / 12 - 0.5 * rb**4 + 0.625 * rb**3 + 5 / 3 * rb**2 - 5 * rb + 4
              - 2 / 3 / rb)
    return np.clip(out, 0.0, 1.0)


@functools.lru_cache(maxsize=64)
def localisation_taper(dim: int, radius: float, periodic: bool = False) -> np.ndarray:
    """The ``(d, d)`` Gaspari-Cohn taper of ``|i - j| / radius`` (ring distance with ``periodic``)."""
    i = np.arange(dim)
    dist = np.abs(i[:, None] - i[None, :]).astype(np.float64)
    if periodic:
        dist = np.minimum(dist, dim - dist)
    taper = gaspari_cohn(dist / radius)
    taper.setflags(write=False)
    return taper


@_linalg.precise
def estimate(ensemble, config: CovarianceConfig = SAMPLE, jitter: float = 1e-6):
    """Mean ``(d,)``, covariance ``(d, d)`` by ``config``, and the diagonal floor (``jitter`` times
    the mean variance plus a tiny absolute amount) that keeps a collapsed or rank-deficient
    ensemble's covariance positive definite; ``ensemble: (N, d)``. The floor is returned apart, so
    callers add it beside their own diagonal terms."""
    n, d = ensemble.shape
    mean = ensemble.mean(0)
    centred = ensemble - mean
    cov = centred.T @ centred / max(n - 1, 1)
    if config.estimator == "ledoit_wolf":
        rho = ledoit_wolf_intensity(centred).astype(cov.dtype)
        mu = jnp.trace(cov) / d
        cov = (1.0 - rho) * cov + rho * mu * jnp.eye(d, dtype=cov.dtype)
    elif config.estimator == "localised":
        cov = cov * jnp.asarray(localisation_taper(d, float(config.radius), config.periodic),
                                cov.dtype)
    return mean, cov, jitter * jnp.trace(cov) / d + jnp.finfo(ensemble.dtype).tiny ** 0.5
