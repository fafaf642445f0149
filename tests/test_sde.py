"""The VE SDE against its closed forms (float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax import sde


def test_marginal_std_closed_form(x64):
    t = jnp.linspace(0.0, 1.0, 11)
    s = 25.0
    expected = np.sqrt((s ** (2 * np.asarray(t)) - 1) / (2 * np.log(s)))
    np.testing.assert_allclose(sde.marginal_std(t, s), expected, rtol=1e-12, atol=1e-15)
    assert float(sde.marginal_std(1.0)) == pytest.approx(9.8452, abs=1e-4)


def test_variance_is_integral_of_g_squared(x64):
    """sigma_t^2 = int_0^t g(u)^2 du: check by the trapezoid rule on a fine grid."""
    u = jnp.linspace(0.0, 0.7, 200001)
    integral = jnp.trapezoid(sde.diffusion_sq(u), u)
    assert float(integral) == pytest.approx(float(sde.marginal_std(0.7) ** 2), rel=1e-9)


def test_forward_sde_marginals_match_sigma_t(x64):
    """Euler-Maruyama on dx = g(t) dw from x_0 = 0: Var(x_t) matches sigma_t^2 statistically."""
    n, steps, t_end = 20000, 400, 0.8
    dt = t_end / steps
    keys = jax.random.split(jax.random.key(0), steps)

    def step(x, inputs):
        t, k = inputs
        g = jnp.sqrt(sde.diffusion_sq(t + 0.5 * dt))  # midpoint g: O(dt^2) per step
        return x + g * jnp.sqrt(dt) * jax.random.normal(k, x.shape), None

    x, _ = jax.lax.scan(step, jnp.zeros(n), (jnp.arange(steps) * dt, keys))
    var_hat = float(jnp.var(x))
    var = float(sde.marginal_std(t_end) ** 2)
    # Sample variance of n Gaussians has relative std sqrt(2/n) = 1%; allow 4 sigma.
    assert abs(var_hat / var - 1.0) < 4 * np.sqrt(2.0 / n)


def test_perturb_uses_sigma_t(x64):
    x0 = jnp.ones((3, 2))
    z = jnp.full((3, 2), 2.0)
    t = jnp.array([0.1, 0.5, 1.0])
    out = sde.perturb(x0, z, t)
    np.testing.assert_allclose(out, np.broadcast_to(1.0 + 2.0 * sde.marginal_std(t)[:, None], (3, 2)), rtol=1e-12)


@pytest.mark.parametrize("t", [1e-3, 0.3, 1.0])
def test_tweedie_recovers_clean_mean_for_gaussian(x64, t):
    """x_0 ~ N(mu, v): E[x_0 | x_t] = mu + v / (v + sigma_t^2) (x_t - mu); Tweedie with the exact
    score -(x - mu) / (v + sigma_t^2) must give exactly that."""
    mu, v = jnp.array([0.5, -2.0]), jnp.array([0.3, 4.0])
    x_t = jnp.array([[1.0, 3.0], [-7.0, 0.2]])
    var_t = v + sde.marginal_std(t) ** 2
    score = -(x_t - mu) / var_t
    expected = mu + v / var_t * (x_t - mu)
    np.testing.assert_allclose(sde.tweedie(x_t, score, t), expected, rtol=1e-12, atol=1e-12)


def test_tweedie_is_the_mean_of_x0_given_xt(x64):
    """Monte Carlo: regress x_0 on x_t for Gaussian data; slope and intercept match Tweedie's."""
    key0, key1 = jax.random.split(jax.random.key(1))
    mu, v, t, n = 1.5, 0.5, 0.4, 200000
    x0 = mu + jnp.sqrt(v) * jax.random.normal(key0, (n,))
    xt = x0 + sde.marginal_std(t) * jax.random.normal(key1, (n,))
    slope = jnp.cov(x0, xt)[0, 1] / jnp.var(xt, ddof=1)
    expected = v / (v + sde.marginal_std(t) ** 2)
    assert float(slope) == pytest.approx(float(expected), abs=0.01)


def test_reverse_grid():
    grid = sde.reverse_grid(500)
    assert grid.times.shape == (500,) and grid.dt.shape == (500,)
    assert float(grid.times[0]) == pytest.approx(1.0) and float(grid.times[-1]) == pytest.approx(1e-3)
    np.testing.assert_allclose(grid.dt, (1.0 - 1e-3) / 499, rtol=1e-6)
    with pytest.raises(ValueError, match="num_steps"):
        sde.reverse_grid(1)


def test_time_of_std_inverts_marginal_std(x64):
    t = jnp.linspace(0.0, 1.0, 21)
    np.testing.assert_allclose(sde.time_of_std(sde.marginal_std(t, 25.0), 25.0), t, atol=1e-12)


@pytest.mark.parametrize("tau", [0.0, 0.3, 2.0])
def test_inflated_time_adds_variance(x64, tau):
    """sigma at the inflated time is sqrt(sigma_t^2 + tau^2): the prior convolved with N(0, tau^2)."""
    t = jnp.linspace(1e-3, 1.0, 11)
    got = sde.marginal_std(sde.inflated_time(t, tau, 25.0), 25.0)
    np.testing.assert_allclose(got, np.sqrt(np.asarray(sde.marginal_std(t, 25.0)) ** 2 + tau ** 2),
                               rtol=1e-12)


def test_noise_levels_are_geometric_and_end_at_zero():
    levels = sde.noise_levels(5, 8.0, 0.5)
    assert levels.shape == (6,) and levels[-1] == 0.0
    np.testing.assert_allclose(levels[:-1], [8.0, 4.0, 2.0, 1.0, 0.5])
    with pytest.raises(ValueError, match="sigma_start >= sigma_end > 0"):
        sde.noise_levels(5, 0.1, 0.5)


def test_bridge_keeps_the_ve_marginal(x64):
    """x_sigma = x0 + sigma z, then one bridge step with the true x0: x_sigma' ~ N(x0, sigma'^2),
    for any step size (rho^2 sigma^2 + v = sigma'^2)."""
    for sigma, nxt in [(9.8, 0.03), (2.0, 1.5), (1.0, 0.0)]:
        rho, v = sde.bridge(jnp.float64(sigma), jnp.float64(nxt))
        assert float(rho ** 2 * sigma ** 2 + v) == pytest.approx(nxt ** 2, abs=1e-12)
    rho, v = sde.bridge(jnp.float64(2.0), jnp.float64(0.0))
    assert float(rho) == 0.0 and float(v) == 0.0
