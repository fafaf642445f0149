"""The Conditional Score-based Filter, online stage (paper Sec. 2.2, Alg. 2).

Each filter step, inside one jitted ``lax.scan`` over the K observations (``csf_jax.filters.driver``):

    propagate (vmapped drift + process noise) -> prior ensemble -> condition the prior score once
      -> the mixture prior's evidence stage (``csf_jax.mixture``: particle, ensemble and shock
         components; each member's component drawn by prior weight x evidence)
      -> lax.scan over L reverse steps for the ensemble component's members (particle and shock
         members keep their importance draws) -> posterior ensemble (the next carry); mean, std.

Two samplers, chosen by ``CSFConfig.sampler.guidance.mode``:

* ``"kalman"`` (default): the ancestral sampler. It starts from the prior ensemble noised to
  ``sigma_start`` and walks down a geometric grid of noise levels to 0. At each level the prior
  score gives Tweedie's ``x0_hat``, the ensemble's Gaussian gives the covariance ``P`` of
  ``x_0 | x_t``, Kalman guidance (``csf_jax.guidance.kalman_tweedie``) turns them into the
  posterior ``x_0 | x_t, y ~ N(u, A^{-1})``, and the exact VE bridge (``csf_jax.sde.bridge``) draws
  the next level. Every step is exact for a Gaussian prior and a linear Gaussian likelihood,
  whatever the step count, so few steps suffice (the default 20; the paper's Euler-Maruyama
  takes 500; measured on docs/ablation.md).
* a DPS mode (``"clipped"``, ``"raw"``, ``"normalized"``, ``"none"``): the paper's Euler-Maruyama
  on the reverse VE SDE, ``x <- x + g^2 dt (s + guidance) + g sqrt(dt) eps``, on
  ``linspace(1, t_min, L)``, from ``N(0, sigma_1^2 I)``. Alg. 2 writes the drift with a minus sign
  (``- g^2 s dt``), which with a positive ``dt`` runs the SDE forwards; we use the sign of the
  reverse-time SDE.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks, _random, mixture, networks, trained
from csf_jax.filters.driver import Kernel, Method, StepOutput, run
from csf_jax.filters.result import FilterResult
from csf_jax.guidance import (
    GuidanceConfig,
    dps_gradient,
    guidance_displacement,
    kalman_tweedie,
    resample_posterior,
)
from csf_jax.inflation import InflationConfig, adaptive_inflation
from csf_jax.networks import NetworkConfig
from csf_jax.prior import (
    PriorConfig,
    PriorScore,
    ensemble_moments,
    exact_mixture_prior,
    gaussian_precision,
    gaussian_prior,
    learned_prior,
)
from csf_jax.sde import (
    bridge,
    diffusion_sq,
    inflated_time,
    marginal_std,
    marginal_std_host,
    noise_levels,
    reverse_grid,
    time_of_std,
)
from csf_jax.ssm import (
    StateSpaceModel,
    check_model,
    curvature,
    is_isotropic,
    log_likelihood,
    process_draws,
    tail_df,
)


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
    """How CSF draws the posterior ensemble of one filter step (``CSFConfig.sampler``).

    Attributes:
      reverse_steps: L, reverse steps per filter step (paper: 500 Euler-Maruyama steps; the
        ancestral sampler with Kalman guidance is exact for a Gaussian prior and a linear Gaussian
        likelihood at any L, so 20 suffice: docs/ablation.md).
      t_min: last reverse time. Euler-Maruyama: times ``linspace(1, t_min, L)``. Ancestral: the
        noise levels run geometrically from ``sigma_t(1)`` (9.85) to ``sigma_t(t_min)`` (0.032), then
        to 0.
      sigma_max: VE SDE scale s (paper: 25).
      guidance: how the likelihood enters, and with it the sampler (module docstring and
        ``csf_jax.guidance``): "kalman" (ancestral) or a DPS mode (Euler-Maruyama).
      assimilate_first: False reproduces the paper's ``1{k>0}``: the first observation only shapes
        the prior sampling, it is not assimilated. True: every observation is used, as PF/EnKF do.
      denoise_last: drop the noise of the last Euler-Maruyama step (the usual "denoise" of
        score-SDE samplers). The ancestral sampler's last step is the exact draw of
        ``x_0 | x_t, y`` instead.
    """

    reverse_steps: int = 20
    t_min: float = 1e-3
    sigma_max: float = 25.0
    guidance: GuidanceConfig = GuidanceConfig()
    assimilate_first: bool = True
    denoise_last: bool = True

    def __post_init__(self):
        _checks.check_fields(self)
        if self.reverse_steps < 2:
            raise ValueError(f"SamplerConfig.reverse_steps must be >= 2, got {self.reverse_steps}")
        if not 0.0 < self.t_min < 1.0:
            raise ValueError(f"SamplerConfig.t_min must lie in (0, 1), got {self.t_min}")
        if not self.sigma_max > 1.0:
            raise ValueError(f"SamplerConfig.sigma_max must be > 1, got {self.sigma_max}")


# The flat keywords CSFConfig accepts for one version, each with its group and field there.
FLAT_FIELDS = {
    "reverse_steps": ("sampler", "reverse_steps"), "t_min": ("sampler", "t_min"),
    "sigma_max": ("sampler", "sigma_max"), "guidance": ("sampler", "guidance"),
    "assimilate_first": ("sampler", "assimilate_first"),
    "denoise_last": ("sampler", "denoise_last"),
    "prior_inflation": ("inflation", "base"), "adaptive_inflation": ("inflation", "adaptive"),
    "inflation_threshold": ("inflation", "threshold"), "inflation_max": ("inflation", "max"),
    "inflation_statistic": ("inflation", "statistic"),
    "encode_particles": ("prior", "encode_particles"), "mixture": ("prior", "mixture"),
    "covariance": ("prior", "covariance"),
}


@dataclasses.dataclass(frozen=True, init=False)
class CSFConfig:
    """Online-stage settings in three groups; the defaults are what the README's tables show.

    Attributes:
      sampler: how the posterior is drawn (``SamplerConfig``: reverse steps, noise schedule,
        guidance).
      inflation: the prior inflation per filter step (``csf_jax.inflation.InflationConfig``: fixed
        base, adaptive trigger).
      prior: what the prior score is built from besides the network (``csf_jax.prior.PriorConfig``:
        the encoder's particles, the mixture prior, the covariance estimator).

    The flat keywords of the 0.5 series (``CSFConfig(reverse_steps=5)``,
    ``config.reverse_steps``) still work for this version, with a ``DeprecationWarning`` naming
    the grouped form (``FLAT_FIELDS``).
    """

    sampler: SamplerConfig = SamplerConfig()
    inflation: InflationConfig = InflationConfig()
    prior: PriorConfig = PriorConfig()

    def __init__(self, sampler: SamplerConfig = SamplerConfig(),
                 inflation: InflationConfig = InflationConfig(), prior: PriorConfig = PriorConfig(),
                 **flat):
        unknown = sorted(set(flat) - set(FLAT_FIELDS))
        if unknown:
            raise TypeError(f"CSFConfig got unknown field(s) {', '.join(unknown)}; its groups are "
                            f"sampler, inflation and prior (fields: csf_jax.filters.csf.FLAT_FIELDS)")
        groups = {"sampler": sampler, "inflation": inflation, "prior": prior}
        for group in groups.values():
            if not isinstance(group, (SamplerConfig, InflationConfig, PriorConfig)):
                raise TypeError(f"CSFConfig's groups must be SamplerConfig, InflationConfig and "
                                f"PriorConfig, got {group!r}")
        for name, value in flat.items():
            group, field = FLAT_FIELDS[name]
            _warn_flat(name)
            groups[group] = dataclasses.replace(groups[group], **{field: value})
        for name, group in groups.items():
            object.__setattr__(self, name, group)
        _checks.check_fields(self)
        mode = self.sampler.guidance.mode
        if self.prior.mixture is not None and mode != "kalman":
            raise ValueError(f"CSFConfig.prior.mixture needs CSFConfig.sampler.guidance.mode="
                             f"'kalman' (its members come from the ancestral sampler), got "
                             f"{mode!r}; use prior=PriorConfig(mixture=None) for a DPS mode "
                             f"(as csf_jax.PAPER does: dataclasses.replace(csf_jax.PAPER, "
                             f"sampler=...))")

    def __getattr__(self, name):
        if name in FLAT_FIELDS:
            _warn_flat(name)
            group, field = FLAT_FIELDS[name]
            return getattr(getattr(self, group), field)
        raise AttributeError(f"'CSFConfig' object has no attribute {name!r}")


def _warn_flat(name: str) -> None:
    group, field = FLAT_FIELDS[name]
    warnings.warn(f"CSFConfig.{name} is CSFConfig.{group}.{field} (the flat form goes in the next "
                  f"version)", DeprecationWarning, stacklevel=3)


PAPER = CSFConfig(inflation=InflationConfig(adaptive=True), prior=PriorConfig(mixture=None))
"""The paper's filter: the learned (or Gaussian) prior alone, with the innovation-triggered
inflation, as tuned to the paper's table (docs/results.md: ``python -m experiments.table --preset
paper``). ``CSFConfig()`` adds the mixture prior's particle and shock components, which keep it
within reach of the better of PF and EnKF on models it was not tuned for (docs/defaults.md)."""

PRESETS = {"default": CSFConfig(), "paper": PAPER}
"""The named configs of the experiments' ``--preset`` (recorded in each results file)."""


