"""Shipped pretrained priors: ``csf_jax.load_pretrained("double_well")``.

Each model lives in ``csf_jax/pretrained_models/<name>/`` as an orbax checkpoint of the parameters
plus ``meta.json`` (problem, dimension, network and training configs, dataset id, seed, validation
history, training seconds). ``triple_well`` uses the double-well model (the paper's transfer
experiment). They are made by ``python -m experiments.make_pretrained`` (see the README).
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import NamedTuple

import jax
import orbax.checkpoint as ocp

from csf_jax import networks
from csf_jax.training.data import DatasetConfig
from csf_jax.training.train import TrainConfig

MODEL_DIR = os.path.join(os.path.dirname(__file__), "pretrained_models")

# Which model serves which problem.
MODEL_FOR = {"double_well": "double_well", "triple_well": "double_well", "cauchy": "cauchy",
             "cubic10_indep": "cubic10_indep", "cubic10_corr": "cubic10_corr",
             "cubic20_indep": "cubic20_indep", "cubic20_corr": "cubic20_corr"}

# Dataset of each shipped model (paper: M = 1000 wells/Cauchy, M = 2000 cubic; N = 1000).
DATASETS = {
    "double_well": DatasetConfig(trajectories=1000, keep=256, stride=1),
    "cauchy": DatasetConfig(trajectories=1000, keep=256, stride=2),
    "cubic10_indep": DatasetConfig(trajectories=2000, keep=128, stride=2),
    "cubic10_corr": DatasetConfig(trajectories=2000, keep=128, stride=2),
    "cubic20_indep": DatasetConfig(trajectories=2000, keep=128, stride=2),
    "cubic20_corr": DatasetConfig(trajectories=2000, keep=128, stride=2),
}

# Training of each shipped model; the wells' model learns both wells by mirroring (see TrainConfig).
# The cubic models train 3x longer (their validation loss was still falling at 4000 steps; the
# longer schedule lowered cubic10_corr's filter RMSE on two runs from 0.92 to 0.82, docs/results.md).
LONG = TrainConfig(steps=12000, lr_decay_every=4000, save_every=1000, eval_every=1000)
TRAIN = {name: LONG if name.startswith("cubic") else TrainConfig(mirror=name == "double_well")
         for name in DATASETS}


class Pretrained(NamedTuple):
    """A loaded model: ``params`` for ``csf_jax.filter``, its ``network`` config, its ``meta``."""

    params: dict
    network: networks.NetworkConfig
    meta: dict


def export(directory: str, params, network: networks.NetworkConfig, meta: dict) -> None:
    """Write ``params`` (orbax) and ``meta.json`` to ``directory`` (replacing what is there)."""
    directory = os.path.abspath(directory)
    os.makedirs(directory, exist_ok=True)
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(os.path.join(directory, "params"), params, force=True)
    with open(os.path.join(directory, "meta.json"), "w") as f:
        json.dump({**meta, "network": dataclasses.asdict(network)}, f, indent=1)


def load_dir(directory: str) -> Pretrained:
    """Load a model written by ``export``; checks the parameters against the stored config."""
    directory = os.path.abspath(directory)
    with open(os.path.join(directory, "meta.json")) as f:
        meta = json.load(f)
    network = networks.NetworkConfig(**meta["network"])
    target = networks._expected_params(network, int(meta["dim"]))
    with ocp.StandardCheckpointer() as ckpt:
        params = ckpt.restore(os.path.join(directory, "params"), target)
    networks.check_params(params, network, int(meta["dim"]), name=f"model {directory}")
    return Pretrained(jax.tree_util.tree_map(jax.numpy.asarray, params), network, meta)


def available() -> tuple[str, ...]:
    """Problems with a shipped model."""
    return tuple(p for p, m in MODEL_FOR.items()
                 if os.path.exists(os.path.join(MODEL_DIR, m, "meta.json")))


def load_pretrained(problem: str) -> Pretrained:
    """The shipped model for ``problem`` (triple_well gets the double-well model)."""
    if problem not in MODEL_FOR:
        raise KeyError(f"no pretrained model for {problem!r}; known: {', '.join(MODEL_FOR)}")
    path = os.path.join(MODEL_DIR, MODEL_FOR[problem])
    if not os.path.exists(os.path.join(path, "meta.json")):
        raise FileNotFoundError(f"the pretrained model for {problem!r} is missing from {path}; "
                                f"make it with: python -m experiments.make_pretrained "
                                f"{MODEL_FOR[problem]}")
    return load_dir(path)
