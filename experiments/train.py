"""Train the CSF prior (set encoder + conditional score net) for one built-in problem: a thin
command line over ``csf_jax.train_prior`` with the shipped models' recipes.

    python -m experiments.train double_well [--steps S] [--out runs/double_well]
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
from experiments._cli import int_list, nonnegative_int, parser, particle_count, positive_int

DESCRIPTION = ("Train the CSF prior of one built-in problem with the shipped models' recipes: "
               "generate (or finish) its dataset under OUT/data and train with checkpoints under "
               "OUT/ckpt (resumable); --export writes the final model.")
RECIPE = ("default: the problem's recipe, csf_jax.pretrained.{table} (the double well's for a "
          "problem without one)")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.train``."""
    trainer = TrainConfig()
    p = parser("train", DESCRIPTION)
    p.add_argument("problem", choices=problems.NAMES, metavar="PROBLEM",
                   help="the problem: %(choices)s")
    p.add_argument("--out", default=None, help="run directory (default runs/<problem>)")
    p.add_argument("--steps", type=positive_int, default=None,
                   help=f"Adam steps (default: the problem's recipe, csf_jax.pretrained.TRAIN, "
                        f"else {trainer.steps})")
    p.add_argument("--trajectories", type=particle_count, default=None,
                   help="M, at least 2: simulated trajectories, training and validation ("
                        + RECIPE.format(table="DATASETS") + ")")
    p.add_argument("--particles", type=particle_count, default=None,
                   help="N of the particle filter recording the prior ensembles ("
                        + RECIPE.format(table="DATASETS") + ")")
    p.add_argument("--keep", type=particle_count, default=None,
                   help="particles stored per prior ensemble, at most --particles ("
                        + RECIPE.format(table="DATASETS") + ")")
    p.add_argument("--stride", type=positive_int, default=None,
                   help="record every stride-th filter step, at most the problem's number of "
                        "steps (" + RECIPE.format(table="DATASETS") + ")")
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of the data and the training (default %(default)s)")
    p.add_argument("--save-every", type=positive_int, default=None,
                   help=f"checkpoint and validate every this many steps (default: the recipe's, "
                        f"else {trainer.save_every})")
    p.add_argument("--lr-decay-every", type=positive_int, default=None,
                   help=f"halve the learning rate every this many steps (default: the recipe's, "
                        f"else {trainer.lr_decay_every})")
    p.add_argument("--batch-sets", type=positive_int, default=None,
                   help=f"ensembles per training batch (default: the recipe's, else "
                        f"{trainer.batch_sets})")
    p.add_argument("--targets", type=positive_int, default=None,
                   help=f"x0 targets per set (default: the recipe's, else "
                        f"{trainer.targets_per_set})")
    p.add_argument("--set-sizes", type=int_list(2), default=None,
                   help=f"comma-separated encoder subset sizes, each at least 2 (default: the "
                        f"recipe's, else {','.join(map(str, trainer.set_sizes))})")
    p.add_argument("--base", choices=networks.BASES, default=None,
                   help="NetworkConfig.base: 'none' (the net is the whole score) or 'gaussian' "
                        "(the ensemble's Gaussian score plus a learned correction); default: the "
                        "shipped model's recipe (csf_jax.pretrained.NETWORK), else 'none'")
    p.add_argument("--export", default=None,
                   help="write the trained model to this directory (default: not exported)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    """The checked arguments; ``args.dataset`` is the ``DatasetConfig`` they select."""
    p = build_parser()
    args = p.parse_args(argv)
    recipe = DATASETS[args.problem if args.problem in DATASETS else "double_well"]
    fields = {k: v for k, v in (("trajectories", args.trajectories), ("particles", args.particles),
                                ("keep", args.keep), ("stride", args.stride)) if v is not None}
    dcfg = dataclasses.replace(recipe, seed=args.seed)
    particles, keep = fields.get("particles", dcfg.particles), fields.get("keep", dcfg.keep)
    if keep > particles:
        flag = "--keep" if args.keep is not None else "--particles"
        p.error(f"argument {flag}: --keep ({keep}) cannot exceed --particles ({particles}): the "
                f"stored particles are drawn from the filter's")
    num_steps = problems.get(args.problem).num_steps
    stride = fields.get("stride", dcfg.stride)
    if stride > num_steps:
        p.error(f"argument --stride: {stride} leaves no recorded step: {args.problem} has "
                f"{num_steps} filter steps, so the stride must be <= {num_steps}")
    try:
        args.dataset = dataclasses.replace(dcfg, **fields)
    except ValueError as e:
        p.error(str(e))
    return args


def main(argv=None):
    args = parse_args(argv)
    dcfg = args.dataset
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
