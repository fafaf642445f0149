"""Damaged and inconsistent inputs, each of which must end in a correct result or a one-line error naming the cause:
damaged checkpoints (resume from the previous one), inconsistent model folders, a trained prior
used for another problem or network, command-line values, mixed dtypes, non-finite observations
under jit/vmap."""

import dataclasses
import functools
import glob
import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import networks, problems
from csf_jax import trained as trained_mod
from csf_jax.pretrained import MODEL_DIR, load_dir, load_pretrained
from csf_jax.training import DatasetConfig, TrainConfig, generate, load, train

TINY_DATA = DatasetConfig(trajectories=12, particles=200, keep=64, chunk=6)
SMALL_NET = networks.NetworkConfig(hidden=32, heads=2, blocks=1, code_dim=16, score_hidden=64)
SHORT = TrainConfig(steps=10, batch_sets=2, targets_per_set=4, set_sizes=(8,), save_every=2,
                    eval_every=2)


def _one_line(error) -> str:
    text = str(error.value)
    assert "\n" not in text, text
    return text


# --- checkpoints: a damaged newest checkpoint falls back to the previous one -------------------


@pytest.fixture(scope="module")
def training(tmp_path_factory):
    """``(data, pristine, clean)``: a checkpoint folder stopped at step 6 (steps 4 and 6 kept) and
    the parameters of an uninterrupted 10-step run."""
    root = tmp_path_factory.mktemp("ckpt")
    generate("double_well", TINY_DATA, str(root / "data"), verbose=False)
    data = load(str(root / "data"), valid_fraction=0.2)
    pristine = str(root / "pristine")
    train("double_well", data, pristine, network=SMALL_NET,
          config=dataclasses.replace(SHORT, steps=6), verbose=False)
    clean, _ = train("double_well", data, str(root / "clean"), network=SMALL_NET, config=SHORT,
                     verbose=False)
    return data, pristine, clean


def _truncate(path: str) -> None:
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def _largest_file(directory: str) -> str:
    files = [p for p in glob.glob(os.path.join(directory, "**"), recursive=True)
             if os.path.isfile(p)]
    return max(files, key=os.path.getsize)


