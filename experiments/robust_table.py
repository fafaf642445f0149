"""``csf_jax.ROBUST`` on the first runs of the paper's table, against the table's cached rows.

    python -m experiments.robust_table [triple_well=10 double_well=5 cauchy=3 cubic10_corr=3]

Each argument is ``problem=R``: the first R runs of the table (same trajectories, initial ensembles
and keys as ``experiments.run``, N = 1000, seed 0), filtered by ``csf_jax.filter(None, ...,
config=csf_jax.ROBUST)``; printed beside the cached CSF, CSF-G and reference RMSEs of the same runs
(``results/<problem>/results.json``). Why ``ROBUST`` is not the default: README, "Models CSF was not
tuned on".
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np

import csf_jax
from experiments._cli import parser
from experiments.run import simulate_runs

DEFAULT = ("triple_well=10", "double_well=5", "cauchy=3", "cubic10_corr=3")
CACHED_RUNS = 10  # runs of each problem in results/<problem>/results.json


def parse(arg: str) -> tuple[str, int]:
    """``"problem=R"`` -> ``(problem, R)`` (an argparse ``type``)."""
    name, _, runs = arg.partition("=")
    if name not in csf_jax.problems.NAMES or not runs.isdigit() or int(runs) < 1:
        raise argparse.ArgumentTypeError(f"expected problem=R with a table problem "
                                         f"({', '.join(csf_jax.problems.NAMES)}) and R >= 1, "
                                         f"got {arg!r}")
    if int(runs) > CACHED_RUNS:
        raise argparse.ArgumentTypeError(f"R must be <= {CACHED_RUNS}, the table's cached runs, "
                                         f"got {arg!r}")
    return name, int(runs)


def aggregate(per_run) -> float:
    """The table's RMSE over runs: the root of the mean of the per-run mean squares."""
    return float(np.sqrt(np.mean(np.square(per_run))))


def row(name: str, runs: int) -> str:
    model = csf_jax.problems.get(name)
    truth, obs, _, ens, keys = simulate_runs(model, runs, 1000, 0)
    with open(os.path.join("results", name, "results.json")) as f:
        cached = json.load(f)["rmse_per_run"]
    robust = jax.jit(jax.vmap(lambda o, e, k: csf_jax.filter(
        None, o, e, problem=model, key=k, config=csf_jax.ROBUST, check_finite=False).mean))
    mean = np.asarray(robust(obs, ens, keys))
    per_run = np.sqrt(np.mean(np.sum((mean - np.asarray(truth)[:, 1:]) ** 2, -1), -1))
    ref = aggregate(cached["reference"][:runs])
    value = aggregate(per_run)
    return (f"| {name} | {runs} | {value:.4f} | {aggregate(cached['csf'][:runs]):.4f} | "
            f"{aggregate(cached['csf_gaussian'][:runs]):.4f} | {ref:.4f} | {value / ref:.2f} | "
            f"{aggregate(cached['csf'][:runs]) / ref:.2f} |")


DESCRIPTION = ("Filter the first R runs of the table's problems with csf_jax.ROBUST and print "
               "its RMSE beside the cached CSF, CSF-G and reference RMSEs of the same runs.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.robust_table``."""
    p = parser("robust_table", DESCRIPTION)
    p.add_argument("cases", nargs="*", type=parse, metavar="PROBLEM=R",
                   help=f"a table problem and its first R runs, R <= {CACHED_RUNS} (default: "
                        f"{' '.join(DEFAULT)})")
    return p


def main(argv=None):
    cases = build_parser().parse_args(argv).cases or [parse(a) for a in DEFAULT]
    print("| problem | runs | ROBUST | CSF (defaults, cached) | CSF-G (cached) | reference | "
          "ROBUST / ref. | CSF / ref. |")
    print("|---|---|---|---|---|---|---|---|")
    for name, runs in cases:
        print(row(name, runs), flush=True)


if __name__ == "__main__":
    main()
