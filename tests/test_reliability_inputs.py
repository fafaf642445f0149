"""Input reliability: every bad input below ends in a correct result or in one exception whose
one-line message names the cause (the argument or field, and the file or folder where one is
involved), never in a silently wrong result or a traceback from inside jax, orbax or numpy."""

import dataclasses
import gc
import glob
import json
import os
import re
import shutil
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import problems
from csf_jax.pretrained import MODEL_DIR, load_dir, load_pretrained
from csf_jax.problems.linear import linear_gaussian, to_model
from csf_jax.training import generate, train
from csf_jax.training.data import load
from csf_jax.training.fit import key_seed

DATA = csf_jax.DatasetConfig(trajectories=4, particles=16, keep=8, stride=2, chunk=4,
                             dtype="float32")
TRAIN = csf_jax.TrainConfig(steps=4, save_every=2, eval_every=2, batch_sets=2, targets_per_set=4,
                            set_sizes=(4,), valid_sets=2)
NET = csf_jax.NetworkConfig(base="gaussian", hidden=8, heads=2, blocks=1, code_dim=4,
                            score_hidden=8, score_layers=2, fourier_features=2)
KEY = jax.random.key(0)


def _one_line(caught) -> str:
    text = str(caught.value)
    assert "\n" not in text, text
    return text


def _model(name="tiny_lg", **kw):
    return to_model(linear_gaussian(2, 1, num_steps=4, name=name, **kw))