DAMAGE = {
    "array file truncated": lambda s: _truncate(_largest_file(os.path.join(s, "state"))),
    "meta JSON truncated": lambda s: _truncate(os.path.join(s, "meta", "metadata")),
    "state folder missing": lambda s: shutil.rmtree(os.path.join(s, "state")),
    "meta folder missing": lambda s: shutil.rmtree(os.path.join(s, "meta")),
    "array metadata truncated": lambda s: _truncate(os.path.join(s, "state", "_METADATA")),
    "step folder emptied": lambda s: [shutil.rmtree(s), os.mkdir(s)],
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_newest_checkpoint_resumes_from_the_previous_one(training, damage, tmp_path,
                                                                  capsys):
    data, pristine, clean = training
    out = str(tmp_path / "ckpt")
    shutil.copytree(pristine, out)
    DAMAGE[damage](os.path.join(out, "6"))
    params, meta = train("double_well", data, out, network=SMALL_NET, config=SHORT,
                         verbose=False)
    said = [line for line in capsys.readouterr().err.splitlines() if "damaged" in line]
    assert len(said) == 1, said
    assert f"checkpoint {os.path.join(out, '6')} is damaged (" in said[0]
    assert f"moved it to {out}.damaged-6 and resuming from step 4" in said[0]
    assert os.path.isdir(out + ".damaged-6"), "the damaged checkpoint must be kept"
    assert meta["valid_loss"][-1][0] == 10
    assert sorted(int(s) for s in os.listdir(out)) == [8, 10]
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(clean)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_no_intact_checkpoint_is_one_clear_error_and_moves_nothing(training, tmp_path):
    data, pristine, _ = training
    out = str(tmp_path / "ckpt")
    shutil.copytree(pristine, out)
    for step in ("4", "6"):
        _truncate(os.path.join(out, step, "meta", "metadata"))
    with pytest.raises(RuntimeError, match=f"no intact checkpoint in {out} .*step 6: .*step 4: "):
        train("double_well", data, out, network=SMALL_NET, config=SHORT, verbose=False)
    assert sorted(os.listdir(out)) == ["4", "6"]
    assert not glob.glob(out + ".damaged-*")


def test_intact_checkpoint_of_another_run_is_refused_not_skipped(training, tmp_path):
    data, pristine, _ = training
    out = str(tmp_path / "ckpt")
    shutil.copytree(pristine, out)
    with pytest.raises(ValueError, match="seed: checkpoint has 0, requested 1"):
        train("double_well", data, out, network=SMALL_NET,
              config=dataclasses.replace(SHORT, seed=1), verbose=False)
    assert sorted(os.listdir(out)) == ["4", "6"]


# --- exported model folders --------------------------------------------------------------------


@pytest.fixture
def model_dir(tmp_path):
    """A copy of the shipped double-well model."""
    directory = str(tmp_path / "model")
    shutil.copytree(os.path.join(MODEL_DIR, "double_well"), directory)
    return directory


def _edit_meta(directory: str, **changes) -> None:
    path = os.path.join(directory, "meta.json")
    with open(path) as f:
        meta = json.load(f)
    for key, value in changes.items():
        if key in meta["network"]:
            meta["network"][key] = value
        else:
            meta[key] = value
    with open(path, "w") as f:
        json.dump(meta, f)


@pytest.mark.parametrize("change,message", [
    (dict(score_hidden=64), "meta.json says network.score_hidden=64, but the stored parameters "
                            "were made with score_hidden=128"),
    (dict(heads=8), "meta.json says network.heads=8, .* made with heads=4"),
    (dict(score_layers=2), "meta.json says network.score_layers=2, .* made with score_layers=3"),
    (dict(dim=5), "meta.json says dim=5, but the stored parameters were made for dim=1"),
])
def test_model_whose_meta_does_not_match_its_arrays_names_folder_and_field(model_dir, change,
                                                                          message):
    _edit_meta(model_dir, **change)
    with pytest.raises(ValueError, match=f"^model {model_dir}: {message}") as error:
        load_dir(model_dir)
    _one_line(error)


@pytest.mark.parametrize("damage,error,message", [
    (lambda d: _truncate(os.path.join(d, "meta.json")), ValueError, "meta.json cannot be read"),
    (lambda d: os.remove(os.path.join(d, "meta.json")), FileNotFoundError, "no meta.json"),
    (lambda d: shutil.rmtree(os.path.join(d, "params")), FileNotFoundError,
     "parameter folder .* is missing"),
    (lambda d: _truncate(_largest_file(os.path.join(d, "params"))), ValueError,
     "parameters in .* cannot be restored"),
    (lambda d: _truncate(os.path.join(d, "params", "_METADATA")), ValueError,
     "parameters in .* cannot be read"),
    (lambda d: _edit_meta_network(d, foo=1), ValueError,
     "network/dim fields are invalid"),
])
def test_damaged_model_folder_is_one_line_naming_it(model_dir, damage, error, message):
    damage(model_dir)
    with pytest.raises(error, match=f"^model {model_dir}: .*{message}") as caught:
        load_dir(model_dir)
    _one_line(caught)


def _edit_meta_network(directory: str, **extra) -> None:
    path = os.path.join(directory, "meta.json")
    with open(path) as f:
        meta = json.load(f)
    meta["network"].update(extra)
    with open(path, "w") as f:
        json.dump(meta, f)


# --- a trained prior carries its problem and network; filter refuses a mismatch ----------------

SAMPLER = csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=10))


def _data(name: str, particles: int = 16, steps: int = 3):
    model = problems.get(name, num_steps=steps)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    return model, obs, model.initial_ensemble(jax.random.key(1), particles)