def uses_kalman(config: CSFConfig) -> bool:
    """Whether ``config`` selects the ancestral sampler with Kalman guidance."""
    return config.sampler.guidance.mode == "kalman"


class SamplerStart(NamedTuple):
    """What one filter step's reverse sampler starts from, besides ``x_init``.

    precision: (d, d) the ensemble Gaussian's ``(C + tau^2 I)^{-1}`` (ancestral sampler), or None
      (Euler-Maruyama).
    tau: prior inflation of this filter step: ``CSFConfig.prior_inflation`` (a float), or the
      adaptive one of ``csf_jax.inflation`` (a scalar array).
    """

    precision: jax.Array | None
    tau: float | jax.Array


def step_inflation(config: CSFConfig, prior_ens, y=None, model: StateSpaceModel | None = None,
                   guide=1.0):
    """This filter step's prior inflation ``tau``: fixed (``config.inflation.base``, a Python
    float, so that the samplers keep their static shortcut for 0), or adaptive (a traced scalar) from
    the innovation of ``y (m,)`` under ``prior_ens (N, d)`` when ``config.inflation.adaptive`` (and y
    is assimilated: ``guide`` 1)."""
    tau = config.inflation.base
    if not config.inflation.adaptive or y is None:
        return tau
    adaptive = adaptive_inflation(prior_ens, y, model, config.inflation.base,
                                  config.inflation.threshold, config.inflation.max,
                                  statistic=config.inflation.statistic)
    return jnp.where(guide > 0, adaptive, tau).astype(prior_ens.dtype)


