"""``csf_jax.train_prior``: the offline stage for any ``StateSpaceModel``, in one call.

    trained = csf_jax.train_prior(model, jax.random.key(0), directory="runs/my_model")
    trained.save("my_prior")                       # later: csf_jax.load_prior("my_prior", model)
    result = csf_jax.filter(trained, obs, ensemble, model=model, key=key)

It records the particle-filter prior ensembles of ``model`` (``csf_jax.training.data``), trains the
set encoder and score net on them (``csf_jax.training.train``) with progress lines on stderr and
orbax checkpoints, and returns a ``TrainedPrior`` that records the model's fingerprint. Everything
lives under ``directory``: interrupt it at any moment (even ``kill -9``) and call it again with the
same arguments to resume from the last finished data chunk and checkpoint.

Defaults (``DATASET``, ``TRAIN``, ``NETWORK``): 200 PF rollouts of 1000 particles, 128 kept per
recorded step, every second step, then 1500 optimizer steps of the Gaussian-base network (the
ensemble's own Gaussian score plus a learned correction). The shipped priors' learned correction
learns nothing beyond the Gaussian on PF-rollout data, so the smaller recipe loses nothing and
trains a d <= 10 model quickly on a CPU (both measured on docs/design.md, "``train_prior``'s
recipe").
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks, networks, problems
from csf_jax.ssm import StateSpaceModel, Step, at_step, check_model
from csf_jax.trained import TrainedPrior, model_fingerprint
from csf_jax.training.data import DatasetConfig, generate, load
from csf_jax.training.train import TrainConfig, train

DATASET = DatasetConfig(trajectories=200, particles=1000, keep=128, stride=2, dtype="float32")
TRAIN = TrainConfig(steps=1500, lr_decay_every=600)
NETWORK = networks.NetworkConfig(base="gaussian")


def key_seed(key) -> int:
    """A non-negative int seed from a JAX key: ``jax.random.key(s)`` gives ``s`` (so
    ``jax.random.key(0)`` reproduces the seed-0 recipes); any other key a hash of its bits."""
    data = np.asarray(jax.random.key_data(key)).astype(np.uint64).ravel()
    if data.size == 2 and data[0] == 0:
        return int(data[1])
    return int(np.bitwise_xor.reduce(data * np.uint64(0x9E3779B97F4A7C15)) % np.uint64(2 ** 62))


def _check_model(model) -> StateSpaceModel:
    if isinstance(model, str):
        return problems.get(model)
    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"train_prior: model must be a csf_jax.StateSpaceModel (or a built-in "
                        f"problem's name), got {type(model).__name__}")
    check_model(model, "train_prior")
    x = model.initial_ensemble(jax.random.key(0), 4)
    if np.shape(x) != (4, model.dim):
        raise ValueError(f"train_prior: model {model.name!r}: initial_ensemble(key, 4) has shape "
                         f"{np.shape(x)}, expected (4, {model.dim})")
    probe = at_step(model, Step(jnp.asarray(1, jnp.int32), None))
    try:
        fx, hx = jax.vmap(probe.drift)(x), jax.vmap(probe.observe)(x)
    except (TypeError, AttributeError) as e:
        if not model.time_varying:
            raise
        raise ValueError(f"train_prior: model {model.name!r} is time-varying and its drift or "
                         f"observe needs a per-step input (step.u); train_prior records rollouts "
                         f"without inputs ({type(e).__name__}: {e})") from None
    if np.shape(fx) != (4, model.dim) or np.shape(hx) != (4, model.obs_dim):
        raise ValueError(f"train_prior: model {model.name!r}: drift gives {np.shape(fx)[1:]} and "
                         f"observe {np.shape(hx)[1:]} per particle; expected ({model.dim},) and "
                         f"({model.obs_dim},)")
    for label, values in (("drift", fx), ("observe", hx), ("initial_ensemble", x)):
        if not np.isfinite(np.asarray(values)).all():
            raise ValueError(f"train_prior: model {model.name!r}: its {label} gives NaN/inf at "
                             f"points of its initial ensemble; check the model's {label}")
    return model


def train_prior(model: StateSpaceModel | str, key, *, directory: str | None = None,
                dataset: DatasetConfig = DATASET, config: TrainConfig = TRAIN,
                network: networks.NetworkConfig = NETWORK, verbose: bool = True) -> TrainedPrior:
    """Train a CSF prior for ``model``; returns a ``TrainedPrior`` for ``csf_jax.filter``.

    Args:
      model: any ``StateSpaceModel`` (or a built-in problem's name). Its ``initial_ensemble``,
        ``drift``, process noise and likelihood drive the particle-filter rollouts that make the
        training data; its ``num_steps`` is the rollout length.
      key: one ``jax.random.key`` (or a legacy uint32 ``(2,)`` key); the seeds of the data and
        of the training come from it (``key_seed``). Same key, same prior.
      directory: where the data (``data/``) and checkpoints (``ckpt/``) live, for resuming
        (default ``runs/<model.name>``). A directory made for another model, dataset, training
        config (a longer ``steps`` continues the run) or key is refused with the differing fields
        named; so is damaged data (a truncated ``data/ensembles.npy`` or ``meta.json``).
      dataset: what to record (``DatasetConfig``; its seed is replaced by the key's).
      config: the training (``TrainConfig``; its seed is replaced by the key's).
      network: the encoder and score-net architecture (``NetworkConfig``).
      verbose: progress lines on stderr (data chunks, then steps, loss and validation loss).

    Returns:
      ``TrainedPrior(params, network, meta)``; ``meta`` records the model's fingerprint, the
      configs, the dataset id, the validation losses and the seconds spent.
    """
    _checks.check_key(key, "train_prior")
    for label, value, kind in (("dataset", dataset, DatasetConfig), ("config", config, TrainConfig),
                               ("network", network, networks.NetworkConfig)):
        if not isinstance(value, kind):
            raise TypeError(f"train_prior: {label}= must be a csf_jax.{kind.__name__}, got "
                            f"{type(value).__name__}")
    spec, model = model, _check_model(model)  # a registry name keeps its name-based dataset id
    seed = key_seed(key)
    directory = (os.path.join("runs", model.name) if directory is None
                 else _checks.check_path(directory, "train_prior: directory"))
    _checks.check_folder(directory, "train_prior: directory", writable=True)
    dataset = dataclasses.replace(dataset, seed=seed)
    config = dataclasses.replace(config, seed=seed)
    t0 = time.perf_counter()
    data_dir = os.path.join(directory, "data")
    generate(spec, dataset, data_dir, verbose=verbose)
    data_seconds = time.perf_counter() - t0
    params, meta = train(model.name, load(data_dir), os.path.join(directory, "ckpt"),
                         network=network, config=config, verbose=verbose)
    meta = {**meta, "obs_dim": int(model.obs_dim), "model": model_fingerprint(model),
            "dataset": dataclasses.asdict(dataset), "data_seconds": round(data_seconds, 1)}
    if verbose:
        final = meta["valid_loss"][-1][1] if meta["valid_loss"] else float("nan")
        print(f"[train_prior {model.name}] done: data {data_seconds:.0f} s, training "
              f"{meta['seconds']:.0f} s, validation loss {final:.4f}", file=sys.stderr, flush=True)
    return TrainedPrior(params, network, meta)
