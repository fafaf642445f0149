"""A trained prior: parameters together with the network config and the model they were made for.

``TrainedPrior`` is what ``csf_jax.train_prior``, ``csf_jax.load_prior`` and
``csf_jax.load_pretrained`` return and what ``csf_jax.filter`` checks when given it whole: the
filter takes the network config from it and refuses a model, a ``network=`` or a ``sigma_max`` it
was not trained for, naming both sides. Raw parameter dicts still work, but nothing about them can
be checked beyond their shapes.

On disk a trained prior is a folder: an orbax checkpoint of the parameters (``params/``) and
``meta.json`` (model fingerprint, network and training configs, dataset id, validation history).
``save`` writes one, ``load_prior`` reads one and checks it against the model it is meant for.
The parameters are written as host arrays and restored onto this process's default device, so a
folder loads on any platform and device count, whatever devices its orbax metadata records.

A model is identified by its ``model_fingerprint``: name, dimensions, noise settings, and the values
of its drift and observation map at four points of its own initial ensemble. A model with the same
name but another drift, sensor or noise is refused.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from csf_jax import _checks, _store, networks
from csf_jax.ssm import StateSpaceModel, Step, at_step, is_additive


class TrainedPrior(NamedTuple):
    """A trained prior: ``params`` for ``csf_jax.filter``, the ``network`` config they were made
    with, and their ``meta`` record.

    A pytree whose only leaves are ``params``, so it passes through ``jax.jit`` and ``jax.vmap`` as
    raw params do.

    Attributes:
      params: the network parameters.
      network: the ``NetworkConfig`` they were made with.
      meta: the record: ``meta["problem"]`` and ``meta["dim"]``, the model it was trained for;
        ``meta["model"]``, where present, its ``model_fingerprint``; also training configs, dataset
        id, validation history.
      serves: names of further problems it may filter besides ``meta["problem"]`` (a transfer,
        such as the double-well model on ``triple_well``).
    """

    params: dict
    network: networks.NetworkConfig
    meta: dict
    serves: tuple = ()

    def save(self, directory: str) -> str:
        """Write this prior to ``directory`` (replacing a prior saved there); returns its path.
        ``csf_jax.load_prior(directory, model)`` reads it back. An empty path, a file, a folder
        that cannot be written, or one whose ``params/`` or ``meta.json`` a save did not write
        (``csf_jax.trained.foreign_content``) is refused with one line naming it; nothing of the
        user's is deleted."""
        directory = _checks.check_path(directory, "TrainedPrior.save")
        export(directory, self.params, self.network, self.meta)
        return os.path.abspath(directory)

    def __repr__(self) -> str:
        n_params = sum(math.prod(jnp.shape(x)) for x in jax.tree_util.tree_leaves(self.params))
        serves = f", serves={tuple(self.serves)!r}" if self.serves else ""
        return (f"TrainedPrior(problem={self.problem!r}, dim={self.dim}, "
                f"network={_short_config(self.network)}, n_params={n_params}{serves})")

    @property
    def problem(self) -> str | None:
        """The name of the problem it was trained for (None if the meta record has none)."""
        return self.meta.get("problem")

    @property
    def dim(self) -> int | None:
        """The state dimension it was trained for (None if the meta record has none)."""
        return None if self.meta.get("dim") is None else int(self.meta["dim"])


def _short_config(config) -> str:
    """A dataclass config's repr with only the fields that differ from its defaults."""
    default = type(config)()
    changed = ", ".join(f"{f.name}={getattr(config, f.name)!r}" for f in dataclasses.fields(config)
                        if getattr(config, f.name) != getattr(default, f.name))
    return f"{type(config).__name__}({changed})"


class _Static:
    """A dict held as hashable pytree aux data: equal when the dicts are equal."""

    def __init__(self, value: dict):
        self.value = value
        self._key = json.dumps(value, sort_keys=True, default=repr)

    def __eq__(self, other):
        return isinstance(other, _Static) and self._key == other._key

    def __hash__(self):
        return hash(self._key)


jax.tree_util.register_pytree_with_keys(
    TrainedPrior,
    lambda p: (((jax.tree_util.GetAttrKey("params"), p.params),),
               (p.network, _Static(p.meta), tuple(p.serves))),
    lambda aux, children: TrainedPrior(children[0], aux[0], aux[1].value, aux[2]))


