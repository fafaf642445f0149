"""CSF's mixture prior: which prior each posterior member is drawn under, decided by the evidence.

The propagated ensemble admits three readings of the prior, and a filter step mixes them:

* **particle** components ``N(f(x_i), Q)``, one per member: the exact prior given the previous
  posterior ensemble (the optimal-proposal particle filter). Right in low dimension and for
  multimodal or strongly non-Gaussian priors, degenerate when few components fit the observation.
* the **ensemble** component: the prior score of the ``PriorScore`` (the ensemble's Gaussian, or
  the learned conditional score), sampled by CSF's reverse-diffusion sampler. Right when the prior
  is close to its Gaussian or the particles are too few for the observation.
* **shock** components ``N(m, C + tau^2 S)``: the ensemble inflated by a few scales tau, with a
  small prior probability (``shock_hazard``): after an unmodelled jump of the truth, they are the
  only part of the prior that explains the observation, and the evidence moves the posterior
  there. ``S`` widens the directions the observed entries see, the others by at most twice the
  ensemble's spread (``shock_span``, ``shock_unseen``).

Each component's evidence ``int N(x; mu, B) p(y | x) dx`` is estimated by a few damped Gauss-Newton
steps to the mode of ``N(x; mu, B) p(y | x)`` and importance sampling from its Laplace Gaussian
(``guidance.importance_weights``); members are resampled over all components by prior weight x
evidence. A member that lands on a particle or shock component keeps an importance draw from that
component's posterior. The ensemble component's members are drawn by the reverse-diffusion sampler
where the prior score is learned (the only part of the step that uses it); where it is the
ensemble's Gaussian (``params=None``), ``ensemble_draws="transport"`` takes propagated members
instead (a random subset) and moves them down a probability flow onto the component's posterior
(``flow_transport``): the linear map that carries the ensemble's Gaussian onto the component's
Laplace posterior (``gaussian_transport``: with a linear sensor, the ensemble transform Kalman
filter's symmetric square root), split into noise levels at which each member is moved by the
sensor's gradient at its own point, so that a posterior with several modes (a sensor blind to
the sign) keeps members in each. Fresh draws from the posterior
Gaussian would forget each member's own deviation, which carries the prior's shape beyond its two
moments, and re-sample the covariance at every step; with few members that noise compounds
(docs/zoo.md). The shock components' wide Gaussians are not left to the sampler: under a weakly
informative likelihood (stochastic volatility's) its early, far-flung Tweedie estimates overflow
the likelihood.

A step without an observed entry (an outage, or the first step with
``SamplerConfig.assimilate_first`` False) brings no evidence, and its posterior is its prior. The
propagated members ``f(x_i) + v_i`` are exact draws of that prior, so such a step keeps them: no
component is chosen and nothing is redrawn. Redrawing a share of them from the ensemble's
Gaussian at each blind step would replace the prior's shape (Lorenz-63's two lobes, forty steps
into an outage) by its Gaussian, step after step, and leave the first observation after the
outage a Gaussian to correct (docs/zoo.md). Nor are there shock components: a jump can be told
from the ensemble only by an observation; drawn without one, a shock member is a point up to
``sqrt(max(shock_scales))`` (64) ensemble spreads off, which the dynamics carry wherever they go
(Lorenz-96's RK4: to overflow), and which widens the next step's covariance and with it the next
step's shock scales, a runaway over consecutive blind steps. The shock components of the next
observed step, scaled to the ensemble there, cover a jump at any step in between.

The particle and ensemble readings compete through their prior odds, updated by their evidence
over the recent steps (log Bayes factor with forgetting ``memory``): on a model where the Gaussian
predicts the observations better (high dimension, few particles for the observation) the ensemble
component takes over; where it does not, the particle components keep the prior odds' preference.
The forgetting counts steps with evidence: a step without any leaves the accumulated Bayes factor
as it was (``next_odds``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

from csf_jax import _checks, _linalg
from csf_jax._batch import batch_max
from csf_jax.guidance import (
    importance_weights,
    kalman_tweedie,
    particle_map,
    quadratic_along,
    weighted_gram,
)
from csf_jax.sde import SIGMA_MAX, marginal_std_host, noise_levels
from csf_jax.ssm import (
    StateSpaceModel,
    curvature,
    log_likelihood,
    log_normalizer,
    observed,
    process_cov,
    tail_df,
)

ENSEMBLE_DRAWS = ("transport", "sampler")
NEWTON_SCHULZ_STEPS = 32
ROW_BLOCK = 4                 # fill_rows' block: N // 4 members (row_block)
MIN_ROW_BLOCK = 16
# the transport's line search: the step fractions tried along each Gauss-Newton direction, from
# 64 full steps (where the sensor is flatter than at the mode, the mode's curvature makes the
# step short) down to 2^-12 (where it is steeper, long), and 0
TRANSPORT_STEPS = tuple(2.0 ** k for k in range(6, -13, -1)) + (0.0,)
TRANSPORT_FLOWS = ("hybrid", "member", "mode")
KERNEL_CHOICES = ("loo", "evidence")


@dataclasses.dataclass(frozen=True)
class MixtureConfig:
    """The mixture prior's settings (``CSFConfig.prior.mixture``, on by default); the defaults were
    chosen on models outside the paper's table, against the better of PF and EnKF
    (docs/defaults.md).

    Attributes:
      particles: include the particle components ``N(f(x_i), Q)`` (they need the process noise's
        covariance Q: i.i.d. noise, or ``ProcessNoise.covariance``; a ``ProcessNoise`` without one
        is refused, not run without them).
      particle_logodds: prior log-odds of the particle reading against the ensemble one, before the
        evidence of the recent steps.
      memory: forgetting factor of the accumulated log Bayes factor (0: this step's prior odds only;
        0.9: about the last ten steps).
      shock_hazard: the prior probability that the step holds an unmodelled jump (the shock
        components' total weight); 0 switches them off.
      shock_scales: the shock components' inflations ``tau^2``, as multiples of the ensemble's mean
        variance: a geometric grid from twice to 64 times its spread, so that one component is
        within a factor 2 of any jump in that range (the evidence then pays at most ``2^d`` for the
        grid's coarseness, against the ``exp(-jump^2 / spread^2)`` the ensemble pays).
      shock_span: "isotropic": a shock widens the prior along every direction (``tau^2 I``);
        "observed": along the directions the step's observed entries see (``seen_directions``)
        by its ``tau^2``, along the others by at most ``shock_unseen`` times the ensemble's mean
        variance. Observed, by measurement (docs/defaults.md, the "isotropic" candidate): only
        the observed entries can tell a jump from the ensemble, and an isotropic shock that
        explains them also spreads members up to 64 spreads along the unseen directions, where
        an exponential drift carries them off (the zoo's ``lotka_volterra``). A model whose
        state is seen whole (the paper's) is the same either way.
      shock_unseen: with ``shock_span="observed"``, the largest widening of the directions the
        observation does not see, a multiple of the ensemble's mean variance (each shock's own
        scale below it): 0 keeps the ensemble's spread there; 4 (the smallest shock's scale,
        twice the spread) lets a jump that moved them be found by the next observations.
      shock_gate: the least posterior probability of a jump at which the shock components take
        members (0: at any probability, a share ``hazard x Bayes factor`` of them); below it the
        step's members come from the particle and ensemble readings alone. A shock member is a
        draw up to tens of spreads off along the directions the observation does not see; drawn
        at the steps where a jump is merely possible (a Bayes factor of 10 at the hazard 1e-3),
        a few of them widen the next step's covariance, shock scales and kernels on a model that
        never jumps. Off by default, by measurement (CHANGELOG, Unreleased): at 0.5 (a jump is the
        more probable reading) the zoo's bearings and ``lorenz96_abs`` rows at N = 1000 improve,
        the paper's jumps pass it at once, but at N = 50 ``lorenz96_square`` goes from 1.01x to
        3.52x the better of PF and EnKF.
      iterations, proposals: Gauss-Newton steps and importance draws per particle component.
      ensemble_iterations, ensemble_proposals: the same for the ensemble and shock components (one
        each, so they can afford more: their evidence decides between readings).
      particle_ess: 0 (off), or a multiple ``c`` of the dimension d: where the particle
        components' evidence weights have an effective sample size ``ESS < min(c d, N)``, the
        particle reading's log-odds for the step, and its log Bayes factor into the memory, drop
        by ``log(min(c d, N) / ESS)``. The evidence compares how well each reading predicts
        ``y``, not how many particles carry its posterior: a posterior on ``ESS`` particles
        spreads over at most ``ESS - 1`` directions, so with fewer effective particles than
        dimensions it is degenerate, and the next steps' ensemble collapses onto it
        (docs/defaults.md). The threshold is in dimensions, not a fraction of N: a 3-d model
        keeps its particles at any N, Lorenz-96 at d = 40 hands them over at N = 50.
      ensemble_draws: how the ensemble component's members are drawn where its prior is the
        ensemble's Gaussian (``params=None``; a learned prior score is always sampled):
        "transport": propagated members moved by ``gaussian_transport``, the map from
        the ensemble's Gaussian to the component's Laplace posterior that is symmetric in the
        ensemble's whitened coordinates (with a linear sensor, the ensemble transform Kalman
        filter's analysis); "sampler": fresh draws by the reverse-diffusion sampler. Transport by
        measurement, one change against the other on the zoo at N = 50 and 1000 (docs/zoo.md);
        it also spares the step the sampler's reverse steps.
      transport_levels: L, the noise levels of the transport's probability flow
        (``flow_transport``), geometric from ``sigma_t(1)`` to ``sigma_t(1e-3)`` of the VE SDE
        (sigma_max 25) in units of the ensemble's spread, then 0; 0 moves the members by the single
        linear map at the posterior's mode (``gaussian_transport``). With a linear sensor and
        Gaussian noise both are the same map. 10 levels by measurement on the zoo at N = 50
        (docs/zoo.md): the single map puts every member in the mode the Laplace approximation
        found, and loses runs where the sensor cannot tell a state's sign (Lorenz-96 seen through
        ``x^2``, the UNGM).
      transport_iterations: damped Gauss-Newton steps of each member's Tweedie estimate per level.
      transport_flow: how ``flow_transport`` moves a member from one level to the next: its
        Tweedie estimate by Gauss-Newton steps with the curvature of the sensor at the member
        ("member", "hybrid"; a (d, d) Cholesky factorisation per member, level and step) or at
        the posterior's mode, shared by every member ("mode"); then the member moves from that
        estimate by the exact flow of a Gaussian posterior ("member"), or by the exact flow of
        the Gaussian linearised at the estimate, about its centre found with the mode's
        curvature ("mode", "hybrid"). All three are the single map under a linear sensor. With
        a sensor whose curvature changes across the ensemble (``x^3`` under a broad prior) and
        more than a few dimensions, the shared curvature and the one step fraction a member's
        line search picks for all its coordinates leave members spreads away from the posterior
        (the paper's 20-D columns: "mode" 1.7-1.9x the reference, the others 1.1x); with 50
        members the move from the Tweedie estimate lost runs that the linearised flow keeps
        (Cauchy noise, Lorenz-96 through ``|x|``). "hybrid" keeps both, by measurement on
        held-out runs (docs/defaults.md, "Which transport flow").
      wild_ranges: a propagated member is dropped (``wild_members``: replaced by a copy of another,
        counted in the result's ``info["dropped"]``, and warned of after a concrete call) where its
        forecast is non-finite or lies more than this many central ranges (5-95%) of the ensemble
        from its median; 0 drops the non-finite ones only. A shock member placed tens of spreads
        off along a direction the observation does not see can, under an explosive drift, leave
        the state space within a step and take the covariance, and the run, with it (docs/zoo.md,
        ``lotka_volterra``).
      particle_kernel: 0 (off: the components ``N(f(x_i), Q)``), or a factor ``a`` in [0, 1] on
        Silverman's bandwidth ``h^2 = (4 / ((d + 2) N))^(2 / (d + 4))`` (``silverman``): the
        components become the kernels ``N(m + s (f(x_i) - m), Q + a h^2 C)`` of a regularised
        particle filter (``m`` the mean of the ``f(x_i)``, ``C`` the prior ensemble's
        covariance), shrunk by ``s = sqrt(1 - a h^2)`` so that the mixture keeps the ensemble's
        mean and about its covariance. Where no particle is within ``sqrt(Q)`` of the
        observation's preimage, the kernels still reach it, and the particle reading keeps
        evidence the point components lose to the ensemble's Gaussian (folding's first steps,
        docs/defaults.md); as N grows the kernels shrink to the points. A tuple of such factors:
        the particle reading is a mixture over the widths, each width's components weighed by
        its evidence and by the width's prior weight (``kernel_choice``).
      kernel_choice: the prior weights of the widths of a tuple ``particle_kernel``: "loo" in
        proportion to how well each describes the forecast ensemble (``loo_score``, the
        leave-one-out density of the members ``f(x_j) + v_j`` under the others' kernels: a
        multimodal forecast keeps its modes, a sparse one gets wide kernels), "evidence" equal.
    """

    particles: bool = True
    particle_logodds: float = 2.0
    memory: float = 0.9
    shock_hazard: float = 1e-3
    shock_scales: tuple = (4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0)
    shock_span: str = "observed"
    shock_unseen: float = 4.0
    shock_gate: float = 0.0
    iterations: int = 3
    proposals: int = 8
    ensemble_iterations: int = 12
    ensemble_proposals: int = 64
    particle_ess: float = 2.5
    particle_kernel: float | tuple = 1.0
    ensemble_draws: str = "transport"
    transport_levels: int = 10
    transport_iterations: int = 1
    transport_flow: str = "hybrid"
    wild_ranges: float = 1e3
    kernel_choice: str = "loo"

    def __post_init__(self):
        _checks.check_fields(self)
        for name in ("iterations", "proposals", "ensemble_iterations", "ensemble_proposals",
                     "transport_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"MixtureConfig.{name} must be a positive int, got {value!r}")
        if not (isinstance(self.memory, (int, float)) and 0.0 <= self.memory < 1.0):
            raise ValueError(f"MixtureConfig.memory must lie in [0, 1), got {self.memory!r}")
        if not (isinstance(self.shock_hazard, (int, float)) and 0.0 <= self.shock_hazard < 1.0):
            raise ValueError(f"MixtureConfig.shock_hazard must lie in [0, 1), got "
                             f"{self.shock_hazard!r}")
        if not (isinstance(self.shock_unseen, (int, float)) and 0.0 <= self.shock_unseen
                and math.isfinite(self.shock_unseen)):
            raise ValueError(f"MixtureConfig.shock_unseen must be a finite number >= 0, got "
                             f"{self.shock_unseen!r}")
        if not (isinstance(self.shock_gate, (int, float)) and 0.0 <= self.shock_gate < 1.0):
            raise ValueError(f"MixtureConfig.shock_gate must lie in [0, 1), got "
                             f"{self.shock_gate!r}")
        if not (isinstance(self.particle_logodds, (int, float))
                and math.isfinite(self.particle_logodds)):
            raise ValueError(f"MixtureConfig.particle_logodds must be a finite number, got "
                             f"{self.particle_logodds!r}")
        if not (isinstance(self.particle_ess, (int, float)) and 0.0 <= self.particle_ess
                and math.isfinite(self.particle_ess)):
            raise ValueError(f"MixtureConfig.particle_ess must be a finite number >= 0, got "
                             f"{self.particle_ess!r}")
        widths = kernel_widths(self.particle_kernel)
        if not widths or not all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                 and 0.0 <= a <= 1.0 for a in widths):
            raise ValueError(f"MixtureConfig.particle_kernel must lie in [0, 1], or be a "
                             f"non-empty tuple of such factors, got {self.particle_kernel!r}")
        if self.ensemble_draws not in ENSEMBLE_DRAWS:
            raise ValueError(f"MixtureConfig.ensemble_draws must be one of {ENSEMBLE_DRAWS}, got "
                             f"{self.ensemble_draws!r}")
        if not (isinstance(self.wild_ranges, (int, float)) and self.wild_ranges >= 0
                and not math.isnan(self.wild_ranges)):
            raise ValueError(f"MixtureConfig.wild_ranges must be a number >= 0, got "
                             f"{self.wild_ranges!r}")
        levels = self.transport_levels
        if isinstance(levels, bool) or not isinstance(levels, int) or levels < 0:
            raise ValueError(f"MixtureConfig.transport_levels must be an int >= 0, got {levels!r}")
        if self.kernel_choice not in KERNEL_CHOICES:
            raise ValueError(f"MixtureConfig.kernel_choice must be one of {KERNEL_CHOICES}, got "
                             f"{self.kernel_choice!r}")
        if self.transport_flow not in TRANSPORT_FLOWS:
            raise ValueError(f"MixtureConfig.transport_flow must be one of {TRANSPORT_FLOWS}, got "
                             f"{self.transport_flow!r}")
        if self.shock_span not in ("observed", "isotropic"):
            raise ValueError(f"MixtureConfig.shock_span must be 'observed' or 'isotropic', got "
                             f"{self.shock_span!r}")
        scales = self.shock_scales
        if not isinstance(scales, tuple) or not scales or not all(
                isinstance(v, (int, float)) and v > 0 and math.isfinite(v) for v in scales):
            raise ValueError(f"MixtureConfig.shock_scales must be a non-empty tuple of positive "
                             f"numbers, got {scales!r}")


class Selection(NamedTuple):
    """The evidence stage's outcome for one filter step.

    kind: (N,) int32 per posterior member: 0 a particle component, 1 the ensemble component,
      ``1 + g`` the shock component of scale g.
    draws: (N, d) each member's posterior draw from its particle or shock component (by
      importance resampling); the ensemble component's members (``kind == 1``): their
      ``gaussian_transport`` of a random subset of the propagated members where ``select``
      transports, else left to the reverse-diffusion sampler (these rows then hold a particle's
      draw, unused).
    inflation: (1 + G,) ``tau^2`` of kinds 1.. (the ensemble's base inflation, then the shocks').
    log_bf: this step's log Bayes factor of the particle reading against the ensemble one.
    particle_weight, shock_weight: the posterior weights of the particle and shock components (the
      shock's 0 where ``shock_gate`` shuts them).
    informed: whether the step assimilates an observed entry (``informative``); without one
      every member is kind 0 with its own propagated draw (``prior_ens``), the shock components
      are off, ``particle_weight`` is 1, ``log_bf`` is 0 and the memory is carried unchanged.
    log_evidence: this step's ``log p(y | y_1 .. y_{k-1})`` under the model's own prior as the
      mixture reads it: the log of the sum over the particle and ensemble components of each
      one's prior weight given no jump times its evidence, with the observation law's constant.
      The shock components (a jump the model does not have) are left out, so the figure is the
      model's likelihood, comparable with the particle filter's. 0 without an informed step;
      None where the law gives no constant (``ssm.log_normalizer``).
    """

    kind: jax.Array
    draws: jax.Array
    inflation: jax.Array
    log_bf: jax.Array
    particle_weight: jax.Array
    shock_weight: jax.Array
    informed: jax.Array
    log_evidence: jax.Array | None = None


def uses_particles(config: MixtureConfig, model: StateSpaceModel) -> bool:
    """Whether the particle components are on: asked for. They need Q: ``process_cov`` raises
    for a ``ProcessNoise`` without a covariance, and ``csf_jax.filter`` refuses that combination
    at its boundary rather than dropping the components."""
    del model
    return config.particles


def informative(y, guide):
    """Whether a step brings evidence: ``y (m,)`` has an observed entry and is assimilated
    (``guide > 0``); a scalar bool."""
    return (guide > 0) & jnp.any(observed(y))


def _component_evidence(model, y, key, means, precision, iterations: int, proposals: int, guide):
    """Log evidence ``(C,)`` and one posterior draw ``(C, d)`` of each Gaussian component
    ``N(means_c, precision^-1)`` (``precision`` (d, d) shared) times ``p(y | x)^guide``, and the
    Laplace proposal ``N(u (C, d), (chol chol^T)^{-1})`` they came from. The importance proposals
    take the noise's heavy tails where it has them (``ssm.tail_df``)."""
    loglik = lambda x: log_likelihood(model, y, x)
    weight = lambda x: curvature(model, y, x)
    u, chol = kalman_tweedie(means, precision, loglik, model.observe, weight, means, guide,
                             iterations, damped=True)
    k_draw, k_pick = jax.random.split(key)
    cand, log_w = importance_weights(k_draw, means, precision, u, chol, loglik, guide, proposals,
                                     tail_df(model), normalized=True)
    log_w = jnp.where(jnp.isnan(log_w), -jnp.inf, log_w)
    pick = jax.random.categorical(k_pick, log_w, axis=0)
    draws = jnp.take_along_axis(cand, pick[None, :, None], axis=0)[0]
    return logsumexp(log_w, 0) - jnp.log(proposals), draws, u, chol


@_linalg.precise
def precision(cov):
    """``cov^{-1}`` of a symmetric positive-definite ``(..., d, d)``, symmetrised."""
    eye = jnp.broadcast_to(jnp.eye(cov.shape[-1], dtype=cov.dtype), cov.shape)
    p = _linalg.cho_solve(_linalg.cholesky(cov)[..., None, :, :], eye)
    return 0.5 * (p + jnp.swapaxes(p, -1, -2))


@_linalg.precise
def select(model: StateSpaceModel, config: MixtureConfig, key, y, centers, prior_ens, cov,
           base_inflation, odds, guide, transport: bool = False) -> Selection:
    """The evidence stage of one filter step (module docstring).

    centers: (N, d) ``f(x_i)``.  prior_ens: (N, d) ``f(x_i) + v_i``.  cov: (d, d) the ensemble
    component's covariance (the prior ensemble's, floored).  base_inflation: its ``tau^2``.
    odds: the particle reading's prior log-odds for this step.  guide: 1 to assimilate ``y``, 0 not.
    transport: (static) the ensemble component's members are ``flow_transport``'s moves of
    their own propagated draws (``transports``), not left to the sampler.
    """
    n, d = prior_ens.shape
    dtype = prior_ens.dtype
    eye = jnp.eye(d, dtype=dtype)
    k_part, k_ens, k_res, k_shock = jax.random.split(key, 4)
    mean = prior_ens.mean(0)
    scales = jnp.asarray(config.shock_scales, dtype)
    shocks = config.shock_hazard > 0
    informed = informative(y, guide)
    shock_tau2 = jnp.trace(cov) / d * scales
    inflation = jnp.concatenate([jnp.reshape(jnp.asarray(base_inflation, dtype), (1,)),
                                 shock_tau2 if shocks else jnp.zeros((0,), dtype)])
    precisions = precision(cov[None] + inflation[:, None, None]
                           * inflation_shapes(model, config, y, prior_ens, inflation.shape[0]))
    ens_keys = jax.random.split(k_ens, precisions.shape[0])
    log_z_ens, _, u_ens, chol_ens = jax.vmap(lambda p, k: _component_evidence(
        model, y, k, mean[None], p, config.ensemble_iterations, config.ensemble_proposals,
        guide))(precisions, ens_keys)                                         # (1 + G, 1, ...)
    log_z_ens = log_z_ens[:, 0]
    # a jump is a hypothesis about the observation: a step without one has no shock components
    # (module docstring), so its posterior is the prior and its Bayes factor 1
    hazard = jnp.asarray(config.shock_hazard if shocks else 0.0, dtype)
    log_hazard = jnp.where(informed, jnp.log(hazard), -jnp.inf)
    log_calm = jnp.where(informed, jnp.log1p(-hazard), 0.0)
    if uses_particles(config, model):
        widths = kernel_widths(config.particle_kernel)
        keys = [k_part] if len(widths) == 1 else list(jax.random.split(k_part, len(widths)))
        found = [_kernel_evidence(model, config, y, k, centers, cov, eye, a, guide)
                 for a, k in zip(widths, keys)]
        log_z_part, draws = found[0]
        if len(widths) > 1:  # each width a hypothesis, of prior weight its fit to the forecast
            prior_w = kernel_prior(model, config, centers, prior_ens, cov, eye, widths)
            log_z_part = jnp.concatenate([z + w for (z, _), w in zip(found, prior_w)])
            draws = jnp.concatenate([x for _, x in found])
        log_bf = logsumexp(log_z_part) - jnp.log(n) - log_z_ens[0]
        if config.particle_ess > 0:
            penalty = ess_penalty(log_z_part, min(config.particle_ess * d, n))
            odds, log_bf = odds - penalty, log_bf - penalty
        prior_part = log_calm + jax.nn.log_sigmoid(odds) - jnp.log(n)
        prior_ens_comp = log_calm + jax.nn.log_sigmoid(-odds)
    else:
        log_z_part = jnp.full((0,), -jnp.inf, dtype)
        draws = prior_ens
        log_bf = jnp.asarray(-jnp.inf, dtype)
        prior_part = jnp.asarray(-jnp.inf, dtype)
        prior_ens_comp = log_calm
    log_calm_w = jnp.concatenate([prior_part + log_z_part, prior_ens_comp + log_z_ens[:1]])
    log_shock_w = log_hazard - jnp.log(scales.shape[0]) + log_z_ens[1:]
    if shocks and config.shock_gate > 0:
        # below the gate the jump is improbable, and its members would be outliers (docstring)
        log_odds = logsumexp(log_shock_w) - logsumexp(log_calm_w)
        gate = math.log(config.shock_gate) - math.log1p(-config.shock_gate)
        log_shock_w = jnp.where(log_odds >= gate, log_shock_w, -jnp.inf)
    log_w = jnp.concatenate([log_calm_w, log_shock_w])
    log_w = jnp.where(jnp.isnan(log_w), -jnp.inf, log_w)
    idx = _systematic(k_res, log_w, n)
    n_part = log_z_part.shape[0]
    kind = jnp.where(idx < n_part, 0, idx - n_part + 1).astype(jnp.int32)
    total = logsumexp(log_w)
    weights = jnp.exp(log_w - total)
    particle_weight = jnp.sum(weights[:n_part])
    shock_weight = jnp.sum(weights[n_part + 1:])
    draws = draws[jnp.clip(idx, 0, max(n_part, 1) - 1)]
    if shocks:
        draws = shock_draws(model, config, k_shock, y, mean, precisions, u_ens[:, 0],
                            chol_ens[:, 0], kind, draws, guide)
    if transport:
        draws = transported(model, config, k_res, y, prior_ens, cov, u_ens[0, 0], chol_ens[0, 0],
                            precisions[0], kind, draws, guide)
    log_bf = jnp.where(informed & jnp.isfinite(log_bf), log_bf, 0.0)
    # without evidence the posterior is the prior, and the propagated members are exact draws of
    # it (module docstring)
    kind = jnp.where(informed, kind, 0)
    draws = jnp.where(informed, draws, prior_ens)
    particle_weight = jnp.where(informed, particle_weight, 1.0)
    const = log_normalizer(model, y)
    # the model's own evidence: the particle and ensemble readings, each at its prior weight
    # given no jump; the shock components are CSF's hypothesis, not the model's
    calm = logsumexp(jnp.where(jnp.isnan(log_calm_w), -jnp.inf, log_calm_w)) - log_calm
    log_evidence = None if const is None else jnp.where(
        informed, calm + proposal_constant(d, tail_df(model), dtype) + const.astype(dtype), 0.0)
    return Selection(kind, draws, inflation, log_bf, particle_weight, shock_weight, informed,
                     log_evidence)


def kernel_widths(particle_kernel) -> tuple:
    """``MixtureConfig.particle_kernel`` as a tuple of factors on Silverman's bandwidth."""
    return tuple(particle_kernel) if isinstance(particle_kernel, tuple) else (particle_kernel,)


def _kernel(model, centers, cov, eye, width: float):
    """The particle components at kernel factor ``width``: centres (N, d), covariance (d, d)."""
    n, d = centers.shape
    kernels, q_cov = centers, process_cov(model, centers.dtype)
    if width > 0:
        h2 = width * silverman(n, d) ** 2
        centre = centers.mean(0)
        kernels, q_cov = centre + math.sqrt(1.0 - h2) * (centers - centre), q_cov + h2 * cov
    return kernels, q_cov + 1e-12 * eye


def loo_score(kernels, q_cov, points):
    """The leave-one-out log density of ``points (N, d)`` (``f(x_j) + v_j``) under the mixture
    of the other members' kernels ``N(kernels_i (N, d), q_cov (d, d))``, summed over j: how well
    a kernel width describes the forecast ensemble, its modes included."""
    n, d = points.shape
    chol = _linalg.cholesky(q_cov)
    zw = _linalg.solve_lower(chol[None], points)                            # (N, d)
    cw = _linalg.solve_lower(chol[None], kernels)
    dist2 = (jnp.sum(zw ** 2, -1)[:, None] + jnp.sum(cw ** 2, -1)[None]
             - 2.0 * zw @ cw.T)                                             # (N_j, N_i)
    log_k = -0.5 * jnp.maximum(dist2, 0.0) - jnp.sum(jnp.log(jnp.diagonal(chol)))
    log_k = jnp.where(jnp.eye(n, dtype=bool), -jnp.inf, log_k)
    return jnp.sum(logsumexp(log_k, axis=1)) - n * math.log(n - 1)


def kernel_prior(model, config, centers, prior_ens, cov, eye, widths) -> list:
    """Log prior weights of the kernel ``widths`` (``MixtureConfig.kernel_choice``)."""
    g = len(widths)
    if config.kernel_choice == "evidence":
        return [-math.log(g)] * g
    scores = jnp.stack([loo_score(*_kernel(model, centers, cov, eye, a), prior_ens)
                        for a in widths])
    return list(jax.nn.log_softmax(scores))


def _kernel_evidence(model, config, y, key, centers, cov, eye, width: float, guide):
    """The particle components at kernel factor ``width`` (``MixtureConfig.particle_kernel``):
    their log evidence (N,) (-inf where non-finite) and a posterior draw of each (N, d)."""
    kernels, q_cov = _kernel(model, centers, cov, eye, width)
    q_prec = precision(q_cov)
    log_z, draws, _, _ = _component_evidence(
        model, y, key, kernels, q_prec, config.iterations, config.proposals, guide)
    return jnp.where(jnp.isfinite(log_z), log_z, -jnp.inf), draws


WILD_QUANTILES = (0.05, 0.95)


def wild_members(prior_ens, ranges: float):
    """(N,) bool: the members of ``prior_ens (N, d)`` whose forecast is lost, non-finite or more
    than ``ranges`` times the ensemble's central range (the 5-95% quantiles, coordinate by
    coordinate) from its median. A jump hypothesis feeds the model a member tens of spreads off,
    and an explosive drift (an exponential one, Lotka-Volterra's) carries it to 1e13 within a step:
    left in, that one member is the ensemble's covariance, every component's scale, and the run is
    lost. The quantiles stand a few such members (up to 5% of them), the range includes the
    process noise, and a minority mode is inside it unless it is 1000 times the main mode's width
    off. ``ranges`` 0 marks the non-finite members only."""
    finite = jnp.all(jnp.isfinite(prior_ens), axis=1)
    if ranges == 0:
        return ~finite
    clean = jnp.where(finite[:, None], prior_ens, jnp.nan)
    low, high, mid = jnp.nanquantile(clean, jnp.asarray((*WILD_QUANTILES, 0.5)), axis=0)
    far = jnp.abs(prior_ens - mid) > ranges * (high - low)
    return ~finite | jnp.any(far & (high > low), axis=1)


def tame(key, wild, *rows):
    """``rows`` (each (N, ...)) with the ``wild (N,)`` members replaced by copies of members drawn
    uniformly from the others (the same member in every array), and the count replaced. A
    dropped member's prior weight goes to the others; nothing changes without a wild member, or
    where every member is wild."""
    n = wild.shape[0]
    kept = jnp.cumsum(~wild)
    pick = jax.random.randint(key, (n,), 1, jnp.maximum(kept[-1], 1) + 1)
    source = jnp.searchsorted(kept, pick)
    replace = wild & (kept[-1] > 0)
    out = tuple(jnp.where(replace.reshape((n,) + (1,) * (r.ndim - 1)), r[source], r)
                for r in rows)
    return out, jnp.sum(replace).astype(jnp.int32)


def shock_draws(model: StateSpaceModel, config: MixtureConfig, key, y, mean, precisions, u, chol,
                kind, draws, guide):
    """``draws (N, d)`` with the shock members' (``kind > 1``) replaced by importance resampling
    from their component's Laplace proposal (``config.proposals`` candidates each): the
    reverse-diffusion sampler is left to the ensemble component. ``mean (d,)``: the prior
    ensemble's; ``precisions (1 + G, d, d)``, ``u (1 + G, d)``, ``chol (1 + G, d, d)``: the
    components' prior precisions and Laplace fits. Skipped on steps without a shock member."""
    n, d = draws.shape

    def fill(idx):
        g = jnp.clip(kind - 1, 0, precisions.shape[0] - 1)
        cand, log_wc = importance_weights(
            key, jnp.broadcast_to(mean, (n, d)), precisions[g], u[g], chol[g],
            lambda x: log_likelihood(model, y, x), guide, config.proposals, tail_df(model))
        log_wc = jnp.where(jnp.isnan(log_wc), -jnp.inf, log_wc)
        pick = jax.random.categorical(jax.random.fold_in(key, 1), log_wc, axis=0)
        return jnp.take_along_axis(cand, pick[None, :, None], axis=0)[0]

    return fill_rows(kind > 1, fill, draws)


def transported(model: StateSpaceModel, config: MixtureConfig, key, y, prior_ens, cov, u, chol,
                prior_prec, kind, draws, guide):
    """``draws (N, d)`` with the ensemble component's members (``kind == 1``) replaced by moves
    of a random subset of the propagated members ``prior_ens (N, d)`` onto its posterior
    (``flow_transport``, or ``gaussian_transport`` without levels; ``cov``, ``u``, ``chol``,
    ``prior_prec``: the component's). The subset is random because the systematic resampling
    orders the members by component: a fixed block would move the same members step after step,
    last step's shock members among them (the transport keeps an outlier an outlier). Each move
    depends on its own member and the ensemble's mean only, so only the members drawn are moved
    (``fill_rows``' blocks), the same numbers as moving all N at once."""
    n = prior_ens.shape[0]
    chosen = prior_ens[jax.random.permutation(jax.random.fold_in(key, 1), n)]
    mean = prior_ens.mean(0)

    def fill(idx):
        members = jnp.take(chosen, idx, axis=0, mode="clip")
        if config.transport_levels > 0:
            own = config.transport_flow != "mode"
            return flow_transport(members, cov, u, chol, prior_prec,
                                  lambda x: guide * log_likelihood(model, y, x),
                                  transport_levels(config), config.transport_iterations, mean,
                                  model.observe if own else None,
                                  (lambda x: guide * curvature(model, y, x)) if own else None,
                                  centred=config.transport_flow != "member")
        return gaussian_transport(members, cov, u, chol, mean)

    return fill_rows(kind == 1, fill, draws, row_block(n))


def row_block(n: int) -> int | None:
    """The block of members ``fill_rows`` gathers a step's few members of one kind into: ``n //
    ROW_BLOCK`` (None below ``MIN_ROW_BLOCK`` members). The ensemble component's share of the
    members is at most a quarter on 73-100% of the steps of the paper's problems (60 steps each,
    N = 1000: the double well's median 11%, 20-D's 0 or above a third), and each size is one
    more compiled copy of the draws: one block and the whole ensemble."""
    return n // ROW_BLOCK if n // ROW_BLOCK >= MIN_ROW_BLOCK else None


def fill_rows(rows, fill, draws, block: int | None = None):
    """``draws (N, d)`` with its rows where ``rows (N,)`` is set replaced by ``fill``'s.

    ``fill(idx)``: the new rows ``(M, d)`` of the members ``idx (M,)`` (an index N pads: gather
    with ``mode="clip"``; its row is dropped). One branch runs: nothing on a step without a set
    row (most steps have no shock member; a model without jumps never does); with ``block``, the
    set rows gathered into ``block`` rows where they fit (``fill`` must then compute each row from
    its own member: the transport; the sampler, whose noise then differs); else
    ``fill(arange(N))`` for all N (the shock draws, whose random numbers are drawn for all N at
    once). Under ``jax.vmap`` every run takes the branch of the neediest run (``batch_max``), so
    the switch stays a switch, not every branch's work selected.
    """
    n = draws.shape[0]
    count = jnp.sum(rows.astype(jnp.int32))

    def every(draws):
        return jnp.where(rows[:, None], fill(jnp.arange(n)).astype(draws.dtype), draws)

    def gathered(draws):
        idx = jnp.nonzero(rows, size=block, fill_value=n)[0]
        return draws.at[idx].set(fill(idx).astype(draws.dtype), mode="drop")

    branches = [lambda draws: draws, every]
    index = jnp.where(count > 0, 1, 0)
    if block is not None and block < n:
        branches = [lambda draws: draws, gathered, every]
        index = jnp.where(count > block, 2, index)
    return jax.lax.switch(batch_max(index), branches, draws)


def proposal_constant(d: int, df: int | None, dtype) -> jax.Array:
    """What ``importance_weights(normalized=True)`` leaves out of a component's log evidence: the
    Gaussian normalising constants cancel between the prior and a Gaussian proposal (0); a
    Student-t proposal with ``df`` degrees of freedom per whitened coordinate (``tail_df``) has
    its own, ``d (log Gamma((df + 1) / 2) - log Gamma(df / 2) - log(df pi) / 2)`` in place of
    the Gaussian's ``-d log(2 pi) / 2``."""
    if df is None:
        return jnp.zeros((), dtype)
    t_const = math.lgamma(0.5 * (df + 1.0)) - math.lgamma(0.5 * df) - 0.5 * math.log(df * math.pi)
    return jnp.asarray(d * (-0.5 * math.log(2.0 * math.pi) - t_const), dtype)


def transports(config: MixtureConfig, prior_name: str) -> bool:
    """Whether the ensemble component's members are transported (``MixtureConfig.ensemble_draws``)
    under the prior score named ``prior_name`` (``PriorScore.name``): only the ensemble's own
    Gaussian, whose posterior the map knows; a learned score is sampled."""
    return config.ensemble_draws == "transport" and prior_name == "gaussian"


@_linalg.precise
def gaussian_transport(prior_ens, cov, u, chol, mean=None):
    """``prior_ens (N, d)`` moved onto the Laplace posterior ``N(u (d,), A^{-1})``
    (``chol chol^T = A``, ``chol: (d, d)``) of the ensemble component with covariance
    ``cov (d, d)`` (its members' mean m): ``x -> u + L (L^T A L)^{-1/2} L^{-1} (x - m)``, with
    ``cov = L L^T``.

    The map is linear, so the members' mean goes to ``u``, and it takes ``cov`` to exactly
    ``A^{-1}`` (``mean (d,)``: m, None for the members' own mean). Among such maps it is the one
    symmetric in the whitened coordinates ``L^{-1} (x - m)``, which moves them least: with
    ``cov`` the members' sample covariance and a linear sensor it is the ensemble transform
    Kalman filter's symmetric square root (Hunt et al. 2007; ``tests/test_mixture.py``). Each
    member keeps its own deviation, so what the prior holds beyond its two moments (skew, a
    curved attractor) is carried into the posterior, where fresh draws from ``N(u, A^{-1})``
    would drop it. Matrix products and triangular solves only
    (``inverse_sqrt``): no LAPACK call inside the filter's scan (docs/design.md).
    """
    mean = prior_ens.mean(0) if mean is None else mean
    lower = _linalg.cholesky(cov)
    whitened = _linalg.solve_lower(lower, prior_ens - mean)                  # (N, d)
    k = chol.T @ lower                                                       # L^T A L = k^T k
    root = inverse_sqrt(k.T @ k)
    return u + (whitened @ root) @ lower.T


def transport_levels(config: MixtureConfig):
    """``(L + 1,)`` host floats: the transport's noise levels (``MixtureConfig.transport_levels``),
    geometric from ``sigma_t(1)`` to ``sigma_t(1e-3)`` of the VE SDE, then 0."""
    return noise_levels(config.transport_levels, marginal_std_host(1.0, SIGMA_MAX),
                        marginal_std_host(1e-3, SIGMA_MAX))


@_linalg.precise
def flow_transport(prior_ens, cov, u, chol, prior_prec, loglik, levels, iterations: int,
                   mean=None, observe=None, weight=None, centred: bool = True):
    """``prior_ens (N, d)`` moved down the probability flow of the VE SDE onto the posterior
    ``N(m, B) p(y | x)`` of the ensemble component (prior mean m, the members' mean; prior
    precision ``prior_prec = B^{-1} (d, d)``; ``loglik: x (d,) -> log p(y | x)``, weighted by the
    guidance), with the Laplace posterior ``N(u (d,), A^{-1})`` (``chol chol^T = A``) as its
    guide (``mean (d,)``: m, None for the members' own; each member moves by itself given m). In
    the whitened coordinates ``z = L^{-1} (x - m)`` (``cov = L L^T``), where the
    members' deviations are ``e_n`` and the Laplace posterior is ``N(z*, P)``:

    * **top** (``levels[0] = s_0``): ``z_n = z* + (P + s_0^2)^{1/2} e_n``, the members carried up
      the prior's flow and across to the diffused Laplace posterior;
    * **each level** ``s -> s'``: the member's Tweedie estimate ``t_n``, the maximiser of
      ``log N(t; 0, B_z) + log p(y | t) - |t - z_n|^2 / (2 s^2)``, by ``iterations`` damped
      Gauss-Newton steps (the gradient at the member's own point, the best of the step fractions
      ``TRANSPORT_STEPS``), warm-started from the level above (at the top, from ``e_n``: the
      member's own propagated point, so that it looks for the posterior on its own side); then
      the member moves to level ``s'`` (``MixtureConfig.transport_flow``):

      - the Gauss-Newton steps: with ``observe`` and ``weight`` given ("hybrid", "member"), each
        with the member's own curvature ``B_z + L^T J^T W J L + I / s^2`` (``J = dh/dx`` at the
        member's estimate, ``W = weight(x)``: per-coordinate weights (m,) or a precision (m, m),
        as ``kalman_tweedie`` takes them); without ("mode"), with the curvature at the mode,
        ``A_z + I / s^2``, shared by every member;
      - the move: ``centred`` ("hybrid", "mode"), the centre ``mu_n`` of the Gaussian
        linearised at ``t_n``, one Newton step ``t_n + P grad`` of the posterior, searched along
        the same way, then the exact flow of that Gaussian, ``z_n <- mu_n + (P + s'^2)^{1/2} (P +
        s^2)^{-1/2} (z_n - mu_n)``; not ``centred`` ("member", with ``observe``),
        ``z_n <- t_n + K (z_n - t_n)`` with ``K = ((P + s'^2)^{1/2} (P + s^2)^{1/2} - P) / s^2``:
        the exact flow of a Gaussian posterior written from its Tweedie estimate (the
        probability flow's DDIM step ``s' / s`` where ``P`` is negligible against ``s^2``, which
        with 10 levels narrows the ensemble by 15% even under a linear sensor).

    With a linear sensor and Gaussian noise every ``mu_n`` is ``z*``, every ``t_n`` the exact
    Tweedie estimate, and all three ways telescope to ``z* + P^{1/2} e_n``: ``gaussian_transport``,
    whatever the levels (tested).
    Otherwise each member follows the posterior's gradient where it is: a member that starts on
    the side of a second mode (a state the sensor sees only up to its sign) ends in that mode,
    where the single map at the mode moves every member into the one the Gauss-Newton steps
    found. The line search keeps a steep sensor (``x^2``, ``x^3``) from throwing a member past
    the posterior. Under the shared curvature it also lets a member where the sensor is flatter
    than at the mode travel further, but with one fraction for all of a member's coordinates:
    where the sensor's curvature varies across coordinates and members (``x^3``, d = 10 and a
    broad prior) members stay far from the posterior, which the member's own curvature avoids
    (docs/defaults.md). A member that starts at a point where the likelihood's gradient
    vanishes (a cubic sensor's 0, against an observation far from it) can stay caught there
    (tested). Matrix functions by ``inverse_sqrt``, factorisations and triangular solves by
    ``_linalg``: no LAPACK call in the scan.
    """
    d = prior_ens.shape[1]
    dtype = prior_ens.dtype
    eye = jnp.eye(d, dtype=dtype)
    mean = prior_ens.mean(0) if mean is None else mean
    lower = _linalg.cholesky(cov)
    e = _linalg.solve_lower(lower, prior_ens - mean)                         # (N, d)
    k = chol.T @ lower
    a_z = k.T @ k                                                           # L^T A L
    p = precision(a_z)
    b_z = lower.T @ prior_prec @ lower                                      # B_z^{-1}
    z_star = _linalg.solve_lower(lower, (u - mean)[None])[0]
    fractions = jnp.asarray(TRANSPORT_STEPS, dtype)
    own = observe is not None

    def grad(z):
        g = jax.grad(loglik)(mean + lower @ z)
        return -b_z @ z + lower.T @ jnp.where(jnp.isfinite(g), g, 0.0)

    def curvature_at(z):
        # B_z + L^T J^T W J L at the member's point (the sensor's Gauss-Newton curvature there)
        x = mean + lower @ z
        jac = jax.jacfwd(observe)(x) @ lower
        w = weight(x)
        return b_z + weighted_gram(jnp.where(jnp.isfinite(jac), jac, 0.0),
                                    jnp.where(jnp.isfinite(w), w, 0.0))

    def search(t, direction, extra=0.0):
        # the log posterior (plus ``extra (S,)``) at t + a direction for each step fraction a, its
        # quadratic term in closed form along the line and the likelihood at mean + lower (...)
        x = (mean + lower @ t) + fractions[:, None] * (lower @ direction)
        value = (-0.5 * quadratic_along(b_z, t, direction, fractions) + jax.vmap(loglik)(x)
                 + extra)
        return t + fractions[jnp.argmax(jnp.where(jnp.isnan(value), -jnp.inf, value))] * direction

    def tweedie(t, z, s, solve):
        rhs = grad(t) - (t - z) / s ** 2
        if own:
            direction = _linalg.cho_solve(_linalg.cholesky(curvature_at(t) + eye / s ** 2), rhs)
        else:
            direction = rhs @ solve
        return search(t, direction,
                      -quadratic_along(None, t - z, direction, fractions) / (2.0 * s ** 2))

    def centre(t):
        return search(t, grad(t) @ p)

    def sqrtm(a):
        return a @ inverse_sqrt(a)

    sig = jnp.asarray(levels, dtype)
    from_tweedie = own and not centred
    if from_tweedie:  # the flow's step from the member's Tweedie estimate
        maps = jax.vmap(lambda s, s_next: (sqrtm(p + s_next ** 2 * eye) @ sqrtm(p + s ** 2 * eye)
                                           - p) / s ** 2)(sig[:-1], sig[1:])  # (L, d, d)
    else:
        maps = jax.vmap(lambda s, s_next: sqrtm(p + s_next ** 2 * eye)
                        @ inverse_sqrt(p + s ** 2 * eye))(sig[:-1], sig[1:])  # (L, d, d)
    if own:  # each member's own factorisation; no shared solves
        solves = jnp.zeros((sig.shape[0] - 1, 0), dtype)
    else:
        solves = precision(a_z[None] + eye[None] / sig[:-1, None, None] ** 2)  # (L, d, d)

    def level(carry, xs):
        z, t = carry
        s, flow, solve = xs
        for _ in range(iterations):
            if own:  # a factorisation per member: in blocks that stay in the caches
                t = particle_map(lambda tz: tweedie(*tz, s, solve), (t, z))
            else:
                t = jax.vmap(tweedie, in_axes=(0, 0, None, None))(t, z, s, solve)
        if from_tweedie:
            return (t + (z - t) @ flow, t), None
        mu = jax.vmap(centre)(t)
        return (mu + (z - mu) @ flow, t), None

    z = z_star + e @ sqrtm(p + sig[0] ** 2 * eye)
    (z, _), _ = jax.lax.scan(level, (z, e), (sig[:-1], maps, solves))
    return mean + z @ lower.T


@_linalg.precise
def inverse_sqrt(a, iterations: int = NEWTON_SCHULZ_STEPS):
    """``a^{-1/2}`` of a symmetric positive-definite ``a (d, d)`` by the coupled Newton-Schulz
    iteration on ``a / |a|_F`` (whose eigenvalues lie in (0, 1]): ``T = (3 I - Z Y) / 2``,
    ``Y <- Y T``, ``Z <- T Z``, with Z tending to ``(a / |a|_F)^{-1/2}``. An eigenvalue
    ``lambda`` of the scaled matrix reaches full accuracy in about ``log(1 / lambda) / log(2.25)
    + 5`` steps: 32 reach float64's rounding for condition numbers up to 1e8
    (``tests/test_mixture.py``). Matrix products only."""
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    norm = jnp.sqrt(jnp.sum(a * a))

    def step(_, yz):
        y, z = yz
        t = 1.5 * eye - 0.5 * (z @ y)
        return y @ t, t @ z

    _, z = jax.lax.fori_loop(0, iterations, step, (a / norm, eye))
    return 0.5 * (z + z.T) / jnp.sqrt(norm)


def inflation_shapes(model: StateSpaceModel, config: MixtureConfig, y, prior_ens, count: int):
    """``(d, d)`` or ``(count, d, d)``: the shape each component's inflation ``tau^2`` widens
    the prior along, the ensemble component's first. Isotropic (``I``) for the ensemble
    component and, with ``shock_span="isotropic"``, for the shocks; with "observed" a shock
    widens the directions ``y (m,)`` sees (``seen_directions``) by its ``tau^2`` and the others
    by at most ``shock_unseen`` times the ensemble's mean variance."""
    d = prior_ens.shape[1]
    eye = jnp.eye(d, dtype=prior_ens.dtype)
    if config.shock_span != "observed" or count == 1:
        return eye
    seen = seen_directions(model, y, prior_ens)
    scales = jnp.asarray(config.shock_scales, prior_ens.dtype)
    unseen = jnp.minimum(scales, config.shock_unseen) / scales
    return jnp.concatenate([eye[None], seen + unseen[:, None, None] * (eye - seen)])


def seen_directions(model: StateSpaceModel, y, ensemble):
    """``(d, d)``: the state directions the observed entries of ``y (m,)`` see, averaged over
    ``ensemble (N, d)``: ``mean_n sum_j g_nj g_nj^T`` with ``g_nj`` the unit gradient of
    ``h_j`` at member n (0 where that gradient vanishes). An elementwise sensor of the sites
    ``S`` gives the indicator ``diag(1_S)``; a full one the identity.

    With ``shock_span="observed"`` the shock components widen the prior along these directions
    alone: only the entries ``y`` observes can tell a jump from the ensemble, and widened
    isotropically a shock that explains the observed coordinates spreads the unobserved ones by
    up to 64 ensemble spreads (folding's third coordinate at N = 50)."""
    jac = jax.vmap(jax.jacfwd(model.observe))(ensemble)                     # (N, m, d)
    norm = jnp.sqrt(jnp.sum(jac * jac, -1, keepdims=True))
    unit = jnp.where(norm > 0, jac / jnp.where(norm > 0, norm, 1.0), 0.0)
    unit = jnp.where(observed(y)[None, :, None] & jnp.isfinite(unit), unit, 0.0)
    return jnp.einsum("nji,njk->ik", unit, unit) / ensemble.shape[0]


def silverman(n: int, d: int) -> float:
    """Silverman's bandwidth ``(4 / ((d + 2) n))^(1 / (d + 4))`` of a Gaussian kernel density
    estimate from ``n`` draws in ``d`` dimensions, in units of their standard deviation."""
    return (4.0 / ((d + 2) * n)) ** (1.0 / (d + 4))


def ess_penalty(log_weights, target: float):
    """``max(0, log(target / ESS))`` of unnormalised ``log_weights (N,)`` (``-inf`` entries
    count as weight 0): how far the weights' effective sample size falls below ``target``."""
    n = log_weights.shape[0]
    w = jnp.exp(log_weights - logsumexp(log_weights))
    ess = 1.0 / jnp.maximum(jnp.sum(w * w), 1.0 / n)
    penalty = jnp.maximum(0.0, jnp.log(target) - jnp.log(ess))
    return jnp.where(jnp.isfinite(penalty), penalty, 0.0)


def _systematic(key, log_weights, n: int):
    """``n`` systematic draws of indices from unnormalised ``log_weights (C,)``."""
    w = jnp.exp(log_weights - logsumexp(log_weights))
    cdf = jnp.cumsum(w)
    cdf = cdf / cdf[-1]
    u = (jnp.arange(n, dtype=cdf.dtype) + jax.random.uniform(key, (), cdf.dtype)) / n
    return jnp.clip(jnp.searchsorted(cdf, u, side="left"), 0, log_weights.shape[0] - 1)


def next_odds(config: MixtureConfig, memory, log_bf, informed=True):
    """The accumulated log Bayes factor after this step, and the next step's prior log-odds of
    the particle reading: ``S <- memory S + log_bf``, odds = ``particle_logodds + S``.

    informed: whether the step brought evidence (``Selection.informed``). A step without any
    leaves ``S`` as it was: the forgetting counts assimilated observations, so an outage neither
    adds evidence nor wears away the evidence gathered before it (with ``S`` forgotten per time
    step, ten blind steps would take ``memory^10`` = 35% of it, and a long outage would reset the
    odds to the prior's with nothing observed to justify it)."""
    acc = jnp.where(informed, config.memory * memory + log_bf, memory)
    return acc, config.particle_logodds + acc
