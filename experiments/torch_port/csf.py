"""A PyTorch port of the CSF online step with the learned prior, for benchmarking against csf_jax.

It computes the same thing as ``csf_jax.filter(params, ...)`` with ``learned_prior``, written the
way the paper's authors' stack would: PyTorch modules, ``torch.no_grad()`` everywhere except the
DPS gradient (``torch.autograd.grad`` through the score net eager, ``torch.func.grad`` under
``torch.compile``: :func:`dps_gradient`), float32, and a Python loop over the L reverse steps.
Like csf_jax it has two samplers, chosen by ``config.sampler.guidance.mode``:

* ``"kalman"`` (the default): the ancestral sampler with Kalman guidance
  (``csf_jax.filters.csf.ancestral_sample``). The reverse process starts from the prior ensemble
  noised to ``sigma_1``; at each noise level of ``csf_jax.sde.noise_levels`` Tweedie's ``x0_hat``
  and the ensemble's Gaussian precision (:func:`gaussian_precision`) give ``x_0 | x_t``, a few
  Fisher-scoring steps (:func:`kalman_tweedie`) its posterior ``N(u, A^{-1})`` given ``y``,
  importance resampling over K proposals (:func:`resample_posterior`) one draw of it, and the exact
  VE bridge the next level. Batched ``torch.linalg`` over the particles; no autograd (the
  observation ``x^3`` of every problem here has a closed-form Jacobian and likelihood gradient).
* a DPS mode (``"clipped"``, ``"raw"``, ``"normalized"``, ``"none"``): Euler-Maruyama on the
  reverse VE SDE with DPS guidance (``csf_jax.filters.csf.posterior_sample``), the paper's sampler.

Every piece mirrors a csf_jax one:

* ``SetEncoder`` / ``ScoreNet``: ``csf_jax.networks`` (weights loaded with :func:`flax_to_torch`).
* ``marginal_std`` / ``diffusion_sq`` / ``time_of_std`` / :func:`schedule`: ``csf_jax.sde``; the
  Euler-Maruyama grid ``linspace(1, t_min, L)`` with a constant ``dt`` and a noise-free last step
  (:class:`Schedule`), or the ancestral sampler's geometric noise levels and bridge coefficients
  (:class:`AncestralSchedule`).
* :func:`guidance_displacement`: ``csf_jax.guidance`` (DPS); :func:`kalman_tweedie` and
  :func:`resample_posterior`: ``csf_jax.guidance`` (Kalman); :func:`gaussian_precision`:
  ``csf_jax.prior``.
* :func:`torch_problem`: the drift, log-likelihood, its gradient, the observation's Jacobian and
  the noise's Fisher information of ``csf_jax.problems`` (cubic sensors, Cauchy, double/triple
  well).
* :func:`filter_step`: one step of ``csf_jax.filters.csf._csf_scan`` (propagate, encode, the
  step's prior inflation, L reverse steps); :func:`adaptive_inflation` and :func:`step_schedule`:
  ``csf_jax.inflation`` and ``csf_jax.filters.csf.step_inflation`` (the default adaptive
  inflation, median or chi-square statistic).

:func:`make_reverse_step` returns the per-reverse-step function of the configured sampler, eager
or wrapped by ``torch.compile(..., dynamic=False, fullgraph=True, mode=...)``
(:func:`compile_step`): either sampler's step is one Dynamo graph (no graph break), so Inductor
fuses it whole and ``mode="reduce-overhead"`` can replay it as one CUDA graph. All random draws
can be injected (:class:`StepNoise`, :class:`AncestralNoise`) so that tests feed identical noise to
both implementations.

Devices: the builders take a ``device`` (default the CPU) and put every tensor they make there:
:func:`flax_to_torch` the network weights and buffers, :func:`torch_problem` the constants of the
problem (the correlated cubic sensor's coupling matrix), :func:`schedule` the per-step scalars;
everything made per step (identity matrices, draws, generators, the 0-d guide) follows the device
of its inputs. No tensor is made on the CPU implicitly: a CUDA run moves no data to the host inside
a filter step, and a compiled step holds no CPU constant.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from csf_jax.filters.csf import PAPER, CSFConfig
from csf_jax.guidance import GuidanceConfig
from csf_jax.networks import NetworkConfig, fourier_frequencies
from csf_jax.problems import CubicConfig, WellConfig, build
from csf_jax.problems import config as problem_config
from csf_jax.problems import get as get_problem
from csf_jax.problems.cubic import coupling_matrix
from csf_jax.sde import marginal_std_host
from csf_jax.sde import noise_levels as host_noise_levels
from csf_jax.ssm import tail_df

DTYPE = torch.float32
FLAX_LN_EPS = 1e-6


# --------------------------------------------------------------------------------------------
# VE SDE
# --------------------------------------------------------------------------------------------

def marginal_std(t: torch.Tensor, sigma_max: float) -> torch.Tensor:
    """``sqrt((s^(2t) - 1) / (2 ln s))``, any shape (``csf_jax.sde.marginal_std``)."""
    log_s = math.log(sigma_max)
    return torch.sqrt(torch.expm1(2.0 * t * log_s) / (2.0 * log_s))


def diffusion_sq(t: torch.Tensor, sigma_max: float) -> torch.Tensor:
    """``g(t)^2 = s^(2t)``, any shape (``csf_jax.sde.diffusion_sq``)."""
    return torch.exp(2.0 * t * math.log(sigma_max))


class Schedule(NamedTuple):
    """Per-reverse-step scalars, each ``(L,)`` float32; index ``[l]`` gives a 0-d tensor.

    t: times ``linspace(1, t_min, L)``.  t_score: the times at which the prior score is evaluated
    (``csf_jax.sde.inflated_time``: t itself without prior inflation).  var: ``sigma_t^2``.
    g2dt: ``g(t)^2 dt``.  noise_scale: ``g(t) sqrt(dt)``.  noise_on: 1.0, or 0.0 at the last step
    when ``denoise_last``.  inflation, sigma_max, adaptive: as in :class:`AncestralSchedule`.
    """

    t: torch.Tensor
    t_score: torch.Tensor
    var: torch.Tensor
    g2dt: torch.Tensor
    noise_scale: torch.Tensor
    noise_on: torch.Tensor
    inflation: float | torch.Tensor = 0.0
    sigma_max: float = 25.0
    adaptive: AdaptiveInflation | None = None
    encode_particles: int | None = None


def time_of_std(sigma: torch.Tensor, sigma_max: float) -> torch.Tensor:
    """The time t with ``marginal_std(t) = sigma``, any shape (``csf_jax.sde.time_of_std``, op for
    op in sigma's dtype)."""
    log_s = torch.log(torch.tensor(sigma_max, dtype=sigma.dtype, device=sigma.device))
    return torch.log1p(2.0 * log_s * torch.square(sigma)) / (2.0 * log_s)


def inflated_time(t: torch.Tensor, inflation: float | torch.Tensor,
                  sigma_max: float) -> torch.Tensor:
    """The time whose marginal std is ``sqrt(sigma_t^2 + inflation^2)``, any shape
    (``csf_jax.sde.inflated_time``; the shortcut for 0 only for a Python number, as there: a 0-d
    tensor is never read back to the host)."""
    if isinstance(inflation, (int, float)) and inflation == 0.0:
        return t
    return time_of_std(torch.sqrt(torch.square(marginal_std(t, sigma_max)) + inflation ** 2),
                       sigma_max)


def em_schedule(config: CSFConfig, dtype: torch.dtype = DTYPE,
                device: torch.device | str = "cpu") -> Schedule:
    """The reverse grid of ``csf_jax.sde.reverse_grid`` and its per-step scalars, on ``device``."""
    sampler, base = config.sampler, config.inflation.base
    n, t_min, sigma_max = sampler.reverse_steps, sampler.t_min, sampler.sigma_max
    t = torch.linspace(1.0, t_min, n, dtype=dtype, device=device)
    dt = torch.tensor((1.0 - t_min) / (n - 1), dtype=dtype, device=device)
    g2dt = diffusion_sq(t, sigma_max) * dt
    noise_on = torch.ones(n, dtype=dtype, device=device)
    if sampler.denoise_last:
        noise_on[-1] = 0.0
    var = marginal_std(t, sigma_max) ** 2
    t_score = inflated_time(t, base, sigma_max)
    return Schedule(t, t_score, var, g2dt, torch.sqrt(g2dt), noise_on, base, sigma_max,
                    _adaptive(config), config.prior.encode_particles)


class AncestralSchedule(NamedTuple):
    """The ancestral sampler's per-level scalars, each ``(L,)`` (index ``[l]`` gives a 0-d tensor),
    and its settings.

    sigma: the noise levels ``sigma_l`` (``csf_jax.sde.noise_levels`` without its final 0, float32).
    t_score: ``inflated_time(time_of_std(sigma_l), tau)``, where the prior score is evaluated.
    rho, noise_scale: ``rho`` and ``sqrt(v)`` of ``csf_jax.sde.bridge(sigma_l, sigma_{l+1})``.
    first: bool, True at ``l = 0`` (where the Fisher scoring starts from ``x0_hat``).
    sigma_start: 0-d ``marginal_std(1)``, the noise added to the prior ensemble at the start.
    inflation: tau, the prior inflation of :func:`gaussian_precision` (with ``adaptive``: its base).
    proposals: K, the importance-resampling candidates per particle.
    sigma_max: the VE SDE's scale.
    adaptive: None (fixed inflation), or :class:`AdaptiveInflation` (``InflationConfig.adaptive``):
      :func:`step_schedule` then sets ``inflation`` and ``t_score`` per filter step.
    encode_particles: the encoder sees the first n particles of the prior ensemble (None: all).
    proposal_df: the candidates' Student-t degrees of freedom (``GuidanceConfig.proposal_df``), or
      None for Gaussian candidates.
    """

    sigma: torch.Tensor
    t_score: torch.Tensor
    rho: torch.Tensor
    noise_scale: torch.Tensor
    first: torch.Tensor
    sigma_start: torch.Tensor
    inflation: float | torch.Tensor
    proposals: int
    sigma_max: float = 25.0
    adaptive: AdaptiveInflation | None = None
    encode_particles: int | None = None
    proposal_df: int | None = None


class AdaptiveInflation(NamedTuple):
    """``InflationConfig``'s adaptive-inflation settings (``csf_jax.inflation.adaptive_inflation``).
    """

    threshold: float
    max_tau: float
    statistic: str


def noise_levels(config: CSFConfig, dtype: torch.dtype = DTYPE,
                 device: torch.device | str = "cpu") -> torch.Tensor:
    """``(L + 1,)`` in ``dtype`` on ``device``: the host grid of ``csf_jax.sde.noise_levels``
    (geometric from ``sigma_t(1)`` to ``sigma_t(t_min)``, then 0; float64 numpy) rounded once, as
    csf_jax does."""
    sampler = config.sampler
    s = sampler.sigma_max
    levels = host_noise_levels(sampler.reverse_steps, marginal_std_host(1.0, s),
                               marginal_std_host(sampler.t_min, s))
    return torch.tensor(levels, dtype=dtype, device=device)


def ancestral_schedule(config: CSFConfig, dtype: torch.dtype = DTYPE,
                       device: torch.device | str = "cpu") -> AncestralSchedule:
    """The noise levels of ``csf_jax.filters.csf.ancestral_sample`` and their per-level scalars,
    on ``device``."""
    sampler, base = config.sampler, config.inflation.base
    sigma_max, guidance = sampler.sigma_max, sampler.guidance
    levels = noise_levels(config, dtype, device)
    sigma, sigma_next = levels[:-1], levels[1:]
    t_score = inflated_time(time_of_std(sigma, sigma_max), base, sigma_max)
    rho = torch.square(sigma_next / sigma)
    var = (torch.square(sigma) - torch.square(sigma_next)) * rho
    first = torch.arange(sampler.reverse_steps, device=device) == 0
    sigma_start = marginal_std(torch.tensor(1.0, dtype=dtype, device=device), sigma_max)
    return AncestralSchedule(sigma, t_score, rho, torch.sqrt(var), first, sigma_start, base,
                             guidance.proposals, sigma_max, _adaptive(config),
                             config.prior.encode_particles, guidance.proposal_df)


def _adaptive(config: CSFConfig) -> AdaptiveInflation | None:
    """The adaptive-inflation settings of ``config``, or None for a fixed inflation."""
    inflation = config.inflation
    if not inflation.adaptive:
        return None
    return AdaptiveInflation(inflation.threshold, inflation.max, inflation.statistic)


def adaptive_inflation(problem: TorchProblem, prior_ens: torch.Tensor, y: torch.Tensor,
                       base: float, settings: AdaptiveInflation,
                       iterations: int = 60) -> torch.Tensor:
    """``csf_jax.inflation.adaptive_inflation`` (0-d tau) for ``prior_ens (N, d)``, ``y (m,)``:
    the innovation ``e = y - mean h(x_i)``, ``v = var h(x_i) + r + base^2 g``, ``g`` the mean squared
    Jacobian rows; the median statistic or the chi-square one (bisection in ``log s``)."""
    hx = prior_ens ** 3  # every TorchProblem observes x^3
    jac = problem.observe_jacobian(prior_ens)
    g = torch.sum(jac * jac, -1).mean(0)
    e2 = torch.square(y - hx.mean(0))
    v = hx.var(0, correction=0) + problem.gaussian_std ** 2 + base ** 2 * g
    m = e2.shape[-1]
    zero = torch.zeros((), dtype=prior_ens.dtype, device=prior_ens.device)
    if settings.statistic == "median":
        votes = torch.sum(e2 / v > 1.0 + settings.threshold * math.sqrt(2.0))
        s = torch.quantile(torch.clamp((e2 - v) / g, min=0.0), 0.5)  # the midpoint, as jnp.median
        s = torch.where(votes > m / 2, torch.clamp(s, max=settings.max_tau ** 2), zero)
        return torch.sqrt(base ** 2 + s)

    def stat(s):
        return torch.sum(e2 / (v + s * g))

    surprised = stat(zero) > m + settings.threshold * math.sqrt(2.0 * m)
    lo = torch.log(torch.tensor(1e-8, dtype=v.dtype, device=v.device))
    hi = torch.log(torch.tensor(settings.max_tau ** 2, dtype=v.dtype, device=v.device))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        too_small = stat(torch.exp(mid)) > m
        lo, hi = torch.where(too_small, mid, lo), torch.where(too_small, hi, mid)
    return torch.sqrt(base ** 2 + torch.where(surprised, torch.exp(hi), zero))


def step_schedule(sched, problem: TorchProblem, prior_ens: torch.Tensor, y: torch.Tensor,
                  guide: torch.Tensor):
    """This filter step's schedule (:class:`AncestralSchedule` or :class:`Schedule`): ``sched``
    itself (fixed inflation), or with the adaptive tau (0-d; the base where ``guide`` is 0, ``y``
    not assimilated) and the score times it moves (``csf_jax.filters.csf.step_inflation``).
    ``torch.where`` on ``guide``, not a Python branch: no device-to-host read per filter step."""
    if sched.adaptive is None:
        return sched
    adaptive = adaptive_inflation(problem, prior_ens, y, sched.inflation, sched.adaptive)
    tau = torch.where(guide > 0, adaptive, sched.inflation)
    t = (time_of_std(sched.sigma, sched.sigma_max) if isinstance(sched, AncestralSchedule)
         else sched.t)
    return sched._replace(t_score=inflated_time(t, tau, sched.sigma_max), inflation=tau)


def uses_kalman(config: CSFConfig) -> bool:
    """Whether ``config`` selects the ancestral sampler with Kalman guidance
    (``csf_jax.filters.csf.uses_kalman``)."""
    return config.sampler.guidance.mode == "kalman"


def schedule(config: CSFConfig, dtype: torch.dtype = DTYPE, device: torch.device | str = "cpu"):
    """The configured sampler's schedule: :class:`AncestralSchedule` for ``"kalman"``, else the
    Euler-Maruyama :class:`Schedule`; tensors in ``dtype`` (float64 only for tests: the port is
    float32 like csf_jax by default) on ``device``. With ``InflationConfig.adaptive``
    :func:`filter_step` sets the inflation per filter step (:func:`step_schedule`)."""
    make = ancestral_schedule if uses_kalman(config) else em_schedule
    return make(config, dtype, device)


# --------------------------------------------------------------------------------------------
# Networks
# --------------------------------------------------------------------------------------------

class MultiHeadAttention(nn.Module):
    """Flax's ``MultiHeadDotProductAttention`` (no dropout): per-head q/k/v projections of width
    ``hidden``, softmax(q k^T / sqrt(head_dim)) v, output projection.

    Uses ``F.scaled_dot_product_attention`` (the fused CPU kernel does not keep the N x N weights).
    """

    def __init__(self, features: int, hidden: int, heads: int):
        super().__init__()
        self.heads = heads
        self.query = nn.Linear(features, hidden)
        self.key = nn.Linear(features, hidden)
        self.value = nn.Linear(features, hidden)
        self.out = nn.Linear(hidden, hidden)

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., L, H) -> (..., heads, L, H / heads)``."""
        return x.unflatten(-1, (self.heads, -1)).transpose(-3, -2)

    def forward(self, q_in: torch.Tensor, kv_in: torch.Tensor) -> torch.Tensor:
        """``q_in (..., Lq, F)``, ``kv_in (..., Lk, F)`` -> ``(..., Lq, H)``."""
        q = self._split(self.query(q_in))
        k, v = self._split(self.key(kv_in)), self._split(self.value(kv_in))
        o = F.scaled_dot_product_attention(q, k, v)
        return self.out(o.transpose(-3, -2).flatten(-2))


class SetEncoder(nn.Module):
    """``csf_jax.networks.SetEncoder``: ensemble ``(..., N, d)`` -> code ``(..., C)``."""

    def __init__(self, config: NetworkConfig, dim: int):
        super().__init__()
        h = config.hidden
        self.config = config
        self.embed = nn.Linear(3 * dim, h)
        blocks = range(config.blocks)
        self.sab_attn = nn.ModuleList(MultiHeadAttention(h, h, config.heads) for _ in blocks)
        self.sab_norm = nn.ModuleList(nn.LayerNorm(h, eps=FLAX_LN_EPS) for _ in blocks)
        self.pma_seed = nn.Parameter(torch.zeros(h))
        self.pma_attn = MultiHeadAttention(h, h, config.heads)
        self.pma_norm = nn.LayerNorm(h, eps=FLAX_LN_EPS)
        self.head_hidden = nn.Linear(h, h)
        self.head_out = nn.Linear(h, config.code_dim)

    def forward(self, ensemble: torch.Tensor) -> torch.Tensor:
        """``ensemble (..., N, d)`` -> code ``(..., C)``."""
        mean = ensemble.mean(-2, keepdim=True)
        var = (ensemble - mean).square().mean(-2, keepdim=True)
        stats = torch.cat([mean, var], -1).expand(ensemble.shape[:-1] + (2 * ensemble.shape[-1],))
        h = self.embed(torch.cat([ensemble, stats], -1))
        for attn, norm in zip(self.sab_attn, self.sab_norm):
            h = norm(h + attn(h, h))
        query = self.pma_seed.expand(h.shape[:-2] + (1, h.shape[-1]))
        keys = torch.cat([query, h], -2) if self.config.pma_seed_in_keys else h
        z = self.pma_norm(self.pma_attn(query, keys)[..., 0, :])
        return self.head_out(F.silu(self.head_hidden(z)))


class ScoreNet(nn.Module):
    """``csf_jax.networks.ScoreNet``: ``s(x, t; c) = MLP(x, t, c) / sigma_t`` for a scalar t and a
    shared code c; the condition term ``Dense_cond([temb(log sigma_t), c])`` is computed once and
    broadcast over the particles."""

    def __init__(self, config: NetworkConfig, dim: int):
        super().__init__()
        hs, nf = config.score_hidden, config.fourier_features
        self.sigma_max = config.sigma_max
        self.register_buffer("frequencies",
                             torch.from_numpy(fourier_frequencies(nf, config.fourier_scale)))
        self.cond_in = nn.Linear(2 * nf + config.code_dim, hs)
        self.x_in = nn.Linear(dim, hs, bias=False)
        self.residual = nn.ModuleList(nn.Linear(hs, hs) for _ in range(config.score_layers - 1))
        self.out = nn.Linear(hs, dim)

    def condition(self, sigma: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """``Dense_cond([temb(log sigma), code])``: sigma 0-d, code ``(C,)`` -> ``(hidden,)``."""
        angles = 2.0 * math.pi * torch.log(sigma)[..., None] * self.frequencies
        return self.cond_in(torch.cat([torch.sin(angles), torch.cos(angles), code], -1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """``x (N, d)``, ``t`` 0-d, ``code (C,)`` -> score ``(N, d)``."""
        sigma = marginal_std(t, self.sigma_max)
        h = self.x_in(x) + self.condition(sigma, code)
        for layer in self.residual:
            h = h + layer(F.silu(h))
        return self.out(F.silu(h)) / sigma


class Networks(NamedTuple):
    """The two torch modules of the learned prior (eval mode, ``requires_grad=False``) and the
    network's ``NetworkConfig.base``: "none" (the net is the whole score) or "gaussian" (the
    ensemble's Gaussian score plus the net's correction, :func:`prior_score`)."""

    encoder: SetEncoder
    score: ScoreNet
    base: str = "none"


class GaussianBase(NamedTuple):
    """``csf_jax.prior.ResidualContext``: the code ``(C,)`` and the prior ensemble's mean ``(d,)``
    and floored sample covariance ``(d, d)``."""

    code: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor


def _sample_moments(ensemble: torch.Tensor, jitter: float):
    """``csf_jax.covariance.estimate`` (sample estimator): mean ``(d,)``, sample covariance ``(d, d)`` and the floor
    ``jitter * trace(C) / d + sqrt(tiny)`` of ``ensemble (N, d)``."""
    n, d = ensemble.shape
    mean = ensemble.mean(0)
    centred = ensemble - mean
    cov = centred.T @ centred / max(n - 1, 1)
    return mean, cov, jitter * torch.trace(cov) / d + torch.finfo(ensemble.dtype).tiny ** 0.5


def ensemble_moments(ensemble: torch.Tensor, jitter: float = 1e-6):
    """``csf_jax.prior.ensemble_moments``: mean and ``C + floor I`` of ``ensemble (N, d)``."""
    mean, cov, floor = _sample_moments(ensemble, jitter)
    eye = torch.eye(ensemble.shape[-1], dtype=ensemble.dtype, device=ensemble.device)
    return mean, cov + floor * eye


def condition(nets: Networks, prior_ens: torch.Tensor, encode_particles: int | None):
    """The prior's context of one filter step: the code of the first ``encode_particles`` particles,
    with a Gaussian base also the moments of all of them (a :class:`GaussianBase`)."""
    code = nets.encoder(prior_ens[:encode_particles])
    if nets.base == "gaussian":
        return GaussianBase(code, *ensemble_moments(prior_ens))
    return code


def prior_score(nets: Networks, x: torch.Tensor, t: torch.Tensor, ctx) -> torch.Tensor:
    """``csf_jax.prior.learned_prior``'s score at ``x (N, d)``, time ``t`` (0-d): the net alone, or
    with a Gaussian base ``-(C + sigma^2 I)^{-1} (x - m)`` plus the net's output at
    ``z = (x - m) / s`` rescaled by ``sigma / s``, ``s = sqrt(diag C + sigma^2)``."""
    if not isinstance(ctx, GaussianBase):
        return nets.score(x, t, ctx)
    sigma = marginal_std(t, nets.score.sigma_max)
    spread = torch.sqrt(torch.diagonal(ctx.cov) + sigma ** 2)
    correction = nets.score((x - ctx.mean) / spread, t, ctx.code) * (sigma / spread)
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    chol = torch.linalg.cholesky_ex(ctx.cov + sigma ** 2 * eye).L
    return -torch.cholesky_solve((x - ctx.mean).T, chol).T + correction


def _t(a) -> torch.Tensor:
    """A float32 torch copy of a numpy/jax array (on the CPU: :func:`flax_to_torch` loads the
    weights there and moves the modules to their device once)."""
    return torch.tensor(np.asarray(a, dtype=np.float32))


def _load_dense(linear: nn.Linear, p: dict) -> None:
    """Flax ``Dense`` (kernel ``(in, out)``) into ``nn.Linear`` (weight ``(out, in)``)."""
    linear.weight.copy_(_t(p["kernel"]).T)
    if linear.bias is not None:
        linear.bias.copy_(_t(p["bias"]))


def _load_attention(mha: MultiHeadAttention, p: dict) -> None:
    """Flax MHA: q/k/v kernels ``(in, heads, head_dim)``, biases ``(heads, head_dim)``, out kernel
    ``(heads, head_dim, out)``; heads are the major axis of torch's flattened hidden axis."""
    for name in ("query", "key", "value"):
        kernel = _t(p[name]["kernel"])
        getattr(mha, name).weight.copy_(kernel.flatten(1).T)
        getattr(mha, name).bias.copy_(_t(p[name]["bias"]).flatten())
    mha.out.weight.copy_(_t(p["out"]["kernel"]).flatten(0, 1).T)
    mha.out.bias.copy_(_t(p["out"]["bias"]))


