"""A model whose numbers are traced: ``ParametricModel(build, theta)``.

A ``StateSpaceModel`` is static: the filters compile once per model, so a sweep over a noise level
made of ordinary models compiles once per value, and ``jax.grad`` cannot see its numbers. A
``ParametricModel`` splits a model into ``build``, a Python function ``theta -> StateSpaceModel``
(static, hashed by identity), and ``theta``, any pytree of arrays (the pytree's leaves): the
filters call ``build(theta)`` inside their compiled scan, so ``jax.jit``, ``jax.grad`` and
``jax.vmap`` act on ``theta`` and one compilation serves every value::

    def build(theta):
        return StateSpaceModel("pendulum", 2, 1, 50, 0.1, drift, lambda x: x[:1],
                               theta["q"], gaussian_noise(theta["r"]), truth, ensemble)

    model = csf_jax.ParametricModel(build, {"q": 0.1, "r": 0.1})
    csf_jax.run(csf_jax.methods.enkf(), obs, ensemble, model=model, key=key)

For the Kalman filter, ``build`` returns a ``LinearGaussian`` (``csf_jax.problems.linear``), made
directly (``LinearGaussian(A, H, q_std, r_std, m0, p0_std, num_steps, name)``: ``linear_gaussian``
validates with numpy and takes no traced number).

``theta``'s floating leaves are cast to the filter's float dtype (that of ``obs`` and the
ensemble) inside the scan. A concrete ``theta`` is checked as an ordinary model is (the model
``build(theta)`` gives, its 0-d numbers read as floats); under an outer ``jit``/``grad``/``vmap``
only its structure and the shapes of ``obs`` and the ensemble are checked (not its values, nor its
drift's and observation map's output shapes): the caller owns the values.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks


@functools.partial(jax.tree_util.register_dataclass, data_fields=["theta"],
                   meta_fields=["build"])
@dataclasses.dataclass(frozen=True, eq=False)
class ParametricModel:
    """A model ``build(theta)`` whose numbers ``theta`` are traced (module docstring).

    Attributes:
      build: ``theta -> StateSpaceModel`` (or ``-> LinearGaussian`` for the Kalman filter), a
        Python callable, static: hashed by identity, so keep one function object (a module-level
        ``def``) to keep one compilation.
      theta: any pytree of arrays or Python numbers: the pytree's leaves, traced.
    """

    build: Callable[[Any], Any]
    theta: Any

    def __post_init__(self):
        if not callable(self.build):
            raise TypeError(f"csf_jax.ParametricModel: build must be a callable theta -> "
                            f"StateSpaceModel, got {type(self.build).__name__}; pass the "
                            f"function itself, ParametricModel(build, theta)")

    def model(self):
        """``build(theta)``: the model at these numbers."""
        return self.build(self.theta)


def is_parametric(model) -> bool:
    """True for a ``ParametricModel``."""
    return isinstance(model, ParametricModel)


def as_float(x):
    """``x`` as a Python float when it is a concrete number (a Python, numpy or 0-d jax scalar),
    as is when traced: constructors keep their hashable floats on the ordinary path and pass
    tracers through on a ``ParametricModel``'s."""
    if isinstance(x, jax.core.Tracer):
        return x
    return float(x)


def cast_theta(theta, dtype):
    """``theta`` with every floating leaf as an array of ``dtype`` (others as arrays)."""
    def cast(a):
        a = jnp.asarray(a)
        return a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a
    return jax.tree_util.tree_map(cast, theta)


def checkable_model(model, name: str = "filter"):
    """The model ``build(theta)`` as the boundary checks of ordinary models take it: its 0-d
    numbers (``process_std``, the noise's ``gaussian_std`` and ``fisher``) as Python floats when
    concrete, and 1.0 in place of a traced one (a stand-in for the structural checks alone: the
    scan builds the model anew from the traced ``theta``). TypeError if ``build`` did not return a
    ``StateSpaceModel``."""
    from csf_jax.ssm import ObservationNoise, StateSpaceModel

    if not isinstance(model, StateSpaceModel):
        raise TypeError(f"{name}: a ParametricModel's build(theta) must return a "
                        f"csf_jax.StateSpaceModel, got {type(model).__name__}; the Kalman filter "
                        f"(csf_jax.kalman_filter) takes a build returning a LinearGaussian")

    def number(v):
        if v is None or isinstance(v, (bool, np.bool_, int, float)) or np.ndim(v) != 0:
            return v
        return float(v) if _checks.is_concrete(v) else 1.0

    noise = model.obs_noise
    if isinstance(noise, ObservationNoise):
        noise = noise._replace(gaussian_std=number(noise.gaussian_std), fisher=number(noise.fisher))
    return model._replace(process_std=number(model.process_std), obs_noise=noise)
