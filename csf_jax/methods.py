"""Every filter as a ``Method`` made by a builder, and the registry of builders by name.

    method = csf_jax.methods.enkf(inflation=1.05)
    result = csf_jax.run(method, obs, ensemble, model=model, key=key)

A builder takes the filter's settings and no data; ``csf_jax.run`` takes the data. The named
filter functions (``csf_jax.filter``, ``csf_jax.letkf``, ...) are conveniences over exactly this.
``REGISTRY`` maps a name to its builder: the experiments' harness and the tests look filters up
there, so a new filter joins every benchmark with its module and one line here.
"""

from __future__ import annotations

import inspect

from csf_jax.filters.csf import method as csf
from csf_jax.filters.driver import Method, run
from csf_jax.filters.enkf import method as enkf
from csf_jax.filters.ensf import method as ensf
from csf_jax.filters.ienks import method as ienks
from csf_jax.filters.kalman import method as kalman
from csf_jax.filters.letkf import method as letkf
from csf_jax.filters.local_csf import method as local_csf
from csf_jax.filters.local_transform import method as local_transform
from csf_jax.filters.pf import method as pf
from csf_jax.filters.reference import method as reference
from csf_jax.filters.sf import method as sf
from csf_jax.filters.sharded import method as sharded_letkf
from csf_jax.filters.sharded_transform import method as sharded_transform

REGISTRY = {"csf": csf, "enkf": enkf, "pf": pf, "letkf": letkf, "sharded_letkf": sharded_letkf,
            "local_csf": local_csf, "local_transform": local_transform, "ensf": ensf, "sf": sf,
            "reference": reference, "kalman": kalman, "ienks": ienks,
            "sharded_transform": sharded_transform}


def build(name: str, **settings) -> Method:
    """The ``Method`` of the filter registered as ``name``, with ``settings`` for its builder."""
    if name not in REGISTRY:
        raise ValueError(f"unknown filter {name!r}; choose from {', '.join(REGISTRY)}")
    builder = REGISTRY[name]
    accepted = inspect.signature(builder).parameters
    unknown = sorted(set(settings) - set(accepted))
    if unknown and not any(p.kind is p.VAR_KEYWORD for p in accepted.values()):
        raise TypeError(f"methods.build({name!r}): unknown setting(s) {', '.join(unknown)}; "
                        f"methods.{name} takes {', '.join(accepted) or 'none'}")
    return builder(**settings)


__all__ = ["Method", "REGISTRY", "build", "csf", "enkf", "ensf", "ienks", "kalman", "letkf", "local_csf",
           "local_transform", "pf", "reference", "run", "sf", "sharded_letkf", "sharded_transform"]
