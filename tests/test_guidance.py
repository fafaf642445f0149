"""DPS guidance: the gradient flows through Tweedie's estimate; the stable modes bound the step."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax import guidance
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


def test_kalman_tweedie_is_the_kalman_update_for_a_linear_sensor(x64):
    """One Fisher-scoring step with h(u) = H u and Gaussian noise is exact: the posterior of
    N(u; x0_hat, P) N(y; H u, R) has mean x0_hat + P H^T (H P H^T + R)^{-1} (y - H x0_hat) and
    covariance A^{-1}, A = P^{-1} + H^T R^{-1} H."""
    from csf_jax.guidance import kalman_tweedie

    rng = np.random.default_rng(0)
    d, m, r = 4, 3, 0.3
    H = rng.standard_normal((m, d))
    S = rng.standard_normal((d, d))
    P = S @ S.T + 0.5 * np.eye(d)
    y = rng.standard_normal(m)
    x0_hat = rng.standard_normal((5, d))
    loglik = lambda u: -0.5 * jnp.sum((y - H @ u) ** 2) / r ** 2
    u, chol = kalman_tweedie(jnp.asarray(x0_hat), jnp.asarray(np.linalg.inv(P)), loglik,
                             lambda u: jnp.asarray(H) @ u, lambda u: jnp.full((m,), 1.0 / r ** 2),
                             jnp.asarray(x0_hat), 1.0,
                             iterations=1)
    gain = P @ H.T @ np.linalg.inv(H @ P @ H.T + r ** 2 * np.eye(m))
    expected = x0_hat + (y - x0_hat @ H.T) @ gain.T
    np.testing.assert_allclose(u, expected, rtol=1e-9, atol=1e-10)
    a = np.linalg.inv(P) + H.T @ H / r ** 2
    np.testing.assert_allclose(np.asarray(chol[0]) @ np.asarray(chol[0]).T, a, rtol=1e-9)
    # guide = 0: no observation, u = x0_hat and A = P^{-1}
    u0, chol0 = kalman_tweedie(jnp.asarray(x0_hat), jnp.asarray(np.linalg.inv(P)), loglik,
                               lambda u: jnp.asarray(H) @ u,
                               lambda u: jnp.full((m,), 1.0 / r ** 2), jnp.asarray(x0_hat), 0.0,
                               iterations=2)
    np.testing.assert_allclose(u0, x0_hat, atol=1e-12)


def test_curvature_weights_are_the_reweighted_least_squares_weights(x64):
    """Gaussian: the constant 1/std^2. Cauchy: ``-(d log p / dr) / r`` (checked by autodiff)."""
    from csf_jax.ssm import cauchy_noise, gaussian_noise

    r = jnp.asarray([-3.0, -0.2, 0.01, 0.5, 40.0])
    np.testing.assert_allclose(gaussian_noise(0.1).curvature(r), 100.0, rtol=1e-12)
    noise = cauchy_noise(0.0544)
    expected = -jax.grad(noise.log_prob)(r) / r
    np.testing.assert_allclose(noise.curvature(r), expected, rtol=1e-10)


def test_cauchy_guidance_reaches_the_posterior_mode_with_reweighted_curvature(x64):
    """Broad prior N(0, 1), identity sensor, Cauchy(0.0544) noise, y = 1: the posterior mode (found
    on a grid) is 0.9985. Gauss-Newton with the reweighted curvature gets there in 5 steps; with the
    Fisher information as a fixed curvature (170x the prior's) the steps are tiny far from the mode
    and the iterate is still near the prior after 20."""
    from csf_jax.guidance import kalman_tweedie
    from csf_jax.ssm import cauchy_noise

    noise = cauchy_noise(0.0544)
    y = jnp.asarray([1.0])
    x0_hat = jnp.zeros((1, 1))
    grid = np.linspace(-1.0, 2.0, 3_000_001)
    mode = grid[np.argmax(-0.5 * grid ** 2 - np.log1p(((1.0 - grid) / 0.0544) ** 2))]
    solve = lambda weight_fn, n: float(kalman_tweedie(
        x0_hat, jnp.eye(1), lambda u: noise.log_prob(y - u), lambda u: u, weight_fn, x0_hat, 1.0,
        iterations=n)[0][0, 0])
    assert abs(solve(lambda u: noise.curvature(y - u), 5) - mode) < 1e-5
    assert solve(lambda u: jnp.full((1,), noise.fisher_information), 20) < 0.5


def test_kalman_is_the_default_and_iterations_are_checked():
    assert GuidanceConfig().mode == "kalman"
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="iterations"):
            GuidanceConfig(iterations=bad)


def _cauchy_posterior_draws(df, proposals, n=20000):
    """Resampled draws of ``N(x; 0.5, 0.3^2) Cauchy(y - x^3; 0.0544)`` (y = 0.6 + a 4-scale
    outlier) from Laplace candidates at the mode, and the posterior's mean and std on a grid."""
    from csf_jax.guidance import kalman_tweedie, resample_posterior
    from csf_jax.ssm import cauchy_noise

    noise = cauchy_noise(0.0544)
    y = jnp.asarray([0.6 ** 3 + 4 * 0.0544])
    loglik = lambda u: noise.log_prob(y - u ** 3)
    prec = jnp.eye(1) / 0.3 ** 2
    x0_hat = jnp.full((n, 1), 0.5)
    u, chol = kalman_tweedie(x0_hat, prec, loglik, lambda u: u ** 3,
                             lambda u: noise.curvature(y - u ** 3), x0_hat, 1.0, iterations=8)
    draws = resample_posterior(jax.random.key(0), x0_hat, prec, u, chol, loglik, 1.0, proposals,
                               df)
    grid = np.linspace(-3.0, 4.0, 700001)
    logp = -0.5 * ((grid - 0.5) / 0.3) ** 2 - np.log1p(((float(y[0]) - grid ** 3) / 0.0544) ** 2)
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = float((w * grid).sum())
    return np.asarray(draws[:, 0]), mean, float(np.sqrt((w * (grid - mean) ** 2).sum()))


def test_heavy_tailed_proposals_reach_the_tails_of_a_cauchy_posterior(x64):
    """One coordinate, a prior N(0.5, 0.3^2), the cubic sensor with Cauchy noise and an outlying
    observation: the posterior has a sharp peak and heavy tails. Gaussian Laplace candidates
    (K = 8) miss the tails: the draws' std is well below the posterior's. Student-t candidates with
    one degree of freedom (K = 32) recover mean and std to a few percent."""
    gauss, mean, std = _cauchy_posterior_draws(None, 8)
    t1, _, _ = _cauchy_posterior_draws(1, 32)
    assert gauss.std() < 0.8 * std
    assert abs(t1.std() - std) < 0.06 * std and abs(t1.mean() - mean) < 0.05 * std


def test_proposal_df_is_checked():
    assert GuidanceConfig().proposal_df is None
    GuidanceConfig(proposal_df=1)
    for bad in (0, -1, 1.0, float("inf"), float("nan"), True, "1"):
        with pytest.raises(ValueError, match="proposal_df"):
            GuidanceConfig(proposal_df=bad)


def test_student_t_draws_have_the_t_quantiles():
    """``student_t`` with 1 and 3 degrees of freedom: empirical quantiles of 200000 draws against
    the closed-form ones (Cauchy: tan(pi (p - 1/2)); t_3 at p = 0.9, 0.975: 1.6377, 3.1824)."""
    from csf_jax.guidance import student_t

    p = np.array([0.75, 0.9, 0.975])
    z1 = np.asarray(student_t(jax.random.key(1), 1, (200000,), jnp.float32))
    np.testing.assert_allclose(np.quantile(z1, p), np.tan(np.pi * (p - 0.5)), rtol=0.03)
    z3 = np.asarray(student_t(jax.random.key(2), 3, (200000,), jnp.float32))
    np.testing.assert_allclose(np.quantile(z3, [0.9, 0.975]), [1.6377, 3.1824], rtol=0.03)


def test_quadratic_along_is_the_quadratic_form_at_each_fraction(x64):
    """The line searches' closed form against the form evaluated at each point, for a symmetric
    matrix and for the identity (None)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((5, 5))
    m = a @ a.T + np.eye(5)
    p, v = rng.standard_normal(5), rng.standard_normal(5)
    fractions = np.asarray(guidance.DAMPING)
    want = np.array([(p + f * v) @ m @ (p + f * v) for f in fractions])
    np.testing.assert_allclose(guidance.quadratic_along(m, p, v, fractions), want, rtol=1e-12)
    want = np.array([(p + f * v) @ (p + f * v) for f in fractions])
    np.testing.assert_allclose(guidance.quadratic_along(None, p, v, fractions), want, rtol=1e-12)


def test_particle_map_in_blocks_is_the_vmap(x64, monkeypatch):
    """Blocks of particles (with a remainder) give each particle's own result."""
    monkeypatch.setattr(guidance, "PARTICLE_BLOCK", 4)
    xs = (jnp.arange(22.0).reshape(11, 2), jnp.ones((11, 2, 2)))
    fn = lambda x: (x[1] @ x[0], jnp.sum(x[0] ** 2))
    got = guidance.particle_map(fn, xs)
    want = jax.vmap(fn)(xs)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert "while" in jax.jit(lambda xs: guidance.particle_map(fn, xs)).lower(xs).as_text()
