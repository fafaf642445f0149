"""Neural networks of the Conditional Score-based Filter.

Two Flax linen modules make up the learned part of the filter:

* :class:`SetEncoder` -- a Set Transformer that maps an ensemble of particles
  ``x: (N, d)`` to a fixed-size code ``c: (C,)``, invariant to permutations of
  the particles and (by default) to duplicating the whole set.
* :class:`ScoreNet` -- a conditional score network ``s(x, t; c)`` approximating
  the score of the VE-SDE-perturbed prior described by the code ``c``.

Both are configured by the frozen, hashable :class:`NetworkConfig`.
:func:`init_params`, :func:`encode` and :func:`score` are pure helpers that build
the modules inline and call ``init``/``apply``.
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks
from csf_jax.sde import marginal_std

_POSITIVE_INT_FIELDS = (
    "hidden",
    "heads",
    "blocks",
    "code_dim",
    "score_hidden",
    "score_layers",
    "fourier_features",
)


BASES = ("none", "gaussian")


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Hyper-parameters of the set encoder and the conditional score network."""

    hidden: int = 64
    """Width h of the set encoder (embedding, attention and head widths)."""
    heads: int = 4
    """Number of attention heads in every attention layer of the encoder."""
    blocks: int = 2
    """Number L of self-attention blocks (SABs) in the encoder."""
    code_dim: int = 64
    """Dimension C of the ensemble code c produced by the encoder."""
    score_hidden: int = 128
    """Width of the hidden layers of the score MLP."""
    score_layers: int = 3
    """Number of hidden layers of the score MLP, including the first one."""
    fourier_features: int = 16
    """Number of random Fourier frequencies; the time embedding has twice as many dims."""
    pma_seed_in_keys: bool = False
    """Whether the pooling seed also acts as key/value (the paper's literal form)."""
    sigma_max: float = 25.0
    """Largest noise scale of the VE SDE; sets the marginal std sigma_t."""
    fourier_scale: float = 1.0
    """Std of the fixed random Fourier frequencies applied to log(sigma_t).

    log(sigma_t) spans about 8 units for t in [1e-5, 1]; with only
    ``fourier_features`` frequencies, NCSN++'s scale 16 would make the embedding an
    aliased hash of t, while scale 1 keeps it smooth and multi-scale.
    """

    base: str = "none"
    """What the score net's output is added to. "none": the net is the whole score (the paper's
    ``s(x, t; c)``). "gaussian": the score is the ensemble's Gaussian score
    ``-(C + sigma_t^2 I)^{-1} (x - m)`` plus a learned correction, the net fed the standardised
    ``z = (x - m) / sqrt(diag C + sigma_t^2)`` (``csf_jax.prior.learned_prior``); a net that
    outputs zero is the ensemble's Gaussian, and its output layer starts at zero."""

    def __post_init__(self):
        _checks.check_fields(self)
        if self.base not in BASES:
            raise ValueError(f"NetworkConfig.base must be one of {BASES}, got {self.base!r}")
        for name in _POSITIVE_INT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"NetworkConfig.{name} must be a positive int, got {value!r}")
        if self.hidden % self.heads != 0:
            raise ValueError(
                f"NetworkConfig.hidden ({self.hidden}) must be divisible by heads ({self.heads})"
            )
        if not self.sigma_max > 1.0:
            raise ValueError(f"NetworkConfig.sigma_max must be > 1, got {self.sigma_max!r}")
        if not self.fourier_scale > 0.0:
            raise ValueError(f"NetworkConfig.fourier_scale must be > 0, got {self.fourier_scale!r}")


def ensemble_features(ensemble: jax.Array) -> jax.Array:
    """Augments every particle with the ensemble mean and population variance.

    Args:
      ensemble: particles, shape ``(..., N, d)``.

    Returns:
      ``u`` of shape ``(..., N, 3d)`` with ``u_i = [x_i, mean, var]`` where the
      variance divides by ``N``.
    """
    mean = jnp.mean(ensemble, axis=-2, keepdims=True)
    var = jnp.mean(jnp.square(ensemble - mean), axis=-2, keepdims=True)
    stats = jnp.concatenate([mean, var], axis=-1)
    stats = jnp.broadcast_to(stats, ensemble.shape[:-1] + stats.shape[-1:])
    return jnp.concatenate([ensemble, stats], axis=-1)