def deprecated_alias(module: str, name: str):
    """The value of the deprecated name ``module.name``, with a ``DeprecationWarning`` naming its
    new name; AttributeError for any other name (the body of a module ``__getattr__``).
    ``Pretrained``: the former name of ``TrainedPrior``, the same class."""
    if name == "Pretrained":
        import warnings
        warnings.warn(f"{module}.Pretrained is deprecated: it is csf_jax.TrainedPrior, the same "
                      f"class; the old name goes in the next version", DeprecationWarning,
                      stacklevel=3)
        return TrainedPrior
    raise AttributeError(f"module {module!r} has no attribute {name!r}")


def __getattr__(name: str):
    return deprecated_alias(__name__, name)


PROBE_POINTS = 4


def model_fingerprint(model: StateSpaceModel) -> dict:
    """What identifies ``model`` for a trained prior (JSON-ready): name, dimensions, noise settings,
    and its drift and observation map at ``PROBE_POINTS`` points of its own initial ensemble
    (``initial_ensemble(jax.random.key(0), 4)``, float32). Computed once per model object; each
    call returns a fresh copy."""
    return copy.deepcopy(_fingerprint(model))


@functools.lru_cache(maxsize=64)
def _fingerprint(model: StateSpaceModel) -> dict:
    with jax.ensure_compile_time_eval():
        x = jnp.asarray(model.initial_ensemble(jax.random.key(0), PROBE_POINTS), jnp.float32)
        probe = at_step(model, Step(jnp.asarray(1, jnp.int32), None))  # time-varying: at k = 1
        drift = np.asarray(jax.vmap(probe.drift)(x), np.float64)
        observe = np.asarray(jax.vmap(probe.observe)(x), np.float64)
    noise = model.obs_noise
    process = ({"std": float(model.process_std)} if model.process_noise is None else
               {"name": model.process_noise.name,
                "covariance": None if model.process_noise.covariance is None
                else [list(r) for r in model.process_noise.covariance]})
    obs_noise = ({"name": noise.name, "gaussian_std": float(noise.gaussian_std),
                  "covariance": None if noise.covariance is None
                  else [list(r) for r in noise.covariance]} if is_additive(model)
                 else {"name": noise.name, "likelihood": True})
    return {"name": model.name, "dim": int(model.dim), "obs_dim": int(model.obs_dim),
            "process_noise": process,
            "obs_noise": obs_noise,
            "probe": {"x": np.asarray(x, np.float64).tolist(), "drift": drift.tolist(),
                      "observe": observe.tolist()}}


def fingerprint_mismatch(found: dict, model: StateSpaceModel) -> str | None:
    """None if the fingerprint ``found`` (from a meta record) is ``model``'s; else everything
    that differs, ``"; "``-joined: each setting with both values, then the initial ensemble, or
    (at the same probe points) the drift and the observation map."""
    own = _fingerprint(model)
    diffs = [f"{field}: trained {found.get(field)!r}, given {own[field]!r}"
             for field in ("name", "dim", "obs_dim", "process_noise", "obs_noise")
             if not _close(found.get(field), own[field])]
    names = {"x": "initial ensemble", "drift": "drift", "observe": "observation map"}
    for part in ("x", "drift", "observe"):
        a, b = found.get("probe", {}).get(part), own["probe"][part]
        if a is None or np.shape(a) != np.shape(b) or not np.allclose(a, b, rtol=1e-4, atol=1e-5):
            diffs.append(f"its {names[part]} differs at the probe points")
            if part == "x":  # the maps were probed at other points: comparing them says nothing
                break
    return "; ".join(diffs) or None


