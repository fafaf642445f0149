"""Every problem through the main job: ``python -m experiments.run <problem> --quick`` runs CSF
(shipped pretrained prior), SF, EnKF and PF and writes ``results.json`` and the figures; plus CSF
with the exact mixture prior, and the main job's resumption from its cache."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import CSFConfig, problems
from csf_jax.pretrained import MODEL_FOR
from experiments import run

# The cubic problems take 13-53 s each here (mostly compiling the d x d linear algebra of the
# sampler); the default run keeps the 1-D and 5-D problems, ``-m slow`` runs the cubic ones. The
# quick main job (CSF, SF, EnKF, PF and figures: 16-31 s a problem) runs under ``-m slow``; the
# default run keeps its interrupted-and-resumed form below.
FAST = ("double_well", "triple_well", "cauchy")
EVERY_PROBLEM = [n if n in FAST else pytest.param(n, marks=pytest.mark.slow) for n in problems.NAMES]
MAIN_JOB = [pytest.param(n, marks=pytest.mark.slow) for n in problems.NAMES]

RESULT_KEYS = {"problem", "config", "rmse", "rmse_per_dim", "seconds_per_step", "compile_seconds",
               "machine", "versions", "rmse_per_run", "rmse_over_time", "rmse_before_shock",
               "rmse_after_shock", "runs_used", "shock_steps"}


@pytest.mark.parametrize("name", MAIN_JOB)
def test_quick_main_job(name, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    run.main([name, "--quick", "--out", str(tmp_path), "--no-progress"])
    with open(tmp_path / "results.json") as f:
        res = json.load(f)
    assert RESULT_KEYS <= set(res)
    assert res["problem"] == name and res["config"]["csf_model"] == MODEL_FOR[name]
    K = run.QUICK["num_steps"]
    for m in run.METHODS:
        runs = min(run.QUICK["runs"], run.CPU_SF_RUNS) if m == "sf" else run.QUICK["runs"]
        assert res["runs_used"][m] == runs  # SF: the CPU default (this suite runs on a CPU)
        assert len(res["rmse_per_run"][m]) == runs
        assert len(res["rmse_over_time"][m]) == K
        assert res["rmse"][m] >= res["rmse_per_dim"][m] > 0  # finite, positive
        assert res["seconds_per_step"][m] > 0
    assert res["rmse_ratio"]["reference"] == 1.0
    assert res["rmse_ratio"]["pf"] == pytest.approx(res["rmse"]["pf"] / res["rmse"]["reference"])
    model = problems.get(name)
    expected = {"estimates.png", "rmse_over_time.png"} | ({"prior.png"} if model.dim == 1 else set())
    assert expected <= set(os.listdir(tmp_path))
    assert "| CSF |" in capsys.readouterr().out


@pytest.mark.parametrize("name", EVERY_PROBLEM)
def test_exact_prior_csf_runs(name):
    """CSF with the exact mixture prior (no network) on every problem (random-init networks are
    tested in test_csf.py)."""
    model = problems.get(name, num_steps=4)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 32)
    r = csf_jax.filter(None, obs, ens, problem=model, key=jax.random.key(2),
                       config=CSFConfig(reverse_steps=50))
    assert r.mean.shape == (4, model.dim)
    assert bool(jnp.isfinite(r.mean).all())


def test_interrupted_main_job_resumes_from_cache(tmp_path):
    """Finished batches of runs are cached; a second call reuses them (the file is untouched) and
    recomputes only the missing one, to the same numbers."""
    kw = dict(methods=("csf", "enkf"), runs=2, particles=32, steps=10, num_steps=4, batch=1,
              out=str(tmp_path), progress=False, figures=False)
    first = run.run("double_well", **kw)
    cache = tmp_path / "cache"
    csf_files = sorted(c for c in os.listdir(cache) if c.startswith("csf-"))
    assert len(csf_files) == 2
    kept, lost = cache / csf_files[0], cache / csf_files[1]
    stamp = os.stat(kept).st_mtime_ns
    os.remove(lost)  # as if killed during the second batch
    again = run.run("double_well", **kw)
    assert again["rmse"] == first["rmse"]
    assert os.stat(kept).st_mtime_ns == stamp and lost.exists()


SPREAD = r"""
import json, os, sys
os.environ.pop("XLA_FLAGS", None)
from experiments import run  # sets one XLA host device per core before importing jax
import jax
assert jax.local_device_count() == (os.cpu_count() or 1), jax.local_device_count()
out = sys.argv[1]
kw = dict(methods=("csf", "sf"), runs=2, particles=32, steps=10, num_steps=4, progress=False,
          figures=False, sf=run.QUICK_SF)
spread = run.run("double_well", batch=2, out=os.path.join(out, "a"), **kw)
alone = run.run("double_well", batch=1, out=os.path.join(out, "b"), **kw)
json.dump({"spread": spread["rmse_per_run"], "alone": alone["rmse_per_run"],
           "devices": jax.local_device_count()}, sys.stdout)
