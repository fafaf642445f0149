"""Lorenz-96 (dynamics, sensors, initial state) and the LETKF (closed-form analysis, localisation,
gaps, the standard setup's published accuracy)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import problems
from csf_jax.filters.letkf import (
    LETKFConfig,
    Localization,
    gaspari_cohn,
    letkf,
    letkf_analysis,
    local_obs,
    ring_localization,
)
from csf_jax.problems.linear import linear_gaussian, to_model
from csf_jax.problems.lorenz96 import Lorenz96Config, obs_sites, rk4_step, tendency


def test_tendency_matches_the_written_equation():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(7)
    want = np.array([(x[(i + 1) % 7] - x[i - 2]) * x[i - 1] - x[i] + 8.0 for i in range(7)])
    np.testing.assert_allclose(tendency(jnp.asarray(x), 8.0), want, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(tendency(jnp.full(7, 8.0), 8.0), 0.0, atol=1e-6)  # fixed point


def test_rk4_is_fourth_order(x64):
    x = jnp.asarray(np.random.default_rng(1).standard_normal(10) + 8.0)

    def run(h, n):
        return jax.lax.fori_loop(0, n, lambda i, x: rk4_step(x, h, 8.0), x)

    exact = run(0.05 / 64, 64)
    e1 = float(jnp.abs(run(0.05, 1) - exact).max())
    e2 = float(jnp.abs(run(0.025, 2) - exact).max())
    assert 10 < e1 / e2 < 40  # 2^4 = 16 for a fourth-order method


def test_configs_sensors_and_registry():
    model = problems.get("lorenz96")
    assert (model.dim, model.obs_dim, model.dt, model.process_std) == (40, 40, 0.05, 0.0)
    every = problems.get("lorenz96", dim=20, sensor="every", obs_every=4)
    assert every.obs_dim == 5 and list(obs_sites(problems.config("lorenz96", dim=20,
                                                                 sensor="every", obs_every=4))) \
        == [0, 4, 8, 12, 16]
    x = jnp.linspace(-3.0, 3.0, 20)
    np.testing.assert_allclose(every.observe(x), x[::4])
    arctan = problems.get("lorenz96_arctan")
    np.testing.assert_allclose(arctan.observe(jnp.ones(40)), np.full(40, np.pi / 4), rtol=1e-6)
    truth, obs = csf_jax.simulate(problems.get("lorenz96", num_steps=50, burn_in=10),
                                  jax.random.key(0))
    assert truth.shape == (51, 40) and bool(jnp.isfinite(truth).all())
    # the spun-up state is on the attractor: mean near 2.3, std near 3.6 (climatology)
    assert 1.0 < float(truth.mean()) < 3.5 and 2.5 < float(truth.std()) < 4.5
    with pytest.raises(ValueError, match="obs_every"):
        Lorenz96Config(dim=10, sensor="every", obs_every=3)
    with pytest.raises(ValueError, match="sensor"):
        Lorenz96Config(sensor="cubic")
    with pytest.raises(KeyError, match="lorenz96"):
        problems.get("lorenz69")


def test_gaspari_cohn_taper():
    r = np.linspace(0, 2.5, 251)
    g = gaspari_cohn(r)
    assert g[0] == 1.0 and np.all(g[r >= 2] == 0) and np.all(np.diff(g) <= 1e-12)
    np.testing.assert_allclose(gaspari_cohn([0.999999]), gaspari_cohn([1.000001]), atol=1e-5)
    np.testing.assert_allclose(gaspari_cohn([1.0]), 5 / 24, rtol=1e-12)


def test_letkf_without_localisation_is_the_ensemble_kalman_update(x64):
    """All sites and observations at one point: every taper is 1, and the analysis mean and
    covariance are the Kalman update of the forecast ensemble's sample mean and covariance."""
    lg = linear_gaussian(4, 3, r_std=0.7)
    model = to_model(lg)
    loc = Localization((0.0,) * 4, (0.0,) * 3, None)
    index, weight = local_obs(loc, 1.0)
    forecast = jnp.asarray(np.random.default_rng(2).standard_normal((30, 4)) + 1.0)
    y = jnp.array([0.5, -0.3, 1.2])
    post = letkf_analysis(forecast, y, model, jnp.asarray(index), weight)
    m, P = np.mean(forecast, 0), np.cov(np.asarray(forecast).T)
    H, R = lg.H, 0.49 * np.eye(3)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    np.testing.assert_allclose(post.mean(0), m + K @ (y - H @ m), rtol=1e-10)
    np.testing.assert_allclose(np.cov(np.asarray(post).T), (np.eye(4) - K @ H) @ P, rtol=1e-9,
                               atol=1e-12)


def test_letkf_localisation_and_gaps():
    """Observations only at site 0 of a 20-site ring, radius 2: sites 4 or more away keep their
    background; an unobserved (NaN) step leaves every site at its background."""
    model = problems.get("lorenz96", dim=20, sensor="every", obs_every=20)
    loc = ring_localization(20, obs_sites(problems.config("lorenz96", dim=20, sensor="every",
                                                          obs_every=20)))
    index, weight = local_obs(loc, 2.0)
    forecast = jnp.asarray(np.random.default_rng(3).standard_normal((16, 20)) + 2.0)
    post = letkf_analysis(forecast, jnp.array([5.0]), model, jnp.asarray(index), weight)
    far = [i for i in range(20) if min(i, 20 - i) >= 4]
    np.testing.assert_allclose(post[:, far], forecast[:, far], rtol=1e-5, atol=1e-5)
    assert float(jnp.abs(post[:, 0] - forecast[:, 0]).max()) > 0.1
    gap = letkf_analysis(forecast, jnp.array([jnp.nan]), model, jnp.asarray(index), weight)
    np.testing.assert_allclose(gap, forecast, rtol=1e-5, atol=1e-5)


