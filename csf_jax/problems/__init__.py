"""The paper's problems, looked up by name: ``csf_jax.problems.get("double_well")``.

Each name maps to a frozen config (defaults = the README's tables) and a builder; ``get(name,
**overrides)`` replaces config fields, e.g. ``get("cubic10_indep", num_steps=50)``.
"""

from __future__ import annotations

import dataclasses

from csf_jax.problems.cubic import CubicConfig, cubic_problem
from csf_jax.problems.wells import WellConfig, well_problem
from csf_jax.ssm import StateSpaceModel

CONFIGS = {
    "double_well": WellConfig(wells="double"),
    "triple_well": WellConfig(wells="triple", C=0.5),
    "cauchy": CubicConfig(dim=5, noise="cauchy", obs_scale=0.0544, shock_count=1),
    "cubic10_indep": CubicConfig(dim=10),
    "cubic10_corr": CubicConfig(dim=10, correlated=True),
    "cubic20_indep": CubicConfig(dim=20),
    "cubic20_corr": CubicConfig(dim=20, correlated=True),
}

NAMES = tuple(CONFIGS)


def config(name: str, **overrides):
    """The frozen config of problem ``name``, with ``overrides`` applied."""
    if name not in CONFIGS:
        raise KeyError(f"unknown problem {name!r}; known: {', '.join(NAMES)}")
    return dataclasses.replace(CONFIGS[name], **overrides)


def build(cfg) -> StateSpaceModel:
    """The model for a config (``WellConfig`` or ``CubicConfig``)."""
    if isinstance(cfg, WellConfig):
        return well_problem(cfg)
    if isinstance(cfg, CubicConfig):
        return cubic_problem(cfg)
    raise TypeError(f"no problem builder for config type {type(cfg).__name__}")


def get(name: str, **overrides) -> StateSpaceModel:
    """The ``StateSpaceModel`` of problem ``name`` (one of ``NAMES``), with config ``overrides``."""
    return build(config(name, **overrides))


__all__ = ["CONFIGS", "NAMES", "CubicConfig", "WellConfig", "build", "config", "get",
           "cubic_problem", "well_problem"]
