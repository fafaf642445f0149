"""The one driver behind every filter: ``run(method, obs, ensemble, model=, key=)``.

A filter is a ``Method``: its ``Kernel`` (``init`` and ``step``, module-level functions), its
static ``config`` and its array-valued ``params``, made by the filter module's ``method(...)``
builder (``csf_jax.methods``). The driver owns the rest:

    run(method, obs, state0, model=, key=, inputs=)
      ``boundary`` (lists to arrays, an ensemble given, Python flags not traced), checks (model,
      shapes, dtypes, inf, a likelihood's support, keys, inputs), promotion to one float dtype
      (at least float32), then R and Q positive definite in it and drift/observe of the right
      shapes,
      with progress: a line before the first compilation and its time after,
      init -> one jitted lax.scan over y_1 .. y_K:
          model bound to the step (time index k, input u_k: ``ssm.at_step``), progress callback,
          state, out = step(model_k, config, params, state, y_k, key_k, step_k)
      -> mark_nonfinite -> FilterResult, FloatingPointError on a diverged concrete run, and a
         RuntimeWarning when a concrete run's particle weights collapse (``FilterResult.ess``).

A ``Kernel`` is a NamedTuple of module-level functions, so it is hashable and a jitted scan is
compiled once per (kernel, model, config). ``config`` is the method's static settings (hashable);
``params`` its array-valued ones (network weights, an inflation factor), traced: a ``Method`` is a
pytree whose only leaves are its params, so ``jax.jit`` and ``jax.vmap`` take it as an argument.
NaN in ``obs`` means 'not observed' and reaches ``step`` as is: each method leaves it out of its
update.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax._batch import one_at_a_time
from csf_jax.filters.result import FilterResult, mark_nonfinite
from csf_jax.parametric import ParametricModel, cast_theta, checkable_model
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
    info: dict of per-step diagnostics, stacked over steps into ``FilterResult.info`` (which
      lists what each filter reports): CSF's mixture weights ``particle_weight`` and
      ``shock_weight`` (scalars) and its ``dropped`` members (an int32 count), the Kalman
      filter's ``cov`` (d, d); the particle filter's ``ess`` (a scalar) goes to
      ``FilterResult.ess`` instead.
    log_evidence: the scalar ``log p(y_k | y_1 .. y_{k-1})`` (``csf_jax.evidence``), or None where
      the filter does not estimate it.
    """

    mean: jax.Array
    std: jax.Array
    ensemble: jax.Array | None = None
    info: dict = {}
    log_evidence: jax.Array | None = None


class Kernel(NamedTuple):
    """A filter's functions, as the driver runs them.

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
    bind: optional ``(model, config, params, state0) -> (model, config, params, state0)``, run
      first at the boundary: what depends on the model (a trained prior checked against it, the
      Kalman filter's matrices read from it).
    runner: optional ``(method, obs, ensemble, model=, key=, inputs=, return_ensembles=,
      check_finite=, progress=) -> FilterResult`` for a filter with a scan of its own (the sharded
      LETKF places its arrays on a device mesh); ``run`` hands the call over whole.
    parametric: optional, the kernel that runs in its place on a ``ParametricModel``: the same
      filter with what ``jax.grad`` needs added (the particle filter's resampling score).
    bind_checks: ``bind`` only checks the model (it changes nothing the scan reads: the LETKF's
      localisation against the sensor), so the kernel filters a ``ParametricModel`` too; a
      ``bind`` that reads the model's numbers (CSF's trained prior) cannot.
    discrete: the step makes discrete choices (a resampled index, a line search's pick, a member
      past a quantile), which turn the last-bit rounding of a batched run into a different run:
      under ``jax.vmap`` its runs go one at a time (``_batch.one_at_a_time``), each bit for bit
      its separate call. The other filters are smooth maps of their inputs: batched, they differ
      from a separate call by float rounding only, and they stay differentiable.
    """

    name: str
    init: Callable[..., Any]
    step: Callable[..., Any]
    check: Callable[[StateSpaceModel, Any], None] = lambda model, config: None
    ensemble: bool = True
    label: str = ""
    bind: Callable[..., tuple] | None = None
    runner: Callable[..., FilterResult] | None = None
    parametric: Kernel | None = None
    bind_checks: bool = False
    discrete: bool = False


