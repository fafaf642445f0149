"""Input checks at the API boundary, with clear one-line messages: shapes, dimensions, dtypes and
finiteness of arrays; PRNG keys; the field types of the frozen config dataclasses
(``check_fields``); paths and folders to be read or written (``check_path``, ``check_folder``).

Shape checks run at trace time, so they also fire under ``jax.jit`` and ``jax.vmap``. Value checks
(NaN/inf) need concrete arrays and are skipped for tracers: inside a user's ``jit`` the caller owns
them.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import numbers
import os
import types
import typing
import warnings

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(*xs) -> bool:
    """True if no argument is a tracer (we are not inside jit/vmap/grad)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def check_finite(name: str, x, allow_nan: bool = False) -> None:
    """Raise ValueError naming the first non-finite entry of ``x`` (with ``allow_nan``: the first
    infinite one; NaN then means 'missing'); no-op for tracers."""
    if not is_concrete(x):
        return
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.floating):
        return
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        what = "infinite value(s) (NaN marks a missing entry; inf is an error)" if allow_nan \
            else "non-finite value(s)"
        raise ValueError(f"{name} has {int(bad.sum())} {what}; first at index {idx}: "
                         f"{arr[idx]!r}")


def check_missing_supported(name: str, obs, model) -> None:
    """Refuse NaN (missing) observations for a noise that cannot marginalise them (no
    ``ObservationNoise.marginal``); no-op for tracers (there such steps come out non-finite). A
    ``Likelihood`` always can: its entries are independent given the state."""
    if getattr(model.obs_noise, "marginal", True) is not None or not is_concrete(obs):
        return
    if np.isnan(np.asarray(obs)).any():
        raise ValueError(f"{name}: obs has missing (NaN) entries, but the observation noise "
                         f"{model.obs_noise.name!r} has no marginal log-density to leave them out; "
                         f"give ObservationNoise(marginal=...) or use a noise built by csf_jax "
                         f"(gaussian_noise, gaussian_noise_cov, cauchy_noise)")


def check_obs(obs, model, *, name: str = "filter") -> tuple[int, int]:
    """Check ``obs (K, m)`` against ``model``: shape, float dtype, no inf (NaN: missing), and that
    the model's noise can leave missing entries out; return ``(K, m)``."""
    obs = jnp.asarray(obs)
    if obs.ndim != 2:
        raise ValueError(f"{name}: obs must have shape (K, m) = (steps, obs_dim), got {obs.shape}; "
                         f"use jax.vmap for batches of runs")
    K, m = obs.shape
    if m != model.obs_dim:
        raise ValueError(f"{name}: obs has dimension m={m} but model {model.name!r} has "
                         f"obs_dim={model.obs_dim}")
    if K < 1:
        raise ValueError(f"{name}: obs must hold at least one step, got shape {obs.shape}")
    if not jnp.issubdtype(obs.dtype, jnp.floating):
        raise TypeError(f"{name}: obs must be a floating array, got dtype {obs.dtype}")
    check_finite(f"{name}: obs", obs, allow_nan=True)
    check_missing_supported(name, obs, model)
    return K, m


def check_inputs(inputs, num_steps: int, model, *, name: str = "filter") -> None:
    """A time-varying model's per-step ``inputs``: a pytree of arrays with leading axis K (or
    None); refused for a model that is not time-varying."""
    if inputs is None:
        return
    if not model.time_varying:
        raise ValueError(f"{name}: inputs given, but model {model.name!r} is not time-varying "
                         f"(set time_varying=True and let drift/observe take the step)")
    for path, leaf in jax.tree_util.tree_leaves_with_path(inputs):
        shape = jnp.shape(leaf)
        if not shape or shape[0] != num_steps:
            where = jax.tree_util.keystr(path) or "inputs"
            raise ValueError(f"{name}: inputs{'' if where == 'inputs' else where} must have "
                             f"leading axis K={num_steps} (one input per observation), got shape "
                             f"{shape}")
        check_finite(f"{name}: inputs", leaf)


def check_filter_inputs(obs, ensemble, model, *, name: str = "filter") -> tuple[int, int, int, int]:
    """Check ``obs (K, m)`` and ``ensemble (N, d)`` against ``model``; return ``(K, m, N, d)``.

    NaN in ``obs`` means 'not observed' (per step and coordinate); inf in ``obs`` and any
    non-finite entry of ``ensemble`` are errors."""
    obs = jnp.asarray(obs)
    ensemble = jnp.asarray(ensemble)
    if obs.ndim != 2:
        raise ValueError(f"{name}: obs must have shape (K, m) = (steps, obs_dim), got {obs.shape}; "
                         f"use jax.vmap for batches of runs")
    if ensemble.ndim != 2:
        raise ValueError(f"{name}: ensemble must have shape (N, d) = (particles, dim), got "
                         f"{ensemble.shape}; use jax.vmap for batches of runs")
    K, m = obs.shape
    N, d = ensemble.shape
    if d != model.dim:
        raise ValueError(f"{name}: ensemble has dimension d={d} but model {model.name!r} has "
                         f"dim={model.dim}")
    if m != model.obs_dim:
        raise ValueError(f"{name}: obs has dimension m={m} but model {model.name!r} has "
                         f"obs_dim={model.obs_dim}")
    if K < 1:
        raise ValueError(f"{name}: obs must hold at least one step, got shape {obs.shape}")
    if N < 2:
        raise ValueError(f"{name}: ensemble needs at least 2 particles, got N={N}")
    for label, x in (("obs", obs), ("ensemble", ensemble)):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise TypeError(f"{name}: {label} must be a floating array, got dtype {x.dtype}")
        check_finite(f"{name}: {label}", x, allow_nan=label == "obs")
    check_missing_supported(name, obs, model)
    return K, m, N, d


