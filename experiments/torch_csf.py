"""A PyTorch port of the CSF online step with the learned prior, for benchmarking against csf_jax.

It computes the same thing as ``csf_jax.filter(params, ...)`` with ``learned_prior``, written the
way the paper's authors' stack would: PyTorch modules, ``torch.no_grad()`` everywhere except the DPS
gradient (``torch.autograd.grad`` through the score net), float32, and a Python loop over the L
reverse steps. Every piece mirrors a csf_jax one:

* ``SetEncoder`` / ``ScoreNet``: ``csf_jax.networks`` (weights loaded with :func:`flax_to_torch`).
* ``marginal_std`` / ``diffusion_sq`` / :func:`schedule`: ``csf_jax.sde`` and the reverse grid
  ``linspace(1, t_min, L)`` with a constant ``dt`` and a noise-free last step.
* :func:`guidance_displacement`: ``csf_jax.guidance`` (default "clipped").
* :func:`torch_problem`: the drift and log-likelihood of ``csf_jax.problems`` (cubic sensors,
  Cauchy, double/triple well).
* :func:`filter_step`: one step of ``csf_jax.filters.csf._csf_scan`` (propagate, encode, L reverse
  steps).

:func:`make_reverse_step` returns the per-reverse-step function, eager or wrapped by
``torch.compile(..., dynamic=False)``. All random draws can be injected (:class:`StepNoise`) so
that tests feed identical noise to both implementations.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from csf_jax.filters.csf import CSFConfig
from csf_jax.guidance import GuidanceConfig
from csf_jax.networks import NetworkConfig, fourier_frequencies
from csf_jax.problems import CubicConfig, WellConfig
from csf_jax.problems import config as problem_config
from csf_jax.problems.cubic import coupling_matrix

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
    when ``denoise_last``.
    """

    t: torch.Tensor
    t_score: torch.Tensor
    var: torch.Tensor
    g2dt: torch.Tensor
    noise_scale: torch.Tensor
    noise_on: torch.Tensor


def schedule(config: CSFConfig) -> Schedule:
    """The reverse grid of ``csf_jax.sde.reverse_grid`` and its per-step scalars."""
    n = config.reverse_steps
    t = torch.linspace(1.0, config.t_min, n, dtype=DTYPE)
    dt = torch.tensor((1.0 - config.t_min) / (n - 1), dtype=DTYPE)
    g2dt = diffusion_sq(t, config.sigma_max) * dt
    noise_on = torch.ones(n, dtype=DTYPE)
    if config.denoise_last:
        noise_on[-1] = 0.0
    var = marginal_std(t, config.sigma_max) ** 2
    # csf_jax.sde.inflated_time, op for op in float32
    log_s = torch.log(torch.tensor(config.sigma_max, dtype=DTYPE))
    sigma_score = torch.sqrt(torch.square(marginal_std(t, config.sigma_max))
                             + config.prior_inflation ** 2)
    t_score = torch.log1p(2.0 * log_s * torch.square(sigma_score)) / (2.0 * log_s)
    return Schedule(t, t_score if config.prior_inflation else t, var, g2dt, torch.sqrt(g2dt),
                    noise_on)


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
    """The two torch modules of the learned prior (eval mode, ``requires_grad=False``)."""

    encoder: SetEncoder
    score: ScoreNet


def _t(a) -> torch.Tensor:
    """A float32 torch copy of a numpy/jax array."""
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


