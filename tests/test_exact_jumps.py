"""``experiments.exact_jumps``: the grid filter is the exact filter (the Kalman filter's means on
a linear-Gaussian model), and a jump law lets it follow a jump the model without one cannot."""

import jax
import numpy as np

import csf_jax
from csf_jax.problems.linear import linear_gaussian, to_model
from experiments import exact_jumps, harness

GRID = (-6.0, 6.0, 2001)


def test_the_grid_filter_is_the_kalman_filter_on_a_linear_gaussian_model():
    lg = linear_gaussian(dim=1, A=[[0.9]], q_std=0.3, r_std=0.5, m0=[1.0], p0_std=0.7,
                         num_steps=30)
    model = to_model(lg)
    _, obs = csf_jax.simulate(model, jax.random.key(3))
    kalman = np.asarray(csf_jax.kalman_filter(obs, model=lg).mean[:, 0])
    with jax.enable_x64(True):
        grid = np.asarray(exact_jumps.grid_filter(model, np.asarray(obs, np.float64), 0.0,
                                                  exact_jumps.initial_density(model, GRID),
                                                  grid=GRID))
    np.testing.assert_allclose(grid, kalman, atol=5e-3)
    assert not np.allclose(grid[:5], np.asarray(obs)[:5, 0], atol=0.05)  # a filter, not the data


def test_a_jump_law_follows_the_triple_wells_jump():
    case = harness.Case("triple_well", runs=4, particles=100, seed=7)
    data = harness.simulate(case)
    model, truth = case.model, np.asarray(data.truth)[:, 1:, 0]
    p0 = exact_jumps.initial_density(model)
    rmse = {}
    for hazard in (0.0, 0.01):
        with jax.enable_x64(True):
            mean = np.stack([np.asarray(exact_jumps.grid_filter(model, np.asarray(o, np.float64),
                                                                hazard, p0))
                             for o in np.asarray(data.obs)])
        rmse[hazard] = float(np.sqrt(np.mean((mean - truth) ** 2)))
    assert rmse[0.01] < 0.5 * rmse[0.0], rmse