def test_trained_prior_of_another_problem_with_the_same_shapes_is_refused():
    model, obs, ens = _data("cubic10_indep")
    corr = load_pretrained("cubic10_corr")
    with pytest.raises(ValueError, match="made for problem 'cubic10_corr' .*but "
                                         "model='cubic10_indep'") as error:
        csf_jax.filter(corr, obs, ens, model=model, key=jax.random.key(2), config=SAMPLER)
    _one_line(error)
    # triple_well's model is the double-well one, on purpose: load_pretrained says so
    triple = problems.get("triple_well")
    assert trained_mod.unpack(load_pretrained("triple_well"), triple, None)[0] is not None
    with pytest.raises(ValueError, match="made for problem 'double_well'"):
        trained_mod.unpack(load_pretrained("double_well"), triple, None)


@pytest.mark.parametrize("field,value", [("sigma_max", 30.0), ("fourier_scale", 2.0)])
def test_network_differing_from_the_trained_one_is_refused(field, value):
    model, obs, ens = _data("double_well")
    trained = load_pretrained("double_well")
    other = dataclasses.replace(trained.network, **{field: value})
    with pytest.raises(ValueError, match=f"network= differs .*{field}: given {value}, trained"):
        csf_jax.filter(trained, obs, ens, model=model, network=other, key=jax.random.key(2),
                       config=SAMPLER)


def test_sampler_sigma_max_differing_from_the_network_is_refused():
    model, obs, ens = _data("double_well")
    trained = load_pretrained("double_well")
    config = dataclasses.replace(SAMPLER, sampler=dataclasses.replace(SAMPLER.sampler, sigma_max=30.0))
    for params, network in ((trained, None), (trained.params, trained.network)):
        with pytest.raises(ValueError, match="sigma_max=25.0, but the sampler's "
                                             "config.sampler.sigma_max=30.0"):
            csf_jax.filter(params, obs, ens, model=model, network=network,
                           key=jax.random.key(2), config=config)


def test_trained_prior_works_under_jit_and_vmap_like_raw_params():
    model, obs, ens = _data("double_well")
    trained = load_pretrained("double_well")
    raw = csf_jax.filter(trained.params, obs, ens, model=model, network=trained.network,
                         key=jax.random.key(2), config=SAMPLER)
    jitted = jax.jit(functools.partial(csf_jax.filter, model=model, config=SAMPLER))
    got = jitted(trained, obs, ens, key=jax.random.key(2))
    np.testing.assert_allclose(got.mean, raw.mean, rtol=1e-5, atol=1e-6)
    assert jax.tree_util.tree_leaves(trained) == jax.tree_util.tree_leaves(trained.params)
    keys = jax.random.split(jax.random.key(3), 2)
    batched = jax.vmap(lambda k: csf_jax.filter(trained, obs, ens, model=model, key=k,
                                                config=SAMPLER))(keys)
    assert batched.mean.shape == (2,) + raw.mean.shape and bool(batched.finite.all())
    assert isinstance(trained, csf_jax.TrainedPrior) and trained.problem == "double_well"


@pytest.mark.parametrize("module", ["csf_jax", "csf_jax.trained", "csf_jax.pretrained"])
def test_pretrained_is_a_deprecated_name_of_trained_prior(module):
    import importlib
    with pytest.warns(DeprecationWarning, match=rf"{module}\.Pretrained is deprecated: it is "
                                                r"csf_jax\.TrainedPrior"):
        assert importlib.import_module(module).Pretrained is csf_jax.TrainedPrior
    assert "Pretrained" not in csf_jax.__all__
    with pytest.raises(AttributeError, match="has no attribute 'Pretrainde'"):
        csf_jax.Pretrainde  # noqa: B018


# --- dtypes: obs and ensemble are promoted to their common float dtype in every filter ----------

TINY_SF = csf_jax.SFConfig(train_steps=2, warmup_steps=0, batch=16, network=SMALL_NET)

