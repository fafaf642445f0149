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
import inspect
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
    """Check ``obs (K, m)`` against ``model``: shape, dtype (``check_obs_dtype``), no inf (NaN:
    missing), values in the likelihood's support (``check_support``), and that the model's noise
    can leave missing entries out; return ``(K, m)``."""
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
    check_obs_dtype(name, obs, model)
    check_finite(f"{name}: obs", obs, allow_nan=True)
    check_support(name, obs, model)
    check_missing_supported(name, obs, model)
    return K, m


def is_discrete(model) -> bool:
    """Whether ``model``'s observations are counts (a ``Likelihood`` with ``discrete=True``)."""
    return bool(getattr(model.obs_noise, "discrete", False))


def check_obs_dtype(name: str, obs, model) -> None:
    """``obs`` must be floating; integer counts are taken too where the observation law is
    discrete (``Likelihood.discrete``, e.g. ``poisson_likelihood()``): the filter casts them to
    its float dtype. TypeError otherwise, saying to pass floats."""
    dtype = jnp.result_type(obs)
    if jnp.issubdtype(dtype, jnp.floating):
        return
    if is_discrete(model):
        if jnp.issubdtype(dtype, jnp.integer):
            return
        raise TypeError(f"{name}: obs must be integer counts or a floating array (NaN marks a "
                        f"missing entry) for the {model.obs_noise.name} likelihood, got dtype "
                        f"{dtype}")
    raise TypeError(f"{name}: obs must be a floating array, got dtype {dtype}; pass floats "
                    f"(e.g. np.asarray(obs, np.float32)): only a discrete likelihood "
                    f"(Likelihood(discrete=True), e.g. poisson_likelihood()) takes integer obs")


