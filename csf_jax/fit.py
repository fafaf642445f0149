"""Learning a model's parameters: ``csf_jax.fit`` maximises the data's log evidence.

The filters return ``FilterResult.log_evidence (K,)``, ``log p(y_k | y_1 .. y_{k-1})``; its sum
is the log-likelihood of the record given the model's numbers ``theta``. ``fit`` climbs it by
gradient ascent (optax; Adam by default) through a ``ParametricModel(build, theta)``, whose
numbers are traced: one compiled step (``jax.jit`` of ``jax.value_and_grad``) serves every
iteration.

What the gradient is, per filter:

* the Kalman filter (``csf_jax.methods.kalman()``, ``build`` returning a ``LinearGaussian``):
  exact, the gradient of the exact log-likelihood;
* the EnKF (the default): the gradient of the innovation density with the filter's random draws
  held fixed (the same ``key`` at every iteration: common random numbers), so the objective is a
  smooth function of ``theta``; exact as N grows for a linear-Gaussian model;
* the LETKF (``methods.letkf(localization)``): as the EnKF, its keys held fixed, through its
  ensemble transforms' closed-form derivative (``letkf.ensemble_transforms``);
* the particle filter: its propagation is reparametrised (the draws held fixed) and its
  resampling is not differentiable: the resampled indices are constants and each picked
  particle carries ``log w - stop_gradient(log w)`` (0 in value), whose gradient is the score of
  the pick. The estimate is consistent as N grows, with a variance that grows with K (the
  resampled paths coalesce); its objective is piecewise smooth in ``theta`` (a pick changes
  where a weight crosses a resampling threshold).

Constraints: a ``Transform`` maps an unconstrained ``raw`` to ``theta``; ``positive("q", "r")``
takes the named entries of a dict ``theta`` (every leaf when none is named) as ``exp(raw)``.
"""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax.filters.driver import Method, run
from csf_jax.parametric import ParametricModel


class FitResult(NamedTuple):
    """What ``fit`` returns.

    Attributes:
      theta: the fitted parameters (the pytree of ``theta0``), after the last step.
      log_evidence: ``(steps,)`` the summed log evidence ``log p(y_1 .. y_K)`` at each
        iteration's parameters (before its update).
      trace: the parameters at each iteration (before its update): ``theta0``'s pytree with a
        leading axis ``steps`` on every leaf.
    """

    theta: Any
    log_evidence: jax.Array
    trace: Any


class Transform(NamedTuple):
    """A change of variables for ``fit``: the optimiser moves ``raw``, the model sees
    ``theta = forward(raw)``; ``inverse(theta0)`` is where it starts."""

    forward: Callable[[Any], Any]
    inverse: Callable[[Any], Any]


def positive(*names: str) -> Transform:
    """``theta = exp(raw)`` on the entries ``names`` of a dict ``theta`` (on every leaf when no
    name is given), the others as they are: a positive parameter (a noise std) never crosses 0."""

    def on(fn):
        def apply(tree):
            if not names:
                return jax.tree_util.tree_map(fn, tree)
            missing = [n for n in names if n not in tree]
            if missing:
                raise KeyError(f"csf_jax.positive: theta has no entry {missing[0]!r} (it has "
                               f"{sorted(tree)}); name entries of the dict theta0")
            return {k: (fn(v) if k in names else v) for k, v in tree.items()}
        return apply

    return Transform(on(jnp.exp), on(jnp.log))


IDENTITY = Transform(lambda raw: raw, lambda theta: theta)


