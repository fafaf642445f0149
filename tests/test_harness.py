"""The experiments' harness: cells cached by everything that changes a number, and only those
recomputed when something changes; resumable; one data and seeding convention; one schema."""

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

import csf_jax
from csf_jax import CSFConfig, SamplerConfig
from csf_jax.filters import csf as csf_module
from csf_jax.filters import enkf as enkf_module
from csf_jax.filters import pf as pf_module
from experiments import harness

CASE = harness.Case("double_well", settings=(("num_steps", 5),), runs=2, particles=20)
CHEAP = [harness.Entry("EnKF", "enkf"), harness.Entry("PF", "pf")]
CSF_G = harness.Entry("CSF-G", "csf", lambda case, model: {"prior": csf_jax.gaussian_prior()})


def _computed(cache):
    return sorted({label for _, label, _ in cache.computed})


def test_cells_are_cached_and_read_back(tmp_path):
    first = harness.run([CASE], CHEAP, harness.Cache(tmp_path), progress=False)
    cache = harness.Cache(tmp_path)
    again = harness.run([CASE], CHEAP, cache, progress=False)
    assert cache.computed == []
    for entry in CHEAP:
        np.testing.assert_array_equal(first[(CASE, entry.label)].means,
                                      again[(CASE, entry.label)].means)
    assert len(list((tmp_path / "double_well").glob("*.npz"))) == 4


def test_a_changed_default_recomputes_its_cells_and_only_those(tmp_path, monkeypatch):
    entries = CHEAP + [CSF_G]
    harness.run([CASE], entries, harness.Cache(tmp_path), progress=False)
    # the EnKF's default inflation and CSF's default config change: their cells, not the PF's
    monkeypatch.setattr(enkf_module.method, "__defaults__", (1.05,))
    defaults = dict(csf_module.method.__kwdefaults__)
    monkeypatch.setitem(csf_module.method.__kwdefaults__, "config",
                        CSFConfig(sampler=SamplerConfig(reverse_steps=4)))
    assert defaults["config"] != csf_module.method.__kwdefaults__["config"]
    cache = harness.Cache(tmp_path)
    harness.run([CASE], entries, cache, progress=False)
    assert _computed(cache) == ["CSF-G", "EnKF"]
    assert len(cache.computed) == 2 * CASE.runs


@pytest.fixture
def fresh_traces():
    """jax's caches cleared before and after the test (requested before ``monkeypatch``, so
    cleared after its patches are undone): a patched function is traced as a new process
    traces it, and no patch outlives the test in a cached trace."""
    jax.clear_caches()
    yield
    jax.clear_caches()


def test_changed_code_recomputes_the_filters_whose_program_it_changes(tmp_path, fresh_traces,
                                                                      monkeypatch):
    harness.run([CASE], CHEAP, harness.Cache(tmp_path), progress=False)
    original = pf_module.sir_step
    # the PF's step computes something else (its ensemble scaled by 1.0: another program)
    monkeypatch.setattr(pf_module, "sir_step",
                        lambda problem, key, ens, y: original(problem, key, ens * 1.0, y))
    jax.clear_caches()  # as a new process would trace it
    cache = harness.Cache(tmp_path)
    harness.run([CASE], CHEAP, cache, progress=False)
    assert _computed(cache) == ["PF"]


def test_an_edit_that_computes_the_same_program_recomputes_nothing(tmp_path, fresh_traces,
                                                                  monkeypatch):
    first = harness.run([CASE], CHEAP + [CSF_G], harness.Cache(tmp_path), progress=False)
    original = pf_module.sir_step
    # a refactoring: the same computation through another Python function
    monkeypatch.setattr(pf_module, "sir_step", lambda *args: original(*args))
    jax.clear_caches()
    cache = harness.Cache(tmp_path)
    again = harness.run([CASE], CHEAP + [CSF_G], cache, progress=False)
    assert cache.computed == []
    for entry in CHEAP + [CSF_G]:
        np.testing.assert_array_equal(first[(CASE, entry.label)].means,
                                      again[(CASE, entry.label)].means)


def test_the_program_digest_is_the_same_in_another_process():
    import subprocess
    import sys

    code = ("from experiments import harness; c = harness.Case('double_well', runs=1, "
            "particles=20); e = harness.Entry('CSF', 'csf'); m = c.model; "
            "print(harness.program_digest(c, e.build(c, m), m))")
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True, cwd=harness.ROOT, env={**os.environ, "PYTHONHASHSEED": seed})
            for seed in ("1", "2")]
    digests = [r.stdout.strip().splitlines()[-1] for r in runs]
    case = harness.Case("double_well", runs=1, particles=20)
    model = case.model
    assert digests[0] == digests[1] == harness.program_digest(
        case, harness.Entry("CSF", "csf").build(case, model), model)