@functools.partial(jax.tree_util.register_dataclass, data_fields=["params"],
                   meta_fields=["kernel", "config"])
@dataclasses.dataclass(frozen=True)
class Method:
    """A filter ready to run: ``csf_jax.run(method, obs, ensemble, model=, key=)``.

    Made by a filter module's builder (``csf_jax.methods``: ``methods.csf(...)``,
    ``methods.enkf()``, ...). A pytree whose leaves are ``params`` alone, so it passes through
    ``jax.jit`` and ``jax.vmap`` (``kernel`` and ``config`` are static).

    Attributes:
      kernel: the filter's ``Kernel`` (its init and step).
      config: its static settings (hashable): a change recompiles.
      params: its array-valued settings (network weights, an inflation factor): traced.
    """

    kernel: Kernel
    config: Any = None
    params: Any = None

    def __post_init__(self):
        if not isinstance(self.kernel, Kernel):
            raise TypeError(_not_a_kernel(self.kernel))

    @property
    def name(self) -> str:
        """The filter's user-facing name."""
        return self.kernel.name


def _not_a_kernel(kernel) -> str:
    """The one-line message of ``Method(kernel)`` with a ``kernel`` that is not a ``Kernel``
    (a filter's name, None): how a ``Method`` is made instead."""
    from csf_jax.methods import REGISTRY  # the builders import this module

    name = kernel if isinstance(kernel, str) and kernel in REGISTRY else "enkf"
    return (f"csf_jax.Method: kernel must be a csf_jax.filters.driver.Kernel, got {kernel!r:.60} "
            f"({type(kernel).__name__}); make a Method with a builder, csf_jax.methods.{name}(), "
            f"or by name, csf_jax.methods.build({name!r})")


def refuse_settings(name: str, settings: tuple, named: dict) -> None:
    """The one-line TypeError of a builder whose filter has no settings (``methods.pf()``,
    ``methods.kalman()``) when it is given some: ``settings`` positional, ``named`` keywords."""
    if not settings and not named:
        return
    got = ", ".join([type(v).__name__ for v in settings] + [f"{k}=" for k in named])
    raise TypeError(f"{name}: takes no settings (it has no config class), got {got}")


@_checks.positional_limit("csf_jax.run")
def run(method: Method, obs, ensemble, *, model: StateSpaceModel, key, inputs=None,
        return_ensembles: bool = False, check_finite: bool = True,
        progress: Callable[[jax.Array], None] | None = None) -> FilterResult:
    """Filter ``obs`` with ``method``: the one entry point behind every filter.

    Args:
      method: a ``Method`` from a builder of ``csf_jax.methods``.
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype (at least float32). NaN marks a missing entry; inf is an error.
      ensemble: (N, d) initial ensemble at time 0 (None for the Kalman filter, which starts from
        the model's own initial law).
      model: the ``StateSpaceModel`` (static: hashable).
      key: a ``jax.random.key``; same key, same result.
      inputs: a time-varying model's per-step inputs (a pytree, leading axis K), or None.
      return_ensembles: also return the (K, N, d) posterior ensembles.
      check_finite: when called outside jit/vmap, raise FloatingPointError if the filter diverged.
      progress: optional host callback ``k -> None`` at the start of every filter step; a
        concrete call with it also says on stderr when it compiles, and how long that took.

    Returns:
      ``FilterResult``: mean and std (K, d), ``finite`` (K,), the method's ``info``. Under
      ``jax.jit``/``jax.vmap`` a non-finite step is reported (``finite`` False, mean and std
      NaN from there on), not raised.
    """
    if not isinstance(method, Method):
        raise TypeError(f"csf_jax.run: method must be a csf_jax.Method (from a builder of "
                        f"csf_jax.methods, e.g. csf_jax.methods.enkf()), got "
                        f"{type(method).__name__}")
    obs, ensemble = boundary(method.kernel, obs, ensemble, return_ensembles=return_ensembles,
                             check_finite=check_finite, progress=progress)
    if method.kernel.runner is not None:
        return method.kernel.runner(method, obs, ensemble, model=model, key=key, inputs=inputs,
                                    return_ensembles=return_ensembles, check_finite=check_finite,
                                    progress=progress)
    return run_kernel(method.kernel, obs, ensemble, model=model, key=key, config=method.config,
                      params=method.params, inputs=inputs, return_ensembles=return_ensembles,
                      check_finite=check_finite, progress=progress)