def sampler_start(config: CSFConfig, prior_ens, key, y=None, model: StateSpaceModel | None = None,
                  guide=1.0):
    """The reverse process's first state ``(N, d)`` and its ``SamplerStart``.

    Ancestral: the prior ensemble noised to ``sigma_start`` (an exact draw of the diffused prior) and
    ``(C + tau^2 I)^{-1}``. Euler-Maruyama: ``N(0, sigma_1^2 I)`` (Alg. 2) and no precision.
    ``y``/``model``/``guide``: for the adaptive inflation (``step_inflation``).
    """
    sigma_1 = marginal_std(1.0, config.sampler.sigma_max)
    noise = _random.normal(key, prior_ens.shape, prior_ens.dtype)
    tau = step_inflation(config, prior_ens, y, model, guide)
    if not uses_kalman(config):
        return sigma_1 * noise, SamplerStart(None, tau)
    precision = gaussian_precision(prior_ens, tau, covariance=config.prior.covariance)
    return prior_ens + sigma_1 * noise, SamplerStart(precision, tau)


def ancestral_sample(params, prior: PriorScore, context, model: StateSpaceModel, y, x_init,
                     start: SamplerStart, key, config: CSFConfig, guide):
    """The ancestral sampler with Kalman guidance: L steps from ``x_init (N, d)`` to ``(N, d)``.

    start.precision: (d, d) the ensemble Gaussian's ``(C + tau^2 I)^{-1}``; at level sigma the
    covariance of ``x_0 | x_t`` is ``P = (precision + I / sigma^2)^{-1}`` (exact for a Gaussian prior).
    start.tau: the prior inflation.
    """
    precision = start.precision
    sigma_max = config.sampler.sigma_max
    levels = jnp.asarray(noise_levels(config.sampler.reverse_steps, marginal_std_host(1.0, sigma_max),
                                      marginal_std_host(config.sampler.t_min, sigma_max)), x_init.dtype)
    eye = jnp.eye(x_init.shape[-1], dtype=x_init.dtype)
    loglik_fn = functools.partial(log_likelihood, model, y)

    def weight_fn(u):
        return curvature(model, y, u)

    def step(carry, inputs):
        x, u = carry
        sigma, sigma_next, l_idx = inputs
        t = inflated_time(time_of_std(sigma, sigma_max), start.tau, sigma_max)
        x0_hat = x + sigma ** 2 * prior.score(params, context, x, t)
        u = jnp.where(l_idx == 0, x0_hat, u)
        prior_precision = precision + eye / sigma ** 2
        u, chol = kalman_tweedie(x0_hat, prior_precision, loglik_fn, model.observe, weight_fn, u, guide,
                                 config.sampler.guidance.iterations)
        k_bridge, k_post = jax.random.split(jax.random.fold_in(key, l_idx))
        x0 = resample_posterior(k_post, x0_hat, prior_precision, u, chol, loglik_fn, guide,
                                config.sampler.guidance.proposals, config.sampler.guidance.proposal_df)
        rho, var = bridge(sigma, sigma_next)
        x = rho * x + (1.0 - rho) * x0 + jnp.sqrt(var) * _random.normal(k_bridge, x.shape, x.dtype)
        return (x, u), None

    inputs = (levels[:-1], levels[1:], jnp.arange(config.sampler.reverse_steps))
    (x, _), _ = jax.lax.scan(step, (x_init, x_init), inputs)
    return x


