"""The offline stage: a small model trains and its loss falls; kill -9 then resume loses nothing;
mismatched checkpoints fail clearly; the shipped models load and filter every problem."""

import dataclasses
import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import csf_jax
from csf_jax import networks, problems
from csf_jax.pretrained import load_pretrained
from csf_jax.training import DatasetConfig, TrainConfig, generate, load, train
from csf_jax.training.data import Dataset
from csf_jax.training.train import eval_loss, init_state, make_batch

TINY_DATA = DatasetConfig(trajectories=12, particles=200, keep=64, chunk=6)
SMALL_NET = networks.NetworkConfig(hidden=32, heads=2, blocks=1, code_dim=16, score_hidden=64)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    directory = str(tmp_path_factory.mktemp("data"))
    generate("double_well", TINY_DATA, directory, verbose=False)
    return load(directory, valid_fraction=0.2)


def test_dataset_shape_and_resumable_generation(tiny_data, tmp_path):
    M, S, keep, d = tiny_data.ensembles.shape
    assert (M, S, keep, d) == (12, 100, 64, 1)
    assert tiny_data.ensembles.dtype == np.float16
    assert np.isfinite(tiny_data.ensembles).all()
    assert len(tiny_data.valid) == 2 and len(tiny_data.train) == 10
    # ensembles are spread around the truth's well, not a single repeated particle
    assert float(np.std(tiny_data.ensembles[0, 10].astype(np.float32))) > 0.01
    # A second call on a finished dataset does nothing; another config in the same place fails.
    generate("double_well", TINY_DATA, os.path.dirname(tiny_data_path(tiny_data)), verbose=False)
    other = dataclasses.replace(TINY_DATA, keep=32)
    with pytest.raises(ValueError, match="not .*use another directory"):
        generate("double_well", other, os.path.dirname(tiny_data_path(tiny_data)), verbose=False)


def tiny_data_path(data):
    return data.ensembles.filename


@pytest.mark.slow  # kept out of the default run's time budget; run with -m slow
def test_small_model_trains_and_loss_falls(tiny_data, tmp_path):
    cfg = TrainConfig(steps=150, batch_sets=8, targets_per_set=32, set_sizes=(16, 32),
                      save_every=150, eval_every=50, lr=3e-3)
    state0 = init_state(jax.random.key(cfg.seed), SMALL_NET, 1, cfg)
    valid = make_batch(tiny_data, dataclasses.replace(cfg, set_sizes=(32,)), 0, "valid")
    key = jax.random.key(10_000 + cfg.seed)
    before = float(eval_loss(state0.params, *valid, key, network=SMALL_NET, t_min=cfg.t_min))
    t0 = time.perf_counter()
    params, meta = train("double_well", tiny_data, str(tmp_path / "ckpt"), network=SMALL_NET,
                         config=cfg, verbose=False)
    assert time.perf_counter() - t0 < 120
    after = meta["valid_loss"][-1][1]
    assert after < 0.8 * before, (before, meta["valid_loss"])
    # Trained params drive the filter.
    model = problems.get("double_well", num_steps=3)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 32)
    r = csf_jax.filter(params, obs, ens, model=model, network=SMALL_NET, key=jax.random.key(2),
                       config=csf_jax.CSFConfig(sampler=csf_jax.SamplerConfig(reverse_steps=20)))
    assert bool(jnp.isfinite(r.mean).all())


def _bimodal_data() -> Dataset:
    """Ensembles of two clusters at ``c +- a`` (a in [0.5, 1.5], cluster std 0.1): far from
    Gaussian, so a learned correction has something to learn."""
    rng = np.random.default_rng(0)
    M, S, keep = 20, 10, 64
    centre = rng.normal(0.0, 2.0, (M, S, 1, 1))
    half = rng.uniform(0.5, 1.5, (M, S, 1, 1))
    sign = rng.choice([-1.0, 1.0], (M, S, keep, 1))
    ens = centre + half * sign + 0.1 * rng.standard_normal((M, S, keep, 1))
    return Dataset(ens.astype(np.float16), "bimodal", np.arange(16), np.arange(16, 20))


@pytest.mark.slow
def test_gaussian_base_model_trains_and_starts_at_the_gaussian(tmp_path):
    """A ``base="gaussian"`` network: its batches carry the whole ensembles (the base's moments),
    its initial loss is the ensemble Gaussian's (zero-init output layer), and on bimodal ensembles
    training takes the loss well below it. A checkpoint of another base is refused."""
    data = _bimodal_data()
    net = dataclasses.replace(SMALL_NET, base="gaussian")
    cfg = TrainConfig(steps=300, batch_sets=8, targets_per_set=32, set_sizes=(16, 32),
                      save_every=300, eval_every=100, lr=3e-3)
    subsets, x0, full = make_batch(data, cfg, 0, full=True)
    assert subsets.shape[:2] == (8, 16) and full.shape == (8, 64, 1) and x0.shape == (8, 32, 1)
    valid = make_batch(data, dataclasses.replace(cfg, set_sizes=(32,)), 0, "valid", True)
    key = jax.random.key(10_000)
    zero = jax.tree_util.tree_map(jnp.zeros_like, init_state(jax.random.key(0), net, 1, cfg).params)
    gauss = float(eval_loss(zero, valid[0], valid[1], key, valid[2], network=net, t_min=cfg.t_min))
    state0 = init_state(jax.random.key(cfg.seed), net, 1, cfg)
    before = float(eval_loss(state0.params, valid[0], valid[1], key, valid[2], network=net,
                             t_min=cfg.t_min))
    assert abs(before - gauss) < 1e-6 * gauss, (before, gauss)
    params, meta = train("bimodal", data, str(tmp_path / "ckpt"), network=net, config=cfg,
                         verbose=False)
    assert meta["valid_loss"][-1][1] < 0.8 * before, (before, meta["valid_loss"])
    with pytest.raises(ValueError, match="base"):
        train("bimodal", data, str(tmp_path / "ckpt"), network=SMALL_NET, config=cfg,
              verbose=False)


