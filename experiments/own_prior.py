"""``train_prior``'s defaults against the shipped priors, on the table's own runs.

    python -m experiments.own_prior [double_well cauchy cubic10_indep cubic10_corr] [--runs R]

Each built-in problem is renamed (``<name>_own``) so that it is a model the package does not know,
a prior is trained for it with ``csf_jax.train_prior(model, jax.random.key(0))`` and nothing else
(under ``runs/own_prior/<name>``, resumable), and CSF with that prior filters the table's runs
(``experiments.run.simulate_runs``, seed 0, N = 1000, the table's CSF config for the problem).
Beside it: the table's PF, EnKF and CSF (shipped prior) RMSE from ``results/<name>/results.json``
(the same runs). Writes ``docs/own_prior.md``.
"""

from __future__ import annotations

import json
import os
import sys
import time

import jax
import numpy as np

import csf_jax
from csf_jax import problems
from experiments._cli import one_of, parser, positive_int, write_page
from experiments._timing import timed
from experiments.run import _errors, csf_config, machine, simulate_runs, summarize

DEFAULT = ("double_well", "cauchy", "cubic10_indep", "cubic10_corr")


def one(name: str, runs: int) -> dict:
    base = problems.get(name)
    model = base._replace(name=f"{name}_own")
    t0 = time.perf_counter()
    trained = csf_jax.train_prior(model, jax.random.key(0),
                                  directory=os.path.join("runs", "own_prior", name))
    train_s = time.perf_counter() - t0
    truth, obs, shocks, ens, keys = simulate_runs(base, runs, 1000, 0)
    config = csf_config(name)
    fn = jax.jit(jax.vmap(lambda o, e, k: csf_jax.filter(trained, o, e, problem=model, key=k,
                                                         config=config).mean))
    mean, filter_s, _ = timed(fn, obs, ens, keys)
    mean = np.asarray(mean)
    own = summarize(_errors(mean, np.asarray(truth)), np.asarray(shocks), model.dim)["rmse"]
    table = {}
    path = os.path.join("results", name, "results.json")
    if os.path.exists(path):
        with open(path) as f:
            res = json.load(f)
        if res["config"]["runs"] == runs and res["config"]["seed"] == 0:
            table = {m: res["rmse"].get(m) for m in ("pf", "enkf", "csf", "reference")}
    return {"problem": name, "dim": model.dim, "own": own, "train_s": train_s,
            "data_s": trained.meta.get("data_seconds"), "fit_s": trained.meta["seconds"],
            "filter_s": filter_s, **{f"table_{k}": v for k, v in table.items()}}


def _fmt(v):
    return "-" if v is None else f"{v:.4g}"


DESCRIPTION = ("Train a prior with csf_jax.train_prior's defaults for each named problem (as a "
               "model the package does not know; under runs/own_prior), filter the table's runs "
               "with it and write the comparison with the shipped prior to --out.")


def build_parser():
    """The command line of ``python -m experiments.own_prior``."""
    p = parser("own_prior", DESCRIPTION)
    p.add_argument("problems", nargs="*", type=one_of(problems.NAMES, "problem"), metavar="PROBLEM",
                   help=f"problems from: {', '.join(problems.NAMES)} (default: "
                        f"{' '.join(DEFAULT)})")
    p.add_argument("--runs", type=positive_int, default=10,
                   help="the table's runs to filter (default %(default)s)")
    p.add_argument("--out", default=os.path.join("docs", "own_prior.md"),
                   help="markdown page to write (default %(default)s)")
    return p


def parse_args(argv=None):
    args = build_parser().parse_args(argv)
    args.problems = args.problems or list(DEFAULT)
    return args


def main(argv=None):
    args = parse_args(argv)
    rows = []
    for name in args.problems:
        rows.append(one(name, args.runs))
        r = rows[-1]
        print(f"{name}: own prior {r['own']:.4f} (train_prior {r['train_s']:.0f} s), table PF "
              f"{_fmt(r.get('table_pf'))} EnKF {_fmt(r.get('table_enkf'))} CSF "
              f"{_fmt(r.get('table_csf'))}", file=sys.stderr, flush=True)
    lines = ["# `train_prior`'s defaults on the table's runs", "",
             f"Made by `python -m experiments.own_prior {' '.join(args.problems)} --runs "
             f"{args.runs}` on {machine().get('cpu', 'this machine')}. Each problem is "
             "filtered as a model the package does not know (renamed `<name>_own`), with a prior "
             "from `csf_jax.train_prior(model, jax.random.key(0))` and its defaults; PF, EnKF, CSF "
             "(shipped prior) and the reference are the table's figures on the same runs "
             "(`results/<name>/results.json`). RMSE as in the table.", "",
             "| problem | d | train_prior s (data + training) | CSF, own prior | CSF, shipped prior | PF | EnKF | reference |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['problem']} | {r['dim']} | {r['train_s']:.0f} ({r['data_s']:.0f} + "
                     f"{r['fit_s']:.0f}) | {r['own']:.4g} | {_fmt(r.get('table_csf'))} | "
                     f"{_fmt(r.get('table_pf'))} | {_fmt(r.get('table_enkf'))} | "
                     f"{_fmt(r.get('table_reference'))} |")
    write_page(args.out, lines)


if __name__ == "__main__":
    main()