def check_key(key, name: str = "filter") -> None:
    """Require one JAX PRNG key: a typed ``jax.random.key`` (shape ``()``) or a legacy uint32
    ``(2,)`` key (``jax.random.PRNGKey``). A batch of keys (``jax.random.split``) is refused."""
    if key is None:
        raise TypeError(f"{name}: key= is required (e.g. key=jax.random.key(0)); "
                        f"there is no global RNG")
    dtype = getattr(key, "dtype", None)
    shape = jnp.shape(key) if dtype is not None else None
    if dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key):
        if shape != ():
            raise ValueError(f"{name}: key must be a single key, got a batch of keys of shape "
                             f"{shape}; pick one (keys[0]) or vmap over them")
        return
    if dtype is not None and dtype == jnp.uint32 and len(shape) >= 1 and shape[-1] == 2:
        if shape != (2,):
            raise ValueError(f"{name}: key must be a single key, got a batch of legacy keys of "
                             f"shape {shape}; pick one (keys[0]) or vmap over them")
        return
    what = f"{type(key).__name__} with shape {shape} and dtype {dtype}" if dtype is not None \
        else f"{type(key).__name__} {key!r:.40}"
    raise TypeError(f"{name}: key must be a jax.random.key (e.g. key=jax.random.key(0)), got "
                    f"{what}")


def check_result_finite(name: str, result) -> None:
    """After a concrete run: raise FloatingPointError at the first step whose mean is non-finite
    (``mark_nonfinite`` has made it NaN from the first bad step on). The message names no setting
    to switch to: which one helps depends on why the run diverged, and a guess can be worse (the
    clipped DPS guidance is far less accurate than the default Kalman guidance where both run)."""
    if not is_concrete(result.mean):
        return
    mean = np.asarray(result.mean)
    bad = ~np.isfinite(mean).all(axis=-1)
    if bad.any():
        k = int(np.argmax(bad))
        raise FloatingPointError(
            f"{name}: the filtered mean became non-finite at step {k + 1} of {mean.shape[0]} "
            f"(the ensemble diverged: the model's drift or the update overflowed on a member). "
            f"Check the drift on the states the ensemble reaches (check_finite=False with "
            f"return_ensembles=True gives the raw result and the members) and compare with "
            f"csf_jax.ensemble_kalman_filter on the same data.")


def compute_dtype(*dtypes):
    """The float dtype a filter computes in for inputs of ``dtypes``: their common float dtype
    (``jnp.result_type``), at least float32 (half precision has no LAPACK and too little
    resolution for covariances)."""
    dtype = jnp.result_type(*dtypes)
    return jnp.promote_types(dtype, jnp.float32)


def promote(obs, ensemble):
    """``obs (K, m)`` and ``ensemble (N, d)`` as arrays of their compute dtype (``compute_dtype``:
    float16 inputs run in float32; float64 obs with a float32 ensemble in float64 under x64).
    Inputs are already checked to be floating."""
    obs, ensemble = jnp.asarray(obs), jnp.asarray(ensemble)
    dtype = compute_dtype(obs.dtype, ensemble.dtype)
    return obs.astype(dtype), ensemble.astype(dtype)


def promote_tree(obs, state):
    """``obs`` and every floating leaf of ``state`` (an ensemble, or a filter's initial state) as
    arrays of their compute dtype (as ``promote``)."""
    obs = jnp.asarray(obs)
    leaves = [jnp.asarray(x) for x in jax.tree_util.tree_leaves(state)]
    dtype = compute_dtype(obs.dtype, *[x.dtype for x in leaves
                                       if jnp.issubdtype(x.dtype, jnp.floating)])
    cast = lambda x: (jnp.asarray(x).astype(dtype)
                      if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else jnp.asarray(x))
    return obs.astype(dtype), jax.tree_util.tree_map(cast, state)


def check_sigma_max(network, config, name: str) -> None:
    """A learned score net is trained for one VE SDE scale: the sampler must use the same."""
    if network.sigma_max != config.sampler.sigma_max:
        raise ValueError(f"{name}: the network config has sigma_max={network.sigma_max}, but the "
                         f"sampler's config.sampler.sigma_max={config.sampler.sigma_max}; they must agree")


class FieldTypeError(TypeError, ValueError):
    """A config field of the wrong type: a TypeError, and a ValueError too, so that callers that
    catch bad config values (``except ValueError``) catch it as well."""


