"""CSF with few members: the Gaussian part's covariance estimators against the shipped prior.

    python -m experiments.small_ensembles [--problems cubic10_indep,...] [--particles 20,50]
        [--methods csf_g,csf_g_lw,...] [--runs 3] [--seed 7] [--out FILE]

Runs each method on ``--runs`` trajectories of each problem (the main job's runs:
``experiments.run.simulate_runs``; seed 7 is held out from the tables' seed 0) with N members and
prints RMSE and RMSE over the near-exact reference's on the same runs. Methods:

* ``csf``: CSF with the shipped prior (its Gaussian base from all N members);
* ``csf_g``, ``csf_g_lw``, ``csf_g_loc<r>``: CSF's sampler with the ensemble's Gaussian prior,
  the covariance the sample one, Ledoit-Wolf shrunk, or localised with Gaspari-Cohn half-width r
  (``CSFConfig.covariance``; the Kalman guidance uses the same covariance);
  ``csf_g_loc0.5`` is the diagonal covariance (the taper vanishes from ``|i - j| = 1`` on);
* ``csf_robust``: ``csf_jax.ROBUST`` with the column's config: the mixture prior, whose particle
  components are the exact forecast law of the N members for i.i.d. process noise;
* ``enkf``, ``pf``, ``reference``.

Every cell is cached in ``runs/small_ensembles`` (an interrupted job resumes); ``--out`` writes
the table as JSON.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np

import csf_jax
from csf_jax import ROBUST, gaussian_prior, problems
from csf_jax.covariance import CovarianceConfig
from csf_jax.pretrained import load_pretrained
from experiments import run as run_mod
from experiments._cli import int_list, name_list, parser, positive_int

CACHE = os.path.join("runs", "small_ensembles")
COLUMNS = ("cauchy", "cubic10_indep", "cubic10_corr", "cubic20_indep", "cubic20_corr")
METHODS = ("csf", "csf_g", "csf_g_lw", "csf_g_loc0.5", "csf_g_loc1", "csf_g_loc2", "csf_g_loc4",
           "csf_robust", "enkf", "pf", "reference")


def covariance_of(method: str) -> CovarianceConfig:
    """The ``CovarianceConfig`` a ``csf_g*`` method name stands for."""
    if method == "csf_g_lw":
        return CovarianceConfig("ledoit_wolf")
    if method.startswith("csf_g_loc"):
        return CovarianceConfig("localised", radius=float(method[len("csf_g_loc"):]))
    return CovarianceConfig()


def method_fn(method: str, name: str, model):
    """``(obs, ens, key) -> FilterResult`` of one run of ``method`` on problem ``name``."""
    base = run_mod.csf_config(name)
    quiet = run_mod.Progress("", 1, enabled=False)
    if method in ("enkf", "pf", "reference"):
        return run_mod.method_fn(method, model, base, None, None, quiet)
    if method == "csf":
        return run_mod.method_fn("csf", model, base, None, load_pretrained(name), quiet)
    if method == "csf_robust":
        cfg = dataclasses.replace(base, adaptive_inflation=ROBUST.adaptive_inflation,
                                  mixture=ROBUST.mixture)
        prior = None if model.process_noise is None else gaussian_prior(cfg.sigma_max)
        return lambda o, e, k: csf_jax.filter(None, o, e, problem=model, key=k, config=cfg,
                                              prior=prior)
    cfg = dataclasses.replace(base, covariance=covariance_of(method))
    return run_mod.method_fn("csf_gaussian", model, cfg, None, None, quiet)


def cell(name: str, n: int, method: str, runs: int, seed: int):
    """Squared errors ``(R, K)`` of one cell; the filtered means are cached."""
    model = problems.get(name)
    truth, obs, _, ens, keys = run_mod.simulate_runs(model, runs, n, seed)
    path = os.path.join(CACHE, f"{name}-N{n}-{method}-s{seed}-r{runs}.npy")
    if os.path.exists(path):
        mean = np.load(path)
    else:
        t0 = time.perf_counter()
        fn = method_fn(method, name, model)
        mean = np.asarray(jax.jit(jax.vmap(fn))(obs, ens, keys).mean)
        os.makedirs(CACHE, exist_ok=True)
        np.save(path + ".tmp.npy", mean)
        os.replace(path + ".tmp.npy", path)
        print(f"  {name} N={n} {method}: {time.perf_counter() - t0:.0f} s", file=sys.stderr,
              flush=True)
    return np.sum((mean - np.asarray(truth)[:, 1:]) ** 2, axis=-1)


def build_parser():
    """The command line of ``python -m experiments.small_ensembles``."""
    p = parser("small_ensembles", "CSF's Gaussian part with few members: covariance estimators "
               "against the shipped prior and the reference (cached, resumable).")
    p.add_argument("--problems", type=name_list(problems.NAMES, "problem"),
                   default=list(COLUMNS), metavar="P,P,...",
                   help="comma-separated problems (default: %(default)s)")
    p.add_argument("--particles", type=int_list(2), default=[20, 50], metavar="N,N,...",
                   help="comma-separated ensemble sizes N (default: %(default)s)")
    p.add_argument("--methods", type=name_list(METHODS, "method"), default=list(METHODS),
                   metavar="M,M,...", help="comma-separated methods (module doc; default: all)")
    p.add_argument("--runs", type=positive_int, default=3,
                   help="runs per cell (default %(default)s)")
    p.add_argument("--seed", type=int, default=7, help="the runs' seed; 7 is held out from the tables' seed 0 "
                   "(default %(default)s)")
    p.add_argument("--out", default=None, help="write the table as JSON here")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    table = {}
    methods = [m for m in args.methods if m != "reference"] + ["reference"]
    for name in args.problems:
        for n in args.particles:
            errs = {m: cell(name, n, m, args.runs, args.seed) for m in methods}
            ref = errs["reference"].mean()
            row = {m: {"rmse": float(np.sqrt(e.mean())), "ratio": float(np.sqrt(e.mean() / ref))}
                   for m, e in errs.items()}
            table.setdefault(name, {})[str(n)] = row
            print(f"| {name} | {n} | " + " | ".join(
                f"{m} {r['rmse']:.3f} ({r['ratio']:.2f})" for m, r in row.items()) + " |",
                flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"runs": args.runs, "seed": args.seed, "rmse": table,
                       "machine": run_mod.machine()}, f, indent=1)


if __name__ == "__main__":
    main()