def boundary(kernel: Kernel, obs, state0, **settings) -> tuple:
    """What every run checks first, before the model: ``obs`` (and an ensemble filter's
    ``state0``) as arrays (``_checks.as_array``: lists through numpy), an ensemble filter given
    an ensemble (not None), and the Python ``settings`` (``return_ensembles``, ...) not traced
    (``_checks.check_static``). Returns ``(obs, state0)``."""
    name = kernel.name
    _checks.check_static(name, **settings)
    obs = _checks.as_array(obs, "obs", name)
    if kernel.ensemble:
        if state0 is None:
            raise TypeError(f"{name}: ensemble is None, but this filter needs an (N, d) initial "
                            f"ensemble (e.g. model.initial_ensemble(key, 100)); only the Kalman "
                            f"filter (csf_jax.methods.kalman()) starts from None")
        state0 = _checks.as_array(state0, "ensemble", name)
    return obs, state0


def run_kernel(method: Kernel, obs, state0, *, model: StateSpaceModel, key, config=None,
               params=None, inputs=None, return_ensembles: bool = False,
               check_finite: bool = True,
               progress: Callable[[jax.Array], None] | None = None) -> FilterResult:
    """Run ``method`` over ``obs (K, m)`` from ``state0`` (an ``(N, d)`` ensemble for the ensemble
    filters); see the module docstring. ``inputs``: the per-step inputs of a time-varying model,
    a pytree whose leaves have leading axis K."""
    name = method.name
    obs, state0 = boundary(method, obs, state0, return_ensembles=return_ensembles,
                           check_finite=check_finite, progress=progress)
    if isinstance(model, ParametricModel):
        return _run_parametric(method, obs, state0, model, key, config, params, inputs,
                               return_ensembles, check_finite, progress)
    if method.bind is not None:
        model, config, params, state0 = method.bind(model, config, params, state0)
    obs, state0 = _checked(method, model, config, obs, state0, key, inputs)
    static = (method, model, config, bool(return_ensembles), progress)
    args = (params, obs, state0, key, inputs)
    if progress is not None:
        _announce_compile(static, args)
    return _finished(name, mark_nonfinite(_scan(*static, *args), obs), check_finite)


def _checked(method: Kernel, model, config, obs, state0, key, inputs, values: bool = True):
    """The boundary's checks of a run (the module docstring), and ``(obs, state0)`` promoted to
    their float dtype. ``values`` False (a ``ParametricModel`` whose ``theta`` is traced): the
    model's structure and the arrays' shapes only, not its numbers nor its maps' outputs."""
    name = method.name
    if values:
        check_model(model, name)
    if method.ensemble:
        _checks.check_filter_inputs(obs, state0, model, name=name)
    else:
        _checks.check_obs(obs, model, name=name)
    _checks.check_key(key, name=name)
    _checks.check_inputs(inputs, jnp.shape(obs)[0], model, name=name)
    method.check(model, config)
    obs, state0 = _checks.promote_tree(obs, state0)
    if values:
        check_covariances(model, obs.dtype, name)
        check_dynamics(model, obs.dtype, inputs, name)
    return obs, state0