def _load_layer_norm(norm: nn.LayerNorm, p: dict) -> None:
    norm.weight.copy_(_t(p["scale"]))
    norm.bias.copy_(_t(p["bias"]))


def flax_to_torch(params: dict, config: NetworkConfig, dim: int | None = None,
                  device: torch.device | str = "cpu") -> Networks:
    """Torch modules holding the csf_jax parameters ``{"encoder": ..., "score": ...}``.

    Args:
      params: ``csf_jax.init_params`` output (or trained equivalent); leaves may be jax or numpy.
      config: the ``NetworkConfig`` the params were built with.
      dim: state dimension d (default: read off the score net's output layer).
      device: where every parameter and buffer lives (float32).
    """
    enc_p, score_p = params["encoder"]["params"], params["score"]["params"]
    dim = int(np.shape(score_p["out"]["kernel"])[-1]) if dim is None else dim
    encoder, score = SetEncoder(config, dim), ScoreNet(config, dim)
    with torch.no_grad():
        _load_dense(encoder.embed, enc_p["embed"])
        for i in range(config.blocks):
            _load_attention(encoder.sab_attn[i], enc_p[f"sab{i}_attn"])
            _load_layer_norm(encoder.sab_norm[i], enc_p[f"sab{i}_norm"])
        encoder.pma_seed.copy_(_t(enc_p["pma_seed"]))
        _load_attention(encoder.pma_attn, enc_p["pma_attn"])
        _load_layer_norm(encoder.pma_norm, enc_p["pma_norm"])
        _load_dense(encoder.head_hidden, enc_p["head_hidden"])
        _load_dense(encoder.head_out, enc_p["head_out"])
        _load_dense(score.cond_in, score_p["cond_in"])
        _load_dense(score.x_in, score_p["x_in"])
        for i, layer in enumerate(score.residual):
            _load_dense(layer, score_p[f"residual{i}"])
        _load_dense(score.out, score_p["out"])
    for module in (encoder, score):
        module.eval().requires_grad_(False).to(device)
    return Networks(encoder, score, config.base)