def flax_to_torch(params: dict, config: NetworkConfig, dim: Optional[int] = None) -> Networks:
    """Torch modules holding the csf_jax parameters ``{"encoder": ..., "score": ...}``.

    Args:
      params: ``csf_jax.init_params`` output (or trained equivalent); leaves may be jax or numpy.
      config: the ``NetworkConfig`` the params were built with.
      dim: state dimension d (default: read off the score net's output layer).
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
        module.eval().requires_grad_(False)
    return Networks(encoder, score)


# --------------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------------

class TorchProblem(NamedTuple):
    """The parts of a ``StateSpaceModel`` the online step needs, batched over particles.

    drift: ``x (N, d) -> (N, d)``.  loglik: ``(y (m,), x0 (N, d)) -> (N,)`` up to a constant.
    """

    name: str
    dim: int
    process_std: float
    drift: Callable[[torch.Tensor], torch.Tensor]
    loglik: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _noise_loglik(kind: str, scale: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """Residual ``(N, m) -> (N,)``: Gaussian ``-0.5 r^2 / scale^2``, Cauchy
    ``-log1p((r / scale)^2)``, summed over the coordinates."""
    if kind == "gaussian":
        inv_var = 1.0 / scale**2
        return lambda r: -0.5 * inv_var * (r * r).sum(-1)
    return lambda r: -torch.log1p((r / scale) ** 2).sum(-1)


def _cubic(c: CubicConfig) -> TorchProblem:
    a_t = torch.from_numpy(coupling_matrix(c.dim).T.copy()) if c.correlated else None

    def drift(x):
        f = torch.cos(x) if a_t is None else x @ a_t + torch.cos(x)
        return x + f * c.dt

    noise = _noise_loglik(c.noise, c.obs_scale)
    kind = "corr" if c.correlated else "indep"
    name = "cauchy" if c.noise == "cauchy" else f"cubic{c.dim}_{kind}"
    return TorchProblem(name, c.dim, c.process_std, drift, lambda y, x0: noise(y - x0**3))


def _well(c: WellConfig) -> TorchProblem:
    def grad_v(x):
        """V' for ``V = C (x^2 - 1)^2`` (times ``(x - 0.5)^2`` for the triple well)."""
        dv = 4.0 * c.C * x * (x * x - 1.0)
        if c.wells == "triple":
            dv = dv * (x - 0.5) ** 2 + 2.0 * c.C * (x * x - 1.0) ** 2 * (x - 0.5)
        return dv

    def drift(x):
        step = -grad_v(x) * c.dt
        return x + step if c.include_state else step

    noise = _noise_loglik("gaussian", c.obs_std)
    return TorchProblem(f"{c.wells}_well", 1, math.sqrt(c.dt) * c.process_std, drift,
                        lambda y, x0: noise(y - x0**3))


def torch_problem(name: str, **overrides) -> TorchProblem:
    """The torch version of ``csf_jax.problems.get(name, **overrides)`` (constants read from the
    same frozen configs)."""
    cfg = problem_config(name, **overrides)
    return _well(cfg) if isinstance(cfg, WellConfig) else _cubic(cfg)


# --------------------------------------------------------------------------------------------
# The online step
# --------------------------------------------------------------------------------------------

def guidance_displacement(config: GuidanceConfig, grad: torch.Tensor, loglik: torch.Tensor,
                          g2dt: torch.Tensor, noise_scale: torch.Tensor) -> torch.Tensor:
    """``csf_jax.guidance.guidance_displacement``: grad ``(N, d)``, loglik ``(N,)`` -> ``(N, d)``.
    """
    if config.mode == "none":
        return torch.zeros_like(grad)
    step = config.scale * g2dt * grad
    if config.mode == "raw":
        return step
    if config.mode == "normalized":
        return step / torch.sqrt(torch.clamp(-2.0 * loglik, min=1e-12))[:, None]
    cap = config.clip * noise_scale * math.sqrt(grad.shape[-1])
    norm = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
    return step * torch.clamp(cap / torch.clamp(norm, min=1e-30), max=1.0)


def dps_gradient(score_net: ScoreNet, loglik: Callable, y: torch.Tensor, x: torch.Tensor,
                 t: torch.Tensor, var: torch.Tensor, code: torch.Tensor):
    """Prior score, DPS gradient ``d/dx log p(y | x + var s(x))`` and that log-likelihood.

    ``x (N, d)`` -> ``(score (N, d), grad (N, d), loglik (N,))``, one backward pass through the
    score net (particles are independent, so the gradient of the sum is every particle's own).
    """
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        s = score_net(xg, t, code)
        ll = loglik(y, xg + var * s)
        (grad,) = torch.autograd.grad(ll.sum(), xg)
    return s.detach(), grad, ll.detach()


def make_reverse_step(nets: Networks, problem: TorchProblem, config: CSFConfig,
                      compile: bool = False) -> Callable:
    """The Euler-Maruyama step ``x <- x + g^2 dt (s + guide * guidance) + noise_on g sqrt(dt) eps``.

    Returns ``step(x (N, d), y (m,), code (C,), t, var, g2dt, noise_scale, noise_on, guide,
    eps (N, d)) -> x (N, d)``, the scalars 0-d tensors. ``compile=True`` wraps the same function
    in :func:`compile_step`.
    """
    score_net, loglik, guidance = nets.score, problem.loglik, config.guidance

    def step(x, y, code, t, var, g2dt, noise_scale, noise_on, guide, eps):
        if guidance.mode == "none":
            s, disp = score_net(x, t, code), 0.0
        else:
            s, grad, ll = dps_gradient(score_net, loglik, y, x, t, var, code)
            disp = guide * guidance_displacement(guidance, grad, ll, g2dt, noise_scale)
        return x + g2dt * s + disp + noise_on * noise_scale * eps

    return compile_step(step) if compile else step


