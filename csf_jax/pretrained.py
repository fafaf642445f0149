"""Shipped pretrained priors: ``csf_jax.load_pretrained("double_well")``.

Each model lives in ``csf_jax/pretrained_models/<name>/`` as an orbax checkpoint of the parameters
plus ``meta.json`` (problem, dimension, network and training configs, dataset id, seed, validation
history, training seconds). ``triple_well`` uses the double-well model (the paper's transfer
experiment). They are made by ``python -m experiments.make_pretrained`` (see the README).

A loaded model is a ``csf_jax.trained.Pretrained``; pass it whole to ``csf_jax.filter`` (the
checked route). A damaged or inconsistent model folder fails with one line naming the folder and
the mismatching field.
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import orbax.checkpoint as ocp

from csf_jax import networks
from csf_jax.trained import Pretrained  # noqa: F401  (the type load_dir returns)
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
# standardised coordinates (NetworkConfig.base, issue 11), so an untrained or useless correction
# leaves the ensemble's own Gaussian. The whole-score models of earlier sessions needed 12000 steps
# on the cubic problems; the Gaussian-base ones start at the Gaussian's loss, and 4000 steps are
# the recipe for every problem (docs/results.md).
NETWORK = {name: networks.NetworkConfig(base="gaussian") for name in DATASETS}

# Training of each shipped model; the wells' model learns both wells by mirroring (see TrainConfig).
TRAIN = {name: TrainConfig(mirror=name == "double_well") for name in DATASETS}


def export(directory: str, params, network: networks.NetworkConfig, meta: dict) -> None:
    """Write ``params`` (orbax) and ``meta.json`` to ``directory`` (replacing what is there).

    ``meta`` must name the ``problem`` and its ``dim``; ``params`` are checked against
    ``network`` and ``dim`` first, so an exported model always loads.
    """
    missing = [k for k in ("problem", "dim") if k not in meta]
    if missing:
        raise ValueError(f"export: meta must record {' and '.join(missing)} (the problem the "
                         f"model was trained for)")
    networks.check_params(params, network, int(meta["dim"]), name=f"export to {directory}: params")
    directory = os.path.abspath(directory)
    os.makedirs(directory, exist_ok=True)
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(os.path.join(directory, "params"), params, force=True)
    with open(os.path.join(directory, "meta.json"), "w") as f:
        json.dump({**meta, "network": dataclasses.asdict(network)}, f, indent=1)


def _read_meta(directory: str) -> tuple[dict, networks.NetworkConfig, int]:
    """``(meta, network, dim)`` from ``directory/meta.json``; one-line errors naming the folder."""
    path = os.path.join(directory, "meta.json")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"model {directory}: no meta.json there (not a folder written by "
                                f"csf_jax.pretrained.export)")
    try:
        with open(path) as f:
            meta = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"model {directory}: meta.json cannot be read ({type(e).__name__}: {e})"
                         ) from None
    if not isinstance(meta, dict):
        raise ValueError(f"model {directory}: meta.json must hold a JSON object")
    for field in ("problem", "dim", "network"):
        if field not in meta:
            raise ValueError(f"model {directory}: meta.json has no {field!r} field")
    try:
        network = networks.NetworkConfig(**meta["network"])
        dim = int(meta["dim"])
    except (TypeError, ValueError) as e:
        raise ValueError(f"model {directory}: meta.json's network/dim fields are invalid ({e})"
                         ) from None
    return meta, network, dim


def _stored_shapes(params_dir: str, directory: str):
    """The parameter tree of shapes ``(ShapeDtypeStruct)`` saved in ``params_dir``."""
    if not os.path.isdir(params_dir):
        raise FileNotFoundError(f"model {directory}: its parameter folder {params_dir} is missing")
    try:
        with ocp.StandardCheckpointer() as ckpt:
            item = ckpt.metadata(params_dir).item_metadata
        if item is None:
            raise ValueError("its array metadata (_METADATA) is missing or unreadable")
        tree = item.tree
        return jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), tree)
    except Exception as e:  # noqa: BLE001  (orbax, tensorstore and JSON errors alike)
        raise ValueError(f"model {directory}: the parameters in {params_dir} cannot be read "
                         f"({type(e).__name__}: {_first_line(e)})") from None


def _check_stored(shapes, network: networks.NetworkConfig, dim: int, directory: str) -> None:
    """Refuse stored parameter shapes that ``meta.json``'s network config and dim do not build,
    naming the folder and the field that differs."""
    try:
        stored_dim = networks.params_dim(shapes)
    except (KeyError, TypeError, IndexError):
        stored_dim = dim
    if stored_dim != dim:
        raise ValueError(f"model {directory}: meta.json says dim={dim}, but the stored parameters "
                         f"were made for dim={stored_dim}")
    try:
        networks.check_params(shapes, network, dim, name="the stored parameters")
    except ValueError as e:
        guess = networks.mismatched_field(shapes, network, dim)
        if guess is None:
            raise ValueError(f"model {directory}: meta.json does not match the stored parameters "
                             f"({e})") from None
        field, value = guess
        said = dim if field == "dim" else getattr(network, field)
        where = "dim" if field == "dim" else f"network.{field}"
        raise ValueError(f"model {directory}: meta.json says {where}={said}, but the stored "
                         f"parameters were made with {field}={value}") from None


def _first_line(error: Exception, limit: int = 120) -> str:
    first = (str(error).strip().splitlines() or [""])[0]
    return first if len(first) <= limit else first[:limit - 3] + "..."


def load_dir(directory: str, serves: tuple = ()) -> Pretrained:
    """Load a model written by ``export``.

    Checks ``meta.json`` against the stored array shapes before restoring anything: a damaged or
    inconsistent folder fails with one line naming it and the mismatching field.
    serves: further problem names the model may filter (see ``Pretrained``).
    """
    directory = os.path.abspath(directory)
    meta, network, dim = _read_meta(directory)
    params_dir = os.path.join(directory, "params")
    _check_stored(_stored_shapes(params_dir, directory), network, dim, directory)
    target = networks._expected_params(network, dim)
    try:
        with ocp.StandardCheckpointer() as ckpt:
            params = ckpt.restore(params_dir, target)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"model {directory}: the parameters in {params_dir} cannot be restored "
                         f"({type(e).__name__}: {_first_line(e)})") from None
    return Pretrained(jax.tree_util.tree_map(jax.numpy.asarray, params), network, meta,
                      tuple(serves))


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
    model = MODEL_FOR[problem]
    return load_dir(path, serves=() if model == problem else (problem,))
