"""Make the shipped pretrained models (``csf_jax/pretrained_models/<name>``) from scratch.

    python -m experiments.make_pretrained [double_well cauchy cubic10_indep ...]

For each problem: generate its PF prior-ensemble dataset and train with the configs in
``csf_jax.pretrained`` (``DATASETS``, ``TRAIN``), seed 0, under ``runs/pretrained/<name>`` (resumable:
run it again after an interruption), then export the parameters into the package. Prints the
wall-clock and CPU seconds of each problem.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from csf_jax.pretrained import DATASETS, MODEL_DIR
from experiments import train
from experiments._cli import one_of, parser

DESCRIPTION = ("Remake the shipped pretrained models from scratch: for each named problem, "
               "generate its dataset and train under runs/pretrained/<name> (resumable), then "
               "export the parameters into csf_jax/pretrained_models/<name>.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.make_pretrained``."""
    p = parser("make_pretrained", DESCRIPTION)
    p.add_argument("names", nargs="*", type=one_of(tuple(DATASETS), "pretrained recipe"),
                   metavar="NAME",
                   help=f"models to make, from: {', '.join(DATASETS)} (default: all)")
    return p


def main(argv=None):
    names = build_parser().parse_args(argv).names or list(DATASETS)
    for name in names:
        wall, cpu = time.perf_counter(), time.process_time()
        train.main([name, "--out", os.path.join("runs", "pretrained", name),
                    "--export", os.path.join(MODEL_DIR, name)])
        print(f"{name}: {time.perf_counter() - wall:.0f} s wall, {time.process_time() - cpu:.0f} s "
              f"CPU (data + training)", file=sys.stderr)


if __name__ == "__main__":
    main()