def _finished(name: str, result: FilterResult, check_finite: bool) -> FilterResult:
    """A concrete run's result after its warning (collapsed weights) and, with
    ``check_finite``, its FloatingPointError (a diverged run)."""
    warn_if_collapsed(name, result.ess)
    warn_if_dropped(name, None if result.info is None else result.info.get("dropped"))
    if check_finite:
        _checks.check_result_finite(name, result)
    return result


def _run_parametric(method: Kernel, obs, state0, pm: ParametricModel, key, config, params,
                    inputs, return_ensembles: bool, check_finite: bool, progress) -> FilterResult:
    """``run_kernel`` of a ``ParametricModel``: the checks on ``build(theta)`` (all of them when
    ``theta`` is concrete; the structure and the shapes of ``obs`` and ``state0`` when traced),
    then ``_scan_parametric``, which builds the model inside the trace."""
    name = method.name
    if method.bind is not None and not method.bind_checks:
        raise TypeError(f"{name}: takes no csf_jax.ParametricModel (its setup reads the model's "
                        f"numbers before the scan); pass build(theta), or use "
                        f"csf_jax.methods.enkf() or csf_jax.methods.pf()")
    method = method.parametric or method
    model = checkable_model(pm.build(pm.theta), name)
    if method.bind is not None:
        method.bind(model, config, params, state0)
    obs, state0 = _checked(method, model, config, obs, state0, key, inputs,
                           values=_checks.is_concrete(pm.theta))
    static = (method, pm.build, config, bool(return_ensembles), progress)
    args = (pm.theta, params, obs, state0, key, inputs)
    if progress is not None:
        _announce_compile(static, args, _scan_parametric, model.dim)
    return _finished(name, mark_nonfinite(_scan_parametric(*static, *args), obs), check_finite)


COLLAPSED_ESS = 1.5
"""The effective sample size below which a filter's weights count as collapsed: one particle
carries (nearly) all the weight, so the step's mean is that particle and its spread is lost."""


def warn_if_collapsed(name: str, ess) -> None:
    """After a concrete run: one ``RuntimeWarning`` naming the filter and the first step whose
    effective sample size ``ess (K,)`` fell below ``COLLAPSED_ESS``, and what to do about it.
    Silent for None (a filter without weights) and under jit/vmap (a traced ``ess``)."""
    if ess is None or not _checks.is_concrete(ess):
        return
    ess = np.asarray(ess)
    low = ess < COLLAPSED_ESS  # NaN (a diverged step) compares False
    if not low.any():
        return
    k = int(np.argmax(low))
    warnings.warn(
        f"{name}: the particle weights collapsed onto one particle at step {k + 1} of "
        f"{ess.shape[0]} (effective sample size {float(ess[k]):.2f}; below "
        f"{COLLAPSED_ESS} at {int(low.sum())} step(s)), so the filtered mean there is a single "
        f"particle; use more particles, a wider likelihood (a larger observation noise), or "
        f"another filter (csf_jax.filter, csf_jax.ensemble_kalman_filter)",
        RuntimeWarning, stacklevel=_caller_level())


def warn_if_dropped(name: str, dropped) -> None:
    """After a concrete run: one ``RuntimeWarning`` naming the first step at which members'
    forecasts went wild and were dropped (``dropped (K,)``, CSF's ``info["dropped"]``:
    ``mixture.wild_members``), how many, and at how many steps. Such a run is finite, and may
    still be sound, but the model carried members off the state space: the filter's numbers there
    rest on the members left. Silent for None and under jit/vmap."""
    if dropped is None or not _checks.is_concrete(dropped):
        return
    dropped = np.asarray(dropped)
    if not dropped.any():
        return
    k = int(np.argmax(dropped > 0))
    warnings.warn(
        f"{name}: {int(dropped[k])} member(s) went wild at step {k + 1} of {dropped.shape[0]} "
        f"(a forecast non-finite, or more than MixtureConfig.wild_ranges central ranges off the "
        f"ensemble) and were dropped ({int(dropped.sum())} at {int((dropped > 0).sum())} "
        f"step(s); result.info['dropped']); a model with an explosive drift does this to a "
        f"shock member: check the run, or switch the shocks off (MixtureConfig(shock_hazard=0.0), "
        f"docs/choosing.md)", RuntimeWarning, stacklevel=_caller_level())


_PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _caller_level() -> int:
    """The ``stacklevel`` of the first frame outside csf_jax: a warning points at the user's call
    whichever route (a named filter, ``run``) led to it."""
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(
            _PACKAGE + os.sep):
        frame, level = frame.f_back, level + 1
    return level


_COMPILED: set = set()


def _signature(static: tuple, args: tuple):
    """What selects one compilation of ``_scan``: the static arguments and the shapes and dtypes
    of the traced ones."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return static, tree, tuple((jnp.shape(x), str(getattr(x, "dtype", type(x).__name__)))
                               for x in leaves)


def _announce_compile(static: tuple, args: tuple, scan=None, dim: int | None = None) -> None:
    """Before the first (compiling) call of a concrete run with ``progress``: say on stderr what
    is compiled, compile it ahead of the call (the call then reuses it), and say how long it took.
    Silent under an outer jit/vmap (nothing is compiled here then) and for a signature seen."""
    if not _checks.is_concrete(args):
        return
    sig = _signature(static, args)
    if sig in _COMPILED:
        return
    method, model = static[0], static[1]
    obs, state0 = args[-4], args[-3]
    members = f"N={jnp.shape(state0)[0]}, " if method.ensemble else ""
    sizes = f"d={model.dim if dim is None else dim}, {members}K={jnp.shape(obs)[0]}"
    label = method.label or method.name
    print(f"compiling the {label} filter ({sizes}) ...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    (scan or _scan).lower(*static, *args).compile()
    print(f"compiled the {label} filter in {time.perf_counter() - t0:.1f} s", file=sys.stderr,
          flush=True)
    _COMPILED.add(sig)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4))
def _scan(method: Kernel, model: StateSpaceModel, config, return_ensembles: bool, progress,
          params, obs, state0, key, inputs) -> FilterResult:
    """The jitted scan of a run; a ``discrete`` kernel's runs go one at a time under
    ``jax.vmap`` (``_batch.one_at_a_time``), so each gives what its separate call gives."""
    scan = functools.partial(_filter_scan, method, model, config, return_ensembles, progress)
    return (one_at_a_time(scan) if method.discrete else scan)(params, obs, state0, key, inputs)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3, 4))
def _scan_parametric(method: Kernel, build, config, return_ensembles: bool, progress, theta,
                     params, obs, state0, key, inputs) -> FilterResult:
    """``_scan`` of the model ``build(theta)``, built inside the trace: ``theta`` (its floating
    leaves cast to the dtype of ``obs``) is traced, so one compilation serves every value."""
    model = build(cast_theta(theta, obs.dtype))
    return _filter_scan(method, model, config, return_ensembles, progress, params, obs, state0,
                        key, inputs)


def _filter_scan(method: Kernel, model: StateSpaceModel, config, return_ensembles: bool, progress,
                 params, obs, state0, key, inputs) -> FilterResult:
    """The scan of ``method`` over ``obs (K, m)``, traced inside ``_scan`` or
    ``_scan_parametric``."""
    K = obs.shape[0]
    state, scan_key = method.init(model, config, params, state0, key)

    def body(state, xs):
        index, y, step_k, key_k = xs
        if progress is not None:
            jax.debug.callback(progress, index)
        state, out = method.step(at_step(model, step_k), config, params, state, y, key_k, step_k)
        return state, (out.mean, out.std, out.ensemble if return_ensembles else None, out.info,
                       out.log_evidence)

    xs = (jnp.arange(K), obs, steps(K, inputs), jax.random.split(scan_key, K))
    _, (mean, std, ensembles, info, log_evidence) = jax.lax.scan(body, state, xs)
    info = dict(info)
    ess = info.pop("ess", None)
    return FilterResult(mean=mean, std=std, ensembles=ensembles, ess=ess, info=info or None,
                        log_evidence=log_evidence)