def compile_step(step: Callable) -> Callable:
    """``torch.compile(step, dynamic=False, fullgraph=True)``, traced with
    ``torch._dynamo.config.trace_autograd_ops`` on so that the ``torch.autograd.grad`` of the DPS
    gradient is captured in the one graph (off, Dynamo graph-breaks there and the step runs as three
    pieces). One compilation per input shape, none per reverse step (the scalars are tensors).
    Compilation happens at the first call and raises there if Inductor fails.
    """
    compiled = torch.compile(step, dynamic=False, fullgraph=True)

    def run(*args):
        with torch._dynamo.config.patch(trace_autograd_ops=True):
            return compiled(*args)

    return run


class StepNoise(NamedTuple):
    """The random draws of one filter step, for injection (all standard normal, float32).

    prop: ``(N, d)`` process noise.  x_init: ``(N, d)``, scaled by sigma_1 to start the reverse SDE.
    eps: ``(L, N, d)`` the noise of each reverse step, or None to draw it step by step.
    """

    prop: torch.Tensor
    x_init: torch.Tensor
    eps: Optional[torch.Tensor]


def posterior_sample(step: Callable, sched: Schedule, x_init: torch.Tensor, y: torch.Tensor,
                     code: torch.Tensor, guide: torch.Tensor,
                     eps: Optional[torch.Tensor] = None,
                     generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """The L reverse steps from ``x_init (N, d)`` (already scaled); returns ``(N, d)``.

    eps: ``(L, N, d)`` injected noise, or None to draw it step by step from ``generator``.
    """
    x = x_init
    for l in range(sched.t.shape[0]):
        e = eps[l] if eps is not None else torch.randn(x.shape, generator=generator, dtype=x.dtype)
        x = step(x, y, code, sched.t_score[l], sched.var[l], sched.g2dt[l], sched.noise_scale[l],
                 sched.noise_on[l], guide, e)
    return x


@torch.no_grad()
def filter_step(nets: Networks, problem: TorchProblem, step: Callable, sched: Schedule,
                ensemble: torch.Tensor, y: torch.Tensor, guide: torch.Tensor,
                noise: Optional[StepNoise] = None,
                generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """One CSF filter step: propagate, encode the prior ensemble, L reverse steps.

    ensemble: ``(N, d)`` posterior at the previous time.  y: ``(m,)``.  guide: 0-d, 1.0 to
    assimilate ``y``.  noise: injected draws, or None to draw from ``generator``.
    Returns the posterior ensemble ``(N, d)``.
    """
    if noise is None:
        draw = lambda: torch.randn(ensemble.shape, generator=generator, dtype=ensemble.dtype)
        noise = StepNoise(draw(), draw(), None)
    prior_ens = problem.drift(ensemble) + problem.process_std * noise.prop
    code = nets.encoder(prior_ens)
    x_init = torch.sqrt(sched.var[0]) * noise.x_init  # sigma_1: the grid starts at t = 1
    return posterior_sample(step, sched, x_init, y, code, guide, noise.eps, generator)


@torch.no_grad()
def csf_filter(nets: Networks, problem: TorchProblem, obs: torch.Tensor, ensemble: torch.Tensor,
               config: CSFConfig = CSFConfig(), compile: bool = False, seed: int = 0,
               step: Optional[Callable] = None):
    """``K`` filter steps; returns ``(mean (K, d), std (K, d), last posterior ensemble (N, d))``.

    obs: ``(K, m)``.  ensemble: ``(N, d)`` initial ensemble.  step: a :func:`make_reverse_step`
    result to reuse (e.g. an already compiled one); built from ``compile`` when None.
    """
    step = make_reverse_step(nets, problem, config, compile) if step is None else step
    sched = schedule(config)
    gen = torch.Generator().manual_seed(seed)
    means, stds = [], []
    for k in range(obs.shape[0]):
        guide = torch.tensor(1.0 if (k > 0 or config.assimilate_first) else 0.0, dtype=DTYPE)
        ensemble = filter_step(nets, problem, step, sched, ensemble, obs[k], guide, generator=gen)
        means.append(ensemble.mean(0))
        stds.append(ensemble.std(0, correction=0))
    return torch.stack(means), torch.stack(stds), ensemble