def posterior_sample(params, prior: PriorScore, context, loglik_fn, x_init, key, config: CSFConfig,
                     guide, tau=None):
    """Euler-Maruyama with DPS guidance: the L reverse steps from ``x_init (N, d)``; returns the
    posterior ensemble ``(N, d)``.

    loglik_fn: ``x0 (d,) -> scalar``.  guide: scalar, 1.0 to assimilate, 0.0 to sample the prior.
    tau: the prior inflation (default ``config.inflation.base``).
    """
    tau = config.inflation.base if tau is None else tau
    grid = reverse_grid(config.sampler.reverse_steps, 1.0, config.sampler.t_min)
    n_steps = config.sampler.reverse_steps
    is_last = jnp.arange(n_steps) == n_steps - 1

    def step(x, inputs):
        t, dt, last, l_idx = inputs
        g2 = diffusion_sq(t, config.sampler.sigma_max)
        var = marginal_std(t, config.sampler.sigma_max) ** 2
        score_fn = functools.partial(
            prior.score, params, context,
            t=inflated_time(t, tau, config.sampler.sigma_max))
        if config.sampler.guidance.mode == "none":
            s, disp = score_fn(x), 0.0
        else:
            s, grad, loglik = dps_gradient(score_fn, loglik_fn, x, var)
            disp = guide * guidance_displacement(config.sampler.guidance, grad, loglik, g2 * dt,
                                                 jnp.sqrt(g2 * dt))
        noise = _random.normal(jax.random.fold_in(key, l_idx), x.shape, x.dtype)
        noise_on = jnp.where(last & config.sampler.denoise_last, 0.0, 1.0)
        x = x + g2 * dt * s + disp + noise_on * jnp.sqrt(g2 * dt) * noise
        return x, None

    inputs = (grid.times, grid.dt, is_last, jnp.arange(n_steps))
    x, _ = jax.lax.scan(step, x_init, inputs)
    return x


