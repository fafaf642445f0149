"""Validation loss of each shipped Gaussian-base prior against the ensemble's Gaussian alone.

    python -m experiments.gaussian_loss [double_well cauchy ...]

A Gaussian-base network (``NetworkConfig(base="gaussian")``) with its zero-initialised output layer
is exactly the ensemble's Gaussian score, so its loss before training is the Gaussian's. This
evaluates both on the validation batch ``experiments.train`` uses (the datasets of
``python -m experiments.make_pretrained`` under ``runs/pretrained/<name>/data``; generated there
if missing) and prints one line per model: how much the learned correction gained.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import jax

from csf_jax import networks
from csf_jax.pretrained import DATASETS, NETWORK, TRAIN, load_pretrained
from csf_jax.training import generate, load
from csf_jax.training.train import eval_loss, make_batch
from experiments._cli import one_of, parser

GAUSSIAN_BASE = tuple(n for n in DATASETS if NETWORK[n].base == "gaussian")


def losses(name: str) -> tuple[float, float]:
    """``(Gaussian's, shipped model's)`` validation loss of problem ``name``."""
    data_dir = os.path.join("runs", "pretrained", name, "data")
    generate(name, DATASETS[name], data_dir, verbose=False)
    data, cfg, net = load(data_dir), TRAIN[name], NETWORK[name]
    full = net.base == "gaussian"
    valid = make_batch(data, dataclasses.replace(cfg, set_sizes=(max(cfg.set_sizes),)), 0,
                       "valid", full)
    key = jax.random.key(10_000 + cfg.seed)
    untrained = networks.init_params(jax.random.key(cfg.seed), net, int(data.ensembles.shape[-1]))
    ev = lambda p: float(eval_loss(p, valid[0], valid[1], key, *valid[2:], network=net,
                                   t_min=cfg.t_min))
    return ev(untrained), ev(load_pretrained(name).params)


DESCRIPTION = ("Print, per shipped Gaussian-base model, its validation loss against the "
               "ensemble's Gaussian alone (the untrained network), on the datasets under "
               "runs/pretrained/<name>/data (generated there if missing).")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.gaussian_loss``."""
    p = parser("gaussian_loss", DESCRIPTION)
    p.add_argument("names", nargs="*", type=one_of(GAUSSIAN_BASE, "Gaussian-base shipped model"),
                   metavar="NAME",
                   help=f"models, from: {', '.join(GAUSSIAN_BASE)} (default: all)")
    return p


def main(argv=None):
    names = build_parser().parse_args(argv).names or list(GAUSSIAN_BASE)
    print("| model | Gaussian (untrained) | trained | trained / Gaussian |")
    print("|---|---|---|---|")
    for name in names:
        gauss, trained = losses(name)
        print(f"| {name} | {gauss:.5f} | {trained:.5f} | {trained / gauss:.5f} |", flush=True)


if __name__ == "__main__":
    main()
