"""``csf_jax.ROBUST`` on the first runs of the paper's table, against the table's cached rows.

    python -m experiments.robust_table [triple_well=10 double_well=5 cauchy=3 cubic10_corr=3]

Each argument is ``problem=R``: the first R runs of the table (same trajectories, initial ensembles
and keys as ``experiments.run``, N = 1000, seed 0), filtered by ``csf_jax.filter(None, ...,
config=csf_jax.ROBUST)``; printed beside the cached CSF, CSF-G and reference RMSEs of the same runs
(``results/<problem>/results.json``). Why ``ROBUST`` is not the default: README, "Models CSF was not
tuned on".
"""

from __future__ import annotations

import json
import os
import sys

import jax
import numpy as np

import csf_jax
from experiments.run import simulate_runs

DEFAULT = ("triple_well=10", "double_well=5", "cauchy=3", "cubic10_corr=3")


def parse(arg: str) -> tuple[str, int]:
    name, _, runs = arg.partition("=")
    if name not in csf_jax.problems.NAMES or not runs.isdigit() or int(runs) < 1:
        raise SystemExit(f"robust_table: expected problem=R with a table problem "
                         f"({', '.join(csf_jax.problems.NAMES)}) and R >= 1, got {arg!r}")
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


def main(argv=None):
    args = (argv if argv is not None else sys.argv[1:]) or list(DEFAULT)
    print("| problem | runs | ROBUST | CSF (defaults, cached) | CSF-G (cached) | reference | "
          "ROBUST / ref. | CSF / ref. |")
    print("|---|---|---|---|---|---|---|---|")
    for name, runs in map(parse, args):
        print(row(name, runs), flush=True)


if __name__ == "__main__":
    main()