def particle_sampler(model: StateSpaceModel, prior: PriorScore, config: CSFConfig,
                     shards: int = 1):
    """``(params, context, y (m,), x_init (N, d), start, key, guide) -> (N, d)``: the L reverse
    steps of one filter step, with the observation ``y`` assimilated. ``x_init`` and ``start``
    (a ``SamplerStart``) come from ``sampler_start``.

    shards > 1 splits the particle axis over the first ``shards`` local devices with
    ``jax.shard_map`` (the reverse steps are independent per particle given the prior's context,
    which every device gets whole): for several accelerators, or one XLA host device per CPU core
    (``XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`` before importing jax). On a CPU
    it gains little where XLA's intra-op threads already use every core (measured on
    docs/bench/history.md). Each shard draws its noise from ``fold_in(key, shard)``: results
    depend on ``shards``.
    """

    def sample(params, context, y, x_init, start, key, guide):
        if shards > 1:
            key = jax.random.fold_in(key, jax.lax.axis_index("particles"))
        if uses_kalman(config):
            return ancestral_sample(params, prior, context, model, y, x_init, start, key,
                                    config, guide)
        return posterior_sample(params, prior, context, lambda x0: log_likelihood(model, y, x0),
                                x_init, key, config, guide, start.tau)

    if shards == 1:
        return sample
    devices = jax.local_devices()
    if shards > len(devices):
        raise ValueError(f"csf_jax.filter: shards={shards} but only {len(devices)} local devices; "
                         f"on CPU set XLA_FLAGS=--xla_force_host_platform_device_count={shards} "
                         f"before importing jax")
    mesh = jax.sharding.Mesh(np.array(devices[:shards]), ("particles",))
    P = jax.sharding.PartitionSpec

    return jax.shard_map(sample, mesh=mesh, in_specs=(P(), P(), P(), P("particles"), P(), P(), P()),
                         out_specs=P("particles"), check_vma=False)


def _prior_for(params, prior: PriorScore | None, network: NetworkConfig | None,
               config: CSFConfig) -> PriorScore:
    if prior is not None:
        return prior
    if params is None:
        # with the mixture, the particle components are the exact mixture already
        if config.prior.mixture is None:
            return exact_mixture_prior(config.sampler.sigma_max)
        return gaussian_prior(config.sampler.sigma_max, config.prior.covariance)
    return learned_prior(network if network is not None else NetworkConfig(),
                         config.prior.encode_particles, config.prior.covariance)


class CSFStatic(NamedTuple):
    """CSF's static settings for the driver: the config, the prior-score source and the number
    of devices the particles are split over."""

    config: CSFConfig
    prior: PriorScore
    shards: int = 1


def _init(model, static: CSFStatic, params, ensemble, key):
    """Carry ``(ensemble, accumulated log Bayes factor of the mixture's particle reading)``."""
    return (ensemble, jnp.zeros((), ensemble.dtype)), key


def _step(model: StateSpaceModel, static: CSFStatic, params, state, y, key, time):
    """One CSF filter step (module docstring) on ``state = (ensemble (N, d), memory)``."""
    config, prior = static.config, static.prior
    ens, memory = state
    sample = particle_sampler(model, prior, config, static.shards)
    k_prop, k_init, k_rev = jax.random.split(key, 3)
    centers = jax.vmap(model.drift)(ens)
    prior_ens = centers + process_draws(model, k_prop, ens.shape, ens.dtype)
    context = prior.condition(params, centers, prior_ens, model.process_std)
    guide = jnp.where((time.k > 1) | config.sampler.assimilate_first, 1.0, 0.0).astype(ens.dtype)
    x_init, start = sampler_start(config, prior_ens, k_init, y, model, guide)
    if (uses_kalman(config) and config.sampler.guidance.proposal_df is None
            and tail_df(model) is not None):
        # the proposals take the heavy tails of the model's noise (Cauchy: Student-t, 1 dof)
        guidance = dataclasses.replace(config.sampler.guidance, proposal_df=tail_df(model))
        config = dataclasses.replace(config, sampler=dataclasses.replace(config.sampler,
                                                                         guidance=guidance))
        sample = particle_sampler(model, prior, config, static.shards)
    if config.prior.mixture is None or not uses_kalman(config):
        post = sample(params, context, y, x_init, start, k_rev, guide)
        return (post, memory), _output(post, jnp.all(jnp.isfinite(prior_ens)))
    wild = mixture.wild_members(prior_ens, config.prior.mixture.wild_ranges)
    (centers, prior_ens), dropped = mixture.tame(jax.random.fold_in(key, 4), wild, centers,
                                                 prior_ens)
    moments = ensemble_moments(prior_ens, covariance=config.prior.covariance)
    odds = config.prior.mixture.particle_logodds + memory
    transport = mixture.transports(config.prior.mixture, prior.name)
    sel = mixture.select(model, config.prior.mixture, jax.random.fold_in(key, 3), y, centers, prior_ens,
                         moments.cov, jnp.square(start.tau), odds, guide, transport)
    post = sel.draws
    if not transport:
        # the reverse diffusion runs on the ensemble component's members only where they fit in
        # a block (the block's noise its own); across the devices of ``shards`` on all N
        def fill(idx):
            return sample(params, context, y, jnp.take(x_init, idx, axis=0, mode="clip"), start,
                          k_rev, guide)

        block = mixture.row_block(ens.shape[0]) if static.shards == 1 else None
        post = mixture.fill_rows(sel.kind == 1, fill, post, block)
    memory, _ = mixture.next_odds(config.prior.mixture, memory, sel.log_bf, sel.informed)
    info = {"particle_weight": sel.particle_weight, "shock_weight": sel.shock_weight,
            "dropped": dropped}
    kept = jnp.all(jnp.isfinite(prior_ens)) & jnp.all(jnp.isfinite(moments.cov))
    return (post, memory), _output(post, kept, info, sel.log_evidence)


