"""Tests of the linear-Gaussian problem and of the Kalman filter against numpy recursions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from csf_jax.filters.kalman import kalman_filter, kalman_filter_cov
from csf_jax.problems.linear import linear_gaussian, to_model


def numpy_kalman(obs, A, H, q_std, r_std, m0, p0_std):
    """Textbook Kalman recursion in float64 numpy: means (K, d) and covariances (K, d, d)."""
    d, m = A.shape[0], H.shape[0]
    mean, cov = np.array(m0, dtype=np.float64), p0_std**2 * np.eye(d)
    means, covs = [], []
    for y in np.asarray(obs, dtype=np.float64):
        mean = A @ mean
        cov = A @ cov @ A.T + q_std**2 * np.eye(d)
        S = H @ cov @ H.T + r_std**2 * np.eye(m)
        gain = cov @ H.T @ np.linalg.inv(S)
        mean = mean + gain @ (y - H @ mean)
        cov = (np.eye(d) - gain @ H) @ cov
        means.append(mean)
        covs.append(cov)
    return np.array(means), np.array(covs)


def test_scalar_kalman_matches_numpy(x64, linear_obs):
    """d = m = 1, x' = 0.9 x + v, y = 2 x + w: exact agreement to 1e-10 in float64."""
    lg = linear_gaussian(1, 1, A=[[0.9]], H=[[2.0]], q_std=0.3, r_std=0.5, m0=[0.5], p0_std=1.0,
                         num_steps=30)
    obs = linear_obs(lg, 0)
    mean, var = 0.5, 1.0
    ref_mean, ref_var = [], []
    for y in np.asarray(obs)[:, 0]:
        mean, var = 0.9 * mean, 0.81 * var + 0.09
        gain = 2.0 * var / (4.0 * var + 0.25)
        mean, var = mean + gain * (y - 2.0 * mean), (1.0 - 2.0 * gain) * var
        ref_mean.append(mean)
        ref_var.append(var)
    kf = kalman_filter(obs, model=lg)
    assert kf.mean.dtype == jnp.float64 and kf.mean.shape == (30, 1)
    assert kf.ensembles is None and kf.ess is None
    np.testing.assert_allclose(kf.mean[:, 0], ref_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(kf.std[:, 0], np.sqrt(ref_var), rtol=1e-10, atol=1e-10)


def test_kalman_matches_numpy_multivariate(x64, linear_obs):
    """d = 3, m = 2 with a dense H: means and covariances agree with numpy to 1e-10."""
    H = np.array([[1.0, 0.5, 0.0], [0.0, -0.3, 1.2]])
    lg = linear_gaussian(3, 2, H=H, q_std=0.2, r_std=0.4, p0_std=0.8, num_steps=25)
    obs = linear_obs(lg, 1)
    means, covs = kalman_filter_cov(obs, lg)
    ref_means, ref_covs = numpy_kalman(obs, lg.A, lg.H, lg.q_std, lg.r_std, lg.m0, lg.p0_std)
    np.testing.assert_allclose(means, ref_means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(covs, ref_covs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(covs, np.swapaxes(covs, -1, -2), atol=1e-14)
    assert np.all(np.linalg.eigvalsh(np.asarray(covs)) > 0)
    kf = kalman_filter(obs, model=lg)
    np.testing.assert_allclose(kf.std, np.sqrt(np.diagonal(ref_covs, axis1=1, axis2=2)),
                               rtol=1e-10)


def test_kalman_jit_vmap_float32(linear_obs):
    """Default float32: runs, and batching over runs with vmap equals separate calls."""
    lg = linear_gaussian(2, 2)
    obs = jnp.asarray(np.stack([linear_obs(lg, seed) for seed in range(3)]))
    batched = jax.jit(jax.vmap(lambda o: kalman_filter(o, model=lg)))(obs)
    assert batched.mean.dtype == jnp.float32 and batched.mean.shape == (3, 20, 2)
    for i in range(3):
        single = kalman_filter(obs[i], model=lg)
        np.testing.assert_allclose(batched.mean[i], single.mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(batched.std[i], single.std, rtol=1e-5, atol=1e-6)


def test_linear_gaussian_defaults():
    lg = linear_gaussian(4, 2)
    assert lg.A.shape == (4, 4) and lg.H.shape == (2, 4) and lg.m0.shape == (4,)
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(lg.A)), 0.95)
    np.testing.assert_array_equal(lg.H, np.eye(2, 4))
    assert (lg.dim, lg.obs_dim, lg.num_steps) == (4, 2, 20)
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(linear_gaussian(3).A)), 0.95)
    with pytest.raises(ValueError, match="A must have shape"):
        linear_gaussian(2, A=np.eye(3))
    with pytest.raises(ValueError, match="r_std"):
        linear_gaussian(2, r_std=0.0)


def test_to_model_is_cached_and_consistent():
    lg = linear_gaussian(3, 2)
    model = to_model(lg)
    assert to_model(lg) is model
    assert to_model(linear_gaussian(3, 2)) is model
    assert to_model(linear_gaussian(3, 2, r_std=0.7)) is not model
    hash(model)
    assert (model.dim, model.obs_dim, model.num_steps) == (3, 2, 20)
    assert model.process_std == lg.q_std and model.obs_noise.gaussian_std == lg.r_std
    x = jnp.array([0.3, -1.0, 2.0])
    np.testing.assert_allclose(model.drift(x), lg.A @ np.asarray(x), rtol=1e-6)
    np.testing.assert_allclose(model.observe(x), lg.H @ np.asarray(x), rtol=1e-6)
    assert model.initial_ensemble(jax.random.key(0), 5).shape == (5, 3)
    assert model.initial_truth(jax.random.key(0)).shape == (3,)


@pytest.mark.parametrize("obs, error, match", [
    (np.zeros((5, 3)), ValueError, "obs_dim"),
    (np.zeros((2, 5, 2)), ValueError, r"\(K, m\)"),
    (np.zeros((0, 2)), ValueError, "at least one"),
    (np.array([[0.0, 1.0], [np.inf, 0.0]]), ValueError, "infinite"),
    (np.zeros((5, 2), dtype=np.int32), TypeError, "floating"),
])
def test_kalman_bad_inputs(obs, error, match):
    with pytest.raises(error, match=match):
        kalman_filter(obs, model=linear_gaussian(2, 2))