def check_support(name: str, obs, model) -> None:
    """Refuse an observation outside the support of the model's likelihood
    (``Likelihood.support``, e.g. a negative or fractional Poisson count), naming the first
    one by step and entry; NaN (missing) entries are skipped. No-op for tracers and for a law
    without a support check."""
    noise = model.obs_noise
    support = getattr(noise, "support", None)
    if support is None or not is_concrete(obs):
        return
    if not callable(support):
        raise TypeError(f"{name}: the likelihood {noise.name!r} has a support that is not "
                        f"callable ({type(support).__name__}); give y -> bool, or None")
    arr = np.asarray(obs)
    with np.errstate(invalid="ignore"):
        inside = np.asarray(support(arr), bool)
    outside = ~inside & ~np.isnan(arr) if np.issubdtype(arr.dtype, np.floating) else ~inside
    if not outside.any():
        return
    k, j = (int(i) for i in np.argwhere(outside)[0])
    text = getattr(noise, "support_text", "")
    what = f" ({text})" if text else ""
    raise ValueError(f"{name}: obs[{k}, {j}] = {arr[k, j]:g} is outside the support of the "
                     f"{noise.name} likelihood{what}; correct the data, or mark an entry that "
                     f"was not observed with NaN (entries outside: {int(outside.sum())})")


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
    non-finite entry of ``ensemble`` are errors, as are observations outside the likelihood's
    support. ``obs`` is floating, or integer counts for a discrete likelihood."""
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
    check_obs_dtype(name, obs, model)
    if not jnp.issubdtype(ensemble.dtype, jnp.floating):
        raise TypeError(f"{name}: ensemble must be a floating array, got dtype {ensemble.dtype}")
    check_finite(f"{name}: obs", obs, allow_nan=True)
    check_finite(f"{name}: ensemble", ensemble)
    check_support(name, obs, model)
    check_missing_supported(name, obs, model)
    return K, m, N, d


def as_array(x, label: str, name: str):
    """``x`` as an array at the API boundary: a ``jax.Array`` (a tracer, a global array) or a
    numpy array as it is; a list or other array-like through numpy (``jnp.shape`` of a list is
    deprecated in JAX), so no warning comes from inside the library. None, and what numpy cannot
    make a numeric array of (ragged rows, objects), is a one-line TypeError naming ``label``."""
    if isinstance(x, (jax.Array, jax.core.Tracer, np.ndarray)):
        return x
    if x is None:
        raise TypeError(f"{name}: {label} is None; give an array {_SHAPES.get(label, '')}")
    if not is_concrete(x):
        return jnp.asarray(x)  # a list of tracers: stacked by jnp
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.dtype == object or not (np.issubdtype(arr.dtype, np.number)
                                                  or arr.dtype == np.bool_):
        raise TypeError(f"{name}: {label} must be a numeric array {_SHAPES.get(label, '')}, got "
                        f"a {type(x).__name__} that numpy cannot make one of (ragged rows or "
                        f"non-numbers?)")
    return arr


_SHAPES = {"obs": "of shape (K, m) = (steps, obs_dim)",
           "ensemble": "of shape (N, d) = (particles, dim)"}


def check_static(name: str, **settings) -> None:
    """Refuse a traced Python setting (``return_ensembles``, ``check_finite``, ``shards``): under
    ``jax.jit`` every argument is traced unless marked static, and these choose what is compiled.
    The TypeError says to mark it static. ``progress`` must be a callable or None."""
    for arg, value in settings.items():
        if isinstance(value, jax.core.Tracer):
            raise TypeError(f"{name}: {arg} is traced (an argument of jax.jit), but it chooses "
                            f"what is compiled; mark it static: jax.jit(f, static_argnames="
                            f"({arg!r},)), or bind it with functools.partial")
        if arg == "progress" and value is not None and not callable(value):
            raise TypeError(f"{name}: progress must be a callable k -> None or None, got "
                            f"{type(value).__name__}")


def static_pytree(cls):
    """Register ``cls`` (a hashable NamedTuple or frozen dataclass of settings: a model, a
    config) as a pytree with no leaves, the instance itself its static aux data, so that
    ``jax.jit(f)(..., model=model, config=config)`` takes it as the static value it is rather
    than tracing its numbers and failing on its strings. Idempotent; returns ``cls``."""
    try:
        jax.tree_util.register_static(cls)
    except ValueError:  # registered already
        pass
    return cls


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


def positional_check(fn, call: str | None = None):
    """A check ``args -> None`` refusing more positional arguments than ``fn``'s signature has,
    with a one-line TypeError naming them and the keyword-only arguments to name instead
    (``model=``, ``key=``), in place of Python's bare argument count. ``call``: the name in the
    message (default ``fn.__name__``)."""
    call = call or fn.__name__
    params = inspect.signature(fn).parameters.values()
    if any(p.kind is p.VAR_POSITIONAL for p in params):
        return lambda args: None
    positional = [p.name for p in params
                  if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    required = [p.name for p in params if p.kind is p.KEYWORD_ONLY and p.default is p.empty]
    named = " and ".join(f"{k}=" for k in required) or "the settings"
    example = ", ".join(positional + [f"{k}={k}" for k in required])

    def check(args) -> None:
        if len(args) > len(positional):
            raise TypeError(f"{call}: takes {len(positional)} positional argument(s) "
                            f"({', '.join(positional)}), got {len(args)}; {named} are keywords: "
                            f"{call}({example})")

    return check


def positional_limit(call: str | None = None):
    """Decorator: ``positional_check`` before every call of the function."""

    def wrap(fn):
        check = positional_check(fn, call)

        @functools.wraps(fn)
        def inner(*args, **kwargs):
            check(args)
            return fn(*args, **kwargs)

        return inner

    return wrap


def renamed_keywords(call: str | None = None, /, **renames):
    """Decorator: accept each keyword's old name (``old="new"``) for one version, with a
    ``DeprecationWarning`` naming the new one; both at once is a TypeError. Too many positional
    arguments (``model`` passed positionally) are refused as ``positional_check`` says; ``call``:
    the name in its message (default the function's)."""

    def wrap(fn):
        check = positional_check(fn, call)

        @functools.wraps(fn)
        def inner(*args, **kwargs):
            check(args)
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