# --------------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------------

class TorchProblem(NamedTuple):
    """The parts of a ``StateSpaceModel`` the online step needs, batched over particles. Every
    problem here observes ``h(x) = x^3`` per coordinate (m = d).

    drift: ``x (N, d) -> (N, d)``.  loglik: ``(y (m,), x0 (..., d)) -> (...)`` up to a constant.
    loglik_grad: ``(y (m,), x0 (N, d)) -> (N, d)``, its gradient in ``x0`` (closed form).
    observe_jacobian: ``x (N, d) -> (N, m, d)``, ``dh/dx`` (dense, as ``jax.jacfwd`` gives it).
    weight: ``(y (m,), x (N, d)) -> (N, m)``, the guidance's curvature weights at ``y - h(x)``
    (``ObservationNoise.curvature``).
    gaussian_std: ``ObservationNoise.gaussian_std``, the noise's Gaussian stand-in (the adaptive
    inflation's ``r``).
    device: where the problem's constant tensors live (the correlated cubic sensor's coupling
    matrix); the callables expect their inputs there.
    """

    name: str
    dim: int
    process_std: float
    drift: Callable[[torch.Tensor], torch.Tensor]
    loglik: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    loglik_grad: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    observe_jacobian: Callable[[torch.Tensor], torch.Tensor]
    weight: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    gaussian_std: float
    device: torch.device = torch.device("cpu")