def test_an_unreadable_cell_is_named_moved_aside_and_recomputed(tmp_path, capsys):
    harness.run([CASE], CHEAP[:1], harness.Cache(tmp_path), progress=False)
    path = sorted((tmp_path / "double_well").glob("*.npz"))[0]
    path.write_bytes(path.read_bytes()[:40])
    cache = harness.Cache(tmp_path)
    harness.run([CASE], CHEAP[:1], cache, progress=False)
    err = capsys.readouterr().err
    assert f"cache file {path} cannot be read" in err and "recomputing" in err
    assert len(cache.computed) == 1 and path.with_suffix(".damaged").exists()


def test_an_interrupted_run_keeps_its_finished_cells(tmp_path):
    def broken(case, model):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        harness.run([CASE], CHEAP + [harness.Entry("broken", "enkf", broken)],
                    harness.Cache(tmp_path), progress=False)
    cache = harness.Cache(tmp_path)
    harness.run([CASE], CHEAP, cache, progress=False)
    assert cache.computed == []


def test_a_run_does_not_depend_on_how_many_runs_there_are():
    three = harness.simulate(dataclasses.replace(CASE, runs=3))
    two = harness.simulate(CASE)
    second = harness.simulate(dataclasses.replace(CASE, runs=1, first_run=1))
    np.testing.assert_array_equal(three.truth[:2], two.truth)
    np.testing.assert_array_equal(np.asarray(three.ensembles[:2]), np.asarray(two.ensembles))
    np.testing.assert_array_equal(second.truth[0], two.truth[1])
    assert (jax.random.key_data(second.keys[0]) == jax.random.key_data(two.keys[1])).all()


def test_missing_data_and_outages_are_nan():
    case = harness.Case("double_well", settings=(("num_steps", 30),), runs=1, particles=5,
                        missing=0.3, outage=(10, 20))
    obs = np.asarray(harness.simulate(case).obs[0])
    assert np.isnan(obs[10:20]).all() and 0 < np.isnan(obs[:10]).sum() < 10


def test_results_files_have_one_schema(tmp_path):
    record = harness.write_results(tmp_path / "r.json", harness.results_record(
        "demo", "python -m experiments.demo", [{"case": {"problem": "x"}, "entry": "EnKF",
                                                "rmse": 1.0}]))
    back = harness.read_results(tmp_path / "r.json")
    assert back == json.loads(json.dumps(record))
    assert {"schema", "benchmark", "command", "date", "machine", "versions", "rows"} <= set(back)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="not a results file"):
        harness.read_results(tmp_path / "bad.json")


def test_summary_counts_diverged_runs_and_uses_the_metrics():
    data = harness.simulate(CASE)
    mean = np.asarray(data.truth[:, 1:]) + 0.1
    finite = np.ones(mean.shape[:2], bool)
    finite[1, 3:] = False
    outcome = harness.Outcome(mean, finite, 0.0, 0.0, 1, None)
    row = harness.summary(outcome, data, window=(1, 5))
    assert row["diverged"] == 1 and row["rmse"] == float("inf")
    assert row["rmse_per_run"][0] == pytest.approx(0.1, rel=1e-5)
    assert row["window_rmse_per_run"][0] == pytest.approx(0.1, rel=1e-5)


def test_any_registered_filter_joins_a_benchmark_by_name(tmp_path):
    import argparse

    entries = harness.extra_entries(argparse.Namespace(with_=["enkf", "letkf"]))
    assert [(e.label, e.method) for e in entries] == [("enkf", "enkf"), ("letkf", "letkf")]
    ring = harness.Case("lorenz96", (("dim", 8), ("num_steps", 3), ("burn_in", 0)), runs=1,
                        particles=10)
    method = entries[1].build(ring, ring.model)
    assert len(method.config.localization.state) == 8
    found = harness.run([ring], entries, harness.Cache(tmp_path), progress=False)
    assert all(o.finite.all() for o in found.values())
    with pytest.raises(ValueError, match="--with letkf: model 'bearings' is not a point sensor"):
        entries[1].build(CASE, csf_jax.problems.get("bearings"))
    p = harness.parser("demo", "a demo")
    assert p.parse_args(["--with", "ensf,pf"]).with_ == ["ensf", "pf"]
