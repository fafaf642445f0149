"""How near-exact the reference filter is: its RMSE on the table's runs at more particles.

    python -m experiments.reference [--problems cubic10_indep,...] [--runs 3]
        [--particles 20000,80000] [--out docs/reference/convergence.json]

For each problem, runs ``csf_jax.filters.reference`` on the first ``--runs`` runs of the table
(seed 0, ``experiments.run.simulate_runs``) at each particle count, with the shock hypothesis on,
and once without it (a plain per-coordinate particle filter, the first count), and prints RMSE per
setting. The reference row of the table is near-exact where more particles do not change it:
the sampling error of the per-coordinate filter is then below the table's precision. Rows are
appended to ``--out`` (JSON) with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import numpy as np

from csf_jax import problems  # noqa: E402
from csf_jax.filters.reference import ReferenceConfig  # noqa: E402
from experiments import run as run_mod  # first: it sets XLA's host devices before jax loads
from experiments._cli import int_list, name_list, parser, positive_int  # noqa: E402
from experiments._timing import timed  # noqa: E402


def convergence(name: str, runs: int, counts, seed: int = 0):
    """Rows ``{problem, particles, model_shocks, runs, rmse, rmse_per_run, seconds}``."""
    model = problems.get(name)
    truth, obs, _, ens, keys = run_mod.simulate_runs(model, runs, 1000, seed)
    truth = np.asarray(truth)
    settings = [ReferenceConfig(particles=m) for m in counts]
    settings.append(ReferenceConfig(particles=counts[0], model_shocks=False))
    rows = []
    for cfg in settings:
        fn = jax.jit(jax.vmap(run_mod.method_fn("reference", model, None, None, None, None,
                                                reference=cfg)))
        result, seconds, _ = timed(fn, obs, ens, keys)
        mean = np.asarray(result.mean)
        err = run_mod._errors(mean, truth)
        rows.append({"problem": name, "particles": cfg.particles, "model_shocks": cfg.model_shocks,
                     "runs": runs, "rmse": float(np.sqrt(err.mean())),
                     "rmse_per_run": np.sqrt(err.mean(1)).round(4).tolist(),
                     "seconds": seconds})
        r = rows[-1]
        print(f"| {name} | {r['particles']} | {'yes' if r['model_shocks'] else 'no'} | {runs} | "
              f"{r['rmse']:.4f} | {', '.join(f'{v:.3f}' for v in r['rmse_per_run'])} | "
              f"{r['seconds']:.0f} |", flush=True)
    return rows


DESCRIPTION = ("Run the reference filter on the table's first runs at each particle count (and "
               "once without the shock hypothesis) and print the RMSE per setting; --out appends "
               "the rows to a JSON file.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.reference``."""
    p = parser("reference", DESCRIPTION)
    p.add_argument("--problems", type=name_list(problems.NAMES, "problem"),
                   default=list(problems.NAMES), metavar="P,P,...",
                   help=f"comma-separated problems from: {', '.join(problems.NAMES)} (default: "
                        f"all)")
    p.add_argument("--runs", type=positive_int, default=3,
                   help="the table's first runs to filter (default %(default)s)")
    p.add_argument("--particles", type=int_list(2), default=(20000, 80000), metavar="M,M,...",
                   help="comma-separated particle counts per coordinate, each at least 2 "
                        "(default 20000,80000)")
    p.add_argument("--out", default=None, help="JSON file the rows are appended to (default: none)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    counts = list(args.particles)
    print("| problem | particles per coordinate | shocks modelled | runs | RMSE | per run | s "
          "(compile excluded) |\n|---|---|---|---|---|---|---|", flush=True)
    rows = []
    for name in args.problems:
        rows += convergence(name, args.runs, counts)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        old = json.load(open(args.out)) if os.path.exists(args.out) else {"rows": []}
        old["rows"].extend(rows)
        old["machine"] = run_mod.machine()
        with open(args.out, "w") as f:
            json.dump(old, f, indent=1)
        print(f"appended {len(rows)} rows to {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
