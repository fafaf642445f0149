"""A linear-Gaussian state-space model: the one case with an exact filter (Kalman) to test against.

``x_{k+1} = A x_k + v_k``, ``v_k ~ N(0, Q)``; ``y_{k+1} = H x_{k+1} + w_k``, ``w_k ~ N(0, R)``;
``x_0 ~ N(m0, p0_std^2 I)``. ``Q = q_std^2 I`` and ``R = r_std^2 I`` unless full matrices are given.

``LinearGaussian`` holds the matrices as numpy float64 arrays, which is what the Kalman filter
(``csf_jax.filters.kalman``) reads. ``to_model`` wraps it as a ``StateSpaceModel`` for the ensemble
filters; it is cached, so the same ``LinearGaussian`` always gives the same (hashable) model object
and jitted filters reuse their compilations.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax.ssm import (
    StateSpaceModel,
    covariance_tuple,
    gaussian_noise,
    gaussian_noise_cov,
    gaussian_process_noise,
)


class LinearGaussian(NamedTuple):
    """The parameters of a linear-Gaussian model.

    Attributes:
      A: (d, d) transition matrix.   H: (m, d) observation matrix.
      q_std: std of the isotropic process noise.   r_std: std of the isotropic observation noise.
      m0: (d,) mean of ``x_0``.   p0_std: isotropic std of ``x_0`` (for truth and filters alike).
      num_steps: default trajectory length K.   name: identifier.
      Q: optional (d, d) process-noise covariance (then q_std is unused).
      R: optional (m, m) observation-noise covariance (then r_std is unused).
    Properties ``dim`` (d) and ``obs_dim`` (m) are read off the matrices.
    """

    A: np.ndarray
    H: np.ndarray
    q_std: float
    r_std: float
    m0: np.ndarray
    p0_std: float
    num_steps: int
    name: str
    Q: np.ndarray | None = None
    R: np.ndarray | None = None

    def process_cov(self) -> np.ndarray:
        """``(d, d)``: ``Q``, or ``q_std^2 I`` (a jax array where they are traced)."""
        return _matrix(self.Q) if self.Q is not None else self.q_std ** 2 * np.eye(self.dim)

    def obs_cov(self) -> np.ndarray:
        """``(m, m)``: ``R``, or ``r_std^2 I`` (a jax array where they are traced)."""
        return _matrix(self.R) if self.R is not None else self.r_std ** 2 * np.eye(self.obs_dim)

    @property
    def dim(self) -> int:
        return int(np.shape(self.A)[0])

    @property
    def obs_dim(self) -> int:
        return int(np.shape(self.H)[0])


def _matrix(a):
    """``a`` as a numpy array, or as it is where it is traced (a ``ParametricModel``'s)."""
    return a if isinstance(a, jax.core.Tracer) else np.asarray(a)


def rotation_decay(dim: int, radius: float = 0.95, angle: float = 0.3) -> np.ndarray:
    """A stable ``(d, d)`` transition: ``radius`` times a block-diagonal rotation.

    Block ``j`` rotates coordinates ``(2j, 2j+1)`` by ``angle * (j + 1)``, so every eigenvalue has
    modulus ``radius`` (a trailing odd coordinate just decays by ``radius``). Rotation makes the
    unobserved coordinates visible through the observed ones over time.
    """
    A = np.zeros((dim, dim))
    for j in range(dim // 2):
        c, s = np.cos(angle * (j + 1)), np.sin(angle * (j + 1))
        A[2 * j:2 * j + 2, 2 * j:2 * j + 2] = [[c, -s], [s, c]]
    if dim % 2:
        A[-1, -1] = 1.0
    return radius * A


def linear_gaussian(dim: int = 2, obs_dim: int | None = None, *, q_std: float = 0.3,
                    r_std: float = 0.5, p0_std: float = 1.0, m0=None, A=None, H=None,
                    radius: float = 0.95, angle: float = 0.3, num_steps: int = 20,
                    name: str | None = None, Q=None, R=None) -> LinearGaussian:
    """Build a ``LinearGaussian``.

    Defaults: ``A = rotation_decay(dim, radius, angle)`` (spectral radius 0.95), ``H`` observes the
    first ``obs_dim`` coordinates (``obs_dim = dim`` if None), ``m0 = ones(dim)`` so the prior mean
    is not trivially zero. Pass ``A`` (d, d), ``H`` (m, d) or ``m0`` (d,) to override, and ``Q``
    (d, d) or ``R`` (m, m) for correlated noise (symmetric positive definite).
    """
    for label, v in (("dim", dim), ("obs_dim", obs_dim), ("num_steps", num_steps)):
        if v is not None and (isinstance(v, (bool, np.bool_))
                              or not isinstance(v, (int, np.integer)) or v < 1):
            raise ValueError(f"linear_gaussian: {label} must be a positive int, got {v!r}")
    A = rotation_decay(dim, radius, angle) if A is None else A
    A = np.array(A, dtype=np.float64)
    if not np.isfinite(A).all():
        raise ValueError("linear_gaussian: A has non-finite entries")
    if A.shape != (dim, dim):
        raise ValueError(f"linear_gaussian: A must have shape ({dim}, {dim}), got {A.shape}")
    obs_dim = dim if obs_dim is None else int(obs_dim)
    H = np.eye(obs_dim, dim) if H is None else H
    H = np.array(H, dtype=np.float64)
    if H.shape != (obs_dim, dim):
        raise ValueError(f"linear_gaussian: H must have shape ({obs_dim}, {dim}), got {H.shape}")
    m0 = np.ones(dim) if m0 is None else m0
    m0 = np.array(m0, dtype=np.float64)
    if m0.shape != (dim,):
        raise ValueError(f"linear_gaussian: m0 must have shape ({dim},), got {m0.shape}")
    if not (np.isfinite(H).all() and np.isfinite(m0).all()):
        raise ValueError("linear_gaussian: H and m0 must be finite")
    for label, v in (("q_std", q_std), ("r_std", r_std), ("p0_std", p0_std)):
        number = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
            v, (bool, np.bool_))
        if not (number and np.isfinite(v) and v > 0):
            raise ValueError(f"linear_gaussian: {label} must be positive and finite, got {v}")
    for arr in (A, H, m0):
        arr.setflags(write=False)
    Q = None if Q is None else _frozen(np.array(covariance_tuple(Q, "linear_gaussian: Q", dim)))
    R = None if R is None else _frozen(np.array(covariance_tuple(R, "linear_gaussian: R", obs_dim)))
    name = f"linear_gaussian_d{dim}_m{obs_dim}" if name is None else name
    return LinearGaussian(A, H, float(q_std), float(r_std), m0, float(p0_std), int(num_steps), name,
                          Q, R)


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr.setflags(write=False)
    return arr


def _as_tuple(x) -> tuple:
    """A hashable (nested) tuple of Python floats from a 1-D or 2-D array."""
    arr = np.asarray(x, dtype=np.float64)
    return tuple(arr.tolist()) if arr.ndim == 1 else tuple(map(tuple, arr.tolist()))


def to_model(lg: LinearGaussian) -> StateSpaceModel:
    """The ``StateSpaceModel`` of ``lg``; equal parameters give the very same model object.

    The cache is keyed on the parameter values (arrays as tuples of floats), so repeated calls
    return one model and a jitted filter compiles once per model.
    """
    model = _build_model(_as_tuple(lg.A), _as_tuple(lg.H), float(lg.q_std), float(lg.r_std),
                         _as_tuple(lg.m0), float(lg.p0_std), int(lg.num_steps), str(lg.name),
                         None if lg.Q is None else _as_tuple(lg.Q),
                         None if lg.R is None else _as_tuple(lg.R))
    _SOURCES.setdefault(model, lg)
    return model


# The LinearGaussian behind each model ``to_model`` made (its models are cached, so this is
# bounded by the distinct parameter sets used).
_SOURCES: dict = {}


def linear_source(model: StateSpaceModel) -> LinearGaussian | None:
    """The ``LinearGaussian`` that ``to_model`` made ``model`` from, or None for any other model
    (a model edited with ``_replace`` is another model)."""
    try:
        return _SOURCES.get(model)
    except TypeError:  # an unhashable model is no to_model model
        return None


@functools.cache
def _build_model(A: tuple, H: tuple, q_std: float, r_std: float, m0: tuple, p0_std: float,
                 num_steps: int, name: str, Q: tuple | None = None,
                 R: tuple | None = None) -> StateSpaceModel:
    """Build the model's closures (no shocks); matrices are cast to the particle's dtype."""
    A_np, H_np, m0_np = np.array(A), np.array(H), np.array(m0)
    dim, obs_dim = A_np.shape[0], H_np.shape[0]

    def drift(x):
        return jnp.asarray(A_np, x.dtype) @ x

    def observe(x):
        return jnp.asarray(H_np, x.dtype) @ x

    def initial_truth(key):
        return jnp.asarray(m0_np) + p0_std * jax.random.normal(key, (dim,))

    def initial_ensemble(key, n):
        return jnp.asarray(m0_np) + p0_std * jax.random.normal(key, (n, dim))

    return StateSpaceModel(name=name, dim=dim, obs_dim=obs_dim, num_steps=num_steps, dt=1.0,
                           drift=drift, observe=observe, process_std=q_std,
                           obs_noise=gaussian_noise(r_std) if R is None else gaussian_noise_cov(R),
                           initial_truth=initial_truth, initial_ensemble=initial_ensemble,
                           process_noise=None if Q is None else gaussian_process_noise(Q))
