"""The offline training loop: encoder and score net jointly, optax Adam with a step decay.

Resumable: the loop restores the latest intact checkpoint of ``out_dir`` if there is one (after
checking it was made for the same problem, network, data, seed and training settings, and is not
beyond the requested steps) and continues; newer, damaged checkpoints are moved aside with a
message (``checkpoint.restore_intact``). Batches are a pure function of ``(seed, step)``, so a
resumed run sees exactly the batches an uninterrupted one would have. A loss that stops being
finite ends the run with a FloatingPointError.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from csf_jax import _checks, networks
from csf_jax.training import checkpoint
from csf_jax.training.data import Dataset, sample_batch
from csf_jax.training.loss import batch_loss, draw_noise
from csf_jax.training.progress import Progress


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training settings; defaults are those of the shipped models.

    Attributes:
      steps: optimizer steps.
      batch_sets: ensembles per step.
      targets_per_set: ``x0`` per ensemble (one encoder pass serves them all).
      set_sizes: sizes of the random subsets the encoder sees, cycled over steps (the encoder
        learns size independence; one compilation per size).
      lr: Adam's learning rate at the start.
      lr_decay: the factor of the staircase step decay (the paper's StepLR).
      lr_decay_every: optimizer steps between two decays.
      grad_clip: global-norm clipping.
      t_min: smallest diffusion time.
      save_every: checkpoint interval.
      eval_every: held-out loss interval.
      valid_sets: held-out ensembles.
      seed: the training seed.
      mirror: flip the sign of each training ensemble (with its targets) with probability 1/2. A
        data augmentation for odd-symmetric models (``f(-x) = -f(x)``, symmetric noises: the
        wells), whose PF rollouts rarely visit the mirror well because the PF loses the truth after
        a shock.
    """

    steps: int = 4000
    batch_sets: int = 16
    targets_per_set: int = 64
    set_sizes: tuple = (32, 64, 128)
    lr: float = 2e-3
    lr_decay: float = 0.5
    lr_decay_every: int = 1500
    grad_clip: float = 1.0
    t_min: float = 1e-3
    save_every: int = 250
    eval_every: int = 250
    valid_sets: int = 64
    seed: int = 0
    mirror: bool = False

    def __post_init__(self):
        _checks.check_fields(self)
        if self.steps < 1 or self.batch_sets < 1 or self.targets_per_set < 1:
            raise ValueError("TrainConfig.steps, batch_sets and targets_per_set must be >= 1")
        if not self.set_sizes or min(self.set_sizes) < 2:
            raise ValueError(f"TrainConfig.set_sizes must be sizes >= 2, got {self.set_sizes}")


class TrainState(NamedTuple):
    """What a checkpoint holds besides its meta record."""

    params: dict
    opt_state: optax.OptState
    step: jax.Array


def optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """Adam with global-norm clipping and a staircase exponential decay (StepLR)."""
    schedule = optax.exponential_decay(config.lr, config.lr_decay_every, config.lr_decay,
                                       staircase=True)
    return optax.chain(optax.clip_by_global_norm(config.grad_clip), optax.adam(schedule))


def init_state(key, network: networks.NetworkConfig, dim: int, config: TrainConfig) -> TrainState:
    """Fresh parameters and optimizer state."""
    params = networks.init_params(key, network, dim)
    return TrainState(params, optimizer(config).init(params), jnp.zeros((), jnp.int32))


@functools.partial(jax.jit, static_argnames=("network", "config"), donate_argnums=(0,))
def train_step(state: TrainState, subsets, x0, key, full=None, *, network, config: TrainConfig):
    """One optimizer step on ``subsets (B, n, d)`` and targets ``x0 (B, T, d)`` (``full (B, M, d)``:
    the whole ensembles, for a Gaussian-base network); returns ``(state, loss)``."""
    t, z = draw_noise(key, x0.shape[:2], x0.shape[-1], config.t_min)
    loss, grads = jax.value_and_grad(batch_loss)(state.params, network, subsets, x0, t, z, full)
    updates, opt_state = optimizer(config).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    return TrainState(params, opt_state, state.step + 1), loss


@functools.partial(jax.jit, static_argnames=("network", "t_min"))
def eval_loss(params, subsets, x0, key, full=None, *, network, t_min: float):
    """Held-out loss with fixed noise (same key, same number)."""
    t, z = draw_noise(key, x0.shape[:2], x0.shape[-1], t_min)
    return batch_loss(params, network, subsets, x0, t, z, full)


