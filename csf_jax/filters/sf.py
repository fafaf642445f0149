"""The score-based filter (SF) baseline of Bao et al. (2024), the paper's ``bao2024score``.

SF has no offline stage: at every filter step it trains an unconditional score net on the prior
ensemble (warm-started from the previous step's net and Adam state), then conditions with the same
reverse-SDE sampler and DPS guidance as CSF. Its per-step training budget is ``SFConfig.train_steps``
Adam steps on batches of ``SFConfig.batch`` particles; the first filter step adds
``SFConfig.warmup_steps`` on the initial ensemble from a fresh net.

One jitted ``lax.scan`` over the K observations, carrying (ensemble, score-net variables, Adam state).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from csf_jax import _checks, networks
from csf_jax.dsm import dsm_fit
from csf_jax.filters.csf import PAPER, CSFConfig, particle_sampler, sampler_start
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.result import FilterResult
from csf_jax.prior import unconditional_prior
from csf_jax.ssm import StateSpaceModel, process_draws


@dataclasses.dataclass(frozen=True)
class SFConfig:
    """Per-step training of the SF baseline; defaults reproduce the README's tables.

    Attributes:
      train_steps: Adam steps per filter step, warm-started (the SF's per-step training budget).
      warmup_steps: Adam steps on the initial ensemble, from a fresh net, before the first step.
      batch: particles per Adam step (drawn with replacement from the N-particle prior ensemble).
      lr: Adam learning rate (constant).
      network: the score net's architecture (the same ``ScoreNet`` as CSF; the code is fixed at zero).
    """

    train_steps: int = 200
    warmup_steps: int = 2000
    batch: int = 256
    lr: float = 1e-3
    network: networks.NetworkConfig = networks.NetworkConfig()

    def __post_init__(self):
        _checks.check_fields(self)
        for name in ("train_steps", "warmup_steps", "batch"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < (0 if name == "warmup_steps" else 1):
                raise ValueError(f"SFConfig.{name} must be a positive int, got {value!r}")
        if not self.lr > 0:
            raise ValueError(f"SFConfig.lr must be > 0, got {self.lr!r}")


class SFStatic(NamedTuple):
    """SF's static settings for the driver."""

    config: SFConfig
    sampler: CSFConfig
    shards: int = 1


def _optimizer(config: SFConfig):
    return optax.adam(config.lr)


def _init(model: StateSpaceModel, static: SFStatic, params, ensemble, key):
    """A fresh score net, trained ``warmup_steps`` on the initial ensemble; carry
    ``(ensemble, score variables, Adam state)``."""
    config, sampler = static.config, static.sampler
    net = config.network
    optimizer = _optimizer(config)
    k_init, k_warm, k_scan = jax.random.split(key, 3)
    init = networks.init_params(k_init, net, model.dim)
    score_vars = jax.tree_util.tree_map(lambda a: a.astype(ensemble.dtype), init["score"])
    opt_state = optimizer.init(score_vars)
    if config.warmup_steps:
        score_vars, opt_state, _ = dsm_fit(k_warm, ensemble, score_vars, opt_state, optimizer,
                                           config=net, steps=config.warmup_steps,
                                           batch=config.batch, t_min=sampler.sampler.t_min,
                                           shards=static.shards)
    return (ensemble, score_vars, opt_state), k_scan


def _step(model: StateSpaceModel, static: SFStatic, params, state, y, key, time):
    """Propagate, train the score net on the prior ensemble, sample the posterior."""
    config, sampler = static.config, static.sampler
    net = config.network
    ens, sv, o = state
    k_prop, k_fit, k_x, k_rev = jax.random.split(key, 4)
    centers = jax.vmap(model.drift)(ens)
    prior_ens = centers + process_draws(model, k_prop, ens.shape, ens.dtype)
    sv, o, _ = dsm_fit(k_fit, prior_ens, sv, o, _optimizer(config), config=net,
                       steps=config.train_steps, batch=config.batch, t_min=sampler.sampler.t_min,
                       shards=static.shards)
    prior = unconditional_prior(net)
    full = {"encoder": None, "score": sv}
    context = prior.condition(full, centers, prior_ens, model.process_std)
    guide = jnp.where((time.k > 1) | sampler.sampler.assimilate_first, 1.0, 0.0).astype(ens.dtype)
    x_init, start = sampler_start(sampler, prior_ens, k_x, y, model, guide)
    post = particle_sampler(model, prior, sampler)(full, context, y, x_init, start, k_rev, guide)
    return (post, sv, o), StepOutput(post.mean(0), post.std(0), post)


def _check(model: StateSpaceModel, static: SFStatic) -> None:
    if static.config.network.sigma_max != static.sampler.sampler.sigma_max:
        raise ValueError(f"SFConfig.network.sigma_max ({static.config.network.sigma_max}) must "
                         f"equal the sampler's sigma_max ({static.sampler.sampler.sigma_max})")


SCORE_FILTER = Kernel("score_filter", _init, _step, _check, label="SF", discrete=True)


@_checks.renamed_keywords(problem="model")
def score_filter(obs, ensemble, *, model: StateSpaceModel, key, config: SFConfig = SFConfig(),
                 sampler: CSFConfig = PAPER, inputs=None, return_ensembles: bool = False,
                 check_finite: bool = True,
                 progress: Callable[[jax.Array], None] | None = None,
                 shards: int = 1) -> FilterResult:
    """Filter ``obs`` with the score-based filter (a score net trained online at every step).

    Args:
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype. NaN marks a missing entry (left out of the update); inf is an error.
      ensemble: (N, d) initial ensemble (time 0).
      model: the ``StateSpaceModel`` (static: hashable).
      key: a ``jax.random.key``; it also initialises the score net. Same key, same result.
      config: the per-step training budget and network (``SFConfig``).
      sampler: reverse-SDE, guidance and inflation settings, shared with CSF (``CSFConfig``;
        default ``csf_jax.PAPER``, the paper's: SF samples from its own score net alone, without
        CSF's mixture prior, and its innovation-triggered inflation is what follows a shock).
      inputs: a time-varying model's per-step inputs (leading axis K), or None.
      return_ensembles: also return the (K, N, d) posterior ensembles.
      check_finite: when called outside jit/vmap, raise FloatingPointError if the filter diverged.
      progress: optional host callback ``k -> None`` called at the start of every filter step
        (``jax.debug.callback``; once per step under ``vmap``); a concrete call with it also
        says on stderr when it compiles, and how long that took.
      shards: split each training batch over this many local devices (``dsm_fit``; it must divide
        ``config.batch``): the same filter up to float summation order, one run on several
        devices (on a CPU with one XLA host device per core, ``experiments.run`` does this for a
        single SF run).

    Returns:
      ``FilterResult`` with mean and std (K, d) and ``finite`` (K,). Works under ``jax.jit`` and
      ``jax.vmap`` over ``(obs, ensemble, key)``; there mean and std are NaN and ``finite`` False
      from a non-finite step on (``mark_nonfinite``).
    """
    return run(method(config, sampler, shards), obs, ensemble, model=model, key=key,
               inputs=inputs, return_ensembles=return_ensembles, check_finite=check_finite,
               progress=progress)


def method(config: SFConfig = SFConfig(), sampler: CSFConfig = PAPER,
           shards: int = 1) -> Method:
    """The score filter as a ``Method`` for ``csf_jax.run`` (arguments: ``score_filter``)."""
    if not isinstance(config, SFConfig) or not isinstance(sampler, CSFConfig):
        raise TypeError(f"score_filter: config must be an SFConfig and sampler a CSFConfig, got "
                        f"{type(config).__name__} and {type(sampler).__name__}")
    if isinstance(shards, bool) or not isinstance(shards, int) or shards < 1\
            or config.batch % shards or shards > jax.local_device_count():
        raise ValueError(f"score_filter: shards must be a positive int dividing SFConfig.batch "
                         f"({config.batch}) and at most the {jax.local_device_count()} local "
                         f"devices, got {shards!r}")
    return Method(SCORE_FILTER, SFStatic(config, sampler, shards))
