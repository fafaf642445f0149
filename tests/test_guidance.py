"""DPS guidance: the gradient flows through Tweedie's estimate; the stable modes bound the step."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax.guidance import GuidanceConfig, dps_gradient, guidance_displacement
from csf_jax.prior import mixture_score


def _setup():
    centers = jnp.array([[1.0, 0.0], [-1.0, 0.5], [0.0, 2.0]])
    y = jnp.array([0.3, -0.2])

    def score_fn(x):
        return mixture_score(x, centers, 0.5)

    def loglik(x0):
        return -0.5 * jnp.sum((y - x0**3) ** 2) / 0.01

    x = jax.random.normal(jax.random.key(0), (4, 2))
    return score_fn, loglik, x


def test_dps_gradient_goes_through_the_score(x64):
    score_fn, loglik, x = _setup()
    var = 0.7
    s, grad, ll = dps_gradient(score_fn, loglik, x, var)

    def per_particle(xi):
        x0 = xi + var * score_fn(xi[None])[0]
        return loglik(x0)

    expected = jax.vmap(jax.grad(per_particle))(x)
    np.testing.assert_allclose(grad, expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(s, score_fn(x), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ll, jax.vmap(lambda xi: per_particle(xi))(x), rtol=1e-9)
    # Not the naive gradient at x itself (that would skip Tweedie):
    naive = jax.vmap(jax.grad(loglik))(x)
    assert not np.allclose(grad, naive, rtol=1e-2)


def test_raw_is_the_paper_step():
    grad = jnp.array([[3.0, 4.0], [1e6, 0.0]])
    out = guidance_displacement(GuidanceConfig(mode="raw", scale=2.0), grad, jnp.zeros(2), 0.1, 1.0)
    np.testing.assert_allclose(out, 0.2 * grad)


def test_clipped_caps_the_displacement_per_particle():
    grad = jnp.array([[3.0, 4.0], [1e6, 0.0]])
    cfg = GuidanceConfig(mode="clipped", clip=1.0)
    noise_scale = 0.5
    out = guidance_displacement(cfg, grad, jnp.zeros(2), 0.1, noise_scale)
    cap = noise_scale * np.sqrt(2.0)
    np.testing.assert_allclose(out[0], 0.1 * grad[0], rtol=1e-6)  # small step: untouched
    assert float(jnp.linalg.norm(out[1])) == pytest.approx(cap, rel=1e-6)  # big step: capped
    np.testing.assert_allclose(out[1] / jnp.linalg.norm(out[1]), jnp.array([1.0, 0.0]))


def test_normalized_and_none():
    grad = jnp.array([[3.0, 4.0]])
    ll = jnp.array([-8.0])  # sqrt(-2 ll) = 4
    out = guidance_displacement(GuidanceConfig(mode="normalized"), grad, ll, 1.0, 1.0)
    np.testing.assert_allclose(out, grad / 4.0)
    out = guidance_displacement(GuidanceConfig(mode="none"), grad, ll, 1.0, 1.0)
    np.testing.assert_allclose(out, 0.0)


def test_config_validation():
    with pytest.raises(ValueError, match="mode"):
        GuidanceConfig(mode="fancy")
    with pytest.raises(ValueError, match="clip"):
        GuidanceConfig(clip=0.0)
