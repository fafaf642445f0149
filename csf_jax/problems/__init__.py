"""The paper's problems, Lorenz-96 and the zoo, looked up by name: ``csf_jax.problems.get("ungm")``.

Each name maps to a frozen config (defaults = the README's tables) and a builder; ``get(name,
**overrides)`` replaces config fields, e.g. ``get("cubic10_indep", num_steps=50)`` or
``get("lorenz96", dim=1000)``. ``NAMES`` are the paper's seven problems (the table's columns);
``BENCHMARKS`` the Lorenz-96 setups beyond the paper; ``ZOO`` the benchmark of unseen models
(``csf_jax.problems.zoo``).
"""

from __future__ import annotations

import dataclasses

from csf_jax.problems import zoo
from csf_jax.problems.cubic import CubicConfig, cubic_problem
from csf_jax.problems.lorenz96 import Lorenz96Config, lorenz96_problem
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

# Lorenz-96, the data-assimilation standard (F = 8, dt = 0.05, R = I), and its nonlinear sensor.
# lorenz96_ensf: EnSF's setup (Bao, Zhang & Zhang 2024): RK4 steps of 0.01, an arctan observation
# (noise std 0.05) of every site every 10 steps, 150 analyses (errors averaged over the last 50),
# a spun-up truth, an N(0, I) ensemble, random relative shocks of the truth.
BENCHMARKS = {
    "lorenz96": Lorenz96Config(),
    "lorenz96_arctan": Lorenz96Config(sensor="arctan", obs_std=0.05),
    "lorenz96_ensf": Lorenz96Config(dim=100, dt=0.1, substeps=10, sensor="arctan", obs_std=0.05,
                                    num_steps=150, burn_in=100, x0_std=3.0, truth_spinup=100,
                                    ensemble_init="standard", shock_probs=(0.005, 0.01, 0.02),
                                    shock_sizes=(0.5, 0.2, 0.05)),
}


ZOO = dict(zoo.CONFIGS)


def config(name: str, **overrides):
    """The frozen config of problem ``name``, with ``overrides`` applied."""
    known = {**CONFIGS, **BENCHMARKS, **ZOO}
    if name not in known:
        raise KeyError(f"unknown problem {name!r}; known: {', '.join(known)}")
    fields = {f.name for f in dataclasses.fields(known[name])}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise TypeError(f"problem {name!r} has no field(s) {', '.join(unknown)}; its fields: "
                        f"{', '.join(sorted(fields))}")
    return dataclasses.replace(known[name], **overrides)


def build(cfg) -> StateSpaceModel:
    """The model for a config (any of ``config``'s)."""
    if isinstance(cfg, WellConfig):
        return well_problem(cfg)
    if isinstance(cfg, CubicConfig):
        return cubic_problem(cfg)
    if isinstance(cfg, Lorenz96Config):
        return lorenz96_problem(cfg)
    if type(cfg) in zoo.BUILDERS:
        return zoo.BUILDERS[type(cfg)](cfg)
    raise TypeError(f"no problem builder for config type {type(cfg).__name__}")


def get(name: str, **overrides) -> StateSpaceModel:
    """The ``StateSpaceModel`` of problem ``name`` (``NAMES``, ``BENCHMARKS`` or ``ZOO``), with
    config ``overrides``."""
    return build(config(name, **overrides))


__all__ = ["BENCHMARKS", "CONFIGS", "NAMES", "ZOO", "zoo", "CubicConfig", "Lorenz96Config", "WellConfig", "build",
           "config", "get", "cubic_problem", "lorenz96_problem", "well_problem"]
