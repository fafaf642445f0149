"""Prior quality (paper Fig. 2b / 3a): does the pretrained model reproduce held-out prior ensembles?

    python -m experiments.prior_quality double_well [--ensembles 8] [--scratch-steps 2000]

For held-out PF prior ensembles (the validation trajectories of the problem's dataset, regenerated
under runs/pretrained/<name>/data if missing), compares with each ensemble:
  * conditional: samples of the pretrained model conditioned on the ensemble, no observation;
  * scratch: samples of an unconditional diffusion model trained from scratch on that one ensemble;
  * floor: one half of the ensemble against the other (the sampling noise of the comparison).
Reports, averaged over ensembles and coordinates: |mean error|, |std error| and the 1-D Wasserstein
distance, all in state units.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import networks
from csf_jax.dsm import fit_unconditional
from csf_jax.filters.csf import CSFConfig, posterior_sample
from csf_jax.guidance import GuidanceConfig
from csf_jax.metrics import wasserstein_1d
from csf_jax.pretrained import DATASETS, MODEL_FOR, load_pretrained
from csf_jax.prior import learned_prior, unconditional_prior
from csf_jax.sde import marginal_std
from csf_jax.training import generate, load
from experiments._cli import nonnegative_int, parser, positive_int

# The model's own prior: Euler-Maruyama without guidance or inflation, L = 500 (the paper's
# sampler with enough steps to be accurate), fixed whatever the filter's defaults.
PRIOR_ONLY = CSFConfig(reverse_steps=500, guidance=GuidanceConfig(mode="none"), prior_inflation=0.0,
                       adaptive_inflation=False)


def compare(samples, ensemble):
    """``(|mean err|, |std err|, W1)`` averaged over coordinates; both ``(n, d)``."""
    m = float(jnp.mean(jnp.abs(samples.mean(0) - ensemble.mean(0))))
    s = float(jnp.mean(jnp.abs(samples.std(0) - ensemble.std(0))))
    return m, s, float(jnp.mean(wasserstein_1d(samples, ensemble)))


def sample(params, prior, context, n, d, key):
    """``n`` prior samples from ``prior`` conditioned on ``context`` (no observation)."""
    k_init, k_rev = jax.random.split(key)
    x0 = marginal_std(1.0, PRIOR_ONLY.sigma_max) * jax.random.normal(k_init, (n, d))
    return posterior_sample(params, prior, context, lambda x: 0.0, x0, k_rev, PRIOR_ONLY, 0.0)


DESCRIPTION = ("Compare the pretrained prior's samples, conditioned on held-out PF prior "
               "ensembles, with those ensembles (and with a from-scratch model and the sampling "
               "floor); print mean error, std error and W1.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.prior_quality``."""
    p = parser("prior_quality", DESCRIPTION)
    p.add_argument("problem", choices=sorted(set(MODEL_FOR.values())), metavar="PROBLEM",
                   help="a shipped model: %(choices)s")
    p.add_argument("--ensembles", type=positive_int, default=8,
                   help="held-out ensembles compared (default %(default)s)")
    p.add_argument("--scratch-steps", type=positive_int, default=2000,
                   help="Adam steps of the from-scratch model (default %(default)s)")
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of the ensembles' choice and the sampling (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    model = load_pretrained(args.problem)
    data_dir = os.path.join("runs", "pretrained", args.problem, "data")
    generate(args.problem, DATASETS[args.problem], data_dir)
    data = load(data_dir)
    rng = np.random.default_rng(args.seed)
    net = model.network
    scratch_net = dataclasses.replace(net, base="none")  # a plain score net, as the paper's SF
    cond_prior, scratch_prior = learned_prior(net), unconditional_prior(scratch_net)
    sample_j = jax.jit(sample, static_argnames=("prior", "n", "d"))
    rows = {"conditional (pretrained)": [], "scratch (one ensemble)": [], "floor (half vs half)": []}
    for j in range(args.ensembles):
        ens = jnp.asarray(data.ensembles[rng.choice(data.valid),
                                         rng.integers(data.ensembles.shape[1])], jnp.float32)
        n, d = ens.shape
        key = jax.random.fold_in(jax.random.key(args.seed), j)
        context = cond_prior.condition(model.params, ens, ens, 0.0)
        gen = sample_j(model.params, cond_prior, context, n, d, key)
        fresh = networks.init_params(jax.random.fold_in(key, 1), scratch_net, d)
        scratch, _ = fit_unconditional(jax.random.fold_in(key, 2), ens, fresh, config=scratch_net,
                                       steps=args.scratch_steps)
        gen_s = sample_j(scratch, scratch_prior, jnp.zeros((net.code_dim,)), n, d, key)
        rows["conditional (pretrained)"].append(compare(gen, ens))
        rows["scratch (one ensemble)"].append(compare(gen_s, ens))
        rows["floor (half vs half)"].append(compare(ens[: n // 2], ens[n // 2:]))
        print(f"ensemble {j + 1}/{args.ensembles}", end="\r", flush=True)
    print(f"{args.problem}: {args.ensembles} held-out ensembles of {n} particles, d = {d}; "
          f"scratch model: {args.scratch_steps} Adam steps")
    print("| samples | mean error | std error | W1 |")
    print("|---|---|---|---|")
    for name, vals in rows.items():
        m, s, w = np.mean(np.array(vals), axis=0)
        print(f"| {name} | {m:.4f} | {s:.4f} | {w:.4f} |")


if __name__ == "__main__":
    main()
