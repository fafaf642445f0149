"""Every problem through the main job (``python -m experiments.run <problem> --quick``: the
shipped prior, SF, EnKF, PF, the reference and the figures), and CSF with the exact mixture prior
on every problem."""

import jax
import jax.numpy as jnp
import pytest

import csf_jax
from csf_jax import CSFConfig, SamplerConfig, problems
from experiments import harness, run

# The cubic problems take 13-53 s each here (mostly compiling the d x d linear algebra of the
# sampler); the default run keeps the 1-D and 5-D problems, ``-m slow`` runs the cubic ones. The
# quick main job runs under ``-m slow`` (tests/test_cli.py runs it on the double well).
FAST = ("double_well", "triple_well", "cauchy")
EVERY_PROBLEM = [n if n in FAST else pytest.param(n, marks=pytest.mark.slow) for n in problems.NAMES]


@pytest.mark.slow
@pytest.mark.parametrize("name", problems.NAMES)
def test_quick_main_job(name, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    run.main([name, "--quick", "--out", str(tmp_path), "--cache", str(tmp_path / "cache"),
              "--no-progress"])
    record = harness.read_results(tmp_path / "results.json")
    rows = {r["entry"]: r for r in record["rows"]}
    assert set(rows) == set(run.LABELS)
    for label, row in rows.items():
        assert row["rmse"] >= row["rmse_per_dim"] > 0 and row["diverged"] == 0, label
        assert len(row["rmse_per_run"]) == row["runs"]
    assert rows["Ref."]["rmse_ratio"] == 1.0
    expected = {"estimates.png", "rmse_over_time.png"}
    assert expected <= {p.name for p in tmp_path.glob("*.png")}
    assert "| CSF |" in capsys.readouterr().out


@pytest.mark.parametrize("name", EVERY_PROBLEM)
def test_exact_prior_csf_runs(name):
    """CSF with the exact mixture prior (no network) on every problem (random-init networks are
    tested in test_csf.py)."""
    model = problems.get(name, num_steps=4)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 32)
    r = csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(2),
                       config=CSFConfig(sampler=SamplerConfig(reverse_steps=50)))
    assert r.mean.shape == (4, model.dim)
    assert bool(jnp.isfinite(r.mean).all())
