"""Train the CSF prior (set encoder + conditional score net) for one built-in problem: a thin
command line over ``csf_jax.train_prior`` with the shipped models' recipes.

    python -m experiments.train double_well [--steps 4000] [--out runs/double_well]
        [--trajectories M] [--particles N] [--keep K] [--stride S] [--seed 0]

Generates (or finishes) the PF prior-ensemble dataset under ``OUT/data``, then trains with
checkpoints under ``OUT/ckpt``. Interrupt it at any moment (even ``kill -9``) and run the same
command again: it resumes from the last complete checkpoint. ``--export DIR`` writes the final
parameters as a pretrained model directory (what ``csf_jax.load_pretrained`` reads).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import jax

from csf_jax import networks, problems
from csf_jax.pretrained import DATASETS, NETWORK, TRAIN
from csf_jax.training import TrainConfig, train_prior
from experiments._cli import int_list, nonnegative_int, particle_count, positive_int


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("problem", choices=problems.NAMES)
    p.add_argument("--out", default=None, help="run directory (default runs/<problem>)")
    p.add_argument("--steps", type=positive_int, default=None)
    p.add_argument("--trajectories", type=particle_count, default=None,
                   help="M, at least 2 (training and validation trajectories)")
    p.add_argument("--particles", type=particle_count, default=None)
    p.add_argument("--keep", type=particle_count, default=None)
    p.add_argument("--stride", type=positive_int, default=None)
    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--save-every", type=positive_int, default=None)
    p.add_argument("--lr-decay-every", type=positive_int, default=None,
                   help="halve the learning rate every this many steps (default 1500)")
    p.add_argument("--batch-sets", type=positive_int, default=None)
    p.add_argument("--targets", type=positive_int, default=None, help="x0 targets per set")
    p.add_argument("--set-sizes", type=int_list(2), default=None,
                   help="comma-separated encoder subset sizes, each at least 2")
    p.add_argument("--base", choices=networks.BASES, default=None,
                   help="NetworkConfig.base: 'none' (the net is the whole score) or 'gaussian' "
                        "(the ensemble's Gaussian score plus a learned correction); default: the "
                        "shipped model's recipe (csf_jax.pretrained.NETWORK), else 'none'")
    p.add_argument("--export", default=None, help="write the trained model here")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    base = args.problem if args.problem in DATASETS else "double_well"
    try:
        dcfg = dataclasses.replace(DATASETS[base], seed=args.seed, **{
            k: v for k, v in (("trajectories", args.trajectories), ("particles", args.particles),
                              ("keep", args.keep), ("stride", args.stride)) if v is not None})
    except ValueError as e:
        p.error(str(e))
    tcfg = dataclasses.replace(TRAIN.get(args.problem, TrainConfig()), seed=args.seed, **{
        k: v for k, v in (("steps", args.steps), ("save_every", args.save_every),
                          ("lr_decay_every", args.lr_decay_every),
                          ("eval_every", args.save_every), ("batch_sets", args.batch_sets),
                          ("targets_per_set", args.targets), ("set_sizes", args.set_sizes))
        if v is not None})
    out = args.out or os.path.join("runs", args.problem)
    network = NETWORK.get(args.problem, networks.NetworkConfig())
    if args.base is not None:
        network = dataclasses.replace(network, base=args.base)
    trained = train_prior(args.problem, jax.random.key(args.seed), directory=out, dataset=dcfg,
                          config=tcfg, network=network, verbose=not args.quiet)
    meta = trained.meta
    final = meta["valid_loss"][-1] if meta["valid_loss"] else None
    print(f"{args.problem}: {tcfg.steps} steps, {meta['seconds']:.0f} s training, final "
          f"validation loss {final}", file=sys.stderr)
    if args.export:
        trained.save(args.export)
        print(f"exported to {args.export}", file=sys.stderr)


if __name__ == "__main__":
    main()
