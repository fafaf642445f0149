"""The variance-exploding SDE of the score-SDE papers (Song et al. 2021), with sigma_max = 25.

Forward SDE ``dx = g(t) dw`` with ``g(t) = s^t``, ``s = sigma_max``, so that
``x_t | x_0 ~ N(x_0, sigma_t^2 I)`` with ``sigma_t^2 = (s^(2t) - 1) / (2 ln s)`` (alpha_t = 1).
At t = 1, sigma_1 = 9.845 for s = 25: the reverse process starts from N(0, sigma_1^2 I), not N(0, I).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

SIGMA_MAX = 25.0


def marginal_std(t, sigma_max: float = SIGMA_MAX):
    """Std of ``x_t | x_0``: ``sqrt((s^(2t) - 1) / (2 ln s))``. ``t``: any shape, in [0, 1]."""
    log_s = jnp.log(sigma_max)
    return jnp.sqrt(jnp.expm1(2.0 * t * log_s) / (2.0 * log_s))


def marginal_std_host(t: float, sigma_max: float = SIGMA_MAX) -> float:
    """:func:`marginal_std` of a Python float, as a Python float (for static grids)."""
    log_s = np.log(sigma_max)
    return float(np.sqrt(np.expm1(2.0 * t * log_s) / (2.0 * log_s)))


def time_of_std(sigma, sigma_max: float = SIGMA_MAX):
    """Inverse of :func:`marginal_std`: the time t with ``marginal_std(t) = sigma`` (sigma >= 0)."""
    log_s = jnp.log(sigma_max)
    return jnp.log1p(2.0 * log_s * jnp.square(sigma)) / (2.0 * log_s)


def inflated_time(t, inflation, sigma_max: float = SIGMA_MAX):
    """The time whose marginal std is ``sqrt(sigma_t^2 + inflation^2)``.

    The score of the VE-diffused prior at that time is the score at time t of the prior convolved
    with ``N(0, inflation^2 I)``: evaluating a prior score there inflates the prior.
    """
    if isinstance(inflation, (int, float)) and inflation == 0.0:
        return t
    return time_of_std(jnp.sqrt(jnp.square(marginal_std(t, sigma_max)) + inflation ** 2), sigma_max)


def diffusion_sq(t, sigma_max: float = SIGMA_MAX):
    """``g(t)^2 = s^(2t)``, the squared diffusion coefficient; ``d sigma_t^2 / dt``."""
    return jnp.exp(2.0 * t * jnp.log(sigma_max))


def perturb(x0, z, t, sigma_max: float = SIGMA_MAX):
    """A draw of ``x_t | x_0``: ``x0 + sigma_t z``. ``x0, z: (..., d)``, ``t`` broadcastable to ``(...)``."""
    return x0 + marginal_std(t, sigma_max)[..., None] * z


def tweedie(x, score, t, sigma_max: float = SIGMA_MAX):
    """Tweedie's posterior-mean estimate ``E[x_0 | x_t] = x_t + sigma_t^2 score`` (alpha_t = 1)."""
    return x + marginal_std(t, sigma_max) ** 2 * score


class ReverseGrid(NamedTuple):
    """The reverse-time grid of the Euler-Maruyama sampler.

    times: (L,) from ``t_max`` down to ``t_min`` (``linspace(1, 1e-3, L)`` by default).
    dt: (L,) positive step length used at each time.
    """

    times: jnp.ndarray
    dt: jnp.ndarray


def reverse_grid(num_steps: int, t_max: float = 1.0, t_min: float = 1e-3) -> ReverseGrid:
    """``times = linspace(t_max, t_min, L)``; each step integrates over ``dt = t_l - t_{l+1}``.

    The last step, at ``t_min``, uses the same ``dt`` as the others, so the sampler ends at t ~= 0.
    """
    if num_steps < 2:
        raise ValueError(f"reverse_grid needs num_steps >= 2, got {num_steps}")
    times = jnp.linspace(t_max, t_min, num_steps)
    step = (t_max - t_min) / (num_steps - 1)
    return ReverseGrid(times=times, dt=jnp.full((num_steps,), step, dtype=times.dtype))


def noise_levels(num_steps: int, sigma_start: float, sigma_end: float):
    """The noise levels of the ancestral sampler (host floats): ``(L + 1,)``, geometric from ``sigma_start`` down
    to ``sigma_end`` in L levels, then 0 (the last step lands on the clean state).

    A geometric grid spends the steps evenly in ``log sigma``, where the diffused prior changes
    (the VE marginal std grows like ``s^t``): 50 levels cover 9.8 -> 0.03 at a ratio 1.12 per step.
    """
    if num_steps < 1:
        raise ValueError(f"noise_levels needs num_steps >= 1, got {num_steps}")
    if not sigma_start >= sigma_end > 0.0:
        raise ValueError(f"noise_levels needs sigma_start >= sigma_end > 0, got {sigma_start}, "
                         f"{sigma_end}")
    return np.concatenate([np.geomspace(sigma_start, sigma_end, num_steps), [0.0]])


def bridge(sigma, sigma_next):
    """The VE bridge ``x_{sigma'} | x_sigma, x_0 = N(rho x_sigma + (1 - rho) x_0, v I)``.

    Returns ``(rho, v)`` with ``rho = sigma'^2 / sigma^2`` and ``v = (sigma^2 - sigma'^2) rho``
    (exact for the VE SDE, any step size). With ``x_0 | x_sigma ~ N(u, S)`` the step
    ``x_{sigma'} ~ N(rho x + (1 - rho) u, v I + (1 - rho)^2 S)`` is the exact reverse transition:
    the ancestral sampler's one step.
    """
    rho = jnp.square(sigma_next / sigma)
    return rho, (jnp.square(sigma) - jnp.square(sigma_next)) * rho
