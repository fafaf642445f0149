"""Calls a user makes that once went wrong without a word: saving a prior over a folder of one's
own, a shipped prior on a model with other dynamics, a simulation that diverged, and a CSF run on
a state too large for its dense prior. Each ends in a correct result or one line saying what to
do."""

import dataclasses
import json
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import problems, trained
from csf_jax.filters import csf as csf_mod
from csf_jax.filters import driver
from csf_jax.guidance import GuidanceConfig
from csf_jax.pretrained import load_pretrained


def _one_line(caught) -> str:
    text = str(caught.value)
    assert "\n" not in text, text
    return text


# --- saving never deletes what a save did not write ----------------------------------------------


@pytest.fixture(scope="module")
def shipped():
    return load_pretrained("double_well")


def test_save_refuses_a_params_folder_of_the_users_and_keeps_its_files(shipped, tmp_path):
    run = tmp_path / "myrun"
    os.makedirs(run / "params")
    (run / "params" / "notes.txt").write_text("x")
    with pytest.raises(FileExistsError) as caught:
        shipped.save(str(run))
    text = _one_line(caught)
    assert str(run / "params") in text and "notes.txt" in text, text
    assert text.endswith("choose an empty or new folder"), text
    assert (run / "params" / "notes.txt").read_text() == "x"
    assert not (run / "meta.json").exists()


def test_save_refuses_a_meta_json_of_the_users(shipped, tmp_path):
    (tmp_path / "meta.json").write_text(json.dumps({"mine": 1}))
    with pytest.raises(FileExistsError, match="meta.json is not a csf_jax prior's record"):
        shipped.save(str(tmp_path))
    assert json.loads((tmp_path / "meta.json").read_text()) == {"mine": 1}


def test_save_into_a_folder_of_other_files_adds_its_own_and_touches_nothing_else(shipped,
                                                                                 tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "table.csv").write_text("1,2")
    path = shipped.save(str(tmp_path))
    assert (tmp_path / "notes.txt").read_text() == "x"
    assert (tmp_path / "data" / "table.csv").read_text() == "1,2"
    back = csf_jax.load_prior(path, problems.get("double_well"))
    assert back.network == shipped.network


def test_save_replaces_a_prior_saved_there_but_not_a_stray_file_in_it(shipped, tmp_path):
    folder = str(tmp_path / "prior")
    shipped.save(folder)
    shipped.save(folder)  # a prior's own folder is replaced
    csf_jax.load_prior(folder, problems.get("double_well"))
    stray = tmp_path / "prior" / "params" / "notes.txt"
    stray.write_text("x")
    with pytest.raises(FileExistsError, match="holds files orbax did not write \\(notes.txt\\)"):
        shipped.save(folder)
    assert stray.read_text() == "x"


# --- a shipped prior carries its model's fingerprint ---------------------------------------------


def test_a_shipped_prior_is_refused_for_a_model_with_other_dynamics_naming_them():
    prior = load_pretrained("cubic10_indep")
    assert prior.meta["model"]["name"] == "cubic10_indep"
    other = problems.get("cubic10_indep", x0_mean=3., process_std=1., obs_scale=1.)
    ens = other.initial_ensemble(jax.random.key(1), 8)
    with pytest.raises(ValueError) as caught:
        csf_jax.filter(prior, jnp.zeros((2, other.obs_dim)), ens, model=other,
                       key=jax.random.key(0))
    text = _one_line(caught)
    for part in ("another model named 'cubic10_indep'", "process_noise: trained {'std': 0.1}, "
                 "given {'std': 1.0}", "'gaussian_std': 1.0", "initial ensemble differs",
                 "csf_jax.train_prior"):
        assert part in text, text
    with pytest.raises(ValueError, match="its drift differs at the probe points"):
        trained.unpack(prior, problems.get("cubic10_indep", dt=0.02), None)


@pytest.mark.parametrize("name", problems.NAMES)
def test_every_shipped_prior_serves_its_problem_whatever_its_length(name):
    prior = load_pretrained(name)
    for model in (problems.get(name), problems.get(name, num_steps=7, shock_count=0)):
        params, network = trained.unpack(prior, model, None)
        assert params is prior.params and network == prior.network