def test_letkf_reaches_the_published_accuracy_on_the_standard_setup():
    """L96, d = 40, F = 8, dt = 0.05, R = I, N = 40: tuned LETKF (docs/lorenz96.md) about 0.19;
    published ETKF/LETKF figures with 40 members are 0.16-0.22. 600 steps, the first 200 left out."""
    cfg = problems.config("lorenz96", num_steps=600)
    model = problems.get("lorenz96", num_steps=600)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 40)
    r = letkf(obs, ens, model=model, key=jax.random.key(2),
              localization=ring_localization(40, obs_sites(cfg)),
              config=LETKFConfig(radius=10.0, inflation=1.02))
    rmse = float(jnp.sqrt(jnp.mean((r.mean - truth[1:]) ** 2, -1))[cfg.burn_in:].mean())
    assert rmse < 0.22, rmse


def test_letkf_refuses_mismatched_geometry():
    model = problems.get("lorenz96", dim=20)
    obs, ens = jnp.zeros((3, 20)), jnp.ones((8, 20))
    with pytest.raises(ValueError, match="localization has 40 sites"):
        letkf(obs, ens, model=model, key=jax.random.key(0),
              localization=ring_localization(40, range(40)))


def test_csf_with_a_rank_deficient_ensemble_stays_finite():
    """N = 20 < d = 40 in float32, the default CSF at L = 5: the ensemble's covariance is singular
    in float32, and with the floor at 1e-6 of its mean variance these five keys (of 40) ended in
    "became non-finite"; the precision's rounding floor (``prior.rounding_floor``) keeps every
    run finite and at the accuracy of the other keys."""
    model = problems.get("lorenz96", num_steps=5, burn_in=0)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 20)
    config = csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=5))
    for seed in (3, 7, 18, 23, 31):
        result = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(seed),
                                config=config)
        assert float(csf_jax.metrics.rmse_per_dim(result.mean, truth[1:])) < 1.4, seed


def test_the_robustness_block_and_figure_count_the_runs_caught(tmp_path):
    """``experiments.lorenz96_robustness`` renders a results record: a row's runs caught are its
    runs less its lost ones, in the spread table and in the settings table."""
    pytest.importorskip("matplotlib")
    from experiments import harness
    from experiments import lorenz96_robustness as rb

    grid = {label: {"radius": r, "inflation": i} for label, _, r, i in rb.setting_grid()}

    def row(setup, entry, sweep, spread, lost):
        return ({"setup": setup, "entry": entry, "sweep": sweep, "spread": spread, "runs": 10,
                 "lost": lost, "error_kept": 0.05 if lost < 10 else None}
                | grid.get(entry, {"radius": None, "inflation": None}))

    rows = [row(s, e, "spread", v, lost) for s in ("ensf_calm", "ensf")
            for lost, e in enumerate(("LETKF, defaults", "transform CSF, defaults", "EnSF"))
            for v in rb.SPREADS]
    rows += [row(s, e.label, "settings", None, 3) for s in ("ensf_calm", "ensf")
             for e in rb.setting_entries()]
    record = harness.results_record("lorenz96_robustness", "python -m x", rows, lost_above=1.0,
                                    floor=1.5)
    text = "\n".join(rb.page(record))
    assert "an error at most 1.0 or at most 1.5 times the least error" in text
    assert "| EnSF | 8/10 (0.05) | 8/10 (0.05) | 8/10 (0.05) | 8/10 (0.05) |" in text
    assert ("| with jumps | transform CSF, defaults | EnKF-N | 7/10 (0.05) | 7/10 (0.05) | "
            "7/10 (0.05) | 7/10 (0.05) | 7/10 (0.05) | 7/10 (0.05) |") in text
    assert "| without jumps | LETKF | 1.4 | 7/10 (0.05) | 7/10 (0.05) | 7/10 (0.05) | - |" in text
    rb.figure(record, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10_000


def test_a_run_is_lost_against_the_floor_of_the_starts_at_the_truth():
    """``experiments.lorenz96.lost_runs``: a run is lost when it diverged or its error exceeds
    both ``LOST`` and ``FLOOR`` times the least error of the rows started at the truth on that
    run (same N); without such rows, ``LOST`` alone; the kept error is over the other runs."""
    from experiments import lorenz96 as l96

    def row(start, errors, n=20):
        return {"case": {"start": start, "particles": n}, "window_rmse_per_run": errors}

    rows = [row("model", [0.5, 1.2, 2.0, float("inf")]),
            row("truth", [0.4, 1.0, 1.0, 0.5]),
            row("truth", [0.45, 0.9, 1.1, 0.6]),
            row("model", [0.5, 1.2, 2.0, 0.3], n=40)]
    got = l96.lost_runs(rows)
    # floors 0.4, 0.9, 1.0, 0.5: bounds 1.0, 1.35, 1.5, 1.0
    assert [r["lost"] for r in got] == [2, 0, 0, 2]
    assert got[0]["error_kept"] == pytest.approx(0.85)
    assert got[3]["error_kept"] == pytest.approx(0.4)
    assert rows[0].get("lost") is None                      # the input rows stay as they were

