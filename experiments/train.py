"""Train the shipped pretrained priors from scratch, with their recipes (``csf_jax.pretrained``).

    python -m experiments.train [NAME ...] [--out runs/pretrained] [--export] [--quiet]

For each named model (default: all of ``csf_jax.pretrained.DATASETS``): generate its particle-filter
dataset and train the set encoder and the score net with ``csf_jax.train_prior`` under
``OUT/<name>`` (checkpoints: kill it at any moment and run it again to resume), seed 0. With
``--export`` the parameters replace the shipped model in ``csf_jax/pretrained_models/<name>``.
With ``--export`` it also writes ``results/pretrained/results.json``: per model the steps, the
seconds and the final validation loss.
For a model of your own, call ``csf_jax.train_prior(model, key)`` (docs/guide.md).
"""

from __future__ import annotations

import os
import time

import jax

from csf_jax import networks
from csf_jax.pretrained import DATASETS, MODEL_DIR, NETWORK, TRAIN
from csf_jax.training import TrainConfig, train_prior
from experiments import cli, harness, interrupt


def main(argv=None):
    p = harness.parser("train", "Train the shipped priors with their recipes (resumable); "
                       "--export writes them into the package.")
    p.add_argument("names", nargs="*", type=harness.name_list(list(DATASETS), "model"),
                   metavar="NAME", help=f"models from {', '.join(DATASETS)} (default: all)")
    p.add_argument("--out", default=os.path.join("runs", "pretrained"),
                   help="folder of the training runs (default %(default)s)")
    p.add_argument("--export", action="store_true",
                   help="replace the shipped models in csf_jax/pretrained_models")
    p.add_argument("--quiet", action="store_true", help="no training progress")
    args = p.parse_args(argv)
    cli.check_folder(p, "--out", args.out)
    names = [n for group in args.names for n in group] or list(DATASETS)
    rows = []
    for name in names:
        t0 = time.perf_counter()
        trained = train_prior(name, jax.random.key(0), directory=os.path.join(args.out, name),
                              dataset=DATASETS[name], config=TRAIN.get(name, TrainConfig()),
                              network=NETWORK.get(name, networks.NetworkConfig()),
                              verbose=not args.quiet)
        meta = trained.meta
        rows.append({"case": {"problem": name}, "entry": "prior", "steps": meta["train"]["steps"],
                     "training_seconds": meta["seconds"], "wall_seconds": time.perf_counter() - t0,
                     "valid_loss": meta["valid_loss"][-1] if meta["valid_loss"] else None})
        print(f"{name}: {rows[-1]['wall_seconds']:.0f} s, final validation loss "
              f"{rows[-1]['valid_loss']}")
        if args.export:
            print(f"exported to {trained.save(os.path.join(MODEL_DIR, name))}")
    if args.export:
        with interrupt.WRITING:
            harness.write_results(os.path.join("results", "pretrained", "results.json"),
                                  harness.results_record("train", harness.command("train", argv),
                                                         rows))


if __name__ == "__main__":
    interrupt.main(main, "train", "the training checkpoints are kept, rerun to resume")