@functools.cache
def _field_types(cls) -> dict:
    """The resolved annotations of a dataclass's fields (``typing.get_type_hints``), or {} where
    they cannot be resolved (then nothing is checked by type)."""
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001  (an unresolvable forward reference)
        return {}


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


def _is_number(v) -> bool:
    return (isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))
            and math.isfinite(float(v)))


_SIMPLE = {int: (_is_int, "an int"), float: (_is_number, "a finite number"),
           bool: (lambda v: isinstance(v, (bool, np.bool_)), "a bool (True or False)"),
           str: (lambda v: isinstance(v, str), "a str"),
           tuple: (lambda v: isinstance(v, tuple), "a tuple")}


def _field_type_problem(value, hint) -> str | None:
    """None if ``value`` fits the annotation ``hint`` (a class, or a union of classes and None);
    else what was expected. Annotations beyond plain classes (``Callable``) are not checked."""
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) or \
        typing.get_origin(hint) is typing.Union else (hint,)
    words = []
    for option in options:
        if option is type(None):
            if value is None:
                return None
            words.append("None")
        elif option in _SIMPLE:
            ok, word = _SIMPLE[option]
            if value is not None and ok(value):
                return None
            words.append(word)
        elif isinstance(option, type):
            if isinstance(value, option):
                return None
            words.append(f"a {option.__name__}")
        else:
            return None
    return " or ".join(words)


def check_fields(config, *, positive: tuple = (), nonnegative: tuple = ()) -> None:
    """Check a frozen config dataclass: every field holds the type it is annotated with (``int``,
    ``float``, ``bool``, ``str``, ``tuple``, a config class, optionally ``| None``; floats finite,
    ints never bools), then
    the fields named in ``positive`` are > 0 and those in ``nonnegative`` >= 0 (None skipped).
    Raises ``FieldTypeError`` (a TypeError and a ValueError) or ValueError naming
    ``Class.field``; call it first in ``__post_init__``."""
    cls = type(config).__name__
    hints = _field_types(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if field.name not in hints:
            continue
        want = _field_type_problem(value, hints[field.name])
        if want is not None:
            raise FieldTypeError(f"{cls}.{field.name} must be {want}, got {value!r} "
                                 f"({type(value).__name__})")
    for names, ok, word in ((positive, lambda v: v > 0, "> 0"),
                            (nonnegative, lambda v: v >= 0, ">= 0")):
        for name in names:
            value = getattr(config, name)
            if value is not None and not ok(value):
                raise ValueError(f"{cls}.{name} must be {word}, got {value!r}")


def check_path(path, name: str) -> str:
    """``path`` as a non-empty ``str`` (``os.PathLike`` accepted); TypeError or ValueError naming
    ``name`` otherwise (an empty path would mean the working directory)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name}: the path must be a str or os.PathLike, got "
                        f"{type(path).__name__}")
    path = os.fspath(path)
    if not path.strip():
        raise ValueError(f"{name}: the path is empty; give a folder, e.g. 'runs/my_prior'")
    return path


def check_folder(path: str, name: str, *, writable: bool = False) -> None:
    """Refuse a ``path`` that exists but is not a folder (NotADirectoryError), and with
    ``writable`` one that cannot be written (PermissionError), or whose nearest existing parent
    cannot; each message names the path."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise NotADirectoryError(f"{name}: {path} is a file, not a folder; move it away or "
                                 f"choose another folder")
    if not writable:
        return
    probe = os.path.abspath(path)
    while not os.path.exists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.access(probe, os.W_OK | os.X_OK):
        raise PermissionError(f"{name}: cannot write to {path} ({probe} is not writable)")


def read_json_record(directory: str, what: str, missing: str, remedy: str = "") -> dict:
    """The JSON object in ``directory/meta.json``; one-line errors naming ``what`` and the file.

    ``missing`` says what a folder without the file is; ``remedy`` is appended to the messages.
    """
    path = os.path.join(directory, "meta.json")
    tail = f"; {remedy}" if remedy else ""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what} {directory}: no meta.json there ({missing})")
    try:
        with open(path) as f:
            record = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{what} {directory}: {path} cannot be read ({type(e).__name__}: "
                         f"{e}){tail}") from None
    if not isinstance(record, dict):
        raise ValueError(f"{what} {directory}: {path} must hold a JSON object{tail}")
    return record


def renamed_keywords(**renames):
    """Decorator: accept each keyword's old name (``old="new"``) for one version, with a
    ``DeprecationWarning`` naming the new one; both at once is a TypeError."""

    def wrap(fn):
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            for old, new in renames.items():
                if old in kwargs:
                    if new in kwargs:
                        raise TypeError(f"{fn.__name__}: got both {old}= and {new}=; pass {new}= "
                                        f"only")
                    warnings.warn(f"{fn.__name__}({old}=...) is now {fn.__name__}({new}=...); "
                                  f"the old name goes in the next version", DeprecationWarning,
                                  stacklevel=2)
                    kwargs[new] = kwargs.pop(old)
            return fn(*args, **kwargs)

        return inner

    return wrap