# --- simulate says when the trajectory diverged --------------------------------------------------


def test_simulate_refuses_a_diverged_trajectory_and_returns_it_when_asked():
    model = problems.get("double_well", C=5.0, obs_std=1.0, num_steps=8)
    with pytest.raises(FloatingPointError) as caught:
        csf_jax.simulate(model, jax.random.key(0))
    text = _one_line(caught)
    assert text.startswith("simulate: model 'double_well' diverged: the observation y_8 is not "
                           "finite (step 8 of 8"), text
    assert "smaller dt" in text and "check_finite=False" in text, text
    truth, obs = csf_jax.simulate(model, jax.random.key(0), check_finite=False)
    assert not np.isfinite(np.asarray(obs)).all() and truth.shape == (9, 1)
    # traced: nothing to raise, the values come back as they are
    _, traced = jax.jit(lambda k: csf_jax.simulate(model, k))(jax.random.key(0))
    assert not np.isfinite(np.asarray(traced)).all()
    # a stable model is untouched
    truth, obs = csf_jax.simulate(problems.get("double_well", num_steps=8), jax.random.key(0))
    assert np.isfinite(np.asarray(obs)).all()


# --- a CSF run on many dimensions warns before it starts -----------------------------------------


def _identity_model(dim: int) -> csf_jax.StateSpaceModel:
    return csf_jax.StateSpaceModel(
        name="wide", dim=dim, obs_dim=dim, num_steps=2, dt=1.0, drift=lambda x: x,
        observe=lambda x: x, process_std=0.1, obs_noise=csf_jax.gaussian_noise(1.0),
        initial_truth=lambda k: jnp.zeros(dim),
        initial_ensemble=lambda k, n: jax.random.normal(k, (n, dim)))


@pytest.mark.parametrize("config", [csf_jax.CSFConfig(), csf_jax.PAPER], ids=["default", "paper"])
def test_the_dense_prior_warns_past_the_large_dimension(config):
    d = csf_mod.LARGE_DIM + 1
    ens = jnp.zeros((20, d))
    prior = csf_mod._prior_for(None, None, None, config)
    with pytest.warns(RuntimeWarning) as caught:
        csf_mod.warn_if_large(_identity_model(d), config, prior, ens)
    text = str(caught[0].message)
    assert "\n" not in text and text.startswith(f"csf_jax.filter: d={d} state dimensions (N=20)")
    for part in ("d^3", "csf_jax.local_transform_filter", "csf_jax.letkf", "progress=print"):
        assert part in text, text
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        csf_mod.warn_if_large(_identity_model(csf_mod.LARGE_DIM), config, prior, ens)


def test_the_exact_mixture_under_a_dps_mode_does_not_warn():
    config = dataclasses.replace(csf_jax.PAPER, sampler=dataclasses.replace(
        csf_jax.PAPER.sampler, guidance=GuidanceConfig(mode="clipped")))
    prior = csf_mod._prior_for(None, None, None, config)
    assert prior.name == "exact_mixture"
    d = csf_mod.LARGE_DIM + 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        csf_mod.warn_if_large(_identity_model(d), config, prior, jnp.zeros((20, d)))


class _Stop(Exception):
    """Ends a call right after its model-specific checks (so nothing is compiled)."""


@pytest.mark.parametrize("call", ["filter", "methods"])
def test_a_large_csf_call_warns_at_the_users_line_before_compiling(call, monkeypatch):
    """The warning comes from the call's checks, before any compilation; the driver's next check
    is replaced by a stop, since a run at this size would take minutes."""
    def stop(*args, **kwargs):
        raise _Stop

    monkeypatch.setattr(driver, "check_model", stop)
    model = _identity_model(csf_mod.LARGE_DIM + 100)
    obs, ens = jnp.zeros((2, model.obs_dim)), jnp.zeros((20, model.dim))
    with pytest.warns(RuntimeWarning, match="d=300 state dimensions") as seen:
        with pytest.raises(_Stop):
            if call == "filter":
                csf_jax.filter(None, obs, ens, model=model, key=jax.random.key(0))
            else:
                csf_jax.run(csf_jax.methods.csf(), obs, ens, model=model, key=jax.random.key(0))
    assert [w.filename for w in seen] == [__file__]