class CubicSensor(NamedTuple):
    """``y = x^3 + w`` with i.i.d. noise w: the likelihood pieces of :class:`TorchProblem`."""

    loglik: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    loglik_grad: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    observe_jacobian: Callable[[torch.Tensor], torch.Tensor]
    weight: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _noise_loglik(kind: str, scale: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """Residual ``(..., m) -> (...)``: Gaussian ``-0.5 r^2 / scale^2``, Cauchy
    ``-log1p((r / scale)^2)``, summed over the coordinates."""
    if kind == "gaussian":
        inv_var = 1.0 / scale**2
        return lambda r: -0.5 * inv_var * (r * r).sum(-1)
    return lambda r: -torch.log1p((r / scale) ** 2).sum(-1)


def _noise_score(kind: str, scale: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """Residual ``(..., m) -> (..., m)``: the derivative of :func:`_noise_loglik`'s terms,
    ``-r / scale^2`` (Gaussian) or ``-2 r / (scale^2 + r^2)`` (Cauchy)."""
    if kind == "gaussian":
        inv_var = 1.0 / scale**2
        return lambda r: -inv_var * r
    return lambda r: -2.0 * r / (scale**2 + r * r)


def _noise_weight(kind: str, scale: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """Residual ``(..., m) -> (..., m)``: the guidance's curvature weights, ``1 / scale^2``
    (Gaussian) or the reweighted least-squares ``2 / (scale^2 + r^2)`` (Cauchy)."""
    if kind == "gaussian":
        inv_var = 1.0 / scale**2
        return lambda r: torch.full_like(r, inv_var)
    return lambda r: 2.0 / (scale**2 + r * r)


def _cubic_sensor(kind: str, scale: float) -> CubicSensor:
    """The likelihood of ``y = x^3 + w``: ``grad = -h'(x) * noise_score(y - x^3)`` with
    ``h'(x) = 3 x^2``; the Jacobian is ``diag(3 x^2)``; curvature weights of ``y - x^3``."""
    loglik, score = _noise_loglik(kind, scale), _noise_score(kind, scale)
    weight = _noise_weight(kind, scale)
    return CubicSensor(lambda y, x0: loglik(y - x0**3),
                       lambda y, x0: -3.0 * x0 * x0 * score(y - x0**3),
                       lambda x: torch.diag_embed(3.0 * x * x), lambda y, x: weight(y - x**3))


def _gaussian_std(c: CubicConfig) -> float:
    """``ObservationNoise.gaussian_std`` of the csf_jax problem (Cauchy: a derived constant)."""
    return float(build(c).obs_noise.gaussian_std)


def _coupling(dim: int, device: torch.device) -> dict[torch.dtype, torch.Tensor]:
    """``A^T`` of ``csf_jax.problems.cubic.coupling_matrix(dim)`` on ``device``, ``(d, d)``, in
    float32 and float64 (rounded from numpy's float64 once, as ``jnp.asarray`` does), so that the
    drift indexes a constant instead of converting one per call."""
    a_t = torch.from_numpy(coupling_matrix(dim).T.copy())
    return {dtype: a_t.to(device=device, dtype=dtype) for dtype in (torch.float32, torch.float64)}


def _cubic(c: CubicConfig, device: torch.device) -> TorchProblem:
    a_t = _coupling(c.dim, device) if c.correlated else None

    def drift(x):
        f = torch.cos(x) if a_t is None else x @ a_t[x.dtype] + torch.cos(x)
        return x + f * c.dt

    kind = "corr" if c.correlated else "indep"
    name = "cauchy" if c.noise == "cauchy" else f"cubic{c.dim}_{kind}"
    return TorchProblem(name, c.dim, c.process_std, drift, *_cubic_sensor(c.noise, c.obs_scale),
                        _gaussian_std(c), device)


def _well(c: WellConfig, device: torch.device) -> TorchProblem:
    def grad_v(x):
        """V' for ``V = C (x^2 - 1)^2`` (times ``(x - 0.5)^2`` for the triple well)."""
        dv = 4.0 * c.C * x * (x * x - 1.0)
        if c.wells == "triple":
            dv = dv * (x - 0.5) ** 2 + 2.0 * c.C * (x * x - 1.0) ** 2 * (x - 0.5)
        return dv

    def drift(x):
        step = -grad_v(x) * c.dt
        return x + step if c.include_state else step

    return TorchProblem(f"{c.wells}_well", 1, math.sqrt(c.dt) * c.process_std, drift,
                        *_cubic_sensor("gaussian", c.obs_std), c.obs_std, device)


def model_config(config: CSFConfig, name: str, **overrides) -> CSFConfig:
    """``config`` as csf_jax's filter step applies it to the problem ``name``: with the ancestral
    sampler and no ``proposal_df`` of its own, the proposals take the heavy tails of the
    problem's observation noise (``csf_jax.ssm.tail_df``: Cauchy noise, 1 dof)."""
    df = tail_df(get_problem(name, **overrides))
    guidance = config.sampler.guidance
    if guidance.mode != "kalman" or guidance.proposal_df is not None or df is None:
        return config
    sampler = dataclasses.replace(config.sampler,
                                  guidance=dataclasses.replace(guidance, proposal_df=df))
    return dataclasses.replace(config, sampler=sampler)


def torch_problem(name: str, *, device: torch.device | str = "cpu", **overrides) -> TorchProblem:
    """The torch version of ``csf_jax.problems.get(name, **overrides)`` (constants read from the
    same frozen configs), its constant tensors on ``device``."""
    cfg, device = problem_config(name, **overrides), torch.device(device)
    return _well(cfg, device) if isinstance(cfg, WellConfig) else _cubic(cfg, device)


# --------------------------------------------------------------------------------------------
# The online step: Euler-Maruyama with DPS guidance
# --------------------------------------------------------------------------------------------

def guidance_displacement(config: GuidanceConfig, grad: torch.Tensor, loglik: torch.Tensor,
                          g2dt: torch.Tensor, noise_scale: torch.Tensor) -> torch.Tensor:
    """``csf_jax.guidance.guidance_displacement``: grad ``(N, d)``, loglik ``(N,)`` -> ``(N, d)``.

    "clipped" takes each row's squared norm as a matrix product with a ones vector ``(d, 1)``, not
    a fused reduction: Inductor's CPU backend (torch 2.13) miscompiles the reduce-then-rescale
    kernel when d is below the SIMD width (it vectorises over 16 particles but keeps one
    particle's step for all 16: O(1) errors at d = 10 with a Gaussian-base prior). The product's
    extern kernel keeps the step in memory; the values are the same up to summation order.
    """
    if config.mode == "none":
        return torch.zeros_like(grad)
    step = config.scale * g2dt * grad
    if config.mode == "raw":
        return step
    if config.mode == "normalized":
        return step / torch.sqrt(torch.clamp(-2.0 * loglik, min=1e-12))[:, None]
    cap = config.clip * noise_scale * math.sqrt(grad.shape[-1])
    ones = torch.ones((step.shape[-1], 1), dtype=step.dtype, device=step.device)
    norm = torch.sqrt(torch.square(step) @ ones)
    return step * torch.clamp(cap / torch.clamp(norm, min=1e-30), max=1.0)


def dps_gradient(score_net: Callable, loglik: Callable, y: torch.Tensor, x: torch.Tensor,
                 t: torch.Tensor, var: torch.Tensor, code):
    """Prior score, DPS gradient ``d/dx log p(y | x + var s(x))`` and that log-likelihood.

    score_net: ``(x, t, code) -> (N, d)``, a :class:`ScoreNet` or :func:`prior_score` bound to its
    networks; code: its context.

    ``x (N, d)`` -> ``(score (N, d), grad (N, d), loglik (N,))``, one backward pass through the
    score net (particles are independent, so the gradient of the sum is every particle's own).

    Under ``torch.compile`` it is ``torch.func.grad`` (score and log-likelihood as auxiliary
    outputs): a function transform, which needs no ``requires_grad_`` on a leaf (a graph break for
    Dynamo) and which Dynamo traces into the same graph as the rest of the reverse step. Eager, it
    is the tape (``requires_grad_`` and ``torch.autograd.grad``), as a PyTorch user writes it:
    ``torch.func.grad``'s per-op wrapping made an eager DPS step about 1.6 times slower (N = 256,
    d = 10, one thread). Both run the same backward formulas.
    """
    if torch.compiler.is_compiling():

        def objective(x):
            s = score_net(x, t, code)
            ll = loglik(y, x + var * s)
            return ll.sum(), (s, ll)

        grad, (s, ll) = torch.func.grad(objective, has_aux=True)(x)
        return s, grad, ll
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        s = score_net(xg, t, code)
        ll = loglik(y, xg + var * s)
        (grad,) = torch.autograd.grad(ll.sum(), xg)
    return s.detach(), grad, ll.detach()


def make_em_step(nets: Networks, problem: TorchProblem, config: CSFConfig) -> Callable:
    """The Euler-Maruyama step ``x <- x + g^2 dt (s + guide * guidance) + noise_on g sqrt(dt) eps``.

    Returns ``step(x (N, d), y (m,), code (C,), t, var, g2dt, noise_scale, noise_on, guide,
    eps (N, d)) -> x (N, d)``, the scalars 0-d tensors.
    """
    score_net, loglik = functools.partial(prior_score, nets), problem.loglik
    guidance = config.sampler.guidance

    def step(x, y, code, t, var, g2dt, noise_scale, noise_on, guide, eps):
        if guidance.mode == "none":
            s, disp = score_net(x, t, code), 0.0
        else:
            s, grad, ll = dps_gradient(score_net, loglik, y, x, t, var, code)
            disp = guide * guidance_displacement(guidance, grad, ll, g2dt, noise_scale)
        return x + g2dt * s + disp + noise_on * noise_scale * eps

    return step


# --------------------------------------------------------------------------------------------
# The online step: the ancestral sampler with Kalman guidance
# --------------------------------------------------------------------------------------------

def gaussian_precision(ensemble: torch.Tensor, inflation: float = 0.0,
                       jitter: float = 1e-6) -> torch.Tensor:
    """``csf_jax.prior.gaussian_precision``: ``(C + (inflation^2 + floor) I)^{-1}`` of the sample
    covariance C, ``floor = jitter * trace(C) / d + sqrt(tiny)``; ``ensemble (N, d)`` -> ``(d, d)``.
    """
    _, cov, floor = _sample_moments(ensemble, jitter)
    eye = torch.eye(ensemble.shape[-1], dtype=ensemble.dtype, device=ensemble.device)
    chol = torch.linalg.cholesky_ex(cov + (inflation ** 2 + floor) * eye).L
    # csf_jax solves for the rows (cho_solve over the batch of eye's rows): the transpose of ours
    return torch.cholesky_solve(eye, chol).mT


def kalman_tweedie(problem: TorchProblem, y: torch.Tensor, x0_hat: torch.Tensor,
                   prior_precision: torch.Tensor, u: torch.Tensor, guide: torch.Tensor,
                   iterations: int):
    """``csf_jax.guidance.kalman_tweedie``: ``iterations`` Gauss-Newton steps per particle,
    ``u <- u + A^{-1} (P^{-1} (x0_hat - u) + guide grad log p(y | u))``,
    ``A = P^{-1} + guide J^T diag(W(u)) J``, ``J = dh/du``.

    x0_hat, u: ``(N, d)`` (u: the previous level's solution).  prior_precision: ``(d, d)``
    ``P^{-1}``.  guide: 0-d.  Returns ``(u (N, d), chol (N, d, d))``, ``chol chol^T = A`` at the
    last linearisation point.
    """
    for _ in range(iterations):
        jac = problem.observe_jacobian(u)
        grad = problem.loglik_grad(y, u)
        chol = torch.linalg.cholesky_ex(
            prior_precision + guide * (jac.mT * problem.weight(y, u)[..., None, :]) @ jac).L
        rhs = (x0_hat - u) @ prior_precision.mT + guide * grad
        u = u + torch.cholesky_solve(rhs[..., None], chol)[..., 0]
    return u, chol


def resample_posterior(loglik: Callable, y: torch.Tensor, x0_hat: torch.Tensor,
                       prior_precision: torch.Tensor, u: torch.Tensor, chol: torch.Tensor,
                       guide: torch.Tensor, z: torch.Tensor,
                       gumbel: torch.Tensor | None, df: int | None = None) -> torch.Tensor:
    """``csf_jax.guidance.resample_posterior``: one draw per particle of
    ``N(x_0; x0_hat, P) p(y | x_0)`` by importance resampling of K Laplace candidates
    ``u + chol^{-T} z``.

    x0_hat, u: ``(N, d)``.  chol: ``(N, d, d)``.  z: ``(K, N, d)`` standard normal, or Student-t
    with ``df`` degrees of freedom (:func:`student_t`).  gumbel: ``(K, N)`` standard Gumbel (the
    categorical draw is ``argmax(log_w + gumbel)``, as ``jax.random.categorical``), or None for
    K = 1 (the Laplace draw itself). Returns ``(N, d)``.
    """
    cand = u + torch.linalg.solve_triangular(chol.mT, z[..., None], upper=True)[..., 0]
    if gumbel is None:
        return cand[0]
    if df is None:
        log_q = -0.5 * torch.sum(z * z, -1)
    else:
        log_q = -0.5 * (df + 1.0) * torch.sum(torch.log1p(z * z / df), -1)
    diff = cand - x0_hat
    log_w = (-0.5 * torch.einsum("knd,de,kne->kn", diff, prior_precision, diff)
             + guide * loglik(y, cand) - log_q)
    pick = torch.argmax(log_w + gumbel, 0)
    return torch.take_along_dim(cand, pick[None, :, None], 0)[0]


def student_t(normals: torch.Tensor) -> torch.Tensor:
    """``csf_jax.guidance.student_t``: ``normals (df + 1, ...)`` standard normal ->
    ``g_0 / sqrt(mean(g_1^2 .. g_df^2))``, Student-t with df degrees of freedom."""
    return normals[0] / torch.sqrt(torch.mean(normals[1:] * normals[1:], 0))


def make_ancestral_step(nets: Networks, problem: TorchProblem, config: CSFConfig) -> Callable:
    """One level of ``csf_jax.filters.csf.ancestral_sample``: Tweedie, Kalman guidance,
    importance resampling, VE bridge.

    Returns ``step(x (N, d), u (N, d), first, y (m,), code (C,), precision (d, d), t, sigma, rho,
    noise_scale, guide, z_post (K, N, d), gumbel (K, N) or None, z_bridge (N, d)) -> (x, u)``, the
    scalars 0-d tensors (``first`` bool: start the Fisher scoring from ``x0_hat``).
    """
    score_net, guidance = functools.partial(prior_score, nets), config.sampler.guidance

    def step(x, u, first, y, code, precision, t, sigma, rho, noise_scale, guide, z_post, gumbel,
             z_bridge):
        x0_hat = x + sigma ** 2 * score_net(x, t, code)
        u = torch.where(first, x0_hat, u)
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
        prior_precision = precision + eye / sigma ** 2
        u, chol = kalman_tweedie(problem, y, x0_hat, prior_precision, u, guide,
                                 guidance.iterations)
        x0 = resample_posterior(problem.loglik, y, x0_hat, prior_precision, u, chol, guide, z_post,
                                gumbel if guidance.proposals > 1 else None, guidance.proposal_df)
        return rho * x + (1.0 - rho) * x0 + noise_scale * z_bridge, u

    return step


# --------------------------------------------------------------------------------------------
# Both samplers
# --------------------------------------------------------------------------------------------

def make_reverse_step(nets: Networks, problem: TorchProblem, config: CSFConfig,
                      compile: bool = False, mode: str | None = None,
                      backend: str = "inductor") -> Callable:
    """The configured sampler's per-reverse-step function: :func:`make_ancestral_step` for
    ``config.sampler.guidance.mode == "kalman"``, else :func:`make_em_step`. ``compile=True`` wraps
    the same function in :func:`compile_step` with the ``torch.compile`` ``mode`` and
    ``backend``."""
    make = make_ancestral_step if uses_kalman(config) else make_em_step
    step = make(nets, problem, config)
    return compile_step(step, mode, backend) if compile else step


COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""The ``mode`` values of ``torch.compile`` that :func:`compile_step` accepts."""


def compile_step(step: Callable, mode: str | None = None, backend: str = "inductor") -> Callable:
    """``torch.compile(step, dynamic=False, fullgraph=True, mode=mode)``: the whole reverse step
    in one graph (``fullgraph``: a graph break raises instead of splitting the step), one
    compilation per input shape and none per reverse step (the per-step scalars are 0-d tensors).
    Compilation happens at the first call and raises there if Dynamo or Inductor fails.

    mode: None or "default"; "reduce-overhead" replays the step as a CUDA graph on a GPU (kernel
    launches dominate a step at these sizes) and compiles as "default" on a CPU; "max-autotune"
    and "max-autotune-no-cudagraphs" as in ``torch.compile``. With CUDA graphs the outputs live in
    buffers that the next replay overwrites, and the sampler feeds each step's output to the next:
    the wrapper marks each call as a new step (``torch.compiler.cudagraph_mark_step_begin``) and
    returns clones (one ``(N, d)`` copy per output, negligible against the step).

    backend: ``torch.compile``'s; ``mode`` goes to Inductor only (another backend, e.g. the tests'
    "aot_eager", which traces the same graph without generating code, runs the step as traced).
    """
    if mode not in (None, *COMPILE_MODES):
        raise ValueError(f"mode must be None or one of {COMPILE_MODES}, got {mode!r}")
    options = {"mode": mode} if backend == "inductor" else {}
    compiled = torch.compile(step, dynamic=False, fullgraph=True, backend=backend, **options)
    if mode not in ("reduce-overhead", "max-autotune"):  # the modes with CUDA graphs
        return compiled

    def run(*args):
        torch.compiler.cudagraph_mark_step_begin()
        out = compiled(*args)
        return tuple(o.clone() for o in out) if isinstance(out, tuple) else out.clone()

    return run


class AncestralNoise(NamedTuple):
    """The draws of the ancestral sampler's L levels (float32).

    post: ``(L, K, N, d)`` standard normal, the Laplace candidates.  gumbel: ``(L, K, N)`` standard
    Gumbel for the resampling pick, or None when K = 1.  bridge: ``(L, N, d)`` standard normal.
    """

    post: torch.Tensor
    gumbel: torch.Tensor | None
    bridge: torch.Tensor


class StepNoise(NamedTuple):
    """The random draws of one filter step, for injection (float32).

    prop: ``(N, d)`` standard normal process noise.  x_init: ``(N, d)`` standard normal, scaled by
    sigma_1 to start the reverse process (added to the prior ensemble by the ancestral sampler).
    eps: the reverse steps' draws, or None to draw them step by step: Euler-Maruyama ``(L, N, d)``
    standard normal, ancestral an :class:`AncestralNoise`.
    """

    prop: torch.Tensor
    x_init: torch.Tensor
    eps: torch.Tensor | AncestralNoise | None


def _em_call(step: Callable, sched: Schedule, l: int, x, y, code, guide, eps) -> torch.Tensor:
    """``step`` at reverse time ``l`` of the Euler-Maruyama schedule."""
    return step(x, y, code, sched.t_score[l], sched.var[l], sched.g2dt[l], sched.noise_scale[l],
                sched.noise_on[l], guide, eps)


def posterior_sample(step: Callable, sched: Schedule, x_init: torch.Tensor, y: torch.Tensor,
                     code: torch.Tensor, guide: torch.Tensor,
                     eps: torch.Tensor | None = None,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Euler-Maruyama: the L reverse steps from ``x_init (N, d)`` (already scaled); returns
    ``(N, d)``.

    eps: ``(L, N, d)`` injected noise, or None to draw it step by step from ``generator`` (on
    ``x_init``'s device).
    """
    x = x_init
    for l in range(sched.t.shape[0]):
        e = eps[l] if eps is not None else torch.randn(x.shape, generator=generator, dtype=x.dtype,
                                                       device=x.device)
        x = _em_call(step, sched, l, x, y, code, guide, e)
    return x


def draw_level(shape: tuple, proposals: int, generator: torch.Generator | None = None,
               dtype: torch.dtype = DTYPE, df: int | None = None,
               device: torch.device | str = "cpu"):
    """One level's ancestral draws for ``shape = (N, d)`` on ``device`` (``generator``, if given,
    must live there too): ``(z_post (K, N, d), gumbel (K, N) or None, z_bridge (N, d))``;
    ``z_post`` standard normal, or Student-t with ``df`` degrees of freedom; Gumbel as ``-log`` of
    a standard exponential."""
    opts = {"dtype": dtype, "device": device}
    if df is None:
        z_post = torch.randn((proposals, *shape), generator=generator, **opts)
    else:
        z_post = student_t(torch.randn((df + 1, proposals, *shape), generator=generator, **opts))
    gumbel = None
    if proposals > 1:
        exp = torch.empty((proposals, shape[0]), **opts).exponential_(generator=generator)
        gumbel = -torch.log(exp)
    return z_post, gumbel, torch.randn(shape, generator=generator, **opts)


def _level_noise(noise: AncestralNoise, l: int):
    """Level ``l`` of injected draws, as :func:`draw_level` returns them."""
    return noise.post[l], None if noise.gumbel is None else noise.gumbel[l], noise.bridge[l]


def _ancestral_call(step: Callable, sched: AncestralSchedule, l: int, x, u, y, code, precision,
                    guide, level_noise):
    """``step`` at level ``l`` of the ancestral schedule; returns ``(x, u)``."""
    return step(x, u, sched.first[l], y, code, precision, sched.t_score[l], sched.sigma[l],
                sched.rho[l], sched.noise_scale[l], guide, *level_noise)


def ancestral_sample(step: Callable, sched: AncestralSchedule, x_init: torch.Tensor,
                     y: torch.Tensor, code: torch.Tensor, precision: torch.Tensor,
                     guide: torch.Tensor, noise: AncestralNoise | None = None,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """The ancestral sampler's L levels from ``x_init (N, d)`` (the noised prior ensemble);
    returns ``(N, d)``. precision: ``(d, d)`` from :func:`gaussian_precision`.

    noise: injected draws, or None to draw them level by level from ``generator`` (on
    ``x_init``'s device).
    """
    x, u = x_init, x_init
    for l in range(sched.sigma.shape[0]):
        level = (_level_noise(noise, l) if noise is not None
                 else draw_level(tuple(x.shape), sched.proposals, generator, x.dtype,
                                 sched.proposal_df, x.device))
        x, u = _ancestral_call(step, sched, l, x, u, y, code, precision, guide, level)
    return x


@torch.no_grad()
def filter_step(nets: Networks, problem: TorchProblem, step: Callable, sched,
                ensemble: torch.Tensor,
                y: torch.Tensor, guide: torch.Tensor, noise: StepNoise | None = None,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """One CSF filter step: propagate, encode the prior ensemble, L reverse steps of the sampler
    that ``sched`` belongs to (:class:`AncestralSchedule` or :class:`Schedule`; ``step`` from
    :func:`make_reverse_step` with the same config).

    ensemble: ``(N, d)`` posterior at the previous time.  y: ``(m,)``.  guide: 0-d, 1.0 to
    assimilate ``y``.  noise: injected draws, or None to draw from ``generator``.  Every tensor
    (and the generator) on the device of ``nets``, ``problem`` and ``sched``.
    Returns the posterior ensemble ``(N, d)``.
    """
    if noise is None:
        draw = lambda: torch.randn(ensemble.shape, generator=generator, dtype=ensemble.dtype,
                                   device=ensemble.device)
        noise = StepNoise(draw(), draw(), None)
    prior_ens = problem.drift(ensemble) + problem.process_std * noise.prop
    code = condition(nets, prior_ens, sched.encode_particles)
    sched = step_schedule(sched, problem, prior_ens, y, guide)
    if isinstance(sched, AncestralSchedule):
        x_init = prior_ens + sched.sigma_start * noise.x_init
        precision = gaussian_precision(prior_ens, sched.inflation)
        return ancestral_sample(step, sched, x_init, y, code, precision, guide, noise.eps,
                                generator)
    x_init = torch.sqrt(sched.var[0]) * noise.x_init  # sigma_1: the grid starts at t = 1
    return posterior_sample(step, sched, x_init, y, code, guide, noise.eps, generator)


@torch.no_grad()
def first_reverse_step(nets: Networks, step: Callable, sched, ensemble: torch.Tensor,
                       y: torch.Tensor) -> torch.Tensor:
    """One call of ``step`` at the first level (time) of ``sched``, from ``ensemble (N, d)`` as the
    prior ensemble and the current state, with noise from torch's global generator: what
    ``torch.compile`` compiles on (e.g. to time the compilation). Returns the new state ``(N, d)``.
    """
    code = condition(nets, ensemble, sched.encode_particles)
    guide = torch.tensor(1.0, dtype=ensemble.dtype, device=ensemble.device)
    if isinstance(sched, AncestralSchedule):
        precision = gaussian_precision(ensemble, sched.inflation)
        level = draw_level(tuple(ensemble.shape), sched.proposals, dtype=ensemble.dtype,
                           df=sched.proposal_df, device=ensemble.device)
        return _ancestral_call(step, sched, 0, ensemble, ensemble, y, code, precision, guide,
                               level)[0]
    return _em_call(step, sched, 0, ensemble, y, code, guide, torch.randn_like(ensemble))


@torch.no_grad()
def csf_filter(nets: Networks, problem: TorchProblem, obs: torch.Tensor, ensemble: torch.Tensor,
               config: CSFConfig = PAPER, compile: bool = False, seed: int = 0,
               step: Callable | None = None, mode: str | None = None,
               device: torch.device | str | None = None):
    """``K`` filter steps; returns ``(mean (K, d), std (K, d), last posterior ensemble (N, d))``.

    obs: ``(K, m)``.  ensemble: ``(N, d)`` initial ensemble.  config: the sampler (and its
    settings) as in csf_jax.  step: a :func:`make_reverse_step` result for the same config to
    reuse (e.g. an already compiled one); built from ``compile`` and ``mode`` when None.
    device: where the filter runs (``nets`` and ``problem`` must have been built there): obs and
    ensemble are moved there; None: the ensemble's device (the CPU for a CPU ensemble). The
    schedule, the generator (seeded with ``seed``) and every draw live there too.
    """
    device = ensemble.device if device is None else torch.device(device)
    obs, ensemble = obs.to(device), ensemble.to(device)
    config = model_config(config, problem.name)
    step = make_reverse_step(nets, problem, config, compile, mode) if step is None else step
    sched = schedule(config, ensemble.dtype, device)
    gen = torch.Generator(device=device).manual_seed(seed)
    means, stds = [], []
    for k in range(obs.shape[0]):
        guide = torch.tensor(1.0 if (k > 0 or config.sampler.assimilate_first) else 0.0,
                             dtype=ensemble.dtype, device=device)
        ensemble = filter_step(nets, problem, step, sched, ensemble, obs[k], guide, generator=gen)
        means.append(ensemble.mean(0))
        stds.append(ensemble.std(0, correction=0))
    return torch.stack(means), torch.stack(stds), ensemble
