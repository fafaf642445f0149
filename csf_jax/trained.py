"""A trained prior: parameters together with the network config and the problem they were made for.

``Pretrained`` is what ``csf_jax.load_pretrained`` returns and what ``csf_jax.filter`` checks when
given it whole: the filter takes the network config from it and refuses a problem, a ``network=``
or a ``sigma_max`` it was not trained for, naming both sides. Raw parameter dicts still work, but
nothing about them can be checked beyond their shapes.
"""

from __future__ import annotations

import dataclasses
import json
from typing import NamedTuple, Optional

import jax

from csf_jax import networks


class Pretrained(NamedTuple):
    """A trained prior: ``params`` for ``csf_jax.filter``, the ``network`` config they were made
    with, and their ``meta`` record (``meta["problem"]`` and ``meta["dim"]``: the problem it was
    trained for; also training configs, dataset id, validation history).

    serves: names of further problems it may filter besides ``meta["problem"]`` (a transfer, such
    as the double-well model on ``triple_well``). A pytree whose only leaves are ``params``, so it
    passes through ``jax.jit`` and ``jax.vmap`` as raw params do.
    """

    params: dict
    network: networks.NetworkConfig
    meta: dict
    serves: tuple = ()

    @property
    def problem(self) -> Optional[str]:
        """The name of the problem it was trained for (None if the meta record has none)."""
        return self.meta.get("problem")

    @property
    def dim(self) -> Optional[int]:
        """The state dimension it was trained for (None if the meta record has none)."""
        return None if self.meta.get("dim") is None else int(self.meta["dim"])


class _Static:
    """A dict held as hashable pytree aux data: equal when the dicts are equal."""

    def __init__(self, value: dict):
        self.value = value
        self._key = json.dumps(value, sort_keys=True, default=repr)

    def __eq__(self, other):
        return isinstance(other, _Static) and self._key == other._key

    def __hash__(self):
        return hash(self._key)


jax.tree_util.register_pytree_with_keys(
    Pretrained,
    lambda p: (((jax.tree_util.GetAttrKey("params"), p.params),),
               (p.network, _Static(p.meta), tuple(p.serves))),
    lambda aux, children: Pretrained(children[0], aux[0], aux[1].value, aux[2]))


def _config_diff(given: networks.NetworkConfig, own: networks.NetworkConfig) -> str:
    """``field: given X, trained Y`` for every field where two network configs differ."""
    return ", ".join(f"{f.name}: given {getattr(given, f.name)!r}, trained {getattr(own, f.name)!r}"
                     for f in dataclasses.fields(own)
                     if getattr(given, f.name) != getattr(own, f.name))


def unpack(trained, problem, network: Optional[networks.NetworkConfig],
           name: str = "csf_jax.filter"):
    """``(params, network)`` for the filter: raw params pass through unchanged; a ``Pretrained``
    is checked against ``problem`` (name and dim) and ``network``, and gives its own params and
    network config (the filter then checks the sampler's ``sigma_max`` against it). Every refusal
    is a one-line ValueError naming both sides."""
    if not isinstance(trained, Pretrained):
        return trained, network
    made_for = trained.problem
    allowed = (made_for,) + tuple(trained.serves)
    if made_for is not None and problem.name not in allowed:
        raise ValueError(f"{name}: the trained prior was made for problem {made_for!r} (d="
                         f"{trained.dim}), but problem={problem.name!r} (d={problem.dim}); load the "
                         f"model of {problem.name!r}")
    if trained.dim is not None and trained.dim != problem.dim:
        raise ValueError(f"{name}: the trained prior was made for d={trained.dim}, but problem "
                         f"{problem.name!r} has d={problem.dim}")
    if network is not None and network != trained.network:
        raise ValueError(f"{name}: network= differs from the trained prior's own network config "
                         f"({_config_diff(network, trained.network)}); leave network= out")
    return trained.params, trained.network