def _fit(directory, **kw):
    args = dict(directory=str(directory), dataset=DATA, config=TRAIN, network=NET, verbose=False)
    return csf_jax.train_prior(_model(), jax.random.key(3), **{**args, **kw})


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A finished tiny ``train_prior`` folder (data and checkpoints at steps 2 and 4)."""
    directory = tmp_path_factory.mktemp("fit")
    _fit(directory)
    return directory


@pytest.fixture
def run_copy(run_dir, tmp_path):
    """A copy of ``run_dir`` to damage."""
    directory = tmp_path / "run"
    shutil.copytree(run_dir, directory)
    return directory


def _truncate(path) -> None:
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


# --- 1, 16: keys ---------------------------------------------------------------------------------


@pytest.mark.parametrize("key,error,message", [
    (jax.random.split(KEY), ValueError, "train_prior: key must be a single key, got a batch"),
    (jax.random.split(jax.random.PRNGKey(0)), ValueError, "single key, got a batch of legacy"),
    (0, TypeError, "train_prior: key must be a jax.random.key"),
    (None, TypeError, "train_prior: key= is required"),
], ids=["split", "split-legacy", "int", "none"])
def test_train_prior_refuses_anything_but_one_key(key, error, message, tmp_path):
    with pytest.raises(error, match=message) as caught:
        csf_jax.train_prior(_model(), key, directory=str(tmp_path), verbose=False)
    _one_line(caught)
    assert not os.listdir(tmp_path)


def test_legacy_and_typed_keys_give_the_same_seed():
    assert key_seed(jax.random.PRNGKey(5)) == key_seed(jax.random.key(5)) == 5


# --- 2: non-finite training data -----------------------------------------------------------------


def test_a_drift_returning_nan_is_refused_before_any_work(tmp_path):
    bad = _model()._replace(drift=lambda x: x * jnp.nan)
    with pytest.raises(ValueError, match="its drift gives NaN/inf .*check the model's drift"):
        csf_jax.train_prior(bad, KEY, directory=str(tmp_path), dataset=DATA, verbose=False)


def test_rollouts_that_blow_up_are_refused_naming_the_drift(tmp_path):
    blowup = _model("blowup")._replace(drift=lambda x: jnp.where(jnp.abs(x) > 3.0, jnp.inf,
                                                                 3.0 * x))
    with pytest.raises(ValueError, match="rollouts .* contain NaN/inf .*check the model's "
                                         "drift") as caught:
        generate(blowup, DATA, str(tmp_path / "data"), verbose=False)
    _one_line(caught)


# --- 3: resuming with another training config ----------------------------------------------------


@pytest.mark.parametrize("change,field", [
    (dict(lr=1e-3), "train.lr: checkpoint has 0.002, requested 0.001"),
    (dict(batch_sets=3), "train.batch_sets: checkpoint has 2, requested 3"),
])
def test_resume_with_another_training_config_is_refused(run_copy, change, field):
    with pytest.raises(ValueError, match=f"{field}.*delete .*ckpt to train afresh") as caught:
        _fit(run_copy, config=dataclasses.replace(TRAIN, **change))
    assert str(run_copy / "ckpt") in _one_line(caught)


def test_resume_with_fewer_steps_is_refused(run_copy):
    with pytest.raises(ValueError, match="at step 4, beyond the requested steps=2; ask for "
                                         "steps >= 4 to continue it") as caught:
        _fit(run_copy, config=dataclasses.replace(TRAIN, steps=2))
    assert str(run_copy / "ckpt") in _one_line(caught)


@pytest.mark.slow
def test_resume_with_more_steps_continues(run_copy):
    longer = _fit(run_copy, config=dataclasses.replace(TRAIN, steps=6))
    assert [s for s, _ in longer.meta["valid_loss"]] == [2, 4, 6]
    assert longer.meta["train"]["steps"] == 6


# --- 4, 17: damaged data and run folders ---------------------------------------------------------


def test_truncated_ensembles_file_is_refused_naming_it(run_copy):
    path = run_copy / "data" / "ensembles.npy"
    _truncate(path)
    damaged = f"{re.escape(str(path))} is damaged or foreign"
    with pytest.raises(ValueError, match=damaged) as caught:
        _fit(run_copy)
    _one_line(caught)
    with pytest.raises(ValueError, match="is damaged or foreign"):
        load(str(run_copy / "data"))


def test_truncated_dataset_meta_is_refused_naming_it(run_copy):
    path = run_copy / "data" / "meta.json"
    _truncate(path)
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} cannot be read "
                                         f"\\(JSONDecodeError") as caught:
        _fit(run_copy)
    _one_line(caught)


def test_checkpoint_folder_replaced_by_a_file_is_refused_naming_it(run_copy):
    shutil.rmtree(run_copy / "ckpt")
    (run_copy / "ckpt").write_text("not a folder")
    ckpt = re.escape(str(run_copy / "ckpt"))
    with pytest.raises(NotADirectoryError, match=f"{ckpt} is a file") as caught:
        _fit(run_copy)
    _one_line(caught)


def test_one_trajectory_is_refused_by_the_dataset_config():
    with pytest.raises(ValueError, match="DatasetConfig.trajectories must be >= 2"):
        csf_jax.DatasetConfig(trajectories=1)


# --- 5, 17, 19: saving, and the prior's repr -----------------------------------------------------


@pytest.fixture(scope="module")
def shipped():
    return load_pretrained("double_well")


def test_save_refuses_an_empty_path_and_a_file(shipped, tmp_path):
    with pytest.raises(ValueError, match="TrainedPrior.save: the path is empty"):
        shipped.save("")
    target = tmp_path / "file"
    target.write_text("")
    with pytest.raises(NotADirectoryError, match=f"{re.escape(str(target))} is a file"):
        shipped.save(str(target))


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root ignores folder permissions")
def test_save_into_a_read_only_folder_names_it(shipped, tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(PermissionError, match=f"cannot write to {re.escape(str(folder))}"):
            shipped.save(str(folder))
    finally:
        folder.chmod(0o700)


def test_repr_is_short(shipped):
    text = repr(shipped)
    assert len(text) < 200, text
    assert text.startswith("TrainedPrior(problem='double_well', dim=1, "
                           "network=NetworkConfig(base='gaussian'), n_params=")


# --- 6, 7: what the CSF filter is given ----------------------------------------------------------


def _double_well(particles=16, steps=2):
    model = problems.get("double_well", num_steps=steps)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    return model, obs, model.initial_ensemble(jax.random.key(1), particles)


def test_a_trained_prior_with_another_prior_is_refused(shipped):
    model, obs, ens = _double_well()
    with pytest.raises(ValueError, match="both a trained prior .* prior='gaussian'"):
        csf_jax.filter(shipped, obs, ens, model=model, key=KEY,
                       prior=csf_jax.gaussian_prior())
    learned = csf_jax.learned_prior(NET, 16)
    with pytest.raises(ValueError, match="both a TrainedPrior and prior= given"):
        csf_jax.filter(shipped, obs, ens, model=model, key=KEY, prior=learned)


def test_raw_params_without_their_network_are_refused(shipped):
    model, obs, ens = _double_well()
    with pytest.raises(ValueError, match="raw params need network=") as caught:
        csf_jax.filter(shipped.params, obs, ens, model=model, key=KEY)
    _one_line(caught)


# --- 8: problem parameters -----------------------------------------------------------------------


@pytest.mark.parametrize("name,override,error,message", [
    ("lorenz96", dict(forcing=float("nan")), ValueError, "Lorenz96Config.forcing must be a finite"),
    ("lorenz96", dict(dim=4.5), TypeError, "Lorenz96Config.dim must be an int, got 4.5"),
    ("lorenz96", dict(sensor=3), TypeError, "Lorenz96Config.sensor must be a str"),
    ("double_well", dict(obs_std=float("inf")), ValueError, "WellConfig.obs_std must be a finite"),
    ("cubic10_indep", dict(dim=True), TypeError, "CubicConfig.dim must be an int"),
    ("pendulum", dict(dt=-0.1), ValueError, "PendulumConfig.dt must be > 0"),
    ("ungm", dict(forcing=float("inf")), ValueError, "UNGMConfig.forcing must be a finite"),
    ("bearings", dict(sensors=[[0.0, 0.0]]), TypeError, "BearingsConfig.sensors must be a tuple"),
    ("bearings", dict(start=(1.0, 2.0)), ValueError, "BearingsConfig.start must hold finite"),
    ("folding", dict(obs_std=0.0), ValueError, "FoldingConfig.obs_std must be > 0"),
    ("stochastic_volatility", dict(phi=1.0), ValueError, "VolatilityConfig.phi must lie in"),
    ("poisson_counts", dict(radius=1.5), ValueError, "PoissonConfig.radius must lie in"),
    ("linear20", dict(dim=3.0), TypeError, "Linear20Config.dim must be an int"),
    ("lorenz63_gaps", dict(substeps=0), ValueError, "Lorenz63Config.substeps must be > 0"),
])
def test_bad_problem_parameters_are_refused_by_name(name, override, error, message):
    with pytest.raises(error, match=message) as caught:
        problems.get(name, **override)
    _one_line(caught)


def test_bad_linear_gaussian_parameters_are_refused():
    with pytest.raises(ValueError, match="linear_gaussian: dim must be a positive int"):
        linear_gaussian(2.5)
    with pytest.raises(ValueError, match="linear_gaussian: r_std must be positive and finite"):
        linear_gaussian(2, r_std=float("nan"))


# --- 9, Lorenz-96 filters ------------------------------------------------------------------------


def _lorenz96(particles=10, **kw):
    model = problems.get("lorenz96", dim=12, num_steps=2, burn_in=0, **kw)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    return model, obs, model.initial_ensemble(jax.random.key(1), particles)


LOCAL = csf_jax.LocalCSFConfig(half_width=2, block=6, reverse_steps=2, cg_iterations=2,
                               top_iterations=1)


@pytest.mark.parametrize("filt", ["letkf", "local_filter"])
def test_localization_out_of_the_sensors_order_is_refused(filt):
    model, obs, ens = _lorenz96()
    loc = csf_jax.ring_localization(12, np.arange(12)[::-1])
    kw = dict(config=LOCAL) if filt == "local_filter" else {}
    with pytest.raises(ValueError, match=f"{filt}: observation 0 reads state site 0 .* places it "
                                         f"at 11") as caught:
        getattr(csf_jax, filt)(obs, ens, model=model, key=KEY, localization=loc, **kw)
    _one_line(caught)


@pytest.mark.parametrize("filt", ["letkf", "local_filter"])
def test_lorenz96_filters_refuse_one_particle_and_bad_sites(filt):
    model, obs, ens = _lorenz96()
    kw = dict(config=LOCAL) if filt == "local_filter" else {}
    ring = csf_jax.ring_localization(12, np.arange(12))
    with pytest.raises(ValueError, match="at least 2 particles"):
        getattr(csf_jax, filt)(obs, ens[:1], model=model, key=KEY, localization=ring, **kw)
    with pytest.raises(ValueError, match="obs_sites must be a 1-D sequence"):
        csf_jax.ring_localization(12, [[0, 1]])
    with pytest.raises(ValueError, match="ring_localization: dim must be a positive int"):
        csf_jax.ring_localization(12.0, range(12))


# --- 10: missing-data rates ----------------------------------------------------------------------


@pytest.mark.parametrize("rate", [1.5, -0.5, float("nan"), True])
def test_drop_observations_refuses_rates_outside_0_1(rate):
    with pytest.raises(ValueError, match="drop_observations: rate must be a probability in"):
        csf_jax.drop_observations(KEY, jnp.zeros((3, 2)), rate)


def test_drop_observations_at_rate_1_drops_everything():
    assert bool(jnp.isnan(csf_jax.drop_observations(KEY, jnp.zeros((3, 2)), 1.0)).all())


# --- 11, 12: noise covariances -------------------------------------------------------------------

NEARLY_SINGULAR = [[1.0, 1.0 - 1e-9], [1.0 - 1e-9, 1.0]]

FILTERS = {
    "enkf": lambda o, e, m: csf_jax.ensemble_kalman_filter(o, e, model=m, key=KEY),
    "pf": lambda o, e, m: csf_jax.particle_filter(o, e, model=m, key=KEY),
    "csf": lambda o, e, m: csf_jax.filter(None, o, e, model=m, key=KEY,
                                          config=csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=2))),
}


@pytest.mark.parametrize("name", list(FILTERS))
def test_an_r_singular_in_float32_is_refused_at_the_call(name):
    model = to_model(linear_gaussian(2, 2, num_steps=3, R=NEARLY_SINGULAR))
    ens = model.initial_ensemble(KEY, 10)
    with pytest.raises(ValueError, match="observation-noise covariance R .* not positive definite "
                                         "in float32") as caught:
        FILTERS[name](jnp.zeros((3, 2)), ens, model)
    _one_line(caught)


def test_an_r_singular_in_float32_runs_in_float64(x64):
    model = to_model(linear_gaussian(2, 2, num_steps=3, R=NEARLY_SINGULAR))
    ens = model.initial_ensemble(KEY, 10).astype(jnp.float64)
    assert bool(FILTERS["pf"](jnp.zeros((3, 2), jnp.float64), ens, model).finite.all())


@pytest.mark.parametrize("which,noise,message", [
    ("R", dict(obs_noise=csf_jax.gaussian_noise_cov(np.eye(3))),
     "observation-noise covariance R has shape \\(3, 3\\), but the model needs \\(1, 1\\)"),
    ("Q", dict(process_noise=csf_jax.gaussian_process_noise(np.eye(3))),
     "process-noise covariance Q has shape \\(3, 3\\), but the model needs \\(2, 2\\)"),
])
@pytest.mark.parametrize("call", ["enkf", "pf", "csf", "simulate"])
def test_a_covariance_of_the_wrong_size_is_refused(which, noise, message, call):
    model = _model()._replace(**noise)
    with pytest.raises(ValueError, match=message) as caught:
        if call == "simulate":
            csf_jax.simulate(model, KEY)
        else:
            FILTERS[call](jnp.zeros((3, 1)), jnp.zeros((10, 2)), model)
    _one_line(caught)


# --- 13: half precision --------------------------------------------------------------------------


@pytest.mark.parametrize("filt", ["enkf", "letkf", "local_filter"])
def test_half_precision_inputs_run_in_float32(filt):
    model, obs, ens = _lorenz96()
    ring = csf_jax.ring_localization(12, np.arange(12))
    run = {"enkf": lambda o, e: csf_jax.ensemble_kalman_filter(o, e, model=model, key=KEY),
           "letkf": lambda o, e: csf_jax.letkf(o, e, model=model, key=KEY, localization=ring),
           "local_filter": lambda o, e: csf_jax.local_filter(o, e, model=model, key=KEY,
                                                             localization=ring, config=LOCAL)}
    result = run[filt](obs.astype(jnp.float16), ens.astype(jnp.float16))
    assert result.mean.dtype == jnp.float32 and bool(result.finite.all())


# --- 14: config field types ----------------------------------------------------------------------


@pytest.mark.parametrize("make,message", [
    (lambda: csf_jax.LETKFConfig(radius="4"), "LETKFConfig.radius must be a finite number, "
                                              "got '4'"),
    (lambda: csf_jax.LETKFConfig(inflation=float("nan")), "LETKFConfig.inflation must be a finite"),
    (lambda: csf_jax.LETKFConfig(radius=-1.0), "LETKFConfig.radius must be > 0"),
    (lambda: csf_jax.LocalCSFConfig(ridge="0.1"), "LocalCSFConfig.ridge must be a finite number"),
    (lambda: csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(assimilate_first="yes")),
     "SamplerConfig.assimilate_first must be a bool"),
    (lambda: csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(t_min=None)), "SamplerConfig.t_min must be a finite number"),
    (lambda: csf_jax.GuidanceConfig(scale="1"), "GuidanceConfig.scale must be a finite number"),
    (lambda: csf_jax.MixtureConfig(particles=1), "MixtureConfig.particles must be a bool"),
    (lambda: csf_jax.NetworkConfig(base=None), "NetworkConfig.base must be a str"),
    (lambda: csf_jax.TrainConfig(lr="1e-3"), "TrainConfig.lr must be a finite number"),
    (lambda: csf_jax.TrainConfig(set_sizes=[8, 16]), "TrainConfig.set_sizes must be a tuple"),
    (lambda: csf_jax.DatasetConfig(keep=8.0), "DatasetConfig.keep must be an int"),
    (lambda: csf_jax.SFConfig(lr=float("inf")), "SFConfig.lr must be a finite number"),
    (lambda: csf_jax.SFConfig(network=None), "SFConfig.network must be a NetworkConfig"),
    (lambda: csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(guidance="kalman")), "SamplerConfig.guidance must be a GuidanceConfig"),
])
def test_config_fields_of_the_wrong_type_are_refused_by_name(make, message):
    with pytest.raises((TypeError, ValueError), match=message) as caught:
        make()
    _one_line(caught)


# --- 15: the Kalman filter's model ---------------------------------------------------------------


def test_kalman_filter_takes_the_linear_model_or_its_state_space_model():
    lg = linear_gaussian(2, 1, num_steps=3)
    obs = jnp.ones((3, 1))
    np.testing.assert_array_equal(csf_jax.kalman_filter(obs, model=to_model(lg)).mean,
                                  csf_jax.kalman_filter(obs, model=lg).mean)
    with pytest.raises(TypeError, match="model must be a LinearGaussian .* got NoneType"):
        csf_jax.kalman_filter(obs, model=None)
    with pytest.raises(TypeError, match="model='pendulum' is a StateSpaceModel not made by "
                                        "to_model"):
        csf_jax.kalman_filter(obs, model=problems.get("pendulum"))


# --- 18: a damaged parameter folder fails quietly ------------------------------------------------


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_truncated_params_fail_in_one_line_and_nothing_after(tmp_path, capfd):
    directory = str(tmp_path / "model")
    shutil.copytree(os.path.join(MODEL_DIR, "double_well"), directory)
    files = [p for p in glob.glob(os.path.join(directory, "params", "**"), recursive=True)
             if os.path.isfile(p)]
    _truncate(max(files, key=os.path.getsize))
    with pytest.raises(ValueError, match=f"^model {re.escape(directory)}: the parameters in .* "
                                         f"cannot be restored \\(array '") as caught:
        load_dir(directory)
    _one_line(caught)
    gc.collect()
    time.sleep(0.2)
    gc.collect()
    assert "Traceback" not in capfd.readouterr().err


# --- 20: progress before a compilation -----------------------------------------------------------


def test_progress_announces_the_compilation_once(capsys):
    model = _model("progress_lg")
    ens = model.initial_ensemble(KEY, 10)
    obs = jnp.zeros((3, 1))
    steps = []
    tick = lambda k: steps.append(int(k))  # noqa: E731
    csf_jax.particle_filter(obs, ens, model=model, key=KEY, progress=tick)
    err = capsys.readouterr().err
    assert "compiling the particle filter (d=2, N=10, K=3) ..." in err
    assert "compiled the particle filter in" in err
    csf_jax.particle_filter(obs, ens, model=model, key=KEY, progress=tick)
    csf_jax.particle_filter(obs, ens, model=model, key=KEY)
    assert capsys.readouterr().err == ""


# --- the model API: time-varying models, inputs, likelihoods -------------------------------------


def _controlled():
    return csf_jax.StateSpaceModel(
        "controlled", 1, 1, 3, 1.0, lambda x, step: 0.9 * x + step.u, lambda x, step: x, 0.5,
        csf_jax.gaussian_noise(0.5), lambda key: jax.random.normal(key, (1,)),
        lambda key, n: jax.random.normal(key, (n, 1)), time_varying=True)


@pytest.mark.parametrize("call", ["pf", "simulate"])
def test_a_time_varying_model_without_its_inputs_is_refused(call):
    model = _controlled()
    with pytest.raises(ValueError, match="its drift fails .*time-varying and got no inputs: pass "
                                         "inputs=") as caught:
        if call == "simulate":
            csf_jax.simulate(model, KEY)
        else:
            csf_jax.particle_filter(jnp.zeros((3, 1)), jnp.zeros((10, 1)), model=model, key=KEY)
    _one_line(caught)


@pytest.mark.parametrize("change,error,message", [
    (dict(obs_noise="gaussian"), TypeError, "obs_noise must be a csf_jax.ObservationNoise or "
                                            "csf_jax.Likelihood"),
    (dict(observe=lambda x: x), ValueError, "its observe returns shape \\(2,\\) .* expected "
                                            "\\(1,\\)"),
    (dict(dim=2.0), ValueError, "dim must be a positive int"),
    (dict(process_std=float("nan")), ValueError, "process_std must be a finite number >= 0"),
    (dict(drift=None), TypeError, "drift must be callable"),
    (dict(process_noise=np.eye(2)), TypeError, "process_noise must be a csf_jax.ProcessNoise"),
    (dict(obs_noise=csf_jax.poisson_likelihood()._replace(mean=3)), TypeError,
     "obs_noise.mean must be callable"),
    (dict(obs_noise=csf_jax.gaussian_noise(0.5)._replace(gaussian_std=float("nan"))), ValueError,
     "obs_noise.gaussian_std must be a finite number > 0"),
])
def test_malformed_models_are_refused_by_field(change, error, message):
    model = _model()._replace(**change)
    with pytest.raises(error, match=f"model 'tiny_lg': {message}") as caught:
        csf_jax.particle_filter(jnp.zeros((3, 1)), jnp.zeros((10, 2)), model=model, key=KEY)
    _one_line(caught)


def test_a_likelihood_model_with_wrong_inputs_is_refused():
    lik = csf_jax.StateSpaceModel(
        "counts", 1, 1, 3, 1.0, lambda x: 0.9 * x, lambda x: x, 0.3,
        csf_jax.poisson_likelihood(), lambda key: jnp.zeros((1,)),
        lambda key, n: jnp.zeros((n, 1)))
    with pytest.raises(ValueError, match="inputs given, but model 'counts' is not time-varying"):
        csf_jax.particle_filter(jnp.zeros((3, 1)), jnp.zeros((10, 1)), model=lik, key=KEY,
                                inputs=jnp.zeros((3, 1)))


def test_the_run_folder_is_left_as_it_was_by_a_refusal(run_copy):
    before = json.loads((run_copy / "data" / "meta.json").read_text())
    with pytest.raises(ValueError):
        _fit(run_copy, config=dataclasses.replace(TRAIN, lr=1e-3))
    assert json.loads((run_copy / "data" / "meta.json").read_text()) == before
    assert sorted(os.listdir(run_copy / "ckpt")) == ["2", "4"]


def test_train_refuses_a_loss_that_is_not_finite(run_copy, tmp_path):
    data_dir = str(run_copy / "data")
    arr = np.load(os.path.join(data_dir, "ensembles.npy"), mmap_mode="r+")
    arr[:] = np.nan
    arr.flush()
    del arr
    with pytest.raises(FloatingPointError, match="the loss became nan by step 2; the training "
                                                 "data .* may hold NaN/inf"):
        train("tiny_lg", load(data_dir), str(tmp_path / "ckpt"), network=NET,
              config=dataclasses.replace(TRAIN, seed=3), log_every=2, verbose=False)


# --- observation laws of the wrong shape, non-finite simulation inputs ---------------------------


def _counts(likelihood, obs_dim=2):
    return csf_jax.StateSpaceModel(
        "counts", 2, obs_dim, 3, 1.0, lambda x: 0.9 * x, lambda x: x[:obs_dim], 0.3, likelihood,
        lambda key: jnp.zeros((2,)), lambda key, n: jnp.zeros((n, 2)))


def test_a_likelihood_log_prob_returning_a_scalar_is_refused():
    poisson = csf_jax.poisson_likelihood()
    summed = poisson._replace(log_prob=lambda y, eta: jnp.sum(poisson.log_prob(y, eta)))
    with pytest.raises(ValueError, match=r"model 'counts': its Likelihood.log_prob returns shape "
                                         r"\(\) for y and eta of shape \(2,\); expected \(2,\)") \
            as caught:
        csf_jax.particle_filter(jnp.zeros((3, 2)), jnp.zeros((10, 2)), model=_counts(summed),
                                key=KEY)
    _one_line(caught)


def test_a_likelihood_sample_of_the_wrong_size_is_refused_by_simulate():
    poisson = csf_jax.poisson_likelihood()
    wide = poisson._replace(sample=lambda key, eta: poisson.sample(key, jnp.append(eta, 0.0)))
    with pytest.raises(ValueError, match=r"simulate: model 'counts': its Likelihood.sample returns "
                                         r"shape \(3,\) for eta of shape \(2,\); expected \(2,\)") \
            as caught:
        csf_jax.simulate(_counts(wide), KEY)
    _one_line(caught)


def test_an_additive_noise_log_prob_of_the_wrong_shape_is_refused():
    noise = csf_jax.gaussian_noise(0.5)
    model = _model()._replace(obs_noise=noise._replace(log_prob=lambda r: -0.5 * r * r))
    with pytest.raises(ValueError, match=r"its ObservationNoise.log_prob returns shape \(1,\) for "
                                         r"a residual of shape \(1,\); expected a scalar") as caught:
        csf_jax.particle_filter(jnp.zeros((3, 1)), jnp.zeros((10, 2)), model=model, key=KEY)
    _one_line(caught)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_simulate_refuses_non_finite_inputs(bad):
    u = np.zeros((3, 1), np.float32)
    u[1, 0] = bad
    with pytest.raises(ValueError, match=r"simulate: inputs has 1 non-finite value\(s\); first at "
                                         r"index \(1, 0\)") as caught:
        csf_jax.simulate(_controlled(), KEY, inputs=jnp.asarray(u))
    _one_line(caught)


_RING = csf_jax.ring_localization(4, (0, 2))


@pytest.mark.parametrize("build,message", [
    (lambda: csf_jax.methods.pf(csf_jax.CSFConfig()), "particle_filter: takes no settings"),
    (lambda: csf_jax.methods.kalman(csf_jax.CSFConfig()), "kalman_filter: takes no settings"),
    (lambda: csf_jax.methods.enkf(csf_jax.InflationConfig()),
     "ensemble_kalman_filter: inflation must be a positive number"),
    (lambda: csf_jax.methods.enkf(True), "inflation must be a positive number"),
    (lambda: csf_jax.methods.ensf(csf_jax.CSFConfig()), "config must be an ENSFConfig"),
    (lambda: csf_jax.methods.sf(csf_jax.CSFConfig()), "config must be an SFConfig"),
    (lambda: csf_jax.methods.sf(sampler=csf_jax.SFConfig()), "sampler a CSFConfig"),
    (lambda: csf_jax.methods.reference(csf_jax.CSFConfig()), "config must be a ReferenceConfig"),
    (lambda: csf_jax.methods.local_csf(_RING, csf_jax.CSFConfig()),
     "config must be a LocalCSFConfig"),
    (lambda: csf_jax.methods.local_csf(csf_jax.LocalCSFConfig()),
     "localization must be a Localization"),
    (lambda: csf_jax.methods.letkf(_RING, csf_jax.CSFConfig()), "config must be a LETKFConfig"),
    (lambda: csf_jax.methods.letkf(csf_jax.LETKFConfig()), "localization must be a Localization"),
])
def test_a_builder_given_the_wrong_config_type_names_the_expected_one(build, message):
    with pytest.raises(TypeError, match=message) as caught:
        build()
    _one_line(caught)