def _output(post, kept, info=None, log_evidence=None) -> StepOutput:
    """The step's ``StepOutput`` from the posterior ensemble ``post (N, d)``; mean and std NaN
    where the forecast lost its numbers (``kept`` False: a member's forecast, or the prior
    ensemble's covariance, is non-finite). The mixture's resampling drops such members, so the
    posterior can look sane after the run has diverged; NaN here makes ``mark_nonfinite`` report
    the step and every later one, and a concrete call raise."""
    nan = jnp.asarray(jnp.nan, post.dtype)
    mean = jnp.where(kept, post.mean(0), nan)
    std = jnp.where(kept, post.std(0), nan)
    return StepOutput(mean, std, post, {} if info is None else info, log_evidence)


@_checks.renamed_keywords("csf_jax.filter", problem="model")
def csf_filter(params, obs, ensemble, *, model: StateSpaceModel, key,
               prior: PriorScore | None = None, network: NetworkConfig | None = None,
               config: CSFConfig = CSFConfig(), inputs=None, return_ensembles: bool = False,
               check_finite: bool = True,
               progress: Callable[[jax.Array], None] | None = None,
               shards: int = 1) -> FilterResult:
    """Filter ``obs`` with the Conditional Score-based Filter.

    Args:
      params: a trained prior (``TrainedPrior``, from ``csf_jax.train_prior``, ``load_prior`` or
        ``load_pretrained``: the checked route, see ``csf_jax.trained.unpack``), raw network
        parameters ``{"encoder": ..., "score": ...}`` (only their shapes can be checked), or None:
        no network (no training needed): the exact Gaussian-mixture prior ``sum_i N(f(x_i), Q)``,
        or with ``config.prior.mixture`` the ensemble's own Gaussian as the ensemble component.
      obs: (K, m) observations ``y_1 .. y_K``; float, promoted with ``ensemble`` to their common
        float dtype. NaN marks a missing entry (left out of the update); inf is an error.
      ensemble: (N, d) initial ensemble (time 0).
      model: the ``StateSpaceModel`` (static: hashable).
      key: a ``jax.random.key``; same key, same result.
      prior: the prior-score source of the ensemble component (``gaussian_prior()``,
        ``exact_mixture_prior()``); by default as for params=None above, else the learned
        prior. Not together with params.
      network: the network config of raw ``params``, required with them (a Gaussian-base and a
        whole-score network have the same shapes); a ``TrainedPrior`` brings its own, and a
        different one here is refused.
      config: online-stage settings (``CSFConfig``: its defaults are the filter for a model CSF
        was not tuned on, docs/defaults.md; ``csf_jax.PAPER`` the paper's).
      inputs: a time-varying model's per-step inputs (a pytree, leading axis K), or None.
      return_ensembles: also return the (K, N, d) posterior ensembles.
      check_finite: when called outside jit/vmap, raise FloatingPointError if the filter diverged.
      progress: optional host callback ``k -> None`` called at the start of every filter step
        (``jax.debug.callback``; once per step under ``vmap``). For progress bars on long runs.
        A concrete call with it also says on stderr when it compiles, and how long that took.
      shards: split the particles over this many local devices (see ``particle_sampler``); N must
        be divisible by it.

    Returns:
      ``FilterResult`` with mean and std (K, d), ``finite`` (K,), ``info`` (the mixture's
      ``particle_weight`` and ``shock_weight`` per step), and ensembles if asked for. Works under
      ``jax.jit`` (bind the keyword arguments statically) and ``jax.vmap`` over
      ``(obs, ensemble, key)``; there a non-finite observation or mean is not raised but reported:
      from that step on ``finite`` is False and mean and std are NaN (``mark_nonfinite``).
    """
    _checks.check_static("csf_jax.filter", shards=shards)
    return run(method(params, prior=prior, network=network, config=config, shards=shards), obs,
               ensemble, model=model, key=key, inputs=inputs, return_ensembles=return_ensembles,
               check_finite=check_finite, progress=progress)


