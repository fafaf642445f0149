"""Every filter as a ``Method`` made by a builder, and the registry of builders by name.

    method = csf_jax.methods.enkf(inflation=1.05)
    result = csf_jax.run(method, obs, ensemble, model=model, key=key)

A builder takes the filter's settings and no data; ``csf_jax.run`` takes the data. The named
filter functions (``csf_jax.filter``, ``csf_jax.letkf``, ...) are conveniences over exactly this.
``REGISTRY`` maps a name to its builder: the experiments' harness and the tests look filters up
there, so a new filter joins every benchmark with its module and one line here.

The settings objects a user hands the public calls (``config=``, ``localization=``, ``prior=``,
``network=``) are registered here as pytrees with no leaves (``STATIC_SETTINGS``), as the model
is (``csf_jax.ssm``): ``jax.jit(csf_jax.letkf)(obs, ensemble, model=model, key=key,
localization=loc, config=config)`` then takes them as the static values they are.
"""

from __future__ import annotations

import inspect

from csf_jax import _checks
from csf_jax.covariance import CovarianceConfig
from csf_jax.filters.csf import CSFConfig, SamplerConfig
from csf_jax.filters.csf import method as csf
from csf_jax.filters.driver import Method, run
from csf_jax.filters.enkf import method as enkf
from csf_jax.filters.ensf import ENSFConfig
from csf_jax.filters.ensf import method as ensf
from csf_jax.filters.ienks import IEnKSConfig
from csf_jax.filters.ienks import method as ienks
from csf_jax.filters.kalman import method as kalman
from csf_jax.filters.letkf import LETKFConfig, Localization
from csf_jax.filters.letkf import method as letkf
from csf_jax.filters.local_csf import LocalCSFConfig
from csf_jax.filters.local_csf import method as local_csf
from csf_jax.filters.local_transform import LocalTransformConfig
from csf_jax.filters.local_transform import method as local_transform
from csf_jax.filters.pf import method as pf
from csf_jax.filters.reference import ReferenceConfig
from csf_jax.filters.reference import method as reference
from csf_jax.filters.sf import SFConfig
from csf_jax.filters.sf import method as sf
from csf_jax.filters.sharded import method as sharded_letkf
from csf_jax.filters.sharded_transform import method as sharded_transform
from csf_jax.guidance import GuidanceConfig
from csf_jax.inflation import InflationConfig
from csf_jax.mixture import MixtureConfig
from csf_jax.networks import NetworkConfig
from csf_jax.prior import PriorConfig, PriorScore

STATIC_SETTINGS = (CSFConfig, SamplerConfig, GuidanceConfig, InflationConfig, PriorConfig,
                   MixtureConfig, CovarianceConfig, NetworkConfig, PriorScore, LETKFConfig,
                   Localization, LocalCSFConfig, LocalTransformConfig, ENSFConfig, IEnKSConfig,
                   SFConfig, ReferenceConfig)
"""The hashable settings classes the filters take, each a pytree with no leaves
(``_checks.static_pytree``) so that they pass through ``jax.jit`` and ``jax.vmap`` as static."""

for _cls in STATIC_SETTINGS:
    _checks.static_pytree(_cls)

REGISTRY = {"csf": csf, "enkf": enkf, "pf": pf, "letkf": letkf, "sharded_letkf": sharded_letkf,
            "local_csf": local_csf, "local_transform": local_transform, "ensf": ensf, "sf": sf,
            "reference": reference, "kalman": kalman, "ienks": ienks,
            "sharded_transform": sharded_transform}


def build(name: str, *positional, **settings) -> Method:
    """The ``Method`` of the filter registered as ``name``, with ``settings`` (keywords) for its
    builder: ``build("enkf", inflation=1.05)``. A name that is not a registered str, or a
    setting given positionally, is a one-line TypeError (ValueError for an unknown name)."""
    names = ", ".join(REGISTRY)
    if not isinstance(name, str):
        raise TypeError(f"methods.build: name must be a str, one of {names}; got {name!r:.60} "
                        f"({type(name).__name__})")
    if name not in REGISTRY:
        raise ValueError(f"methods.build: unknown filter {name!r}; choose from {names}")
    builder = REGISTRY[name]
    accepted = inspect.signature(builder).parameters
    if positional:
        keywords = [p for p in accepted.values() if p.kind not in (p.VAR_POSITIONAL,
                                                                  p.VAR_KEYWORD)]
        example = (f"methods.build({name!r}, {keywords[0].name}={positional[0]!r:.40})"
                   if keywords else f"methods.build({name!r}) (methods.{name} takes none)")
        raise TypeError(f"methods.build({name!r}): settings are keywords, got "
                        f"{len(positional)} positional value(s); name them, e.g. {example}")
    unknown = sorted(set(settings) - set(accepted))
    if unknown and not any(p.kind is p.VAR_KEYWORD for p in accepted.values()):
        raise TypeError(f"methods.build({name!r}): unknown setting(s) {', '.join(unknown)}; "
                        f"methods.{name} takes {', '.join(accepted) or 'none'}")
    return builder(**settings)


__all__ = ["Method", "REGISTRY", "STATIC_SETTINGS", "build", "csf", "enkf", "ensf", "ienks", "kalman", "letkf", "local_csf",
           "local_transform", "pf", "reference", "run", "sf", "sharded_letkf", "sharded_transform"]