FILTERS = {
    "csf": lambda o, e, m: csf_jax.filter(None, o, e, model=m, key=jax.random.key(2),
                                          config=SAMPLER),
    "csf_learned": lambda o, e, m: csf_jax.filter(load_pretrained("double_well"), o, e, model=m,
                                                  key=jax.random.key(2), config=SAMPLER),
    "sf": lambda o, e, m: csf_jax.score_filter(o, e, model=m, key=jax.random.key(2),
                                               config=TINY_SF, sampler=SAMPLER),
    "pf": lambda o, e, m: csf_jax.particle_filter(o, e, model=m, key=jax.random.key(2)),
    "enkf": lambda o, e, m: csf_jax.ensemble_kalman_filter(o, e, model=m,
                                                           key=jax.random.key(2)),
}


@pytest.mark.parametrize("name", list(FILTERS))
def test_narrow_ensemble_is_promoted_to_the_observations_dtype(name):
    model, obs, ens = _data("double_well", particles=32)
    half = ens.astype(jnp.float16)
    got = FILTERS[name](obs, half, model)
    want = FILTERS[name](obs, half.astype(jnp.float32), model)
    assert got.mean.dtype == jnp.float32
    np.testing.assert_array_equal(got.mean, want.mean)


@pytest.mark.parametrize("name", ["csf_learned", "pf", "enkf"])
def test_float64_obs_with_float32_ensemble_run_in_float64_under_x64(name, x64):
    model, obs, ens = _data("double_well", particles=32)
    got = FILTERS[name](obs.astype(jnp.float64), ens.astype(jnp.float32), model)
    assert got.mean.dtype == jnp.float64 and bool(got.finite.all())


def test_integer_inputs_are_refused_by_name():
    model, obs, ens = _data("double_well")
    for name in ("csf", "pf", "enkf"):
        with pytest.raises(TypeError, match="obs must be a floating array, got dtype int32"):
            FILTERS[name](obs.astype(jnp.int32), ens, model)


# --- non-finite observations under jit/vmap: flagged, and NaN from that step on -----------------


@pytest.mark.parametrize("name", ["csf", "sf", "pf", "enkf"])
def test_nonfinite_observation_under_jit_and_vmap_is_reported_from_its_step_on(name):
    """Runs: clean, -inf at step 3, inf at step 2. Only the bad runs are flagged, from the bad step
    on, with NaN means (the particle filter's would look finite again otherwise). NaN is a missing
    observation, not a bad one (tests/test_missing.py)."""
    model, obs, ens = _data("double_well", particles=32, steps=5)
    runs = jnp.stack([obs, obs.at[2, 0].set(-jnp.inf), obs.at[1, 0].set(jnp.inf)])
    r = jax.jit(jax.vmap(lambda o: FILTERS[name](o, ens, model)))(runs)
    np.testing.assert_array_equal(r.finite, [[True] * 5, [True, True, False, False, False],
                                             [True, False, False, False, False]])
    for run, first in ((1, 2), (2, 1)):
        assert bool(jnp.isfinite(r.mean[run, :first]).all())
        assert bool(jnp.isnan(r.mean[run, first:]).all())
        assert bool(jnp.isnan(r.std[run, first:]).all())
    assert bool(jnp.isfinite(r.mean[0]).all())


def test_kalman_and_concrete_calls():
    from csf_jax.problems.linear import linear_gaussian
    lg = linear_gaussian(dim=2, obs_dim=1, num_steps=4)
    obs = jnp.ones((4, 1)).at[1, 0].set(jnp.inf)
    r = jax.jit(lambda o: csf_jax.kalman_filter(o, model=lg))(obs)
    np.testing.assert_array_equal(r.finite, [True, False, False, False])
    model, good, ens = _data("double_well")
    with pytest.raises(ValueError, match="obs has 1 infinite value"):
        csf_jax.particle_filter(good.at[0, 0].set(jnp.inf), ens, model=model,
                                key=jax.random.key(2))
    assert csf_jax.FilterResult(jnp.zeros((2, 1)), jnp.zeros((2, 1))).finite is None