class CSFSpec(NamedTuple):
    """CSF's settings before the model is known: the config, the prior-score source (None: chosen
    from the params), the raw params' network config, the devices the particles are split over."""

    config: CSFConfig
    prior: PriorScore | None
    network: NetworkConfig | None
    shards: int


def method(params=None, *, prior: PriorScore | None = None, network: NetworkConfig | None = None,
           config: CSFConfig = CSFConfig(), shards: int = 1) -> Method:
    """CSF as a ``Method`` for ``csf_jax.run`` (arguments: ``csf_jax.filter``). What can be checked
    without the model is checked here; the trained prior against the model, when it runs."""
    if not isinstance(config, CSFConfig):
        raise TypeError(f"csf_jax.filter: config must be a CSFConfig, got {type(config).__name__}")
    if prior is not None and params is not None and prior.name != "learned":
        raise ValueError(f"csf_jax.filter: both a trained prior (params) and prior="
                         f"{prior.name!r} given; the {prior.name} prior would ignore the "
                         f"params: pass params=None with prior=, or leave prior= out")
    if prior is not None and isinstance(params, trained.TrainedPrior):
        raise ValueError("csf_jax.filter: both a TrainedPrior and prior= given; the TrainedPrior "
                         "brings its own learned prior and network: leave prior= out (or pass "
                         "its .params with network= and prior=)")
    if params is not None and not isinstance(params, trained.TrainedPrior) and prior is None\
            and network is None:
        raise ValueError("csf_jax.filter: raw params need network= (the NetworkConfig they were "
                         "trained with: a Gaussian-base and a whole-score network have the same "
                         "shapes, so the params cannot tell); or pass the TrainedPrior whole "
                         "(csf_jax.load_prior, csf_jax.load_pretrained)")
    if isinstance(shards, bool) or not isinstance(shards, int) or shards < 1:
        raise ValueError(f"csf_jax.filter: shards must be a positive int dividing the number of "
                         f"particles, got {shards!r}")
    return Method(CSF, CSFSpec(config, prior, network, shards), params)


def _bind(model: StateSpaceModel, spec: CSFSpec, params, ensemble):
    """The trained prior checked against ``model``, the prior-score source chosen: the driver's
    ``CSFStatic`` and raw params."""
    check_model(model, CSF.name)
    config, shards = spec.config, spec.shards
    params, network = trained.unpack(params, model, spec.network)
    prior = _prior_for(params, spec.prior, network, config)
    warn_if_large(model, config, prior, ensemble)
    n = jnp.shape(ensemble)[-2] if jnp.ndim(ensemble) >= 2 else 0
    if n and n % shards:
        raise ValueError(f"csf_jax.filter: shards must be a positive int dividing the number of "
                         f"particles N={n}, got {shards!r}")
    _check_combination(model, config, prior, spec.prior is None, network)
    if prior.name == "exact_mixture" and not is_isotropic(model):
        raise ValueError(f"csf_jax.filter: the exact mixture prior needs i.i.d. process noise, but "
                         f"model {model.name!r} has process_noise {model.process_noise.name!r}; "
                         f"pass a trained prior or prior=csf_jax.gaussian_prior()")
    if prior.name == "learned":
        if params is None:
            raise ValueError("csf_jax.filter: a learned prior needs params (got None); pass trained "
                             "params, or params=None without prior= for the Gaussian prior")
        networks.check_params(params, network or NetworkConfig(), model.dim,
                              name="csf_jax.filter: params")
        _checks.check_sigma_max(network or NetworkConfig(), config, "csf_jax.filter")
    return model, CSFStatic(config, prior, shards), params, ensemble