def make_batch(data: Dataset, config: TrainConfig, step: int, split: str = "train",
               full: bool = False):
    """The batch of ``step``: a pure function of ``(seed, step)``. Returns ``subsets (B, n, d)``
    with n = ``set_sizes[step % len]`` and targets ``x0 (B, T, d)`` drawn from the whole ensembles;
    with ``full``, also the whole ensembles ``(B, M, d)`` (a Gaussian-base network's moments)."""
    rng = np.random.default_rng([config.seed, step, 0 if split == "train" else 1])
    ens = sample_batch(data, rng, config.batch_sets if split == "train" else config.valid_sets,
                       split)
    n = min(config.set_sizes[step % len(config.set_sizes)], ens.shape[1])
    keep = ens.shape[1]
    sub_idx = np.argsort(rng.random((ens.shape[0], keep)), axis=1)[:, :n]
    tgt_idx = rng.integers(0, keep, (ens.shape[0], config.targets_per_set))
    subsets = np.take_along_axis(ens, sub_idx[..., None], axis=1)
    x0 = np.take_along_axis(ens, tgt_idx[..., None], axis=1)
    if config.mirror and split == "train":
        sign = rng.choice(np.array([-1.0, 1.0], np.float32), (ens.shape[0], 1, 1))
        subsets, x0, ens = subsets * sign, x0 * sign, ens * sign
    return (subsets, x0, ens) if full else (subsets, x0)


def train(problem: str, data: Dataset, out_dir: str, *, network: networks.NetworkConfig,
          config: TrainConfig, log_every: int = 50, verbose: bool = True):
    """Train (or resume) and return ``(params, meta)``; checkpoints under ``out_dir``."""
    dim = int(data.ensembles.shape[-1])
    meta = {"problem": problem, "dim": dim, "network": dataclasses.asdict(network),
            "train": dataclasses.asdict(config), "dataset_id": data.id, "seed": config.seed,
            "valid_loss": [], "seconds": 0.0}
    meta["train"]["set_sizes"] = list(config.set_sizes)
    _checks.check_folder(out_dir, f"train {problem}: the checkpoint folder", writable=True)
    with checkpoint.manager(out_dir, config.save_every) as mngr:
        return _train(problem, data, out_dir, mngr, meta, network, config, log_every, verbose)


def _train(problem: str, data: Dataset, out_dir: str, mngr, meta: dict,
           network: networks.NetworkConfig, config: TrainConfig, log_every: int, verbose: bool):
    """``train``'s loop on an open checkpoint manager ``mngr``."""
    dim = int(meta["dim"])
    state = init_state(jax.random.key(config.seed), network, dim, config)
    restored = checkpoint.restore_intact(mngr, state, meta, lambda msg: _log(True, msg))
    if restored is not None:
        state, found = restored
        if int(state.step) > config.steps:
            raise ValueError(f"train {problem}: the checkpoint in {out_dir} is at step "
                             f"{int(state.step)}, beyond the requested steps={config.steps}; ask "
                             f"for steps >= {int(state.step)} to continue it, or use another "
                             f"directory (or delete {out_dir}) to train afresh")
        meta["valid_loss"], meta["seconds"] = found["valid_loss"], found["seconds"]
        _log(verbose, f"[train {problem}] resumed from step {int(state.step)} in {out_dir}")
    full = network.base == "gaussian"
    valid = make_batch(data, dataclasses.replace(config, set_sizes=(max(config.set_sizes),)), 0,
                       "valid", full)
    valid_key = jax.random.key(10_000 + config.seed)
    start, t_start, ema = int(state.step), time.perf_counter(), None
    step = start
    progress = Progress(f"[train {problem}]", config.steps, start, unit="steps",
                        per_unit=(config.batch_sets, "sets"), verbose=verbose)
    for step in range(start, config.steps):
        batch = make_batch(data, config, step, full=full)
        key = jax.random.fold_in(jax.random.key(config.seed), step)
        state, loss = train_step(state, batch[0], batch[1], key, *batch[2:], network=network,
                                 config=config)
        done = step + 1
        if done % log_every == 0 or done == config.steps:
            loss = float(loss)
            _check_loss(problem, loss, done, data.id)
            ema = loss if ema is None else 0.9 * ema + 0.1 * loss
            progress.report(done, f"loss {ema:.4f}")
        if done % config.eval_every == 0 or done == config.steps:
            v = float(eval_loss(state.params, valid[0], valid[1], valid_key, *valid[2:],
                                network=network,
                                t_min=config.t_min))
            _check_loss(problem, v, done, data.id)
            meta["valid_loss"].append([done, v])
            progress.note(f"valid {v:.4f}", done)
        if done % config.save_every == 0 or done == config.steps:
            now = time.perf_counter()
            meta["seconds"] += now - t_start
            t_start, start = now, done
            checkpoint.save(mngr, done, state, meta, force=True)
    mngr.wait_until_finished()
    progress.close()
    return state.params, meta


def _check_loss(problem: str, loss: float, step: int, dataset: str) -> None:
    """Stop a run whose loss is no longer finite, naming the likely causes."""
    if not math.isfinite(loss):
        raise FloatingPointError(f"train {problem}: the loss became {loss} by step {step}; the "
                                 f"training data (dataset {dataset}) may hold NaN/inf, or the "
                                 f"learning rate is too large (TrainConfig.lr)")


def _log(verbose: bool, msg: str, end: str = "\n") -> None:
    if verbose:
        print(msg, end=end, file=sys.stderr, flush=True)