def fourier_frequencies(num_features: int, scale: float) -> np.ndarray:
    """Fixed random frequencies of the Gaussian Fourier time embedding.

    Deterministic (drawn from ``np.random.default_rng(0)``), hence identical in
    every process and never trained.

    Returns:
      float32 array of shape ``(num_features,)``.
    """
    return (np.random.default_rng(0).standard_normal(num_features) * scale).astype(np.float32)


def time_embedding(log_sigma: jax.Array, frequencies: np.ndarray) -> jax.Array:
    """Gaussian Fourier features ``[sin(2 pi w log_sigma), cos(2 pi w log_sigma)]``.

    Args:
      log_sigma: log of the marginal std, any shape ``S``.
      frequencies: shape ``(F,)``.

    Returns:
      shape ``S + (2F,)``.
    """
    angles = 2.0 * jnp.pi * log_sigma[..., None] * frequencies
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)


def _attention(config: NetworkConfig, name: str) -> nn.MultiHeadDotProductAttention:
    """Multi-head dot-product attention of width ``config.hidden`` (no dropout)."""
    return nn.MultiHeadDotProductAttention(
        num_heads=config.heads,
        qkv_features=config.hidden,
        out_features=config.hidden,
        deterministic=True,
        name=name,
    )


class SetEncoder(nn.Module):
    """Set Transformer encoder: ensemble ``(..., N, d)`` -> code ``(..., C)``.

    ``u_i = [x_i, mean, var]`` is embedded linearly to width h, passed through
    ``blocks`` self-attention blocks ``H = LayerNorm(H + MHA(H, H, H))`` (no
    feed-forward sublayer), pooled by multi-head attention with a learnable seed
    query ``s``, layer-normalised and mapped to the code by a two-layer SiLU MLP.

    With ``pma_seed_in_keys=False`` (default) the seed attends to ``H`` only, so
    the code is exactly invariant to permutations and to duplicating the set.
    With ``True`` the keys/values are ``[s; H]`` (the paper's literal form), which
    weights the seed by ``1/(N+1)`` and therefore depends on ``N``.
    """

    config: NetworkConfig

    @nn.compact
    def __call__(self, ensemble: jax.Array) -> jax.Array:
        """Encodes an ensemble.

        Args:
          ensemble: particles, shape ``(N, d)`` or ``(..., N, d)``.

        Returns:
          code ``c`` of shape ``(C,)`` or ``(..., C)``.
        """
        cfg = self.config
        h = nn.Dense(cfg.hidden, name="embed")(ensemble_features(ensemble))
        for i in range(cfg.blocks):
            h = nn.LayerNorm(name=f"sab{i}_norm")(h + _attention(cfg, f"sab{i}_attn")(h))
        seed = self.param("pma_seed", nn.initializers.normal(stddev=0.02), (cfg.hidden,))
        query = jnp.broadcast_to(seed.astype(h.dtype), h.shape[:-2] + (1, cfg.hidden))
        keys = jnp.concatenate([query, h], axis=-2) if cfg.pma_seed_in_keys else h
        pooled = _attention(cfg, "pma_attn")(query, keys)[..., 0, :]  # values = keys
        z = nn.LayerNorm(name="pma_norm")(pooled)
        z = nn.silu(nn.Dense(cfg.hidden, name="head_hidden")(z))
        return nn.Dense(cfg.code_dim, name="head_out")(z)