def fit(build: Callable[[Any], Any], theta0, obs, ensemble=None, *, key, method: Method | None = None,
        steps: int = 200, learning_rate: float = 0.05, optimizer=None,
        transform: Transform | None = None, inputs=None, progress: bool = True) -> FitResult:
    """Maximise the summed log evidence of ``obs`` over the model's parameters ``theta``.

    Args:
      build: ``theta -> StateSpaceModel`` (a ``LinearGaussian`` with ``methods.kalman()``), one
        Python function: the model at ``theta`` (``csf_jax.ParametricModel``). Rebuilding a
        model with new noises is ``base._replace(process_std=theta["q"],
        obs_noise=csf_jax.gaussian_noise(theta["r"]))``.
      theta0: the starting parameters, any pytree of floats.
      obs: ``(K, m)`` observations (NaN: missing).
      ensemble: ``(N, d)`` initial ensemble (None for the Kalman filter).
      key: a ``jax.random.key``, the same at every iteration (common random numbers: the
        objective is one smooth function of theta).
      method: the filter, a ``csf_jax.methods`` builder's ``Method``; None: the EnKF.
      steps: the number of gradient steps.
      learning_rate: the step size of the default optimiser (``optax.adam``), in ``raw`` units
        (with ``positive``, a relative change of about that much per step).
      optimizer: an ``optax.GradientTransformation`` in place of Adam.
      transform: a ``Transform`` (``csf_jax.positive(...)``) the optimiser sees ``theta``
        through; None: ``theta`` itself.
      inputs: a time-varying model's per-step inputs.
      progress: a line on stderr about every tenth of the steps.

    Returns:
      ``FitResult(theta, log_evidence (steps,), trace)``. FloatingPointError at the first step
      whose log evidence or gradient is not finite.
    """
    import optax

    _check_fit(build, theta0, steps, learning_rate, method, transform)
    method = _default_method() if method is None else method
    transform = IDENTITY if transform is None else transform
    optimizer = optax.adam(learning_rate) if optimizer is None else optimizer
    obs = jnp.asarray(obs)
    dtype = obs.dtype if jnp.issubdtype(obs.dtype, jnp.floating) else jnp.float32
    theta0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), theta0)
    _first_check(method, build, theta0, obs, ensemble, key, inputs)

    def loss(raw):
        theta = transform.forward(raw)
        result = run(method, obs, ensemble, model=ParametricModel(build, theta), key=key,
                     inputs=inputs, check_finite=False)
        return -jnp.sum(result.log_evidence)

    @jax.jit
    def update(raw, state):
        value, grad = jax.value_and_grad(loss)(raw)
        moves, state = optimizer.update(grad, state, raw)
        finite = functools.reduce(jnp.logical_and, [jnp.all(jnp.isfinite(g)) for g in
                                                    jax.tree_util.tree_leaves(grad)],
                                  jnp.isfinite(value))
        return optax.apply_updates(raw, moves), state, -value, finite

    raw = transform.inverse(theta0)
    state = optimizer.init(raw)
    every = max(1, steps // 10)
    trace, values = [], []
    for i in range(steps):
        theta = transform.forward(raw)
        raw, state, value, finite = update(raw, state)
        if not bool(finite):
            raise FloatingPointError(
                f"fit: the log evidence or its gradient is not finite at step {i + 1} of {steps} "
                f"(theta={_brief(theta)}); lower learning_rate, start nearer, or keep positive "
                f"parameters positive with transform=csf_jax.positive(...)")
        trace.append(theta)
        values.append(value)
        if progress and ((i + 1) % every == 0 or i == 0):
            print(f"fit: step {i + 1}/{steps}: log evidence {float(value):.4g}, "
                  f"theta={_brief(theta)}", file=sys.stderr, flush=True)
    trace = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trace)
    return FitResult(transform.forward(raw), jnp.stack(values), trace)


def _default_method() -> Method:
    from csf_jax import methods

    return methods.enkf()


def _first_check(method, build, theta0, obs, ensemble, key, inputs) -> None:
    """The boundary checks of one concrete run at ``theta0``, without running it: a wrong model,
    obs or ensemble is refused in one line before anything compiles."""
    from csf_jax import _checks
    from csf_jax.filters.driver import boundary
    from csf_jax.parametric import checkable_model
    from csf_jax.ssm import check_dynamics, check_model

    kernel = method.kernel
    obs_, state0 = boundary(kernel, obs, ensemble)
    if not kernel.ensemble:
        return  # the Kalman filter: build returns a LinearGaussian, read at the first step
    model = checkable_model(build(theta0), kernel.name)
    check_model(model, kernel.name)
    _checks.check_filter_inputs(obs_, state0, model, name=kernel.name)
    _checks.check_key(key, name=kernel.name)
    obs_, _ = _checks.promote_tree(obs_, state0)
    check_dynamics(model, obs_.dtype, inputs, kernel.name)


def _check_fit(build, theta0, steps, learning_rate, method, transform) -> None:
    """One-line errors for fit's own arguments."""
    if not callable(build):
        raise TypeError(f"fit: build must be a callable theta -> StateSpaceModel, got "
                        f"{type(build).__name__}")
    if isinstance(steps, (bool, np.bool_)) or not isinstance(steps, (int, np.integer)) \
            or steps < 1:
        raise ValueError(f"fit: steps must be a positive int, got {steps!r}")
    if not (isinstance(learning_rate, (int, float, np.integer, np.floating))
            and math.isfinite(float(learning_rate)) and learning_rate > 0):
        raise ValueError(f"fit: learning_rate must be a positive number, got {learning_rate!r}")
    if method is not None and not isinstance(method, Method):
        raise TypeError(f"fit: method must be a csf_jax.Method (csf_jax.methods.enkf(), "
                        f".pf(), .kalman()) or None, got {type(method).__name__}")
    if transform is not None and not isinstance(transform, Transform):
        raise TypeError(f"fit: transform must be a csf_jax.Transform (e.g. "
                        f"csf_jax.positive('r')) or None, got {type(transform).__name__}")
    for leaf in jax.tree_util.tree_leaves(theta0):
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.number) or isinstance(leaf, bool):
            raise TypeError(f"fit: theta0's leaves must be numbers or float arrays, got "
                            f"{type(leaf).__name__}")


def _brief(theta) -> str:
    """``theta`` in a few significant digits, for the progress lines and messages."""
    leaves = jax.tree_util.tree_leaves_with_path(theta)
    parts = []
    for path, leaf in leaves:
        arr = np.asarray(leaf)
        value = f"{float(arr):.4g}" if arr.ndim == 0 else np.array2string(arr, precision=4)
        name = ".".join(str(getattr(k, "key", getattr(k, "idx", k))) for k in path)
        parts.append(f"{name}={value}" if name else value)
    return ", ".join(parts)
