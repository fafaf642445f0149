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
from csf_jax.pretrained import MODEL_FOR, load_pretrained
from csf_jax.training import DatasetConfig, TrainConfig, generate, load, train
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
    r = csf_jax.filter(params, obs, ens, problem=model, network=SMALL_NET, key=jax.random.key(2),
                       config=csf_jax.CSFConfig(reverse_steps=20))
    assert bool(jnp.isfinite(r.mean).all())


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


TRAIN_CMD = [sys.executable, "-m", "experiments.train", "double_well", "--trajectories", "12",
             "--particles", "200", "--keep", "64", "--steps", "60", "--save-every", "5",
             "--batch-sets", "4", "--targets", "16", "--set-sizes", "16"]


def _final_params(out):
    from csf_jax.training import checkpoint
    mngr = checkpoint.manager(os.path.join(out, "ckpt"), 5)
    state = init_state(jax.random.key(0), networks.NetworkConfig(), 1, TrainConfig())
    restored, meta = checkpoint.restore(mngr, state)
    return int(restored.step), restored.params


def test_kill_dash_nine_then_resume_loses_nothing(tmp_path):
    """SIGKILL mid-training, rerun the same command: it resumes from the last complete checkpoint
    and ends with exactly the parameters of an uninterrupted run (batches depend only on the step)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    killed = str(tmp_path / "killed")
    proc = subprocess.Popen(TRAIN_CMD + ["--out", killed], env=env, stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, cwd=os.path.dirname(os.path.dirname(__file__)))
    ckpt = os.path.join(killed, "ckpt")
    deadline = time.time() + 120
    while time.time() < deadline:
        steps = [int(s) for s in os.listdir(ckpt) if s.isdigit()] if os.path.isdir(ckpt) else []
        if steps and max(steps) >= 15:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    again = subprocess.run(TRAIN_CMD + ["--out", killed], env=env, capture_output=True, text=True,
                           cwd=os.path.dirname(os.path.dirname(__file__)), timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "resumed from step" in again.stderr
    clean = str(tmp_path / "clean")
    subprocess.run(TRAIN_CMD + ["--out", clean], env=env, capture_output=True, check=True,
                   cwd=os.path.dirname(os.path.dirname(__file__)), timeout=300)
    step_a, params_a = _final_params(killed)
    step_b, params_b = _final_params(clean)
    assert step_a == step_b == 60
    for a, b in zip(jax.tree_util.tree_leaves(params_a), jax.tree_util.tree_leaves(params_b)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", problems.NAMES)
def test_shipped_models_load_and_filter(name):
    model_params = load_pretrained(name)
    assert model_params.meta["problem"] == MODEL_FOR[name]
    model = problems.get(name, num_steps=3)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 64)
    r = csf_jax.filter(model_params.params, obs, ens, problem=model,
                       network=model_params.network, key=jax.random.key(2),
                       config=csf_jax.CSFConfig(reverse_steps=50))
    assert bool(jnp.isfinite(r.mean).all())


def test_pretrained_for_wrong_dimension_fails_clearly():
    dw = load_pretrained("double_well")
    model = problems.get("cubic10_corr", num_steps=2)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), 16)
    with pytest.raises(ValueError, match="d=1.*d=10"):
        csf_jax.filter(dw.params, obs, ens, problem=model, network=dw.network,
                       key=jax.random.key(2))