class ScoreNet(nn.Module):
    """Conditional score network ``s(x, t; c) = MLP(x, t, c) / sigma_t``.

    The first layer is ``Dense_x(x) + Dense_cond([temb(log sigma_t), c])``. The
    conditional term is computed on the broadcast batch shape of ``t`` and ``c``
    only, so when all particles share ``t`` (scalar) and ``c`` (shape ``(C,)``)
    it is evaluated once and broadcast over the particles. It is followed by
    SiLU, ``score_layers - 1`` residual layers ``h = h + Dense(SiLU(h))`` and a
    small-init output layer to ``d``.
    """

    config: NetworkConfig

    @nn.compact
    def __call__(self, x: jax.Array, t: jax.Array, c: jax.Array) -> jax.Array:
        """Evaluates the score.

        Args:
          x: points, shape ``(N, d)`` or ``(d,)``.
          t: diffusion times in ``(0, 1]``, scalar or shape ``(N,)``.
          c: ensemble code, shape ``(C,)`` or ``(N, C)``.

        Returns:
          the score, shape of ``x`` (broadcast with the batch shapes of ``t``, ``c``).
        """
        cfg = self.config
        t = jnp.asarray(t, dtype=x.dtype)
        c = jnp.asarray(c, dtype=x.dtype)
        sigma = marginal_std(t, cfg.sigma_max)
        temb = time_embedding(jnp.log(sigma), fourier_frequencies(cfg.fourier_features, cfg.fourier_scale))
        cond_batch = jnp.broadcast_shapes(t.shape, c.shape[:-1])
        cond_in = jnp.concatenate(
            [
                jnp.broadcast_to(temb, cond_batch + temb.shape[-1:]),
                jnp.broadcast_to(c, cond_batch + c.shape[-1:]),
            ],
            axis=-1,
        )
        cond = nn.Dense(cfg.score_hidden, name="cond_in")(cond_in)
        h = nn.Dense(cfg.score_hidden, use_bias=False, name="x_in")(x) + cond
        for i in range(cfg.score_layers - 1):
            h = h + nn.Dense(cfg.score_hidden, name=f"residual{i}")(nn.silu(h))
        out = nn.Dense(
            x.shape[-1],
            # a Gaussian-base net starts as the ensemble's Gaussian exactly: zero correction
            kernel_init=nn.initializers.zeros if cfg.base == "gaussian" else
            nn.initializers.variance_scaling(1e-2, "fan_in", "truncated_normal"),
            name="out",
        )(nn.silu(h))
        return out / sigma[..., None]


def init_params(key: jax.Array, config: NetworkConfig, dim: int, ensemble_size: int = 8) -> dict:
    """Initialises both networks on dummy inputs (compiled, so it is fast).

    Args:
      key: PRNG key.
      config: network configuration.
      dim: state dimension d.
      ensemble_size: number N of particles in the dummy ensemble (parameters do
        not depend on it).

    Returns:
      ``{"encoder": encoder_variables, "score": score_variables}`` (linen
      variable dicts).
    """
    enc_key, score_key = jax.random.split(key)
    ensemble = jnp.zeros((ensemble_size, dim), jnp.float32)
    code = jnp.zeros((config.code_dim,), jnp.float32)
    return {
        "encoder": jax.jit(SetEncoder(config).init)(enc_key, ensemble),
        "score": jax.jit(ScoreNet(config).init)(score_key, ensemble, jnp.ones((), jnp.float32), code),
    }


def encode(params: dict, ensemble: jax.Array, config: NetworkConfig) -> jax.Array:
    """Encodes an ensemble ``(N, d)`` (or ``(..., N, d)``) into a code ``(C,)`` (or ``(..., C)``)."""
    return SetEncoder(config).apply(params["encoder"], ensemble)


def score(params: dict, x: jax.Array, t: jax.Array, c: jax.Array, config: NetworkConfig) -> jax.Array:
    """Conditional score ``s(x, t; c)``.

    Args:
      params: output of :func:`init_params` (or trained equivalent).
      x: points, shape ``(N, d)`` or ``(d,)``.
      t: times in ``(0, 1]``, scalar or ``(N,)``.
      c: code, ``(C,)`` or ``(N, C)``.
      config: network configuration.

    Returns:
      score with the shape of ``x``.
    """
    return ScoreNet(config).apply(params["score"], x, t, c)