"""


@pytest.mark.slow  # a fresh process and its compilations: run with -m slow
def test_runs_spread_over_host_devices_change_nothing_but_time(tmp_path):
    """The main job spreads a batch of CSF/SF runs over one XLA host device per core; every run's
    numbers equal those of the same run alone up to float rounding (runs are independent; only the
    wall clock differs).
    A batch's cache is one file per run, so a later job with another batch size reuses it."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", SPREAD, str(tmp_path)], capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout)
    np.testing.assert_allclose(got["spread"]["csf"], got["alone"]["csf"], rtol=1e-5)
    # SF's online Adam training amplifies float rounding (other matmul shapes): measured 5e-4.
    np.testing.assert_allclose(got["spread"]["sf"], got["alone"]["sf"], rtol=5e-3)
    files = sorted(os.listdir(tmp_path / "a" / "cache"))
    assert [f.split("-")[:3] for f in files if f.startswith("csf-")] == [["csf", "0", "1"],
                                                                         ["csf", "1", "2"]]
    stamps = {f: os.stat(tmp_path / "a" / "cache" / f).st_mtime_ns for f in files}
    kw = dict(methods=("csf",), runs=2, particles=32, steps=10, num_steps=4, progress=False,
              figures=False, out=str(tmp_path / "a"))
    again = run.run("double_well", batch=1, **kw)
    np.testing.assert_allclose(again["rmse_per_run"]["csf"], got["spread"]["csf"], rtol=1e-6)
    assert {f: os.stat(tmp_path / "a" / "cache" / f).st_mtime_ns for f in files} == stamps


@pytest.mark.slow  # a fresh process and its compilations: run with -m slow
def test_cli_runs_sf_on_fewer_runs_on_cpu_and_says_so(capsys):
    """On a CPU the CLI's default SF runs are the first CPU_SF_RUNS runs (its online training is
    the slow column); the table marks the row and stderr says how to get all."""
    assert jax.default_backend() == "cpu"
    run.main(["double_well", "--quick", "--runs", "3", "--methods", "csf,sf", "--no-progress"])
    out = capsys.readouterr()
    assert f"| SF | {run.CPU_SF_RUNS} |" in out.out and "| CSF | 3 |" in out.out
    assert f"SF ran on {run.CPU_SF_RUNS} of 3 runs" in out.err
    run.main(["double_well", "--quick", "--runs", "3", "--methods", "sf", "--sf-runs", "3",
              "--no-progress"])
    assert "| SF | 3 |" in capsys.readouterr().out


def test_table_configs_and_sf_shards():
    """The tables' CSF config: the defaults with the problem's ``CSF_OVERRIDES`` (Cauchy's
    heavy-tailed proposals), ``--steps``/``--guidance`` on top; SF's sampler keeps the base
    inflation its cached runs were made with (``SF_SAMPLER_BASE``; the triple well's is CSF's); one SF
    run is split over the host devices only when there are several (here one: this process
    started jax with one device)."""
    assert run.csf_config("double_well") == CSFConfig()
    cauchy = run.csf_config("cauchy", 7, "clipped")
    assert (cauchy.guidance.proposal_df, cauchy.guidance.proposals) == (1, 32)
    assert (cauchy.reverse_steps, cauchy.guidance.mode) == (7, "clipped")
    assert run.sf_sampler_config("double_well").prior_inflation == 0.2 != \
        CSFConfig().prior_inflation
    tw = run.sf_sampler_config("triple_well", 7, "clipped")
    assert tw == run.csf_config("triple_well", 7, "clipped")
    sf = csf_jax.SFConfig()
    assert run.sf_shards(2, sf) == 1
    assert run.sf_shards(1, sf) == (1 if jax.local_device_count() == 1 else
                                    max(k for k in range(1, jax.local_device_count() + 1)
                                        if sf.batch % k == 0))


def test_cache_idents_follow_what_each_method_depends_on():
    """A cached run is reused only for the config it was made with: CSF and CSF-G follow CSF's
    config, SF its own sampler's, and EnKF neither."""
    cfg = {"problem": {"dim": 1}, "particles": 10, "seed": 0, "csf_prior": "pretrained",
           "csf_model_id": "m", "sf": {"lr": 1.0},
           "csf": dataclasses.asdict(CSFConfig()),
           "sf_sampler": dataclasses.asdict(run.sf_sampler_config("double_well"))}
    moved = cfg | {"csf": dataclasses.asdict(CSFConfig(prior_inflation=0.5))}
    ident = lambda m, c: run.method_ident(m, "double_well", c, run.REFERENCE)
    for m in ("csf", "csf_gaussian"):
        assert ident(m, cfg) != ident(m, moved)
    for m in ("sf", "enkf", "reference"):
        assert ident(m, cfg) == ident(m, moved)
    assert ident("sf", cfg) != ident("sf", cfg | {"sf_sampler": cfg["csf"]})
