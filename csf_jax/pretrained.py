"""Shipped pretrained priors: ``csf_jax.load_pretrained("double_well")``.

Each model lives in ``csf_jax/pretrained_models/<name>/`` as an orbax checkpoint of the parameters
plus ``meta.json`` (problem, dimension, network and training configs, dataset id, seed, validation
history, training seconds). ``triple_well`` uses the double-well model (the paper's transfer
experiment). They are made by ``python -m experiments.train --export`` (docs/guide.md). They
load on any platform and device count: the ``cpu:0`` shardings their orbax metadata records are
ignored and the parameters restored onto the default device (``csf_jax.trained.load_dir``).

A loaded model is a ``csf_jax.TrainedPrior`` carrying the fingerprint of its problem's default
model (``with_fingerprint``); pass it whole to ``csf_jax.filter`` (the checked route), which
refuses it for a model with other dynamics, naming what differs. A damaged or inconsistent model folder fails with one line naming the folder and
the mismatching field.
"""

from __future__ import annotations

import os

from csf_jax import networks, problems
from csf_jax.trained import TrainedPrior, export, load_dir, model_fingerprint  # noqa: F401
from csf_jax.trained import deprecated_alias as _deprecated_alias
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

# Network of each shipped model: the ensemble's Gaussian score plus a learned correction on
# standardised coordinates (NetworkConfig.base), so an untrained or useless correction
# leaves the ensemble's own Gaussian. Whole-score models (no Gaussian base) needed a much longer
# run on the cubic problems; the Gaussian-base ones start at the Gaussian's loss, and
# TrainConfig's default steps are the recipe for every problem (measured on docs/guide.md,
# "Training a prior offline", and docs/design.md).
NETWORK = {name: networks.NetworkConfig(base="gaussian") for name in DATASETS}

# Training of each shipped model; the wells' model learns both wells by mirroring (see TrainConfig).
TRAIN = {name: TrainConfig(mirror=name == "double_well") for name in DATASETS}


def available() -> tuple[str, ...]:
    """Problems with a shipped model."""
    return tuple(p for p, m in MODEL_FOR.items()
                 if os.path.exists(os.path.join(MODEL_DIR, m, "meta.json")))


def load_pretrained(problem: str) -> TrainedPrior:
    """The shipped model for ``problem`` (triple_well gets the double-well model)."""
    if problem not in MODEL_FOR:
        raise KeyError(f"no pretrained model for {problem!r}; known: {', '.join(MODEL_FOR)}")
    path = os.path.join(MODEL_DIR, MODEL_FOR[problem])
    if not os.path.exists(os.path.join(path, "meta.json")):
        raise FileNotFoundError(f"the pretrained model for {problem!r} is missing from {path}; "
                                f"make it with: python -m experiments.train "
                                f"{MODEL_FOR[problem]} --export")
    model = MODEL_FOR[problem]
    return with_fingerprint(load_dir(path, serves=() if model == problem else (problem,)))


def with_fingerprint(prior: TrainedPrior) -> TrainedPrior:
    """``prior`` with ``meta["model"]``, the ``model_fingerprint`` of its registered problem at
    its default settings (``problems.get(prior.problem)``), where the record has none.

    The shipped folders were written before priors recorded their model; the fingerprint is
    computed here, on load, rather than stored, so the folders stay as they are and the probe
    points come from this platform's own random numbers. ``csf_jax.filter`` then refuses the
    shipped prior for a model whose dynamics differ from the one it was trained on (see
    ``csf_jax.trained.model_fingerprint``): its drift (``dt``, ``C``, the wells, the cubic's
    coupling), observation map and noises (``process_std``, ``obs_std``, ``obs_scale``, the
    noise law), dimensions and initial law (``x0_mean``, ``x0_std``). Settings outside the
    dynamics are not compared: the length ``num_steps`` and the truth's shocks (``shock_count``,
    ``shock_size``), which only the simulated data see.
    """
    if "model" in prior.meta or prior.problem not in problems.CONFIGS:
        return prior
    model = problems.get(prior.problem)
    return prior._replace(meta={**prior.meta, "model": model_fingerprint(model)})


def __getattr__(name: str):
    """``Pretrained``: the deprecated name of ``TrainedPrior`` (a ``DeprecationWarning``)."""
    return _deprecated_alias(__name__, name)