def params_dim(params: dict) -> int:
    """The state dimension d that ``params`` were built for (the score net's output width)."""
    return int(params["score"]["params"]["out"]["kernel"].shape[-1])


@functools.lru_cache(maxsize=64)
def _expected_params(config: NetworkConfig, dim: int):
    """Shapes and structure of ``init_params(., config, dim)``, without computing anything."""
    return jax.eval_shape(lambda: init_params(jax.random.key(0), config, dim))


def check_params(params: dict, config: NetworkConfig, dim: int, name: str = "params") -> None:
    """Raise ValueError if ``params`` do not fit ``config`` and state dimension ``dim``.

    Compares the pytree structure and every leaf shape with freshly initialised parameters
    (``jax.eval_shape``: nothing is computed), and names both sides on a mismatch.
    """
    expected = _expected_params(config, dim)
    try:
        got_dim = params_dim(params)
    except (KeyError, TypeError, IndexError, AttributeError):
        got_dim = None
    exp_leaves, exp_tree = jax.tree_util.tree_flatten_with_path(expected)
    got_leaves, got_tree = jax.tree_util.tree_flatten_with_path(params)
    if got_dim is not None and got_dim != dim:
        raise ValueError(f"{name} were made for state dimension d={got_dim}, but the problem has "
                         f"d={dim}")
    if exp_tree != got_tree:
        raise ValueError(f"{name} do not match the network config {config}: their structure "
                         f"differs from what this config builds (another architecture?)")
    for (path, exp), (_, got) in zip(exp_leaves, got_leaves):
        shape = tuple(got.shape) if hasattr(got, "shape") else tuple(jnp.shape(got))
        if tuple(exp.shape) != shape:
            raise ValueError(f"{name} do not match the network config {config} at "
                             f"{jax.tree_util.keystr(path)}: shape {shape}, "
                             f"config expects {tuple(exp.shape)}")


def mismatched_field(shapes, config: NetworkConfig, dim: int):
    """Which ``NetworkConfig`` field (or ``"dim"``) made ``shapes`` differ from ``config``.

    shapes: a params-like pytree whose leaves have ``.shape`` (arrays, ``ShapeDtypeStruct``s).
    Tries the sizes of the first mismatching leaf for each size field and the state dimension, and
    1..8 for the fields that change the structure (``blocks``, ``score_layers``); returns
    ``(field, value)`` for the first change that makes every shape fit, or None. Only for error
    paths: each try costs one ``jax.eval_shape`` (a trace of both networks).
    """
    got = {jax.tree_util.keystr(p): tuple(x.shape)
           for p, x in jax.tree_util.tree_flatten_with_path(shapes)[0]}

    def fits(cfg, d):
        want = jax.tree_util.tree_flatten_with_path(_expected_params(cfg, d))[0]
        return (len(want) == len(got) and
                all(got.get(jax.tree_util.keystr(p)) == tuple(x.shape) for p, x in want))

    want = jax.tree_util.tree_flatten_with_path(_expected_params(config, dim))[0]
    bad = [(got[k], tuple(x.shape)) for k, x in ((jax.tree_util.keystr(p), x) for p, x in want)
           if k in got and got[k] != tuple(x.shape)]
    sizes = sorted(set(bad[0][0]) - set(bad[0][1])) if bad else []
    tries = [("dim", v) for v in sizes] + [(n, v) for v in sizes for n in _POSITIVE_INT_FIELDS]
    if len(want) != len(got):
        tries += [(n, v) for n in ("blocks", "score_layers") for v in range(1, 9)]
    for name, value in tries:
        if name == "dim":
            if fits(config, value):
                return name, value
            continue
        if value == getattr(config, name):
            continue
        try:
            candidate = dataclasses.replace(config, **{name: value})
        except ValueError:
            continue
        if fits(candidate, dim):
            return name, value
    return None