@pytest.mark.slow  # kept out of the default run's time budget; run with -m slow
def test_mismatched_checkpoint_fails_clearly(tiny_data, tmp_path):
    cfg = TrainConfig(steps=2, batch_sets=2, targets_per_set=4, set_sizes=(8,), save_every=2)
    out = str(tmp_path / "ckpt")
    train("double_well", tiny_data, out, network=SMALL_NET, config=cfg, verbose=False)
    bigger = dataclasses.replace(SMALL_NET, score_hidden=128)
    with pytest.raises(ValueError, match="network: checkpoint has .*score_hidden.*64.*requested"):
        train("double_well", tiny_data, out, network=bigger, config=cfg, verbose=False)
    with pytest.raises(ValueError, match="seed"):
        train("double_well", tiny_data, out, network=SMALL_NET,
              config=dataclasses.replace(cfg, seed=1), verbose=False)


TRAIN_SCRIPT = """
import sys, jax, csf_jax
from csf_jax.training import DatasetConfig, TrainConfig
csf_jax.train_prior("double_well", jax.random.key(0), directory=sys.argv[1],
                    dataset=DatasetConfig(trajectories=12, particles=200, keep=64),
                    config=TrainConfig(steps=60, save_every=5, eval_every=5, batch_sets=4,
                                       targets_per_set=16, set_sizes=(16,)))
"""
TRAIN_CMD = [sys.executable, "-c", TRAIN_SCRIPT]


def _final_params(out):
    from csf_jax.training import checkpoint
    mngr = checkpoint.manager(os.path.join(out, "ckpt"), 5)
    state = init_state(jax.random.key(0), networks.NetworkConfig(), 1, TrainConfig())
    restored, meta = checkpoint.restore(mngr, state)
    return int(restored.step), restored.params


def _run(out, env, **kw):
    return subprocess.run(TRAIN_CMD + [out], env=env, capture_output=True, text=True,
                          cwd=ROOT, timeout=300, **kw)


def _kill_mid_training(out, env):
    """Start the CLI, SIGKILL it once a checkpoint at step >= 15 exists; return that step."""
    proc = subprocess.Popen(TRAIN_CMD + [out], env=env, stderr=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, cwd=ROOT)
    ckpt = os.path.join(out, "ckpt")
    deadline = time.time() + 240
    steps = []
    while time.time() < deadline and proc.poll() is None:
        steps = [int(s) for s in os.listdir(ckpt) if s.isdigit()] if os.path.isdir(ckpt) else []
        if steps and max(steps) >= 15:
            break
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "training ended before it could be killed"
    return max(steps)


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}


@pytest.mark.slow  # a fresh process and its compilations: run with -m slow
def test_kill_dash_nine_then_resume(tmp_path):
    """SIGKILL mid-training, then the same command again: it resumes from the last complete
    checkpoint (not from scratch), finishes, and the checkpoint it restores is intact."""
    out = str(tmp_path / "killed")
    killed_at = _kill_mid_training(out, ENV)
    again = _run(out, ENV)
    assert again.returncode == 0, again.stderr[-2000:]
    resumed = int(again.stderr.split("resumed from step ")[1].split()[0])
    assert resumed >= killed_at - 5  # at most one save interval lost
    step, params = _final_params(out)
    assert step == 60
    assert all(bool(jnp.isfinite(x).all()) for x in jax.tree_util.tree_leaves(params))


@pytest.mark.slow
def test_resumed_run_equals_uninterrupted_run(tmp_path):
    """Batches depend only on (seed, step): a killed-and-resumed run ends with the parameters of an
    uninterrupted one."""
    killed, clean = str(tmp_path / "killed"), str(tmp_path / "clean")
    _kill_mid_training(killed, ENV)
    assert _run(killed, ENV).returncode == 0
    assert _run(clean, ENV).returncode == 0
    step_a, params_a = _final_params(killed)
    step_b, params_b = _final_params(clean)
    assert step_a == step_b == 60
    for a, b in zip(jax.tree_util.tree_leaves(params_a), jax.tree_util.tree_leaves(params_b)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_pretrained_for_wrong_dimension_fails_clearly():
    dw = load_pretrained("double_well")
    model = problems.get("cubic10_corr", num_steps=2)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 16)
    with pytest.raises(ValueError, match="d=1.*d=10"):
        csf_jax.filter(dw.params, obs, ens, model=model, network=dw.network,
                       key=jax.random.key(2))


def test_shipped_models_were_trained_by_their_committed_recipe():
    """Every shipped model's recorded training config is ``csf_jax.pretrained.TRAIN`` of its
    problem and its network ``NETWORK``, so ``python -m experiments.train --export`` remakes what
    ships (fields added to TrainConfig after a model was made are read as their defaults); the
    benchmark times that network."""
    import json

    from csf_jax.pretrained import DATASETS, NETWORK, TRAIN
    from experiments.bench import network

    defaults = json.loads(json.dumps(dataclasses.asdict(TrainConfig())))
    for name in DATASETS:
        assert load_pretrained(name).network == NETWORK[name] == network(), name
        recorded = load_pretrained(name).meta["train"]
        expected = json.loads(json.dumps(dataclasses.asdict(TRAIN[name])))
        got = {k: recorded.get(k, defaults[k]) for k in expected}
        assert got == expected, name