def _close(a, b) -> bool:
    """Equality of JSON-like values, floats to a relative 1e-6."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return bool(np.isclose(a, b, rtol=1e-6, atol=0.0))
    return a == b


def _config_diff(given: networks.NetworkConfig, own: networks.NetworkConfig) -> str:
    """``field: given X, trained Y`` for every field where two network configs differ."""
    return ", ".join(f"{f.name}: given {getattr(given, f.name)!r}, trained {getattr(own, f.name)!r}"
                     for f in dataclasses.fields(own)
                     if getattr(given, f.name) != getattr(own, f.name))


def unpack(trained, problem, network: networks.NetworkConfig | None,
           name: str = "csf_jax.filter"):
    """``(params, network)`` for the filter: raw params pass through unchanged; a ``TrainedPrior``
    is checked against ``problem`` (name, dim, and its fingerprint where the prior records one) and
    ``network``, and gives its own params and network config (the filter then checks the sampler's
    ``sigma_max`` against it). Every refusal is a one-line ValueError naming both sides."""
    if not isinstance(trained, TrainedPrior):
        return trained, network
    made_for = trained.problem
    allowed = (made_for,) + tuple(trained.serves)
    if made_for is not None and problem.name not in allowed:
        raise ValueError(f"{name}: the trained prior was made for problem {made_for!r} (d="
                         f"{trained.dim}), but model={problem.name!r} (d={problem.dim}); load the "
                         f"model of {problem.name!r}")
    if trained.dim is not None and trained.dim != problem.dim:
        raise ValueError(f"{name}: the trained prior was made for d={trained.dim}, but problem "
                         f"{problem.name!r} has d={problem.dim}")
    found = trained.meta.get("model")
    if found is not None and problem.name == made_for:
        why = fingerprint_mismatch(found, problem)
        if why is not None:
            raise ValueError(f"{name}: the trained prior was made for another model named "
                             f"{made_for!r} ({why}); train one for this model with "
                             f"csf_jax.train_prior")
    if network is not None and network != trained.network:
        raise ValueError(f"{name}: network= differs from the trained prior's own network config "
                         f"({_config_diff(network, trained.network)}); leave network= out")
    return trained.params, trained.network


# The names orbax writes at the top of a checkpoint folder (files): metadata files start with an
# underscore, the rest are these (OCDBT manifests, the commit marker, older formats' files).
_ORBAX_FILES = ("_", "commit_success", "manifest.", "ocdbt", "descriptor", "checkpoint")


def is_prior_record(path: str) -> bool:
    """Whether the file ``path`` is a ``meta.json`` that ``export`` wrote: a JSON object naming
    the ``problem``, its ``dim`` and the ``network``."""
    try:
        with open(path) as f:
            record = json.load(f)
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and {"problem", "dim", "network"} <= record.keys()


def foreign_content(directory: str) -> str | None:
    """What in ``directory`` a save would replace that no save wrote, in words; None if nothing.

    A save writes ``params/`` (orbax deletes a folder there first) and ``meta.json``, and touches
    nothing else, so other files beside them are safe. Replaced are only: a ``meta.json`` that is
    a prior's record (``is_prior_record``), and a ``params/`` that is empty or an orbax checkpoint
    (``_CHECKPOINT_METADATA`` or ``_METADATA``) with no file orbax does not write, beside such a
    record. Anything else there belongs to someone else and is refused by ``export``.
    """
    meta_path = os.path.join(directory, "meta.json")
    params_dir = os.path.join(directory, "params")
    has_record = os.path.isfile(meta_path) and is_prior_record(meta_path)
    if os.path.lexists(meta_path) and not has_record:
        return f"{meta_path} is not a csf_jax prior's record"
    if not os.path.lexists(params_dir):
        return None
    if os.path.islink(params_dir) or not os.path.isdir(params_dir):
        return f"{params_dir} is not a folder a save wrote"
    entries = sorted(os.listdir(params_dir))
    if not entries:
        return None
    shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
    if not has_record:
        return f"{params_dir} holds files ({shown}) and no csf_jax meta.json is beside it"
    strays = [e for e in entries if os.path.isfile(os.path.join(params_dir, e))
              and not e.startswith(_ORBAX_FILES)]
    if strays or not {"_CHECKPOINT_METADATA", "_METADATA"} & set(entries):
        what = ", ".join(strays[:3]) if strays else shown
        return f"{params_dir} holds files orbax did not write ({what})"
    return None


def export(directory: str, params, network: networks.NetworkConfig, meta: dict) -> None:
    """Write ``params`` (orbax) and ``meta.json`` to ``directory``, replacing a prior saved there.

    A folder holding files that no save wrote (``foreign_content``: a user's ``params/`` or
    ``meta.json``) is refused with one FileExistsError naming them, never emptied; other files
    beside ``params/`` and ``meta.json`` are left alone.

    ``meta`` must name the ``problem`` and its ``dim``; ``params`` are checked against
    ``network`` and ``dim`` first, so an exported model always loads. The arrays are saved as
    numpy arrays, so the folder records no device (``_store.host_arrays``).
    """
    directory = _checks.check_path(directory, "export")
    missing = [k for k in ("problem", "dim") if k not in meta]
    if missing:
        raise ValueError(f"export: meta must record {' and '.join(missing)} (the problem the "
                         f"model was trained for)")
    networks.check_params(params, network, int(meta["dim"]), name=f"export to {directory}: params")
    directory = os.path.abspath(directory)
    _checks.check_folder(directory, f"save to {directory}", writable=True)
    _checks.check_folder(os.path.join(directory, "params"), f"save to {directory}")
    foreign = foreign_content(directory)
    if foreign is not None:
        raise FileExistsError(f"save to {directory}: {foreign}, and saving would replace it; "
                              f"choose an empty or new folder")
    try:
        os.makedirs(directory, exist_ok=True)
        with ocp.StandardCheckpointer() as ckpt:
            ckpt.save(os.path.join(directory, "params"), _store.host_arrays(params), force=True)
        with open(os.path.join(directory, "meta.json"), "w") as f:
            json.dump({**meta, "network": dataclasses.asdict(network)}, f, indent=1)
    except OSError as e:
        raise OSError(f"save to {directory}: cannot write there ({type(e).__name__}: "
                      f"{_first_line(e)})") from None


def _read_meta(directory: str) -> tuple[dict, networks.NetworkConfig, int]:
    """``(meta, network, dim)`` from ``directory/meta.json``; one-line errors naming the folder."""
    meta = _checks.read_json_record(directory, "model", "not a folder written by "
                                    "csf_jax.pretrained.export")
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
    """The parameter tree of shapes ``(ShapeDtypeStruct)`` saved in ``params_dir``.

    Every array is read back with TensorStore first (``_store.damaged_array``): orbax's metadata
    read opens all arrays concurrently, and on a damaged folder the reads it abandons print
    asyncio tracebacks after the error, so a damaged folder is refused here in one line before
    orbax opens it. The shapes come from the metadata alone; the shardings it records are ignored.
    """
    if not os.path.isdir(params_dir):
        raise FileNotFoundError(f"model {directory}: its parameter folder {params_dir} is missing")
    damage = _store.damaged_array(params_dir)
    if damage is not None:
        raise ValueError(f"model {directory}: the parameters in {params_dir} cannot be restored "
                         f"({damage})")
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


def load_dir(directory: str, serves: tuple = ()) -> TrainedPrior:
    """Load a model written by ``export``.

    Checks ``meta.json`` against the stored array shapes before restoring anything: a damaged or
    inconsistent folder fails with one line naming it and the mismatching field. The parameters
    are restored onto this process's default device whatever devices the folder records
    (``_store.restore_target``), so a model saved on one platform loads on any other.
    serves: further problem names the model may filter (see ``TrainedPrior``).
    """
    directory = os.path.abspath(_checks.check_path(directory, "load_prior"))
    _checks.check_folder(directory, f"model {directory}")
    meta, network, dim = _read_meta(directory)
    params_dir = os.path.join(directory, "params")
    _check_stored(_stored_shapes(params_dir, directory), network, dim, directory)
    target = _store.restore_target(networks._expected_params(network, dim))
    try:
        with ocp.StandardCheckpointer() as ckpt:
            params = ckpt.restore(params_dir, target)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"model {directory}: the parameters in {params_dir} cannot be restored "
                         f"({type(e).__name__}: {_first_line(e)})") from None
    return TrainedPrior(jax.tree_util.tree_map(jnp.asarray, params), network, meta,
                      tuple(serves))


def load_prior(directory: str, model: StateSpaceModel | None = None,
               network: networks.NetworkConfig | None = None) -> TrainedPrior:
    """Load a trained prior written by ``TrainedPrior.save`` (or ``csf_jax.train_prior``).

    A damaged or inconsistent folder fails with one line naming it and the field at fault.

    Args:
      directory: the folder ``TrainedPrior.save`` wrote.
      model: the model it is meant to filter: refused (one-line ValueError) if the prior was made
        for another name or dimension, or, where the folder records a fingerprint, for a model whose
        drift, sensor or noise differ (``model_fingerprint``).
      network: the network config expected; refused if the folder's differs.
    """
    prior = load_dir(directory)
    where = f"load_prior({os.path.abspath(directory)})"
    if model is not None:
        unpack(prior, model, None, name=where)
    if network is not None and network != prior.network:
        raise ValueError(f"{where}: the folder's network differs from network= "
                         f"({_config_diff(network, prior.network)})")
    return prior
