"""The one driver behind every filter: a filter supplies ``init`` and ``step``; the driver owns the
rest.

    run(method, obs, state0, model=, key=, config=, params=, inputs=)
      checks (model, shapes, dtypes, inf, keys, inputs), promotion to one float dtype (at least
      float32), then R and Q positive definite in it and drift/observe of the right shapes,
      with progress: a line before the first compilation and its time after,
      init -> one jitted lax.scan over y_1 .. y_K:
          model bound to the step (time index k, input u_k: ``ssm.at_step``), progress callback,
          state, out = step(model_k, config, params, state, y_k, key_k, step_k)
      -> mark_nonfinite -> FilterResult, FloatingPointError on a diverged concrete run.

A ``Method`` is a NamedTuple of module-level functions, so it is hashable and a jitted scan is
compiled once per (method, model, config). ``config`` is the method's static settings (hashable);
``params`` its array-valued ones (network weights, an inflation factor), traced. NaN in ``obs``
means 'not observed' and reaches ``step`` as is: each method leaves it out of its update.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from csf_jax import _checks
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.ssm import (
    StateSpaceModel,
    at_step,
    check_covariances,
    check_dynamics,
    check_model,
    steps,
)


class StepOutput(NamedTuple):
    """What a method's ``step`` reports for one time step.

    mean, std: (d,) the filtered mean and spread of ``x_k``.
    ensemble: (N, d) the posterior ensemble (kept only with ``return_ensembles``), or None.
    info: dict of per-step scalars (the particle filter's ``ess``; CSF's bandwidth and shock
      weight), stacked over steps into ``FilterResult.info``.
    """

    mean: jax.Array
    std: jax.Array
    ensemble: jax.Array | None = None
    info: dict = {}


class Method(NamedTuple):
    """A filter as the driver runs it.

    name: the user-facing name, for messages (``"particle_filter"``).
    init: ``(model, config, params, state0, key) -> (state, scan_key)``: the carry at time 0 and the
      key split into one key per step.
    step: ``(model_k, config, params, state, y (m,), key, time) -> (state, StepOutput)``;
      ``model_k`` is the model with this step's time index and input bound (``ssm.at_step``),
      ``time`` that ``Step`` itself (``time.k`` = 1 .. K).
    check: ``(model, config) -> None``, raising ValueError if the method cannot filter the model
      (a non-additive likelihood without a Gaussian stand-in, say), at the boundary.
    ensemble: whether ``state0`` is an ``(N, d)`` ensemble, checked as one.
    label: the short name in progress lines ("CSF", "EnKF"); default ``name``.
    """

    name: str
    init: Callable[..., Any]
    step: Callable[..., Any]
    check: Callable[[StateSpaceModel, Any], None] = lambda model, config: None
    ensemble: bool = True
    label: str = ""


def run(method: Method, obs, state0, *, model: StateSpaceModel, key, config=None, params=None,
        inputs=None, return_ensembles: bool = False, check_finite: bool = True,
        progress: Callable[[jax.Array], None] | None = None) -> FilterResult:
    """Run ``method`` over ``obs (K, m)`` from ``state0`` (an ``(N, d)`` ensemble for the ensemble
    filters); see the module docstring. ``inputs``: the per-step inputs of a time-varying model,
    a pytree whose leaves have leading axis K."""
    name = method.name
    check_model(model, name)
    if method.ensemble:
        _checks.check_filter_inputs(obs, state0, model, name=name)
    else:
        _checks.check_obs(obs, model, name=name)
    _checks.check_key(key, name=name)
    _checks.check_inputs(inputs, jnp.shape(obs)[0], model, name=name)
    method.check(model, config)
    obs, state0 = _checks.promote_tree(obs, state0)
    check_covariances(model, obs.dtype, name)
    check_dynamics(model, obs.dtype, inputs, name)
    static = (method, model, config, bool(return_ensembles), progress)
    args = (params, obs, state0, key, inputs)
    if progress is not None:
        _announce_compile(static, args)
    result = mark_nonfinite(_scan(*static, *args), obs)
    if check_finite:
        _checks.check_result_finite(name, result)
    return result


_COMPILED: set = set()


def _signature(static: tuple, args: tuple):
    """What selects one compilation of ``_scan``: the static arguments and the shapes and dtypes
    of the traced ones."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return static, tree, tuple((jnp.shape(x), str(getattr(x, "dtype", type(x).__name__)))
                               for x in leaves)


def _announce_compile(static: tuple, args: tuple) -> None:
    """Before the first (compiling) call of a concrete run with ``progress``: say on stderr what
    is compiled, compile it ahead of the call (the call then reuses it), and say how long it took.
    Silent under an outer jit/vmap (nothing is compiled here then) and for a signature seen."""
    if not _checks.is_concrete(args):
        return
    sig = _signature(static, args)
    if sig in _COMPILED:
        return
    method, model = static[0], static[1]
    obs, state0 = args[1], args[2]
    sizes = f"d={model.dim}, " + (f"N={jnp.shape(state0)[0]}, " if method.ensemble else "") + \
        f"K={jnp.shape(obs)[0]}"
    label = method.label or method.name
    print(f"compiling the {label} filter ({sizes}) ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    _scan.lower(*static, *args).compile()
    print(f"compiled the {label} filter in {time.perf_counter() - t0:.1f} s", file=sys.stderr,
          flush=True)
    _COMPILED.add(sig)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4))
def _scan(method: Method, model: StateSpaceModel, config, return_ensembles: bool, progress,
          params, obs, state0, key, inputs) -> FilterResult:
    K = obs.shape[0]
    state, scan_key = method.init(model, config, params, state0, key)

    def body(state, xs):
        index, y, step_k, key_k = xs
        if progress is not None:
            jax.debug.callback(progress, index)
        state, out = method.step(at_step(model, step_k), config, params, state, y, key_k, step_k)
        return state, (out.mean, out.std, out.ensemble if return_ensembles else None, out.info)

    xs = (jnp.arange(K), obs, steps(K, inputs), jax.random.split(scan_key, K))
    _, (mean, std, ensembles, info) = jax.lax.scan(body, state, xs)
    info = dict(info)
    ess = info.pop("ess", None)
    return FilterResult(mean=mean, std=std, ensembles=ensembles, ess=ess, info=info or None)
