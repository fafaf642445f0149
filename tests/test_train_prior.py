"""``csf_jax.train_prior`` / ``TrainedPrior.save`` / ``csf_jax.load_prior`` for a model that is not
built in: the result filters, round-trips through disk, resumes, and refuses other models."""

import dataclasses
import io
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax.problems.linear import linear_gaussian, to_model
from csf_jax.training.fit import key_seed

DATA = csf_jax.DatasetConfig(trajectories=8, particles=64, keep=16, stride=4, chunk=4,
                             dtype="float32")
TRAIN = csf_jax.TrainConfig(steps=20, save_every=10, eval_every=10, batch_sets=4,
                            targets_per_set=8, set_sizes=(8, 16))
NET = csf_jax.NetworkConfig(base="gaussian", hidden=16, heads=2, blocks=1, code_dim=8,
                            score_hidden=16, score_layers=2, fourier_features=4)


def _model(name="own_lg", r_std=0.5):
    return to_model(linear_gaussian(2, 1, num_steps=12, r_std=r_std, name=name))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    directory = tmp_path_factory.mktemp("fit")
    prior = csf_jax.train_prior(_model(), jax.random.key(3), directory=str(directory),
                                dataset=DATA, config=TRAIN, network=NET, verbose=False)
    return prior, directory


def test_it_returns_a_prior_the_filter_takes(trained):
    prior, _ = trained
    assert isinstance(prior, csf_jax.TrainedPrior)
    assert prior.problem == "own_lg" and prior.dim == 2 and prior.meta["obs_dim"] == 1
    assert prior.meta["model"]["name"] == "own_lg" and prior.meta["seed"] == 3
    assert [s for s, _ in prior.meta["valid_loss"]] == [10, 20]
    model = _model()
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 64)
    cfg = csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=4))
    r = csf_jax.filter(prior, obs, ens, model=model, key=jax.random.key(2), config=cfg)
    assert bool(r.finite.all())
    # jit and vmap through the prior, like raw params
    many = jax.jit(jax.vmap(lambda o, k: csf_jax.filter(prior, o, ens, model=model, key=k,
                                                        config=cfg).mean))(
        jnp.stack([obs, obs]), jax.random.split(jax.random.key(2), 2))
    assert many.shape == (2, 12, 2)


def test_save_and_load_round_trip(trained, tmp_path):
    prior, _ = trained
    path = prior.save(str(tmp_path / "prior"))
    back = csf_jax.load_prior(path, _model(), network=NET)
    for a, b in zip(jax.tree_util.tree_leaves(prior.params), jax.tree_util.tree_leaves(back.params)):
        np.testing.assert_array_equal(a, b)
    assert back.network == NET and back.meta["model"] == json.loads(json.dumps(prior.meta["model"]))


def test_loading_refuses_another_model_or_network(trained, tmp_path):
    prior, _ = trained
    path = prior.save(str(tmp_path / "prior"))
    with pytest.raises(ValueError, match="made for problem 'own_lg'"):
        csf_jax.load_prior(path, _model(name="someone_else"))
    with pytest.raises(ValueError, match="obs_noise"):
        csf_jax.load_prior(path, _model(r_std=0.7))
    moved = _model()._replace(drift=lambda x: 0.5 * x)
    with pytest.raises(ValueError, match="drift differs"):
        csf_jax.load_prior(path, moved)
    with pytest.raises(ValueError, match="hidden"):
        csf_jax.load_prior(path, _model(), network=dataclasses.replace(NET, hidden=32))
    # the filter makes the same check when given the prior whole
    obs = jnp.zeros((3, 1))
    ens = moved.initial_ensemble(jax.random.key(0), 16)
    with pytest.raises(ValueError, match="another model named 'own_lg'"):
        csf_jax.filter(prior, obs, ens, model=moved, key=jax.random.key(0))