def _check_combination(model: StateSpaceModel, config: CSFConfig, prior: PriorScore,
                       built: bool, network: NetworkConfig | None) -> None:
    """Refuse the settings the run would ignore, each in one line naming the fields.

    * ``MixtureConfig.particles`` on a model whose ``ProcessNoise`` has no covariance: the
      particle components ``N(f(x_i), Q)`` need Q, and estimating it from the sampler's draws
      would be silently random (and meaningless for a noise without a variance): the user gives
      Q or switches the components off.
    * a covariance estimator other than the sample one where nothing uses the ensemble's
      Gaussian: a DPS mode (Euler-Maruyama) reads the ensemble through the prior score alone, so
      the estimator acts only on a prior built here from it (a Gaussian-base learned prior;
      ``built``: the prior came from ``_prior_for``, not ``prior=``).
    """
    mix = config.prior.mixture
    noise = model.process_noise
    if mix is not None and mix.particles and noise is not None and noise.covariance is None:
        raise ValueError(f"csf_jax.filter: CSFConfig.prior.mixture.particles needs the process "
                         f"noise covariance Q, but model {model.name!r} has ProcessNoise "
                         f"{noise.name!r} with covariance=None; give ProcessNoise(covariance=Q) "
                         f"or use MixtureConfig(particles=False)")
    estimator = config.prior.covariance.estimator
    gaussian_base = (built and prior.name == "learned"
                     and (network or NetworkConfig()).base == "gaussian")
    if estimator != "sample" and not uses_kalman(config) and not gaussian_base:
        raise ValueError(f"csf_jax.filter: CSFConfig.prior.covariance ({estimator!r}) has no "
                         f"effect with CSFConfig.sampler.guidance.mode="
                         f"{config.sampler.guidance.mode!r} and the {prior.name} prior (only the "
                         f"'kalman' mode and a Gaussian-base learned prior use it); use "
                         f"mode='kalman' or the sample covariance")


LARGE_DIM = 200
"""The state dimension above which a CSF call with a dense prior warns (``warn_if_large``).
Measured on Lorenz-96 with N = 20 on 2 CPU cores, seconds per filter step after compilation:
the default config 0.03 at d = 50, 0.08 at d = 100, 0.56 at d = 200, 5.3 at d = 400 (about
d^3); ``csf_jax.PAPER`` 0.05, 0.14 and 0.46 at d = 100, 200, 400. Past d = 200 a default step
takes about a second and more, and d = 2000 (extrapolated) about ten minutes."""


def warn_if_large(model: StateSpaceModel, config: CSFConfig, prior: PriorScore,
                  ensemble) -> None:
    """One ``RuntimeWarning`` when a CSF call's prior is dense and its state dimension d exceeds
    ``LARGE_DIM``: each step then factorises d x d covariances (the ensemble's Gaussian of the
    Kalman sampler and the mixture, a Gaussian or Gaussian-base prior), so its cost grows as
    d^3, and the run may take hours with no sign of life. Only the exact mixture prior under a
    DPS mode is not dense. Shapes only, so it also fires when traced (under jit, once per
    compilation). ``ensemble``: the (N, d) initial ensemble (N is named)."""
    d = int(model.dim)
    if d <= LARGE_DIM or (not uses_kalman(config) and prior.name == "exact_mixture"):
        return
    from csf_jax.filters.driver import _caller_level

    n = jnp.shape(ensemble)[-2] if jnp.ndim(ensemble) >= 2 else "?"
    warnings.warn(f"csf_jax.filter: d={d} state dimensions (N={n}) with CSF's dense prior: each "
                  f"step costs about d^3 (0.6 s at d=200 and 5 s at d=400 with N=20 on 2 CPU "
                  f"cores), so this may run for hours; for many dimensions use "
                  f"csf_jax.local_transform_filter or csf_jax.letkf, and pass progress=print to "
                  f"see each step", RuntimeWarning, stacklevel=_caller_level())


CSF = Kernel("csf_jax.filter", _init, _step, label="CSF", bind=_bind,
             discrete=True)
