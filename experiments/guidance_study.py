"""Measure the DPS guidance variants with the exact-prior CSF (no training involved).

    python -m experiments.guidance_study [--problems double_well,cubic10_indep] [--particles 200]

Prints, per problem and guidance mode, the RMSE over ``--runs`` simulated trajectories and the number
of steps whose filtered mean is non-finite. This is the measurement behind ``GuidanceConfig``'s
``clip=1.0`` for the DPS modes (Euler-Maruyama with ``mode="clipped"``).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

import csf_jax
from csf_jax import CSFConfig, GuidanceConfig, problems
from experiments._cli import name_list, nonnegative_int, parser, particle_count, positive_int
from experiments._timing import timed

VARIANTS = (("raw", 1.0), ("clipped", 0.25), ("clipped", 0.5), ("clipped", 1.0),
            ("clipped", 3.0), ("normalized", 1.0))


DESCRIPTION = ("Compare the DPS guidance variants with the exact-prior CSF (Euler-Maruyama, no "
               "training) and print, per problem and variant, the RMSE and the non-finite steps.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.guidance_study``."""
    p = parser("guidance_study", DESCRIPTION)
    p.add_argument("--problems", type=name_list(problems.NAMES, "problem"),
                   default=["double_well", "cubic10_indep"], metavar="P,P,...",
                   help=f"comma-separated problems from: {', '.join(problems.NAMES)} (default "
                        f"double_well,cubic10_indep)")
    p.add_argument("--particles", type=particle_count, default=200,
                   help="ensemble size N, at least 2 (default %(default)s)")
    p.add_argument("--runs", type=positive_int, default=2,
                   help="simulated trajectories per problem (default %(default)s)")
    p.add_argument("--steps", type=particle_count, default=500,
                   help="reverse steps L, at least 2 (default %(default)s)")
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of the trajectories (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    print("| problem | guidance | clip | RMSE | non-finite steps | seconds |")
    print("|---|---|---|---|---|---|")
    for name in args.problems:
        model = problems.get(name)
        keys = jax.random.split(jax.random.key(args.seed), args.runs)
        truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(keys)
        ens = jax.vmap(lambda k: model.initial_ensemble(k, args.particles))(keys)
        for mode, clip in VARIANTS:
            # no prior inflation, fixed: the guidance variants compared on the plain Bayes update
            cfg = CSFConfig(reverse_steps=args.steps, guidance=GuidanceConfig(mode=mode, clip=clip),
                            prior_inflation=0.0, adaptive_inflation=False)
            r, seconds, _ = timed(jax.jit(jax.vmap(lambda o, e, k: csf_jax.filter(
                None, o, e, problem=model, key=k, config=cfg, check_finite=False))), obs, ens, keys)
            bad = int((~jnp.isfinite(r.mean)).any(-1).sum())
            rmse = float(csf_jax.rmse(r.mean, truth[:, 1:])) if bad == 0 else float("nan")
            print(f"| {name} | {mode} | {clip if mode == 'clipped' else '-'} | {rmse:.3f} | "
                  f"{bad} | {seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