def test_a_second_call_resumes_and_another_key_is_refused(trained):
    prior, directory = trained
    again = csf_jax.train_prior(_model(), jax.random.key(3), directory=str(directory),
                                dataset=DATA, config=TRAIN, network=NET, verbose=False)
    for a, b in zip(jax.tree_util.tree_leaves(prior.params), jax.tree_util.tree_leaves(again.params)):
        np.testing.assert_array_equal(a, b)
    assert again.meta["valid_loss"] == prior.meta["valid_loss"]
    with pytest.raises(ValueError, match="holds dataset"):
        csf_jax.train_prior(_model(), jax.random.key(4), directory=str(directory), dataset=DATA,
                            config=TRAIN, network=NET, verbose=False)


def test_bad_models_are_refused_before_any_work(tmp_path):
    with pytest.raises(TypeError, match="StateSpaceModel"):
        csf_jax.train_prior(object(), jax.random.key(0), directory=str(tmp_path))
    bad = _model()._replace(observe=lambda x: x)  # says obs_dim 1, observes 2
    with pytest.raises(ValueError, match="observe"):
        csf_jax.train_prior(bad, jax.random.key(0), directory=str(tmp_path))


def test_key_seed():
    assert key_seed(jax.random.key(0)) == 0 and key_seed(jax.random.key(7)) == 7
    split = key_seed(jax.random.split(jax.random.key(0))[1])
    assert split > 0 and split == key_seed(jax.random.split(jax.random.key(0))[1])


class _Clock:
    """A clock that stands still until moved."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_in_a_log_is_plain_lines_at_the_average_rate():
    """Not a terminal: one plain line each 5% (and at the end), no ``\\r``; the rate is the average
    since the first report (which holds the compilation: 30 s here), not the last interval's (5 or
    15 s per 100 steps here), and the ETA is from it."""
    from csf_jax.training.progress import Progress
    clock, out = _Clock(), io.StringIO()
    progress = Progress("[train m]", 1000, unit="steps", per_unit=(16, "sets"), stream=out,
                        clock=clock)
    clock.now = 30.0  # the first step, compiling
    progress.report(10, "loss 1.0")
    for done in range(20, 1001, 10):
        clock.now += 0.5 if done % 20 else 1.5
        progress.report(done, "loss 0.5")
        if done == 500:
            progress.note("valid 0.4", done)
    progress.close()
    text = out.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert lines[0] == "[train m] 10/1000 steps (1%) loss 1.0"
    assert len(lines) == 22 and "[train m] 500/1000 steps: valid 0.4" in lines
    # 50 steps in 5.5 s: 9.09 steps/s, 940 steps left
    assert lines[1] == ("[train m] 60/1000 steps (6%) loss 0.5, 9.1 steps/s (145 sets/s), "
                        "ETA 1 min 43 s")
    # 990 steps in 99.5 s
    assert lines[-1] == "[train m] 1000/1000 steps (100%) loss 0.5, 9.9 steps/s (159 sets/s)"


def test_progress_on_a_terminal_rewrites_one_line():
    from csf_jax.training.progress import Progress
    clock, out = _Clock(), _Terminal()
    progress = Progress("[data m]", 4, unit="trajectories", stream=out, clock=clock)
    for done in range(1, 5):
        clock.now += 2.0
        progress.report(done)
    progress.close()
    text = out.getvalue()
    assert text.count("\r") == 4 and text.endswith("\n") and text.count("\n") == 1
    assert text.rstrip().endswith("[data m] 4/4 trajectories (100%), 0.5 trajectories/s")


def test_train_prior_writes_plain_progress_lines_into_a_log(trained, tmp_path, capfd):
    """stderr captured (not a terminal), as in a log file: the data and training lines are plain
    lines with the average rate."""
    _, directory = trained
    from csf_jax.training import load, train
    config = dataclasses.replace(TRAIN, seed=key_seed(jax.random.key(3)))  # the fixture's: compiled
    train("own_lg", load(str(directory / "data")), str(tmp_path / "ckpt"), network=NET,
          config=config, log_every=1, verbose=True)
    err = capfd.readouterr().err
    assert "\r" not in err
    steps = [line for line in err.splitlines() if line.startswith("[train own_lg] ")
             and "steps (" in line]
    assert len(steps) == 20 and steps[-1].startswith("[train own_lg] 20/20 steps (100%) loss ")
    assert all("steps/s (" in line and "sets/s" in line for line in steps[1:])
    assert "ETA " in steps[1]
