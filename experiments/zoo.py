"""The benchmark of unseen models: CSF with its defaults and with ``csf_jax.ROBUST`` (the mixture
prior) against the PF, the EnKF and a near-exact reference on the zoo's eight models
(``csf_jax.problems.zoo``).

    python -m experiments.zoo [--models a,b] [--runs 10] [--particles 1000] [--seed 0]
        [--out results/zoo] [--page docs/zoo.md]

Every method gets the same N particles, the same trajectories and the same initial ensembles;
CSF runs with no trained prior (``params=None``) and ``csf_jax.CSFConfig()`` ("csf") or
``csf_jax.ROBUST`` ("csf_robust"), the same call for every model. The reference is the Kalman filter for the linear model and a bootstrap particle
filter with ``--reference-particles`` (10^5) for the others (all have d <= 4). Runs are cached
under ``--out/cache`` per model, method, setting and library source: an interrupted job resumes,
and a changed library reruns. Seconds per filter step exclude compilation.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import problems
from csf_jax.filters.kalman import kalman_filter
from csf_jax.problems.zoo import ZOO_GAPS, linear20_gaussian
from experiments._cli import int_at_least, name_list, parser, positive_int, write_page
from experiments.run import machine

METHODS = ("csf", "csf_robust", "pf", "enkf", "reference")
LABELS = {"csf": "CSF", "csf_robust": "CSF-R", "pf": "PF", "enkf": "EnKF",
          "reference": "reference"}
CONFIGS = {"csf": csf_jax.CSFConfig(), "csf_robust": csf_jax.ROBUST}


def simulate(name: str, runs: int, particles: int, seed: int):
    """``model, truth (R, K+1, d), obs (R, K, m) (with the zoo's gaps), ens (R, N, d),
    keys (R,)`` for ``runs`` runs; run i uses ``fold_in(key(seed), i)``."""
    model = problems.get(name)
    keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(jax.random.key(seed), i), 4))(
        jnp.arange(runs))
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(keys[:, 0])
    if name in ZOO_GAPS:
        obs = jax.vmap(lambda k, o: csf_jax.drop_observations(k, o, 0.0,
                                                              whole_steps=ZOO_GAPS[name]))(
            keys[:, 3], obs)
    ens = jax.vmap(lambda k: model.initial_ensemble(k, particles))(keys[:, 1])
    return model, truth, obs, ens, keys[:, 2]


def method_fn(method: str, name: str, model, reference_particles: int):
    """``(obs (K, m), ens (N, d), key) -> mean (K, d)`` for one run of ``method``."""
    if method in CONFIGS:
        # the defaults' exact mixture prior needs i.i.d. process noise; else the Gaussian one
        prior = None if model.process_noise is None else csf_jax.gaussian_prior()
        return lambda o, e, k: csf_jax.filter(None, o, e, problem=model, key=k, prior=prior,
                                              config=CONFIGS[method], check_finite=False).mean
    if method == "pf":
        return lambda o, e, k: csf_jax.particle_filter(o, e, problem=model, key=k,
                                                       check_finite=False).mean
    if method == "enkf":
        return lambda o, e, k: csf_jax.ensemble_kalman_filter(o, e, problem=model, key=k,
                                                              check_finite=False).mean
    if name == "linear20":
        lg = linear20_gaussian()
        return lambda o, e, k: kalman_filter(o, lg=lg).mean

    def reference(o, e, k):
        start = model.initial_ensemble(jax.random.fold_in(k, 1), reference_particles)
        return csf_jax.particle_filter(o, start.astype(e.dtype), problem=model, key=k,
                                       check_finite=False).mean

    return reference


def library_hash() -> str:
    """A hash of the library's source (``csf_jax/**/*.py``): a cached run is made by this code."""
    root = os.path.dirname(csf_jax.__file__)
    digest = hashlib.sha256()
    for folder, _, files in sorted(os.walk(root)):
        for f in sorted(files):
            if f.endswith(".py"):
                with open(os.path.join(folder, f), "rb") as fh:
                    digest.update(f.encode() + fh.read())
    return digest.hexdigest()[:16]


def ident(name: str, method: str, runs: int, particles: int, seed: int, ref_particles: int) -> str:
    """The cache key of a (model, method, setting): what its numbers depend on, the library's
    code included (a changed filter reruns)."""
    what = {"model": name, "code": library_hash(), "config": repr(problems.config(name)), "method": method,
            "runs": runs, "particles": particles, "seed": seed,
            "csf": repr(CONFIGS[method]) if method in CONFIGS else None,
            "reference": ref_particles if method == "reference" else None}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def run_method(fn, obs, ens, keys, runs_at_once: int):
    """Means ``(R, K, d)`` and seconds of execution (compilation apart), ``runs_at_once`` runs per
    vmapped call."""
    batched = jax.jit(jax.vmap(fn))
    means, seconds = [], 0.0
    for lo in range(0, obs.shape[0], runs_at_once):
        args = (obs[lo:lo + runs_at_once], ens[lo:lo + runs_at_once], keys[lo:lo + runs_at_once])
        compiled = batched.lower(*args).compile()
        t0 = time.perf_counter()
        means.append(np.asarray(jax.block_until_ready(compiled(*args))))
        seconds += time.perf_counter() - t0
    return np.concatenate(means), seconds


def rmse(mean, truth) -> float:
    """The paper's RMSE over runs and steps (``csf_jax.rmse``); inf if the run diverged."""
    err = np.sum((mean - truth[:, 1:]) ** 2, -1)
    return float(np.sqrt(np.mean(err))) if np.isfinite(err).all() else float("inf")


def benchmark(name: str, runs: int, particles: int, seed: int, ref_particles: int,
              cache: str, methods=METHODS) -> dict:
    """One model's row: RMSE per method, ratios, worst run, seconds per step."""
    model, truth, obs, ens, keys = simulate(name, runs, particles, seed)
    truth = np.asarray(truth)
    out = {"d": model.dim, "m": model.obs_dim, "K": int(obs.shape[1]), "runs": runs,
           "particles": particles, "rmse": {}, "worst_run": {}, "seconds_per_step": {}}
    for method in methods:
        path = os.path.join(cache, f"{name}-{method}-{ident(name, method, runs, particles, seed, ref_particles)}.npz")
        if os.path.exists(path):
            with np.load(path) as f:
                mean, seconds = f["mean"], float(f["seconds"])
        else:
            at_once = 1 if method == "reference" else runs
            mean, seconds = run_method(method_fn(method, name, model, ref_particles), obs, ens,
                                       keys, at_once)
            tmp = path + ".tmp.npz"
            np.savez(tmp, mean=mean, seconds=seconds)
            os.replace(tmp, path)
        per_run = np.sqrt(np.mean(np.sum((mean - truth[:, 1:]) ** 2, -1), -1))
        out["rmse"][method] = rmse(mean, truth)
        out["worst_run"][method] = float(np.max(per_run))
        out["seconds_per_step"][method] = seconds / (runs * obs.shape[1])
        print(f"  {name:22s} {LABELS[method]:9s} RMSE {out['rmse'][method]:.4f}  "
              f"({seconds:.1f} s)", file=sys.stderr, flush=True)
    best = min(out["rmse"].get("pf", np.inf), out["rmse"].get("enkf", np.inf))
    for method in CONFIGS:
        if method in out["rmse"]:
            out[f"{method}_over_best_baseline"] = out["rmse"][method] / best
            if "reference" in out["rmse"]:
                out[f"{method}_over_reference"] = out["rmse"][method] / out["rmse"]["reference"]
    return out


def page(results: dict, command: str) -> list:
    """The markdown page of ``results``."""
    meta = results["config"]
    m = results["machine"]
    lines = ["# The zoo: CSF on models it was not tuned for", "",
             f"Made by `{command}` on {m['cpu']} ({m['cpu_count']} cores, jax {m['jax_backend']}). "
             f"{meta['runs']} runs per model, N = {meta['particles']} particles for CSF, PF and "
             f"EnKF, seed {meta['seed']}; the reference is the Kalman filter (linear20) or a "
             f"bootstrap PF with {meta['reference_particles']} particles. CSF is "
             f"`csf_jax.filter(None, obs, ens, problem=model, key=key)` with `CSFConfig()` (the "
             f"defaults), CSF-R the same with `config=csf_jax.ROBUST` (the mixture prior), on every "
             f"model (`prior=csf_jax.gaussian_prior()` where the process noise is not i.i.d., bearings: the "
             f"defaults' exact mixture prior refuses it). Ratios: CSF's RMSE over the better of "
             f"PF and EnKF, and over the reference's.",
             "",
             "| model | d | m | K | CSF | CSF-R | PF | EnKF | reference | CSF / best | "
             "CSF-R / best | CSF / ref. | CSF-R / ref. | CSF worst run | CSF-R worst run | "
             "CSF-R s / step |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, row in results["models"].items():
        r = row["rmse"]
        fmt = lambda k: f"{r[k]:.4g}" if k in r else "-"
        ratio = lambda k: f"{row[k]:.3f}" if k in row else "-"
        worst = lambda k: f"{row['worst_run'][k]:.3g}" if k in row["worst_run"] else "-"
        sec = row["seconds_per_step"].get("csf_robust")
        lines.append(f"| {name} | {row['d']} | {row['m']} | {row['K']} | {fmt('csf')} | "
                     f"{fmt('csf_robust')} | {fmt('pf')} | {fmt('enkf')} | {fmt('reference')} | "
                     f"{ratio('csf_over_best_baseline')} | "
                     f"{ratio('csf_robust_over_best_baseline')} | "
                     f"{ratio('csf_over_reference')} | {ratio('csf_robust_over_reference')} | "
                     f"{worst('csf')} | {worst('csf_robust')} | "
                     f"{'-' if sec is None else f'{sec:.4f}'} |")
    lines += ["", "RMSE: the root of the mean over runs and steps of the squared error norm "
              "(`csf_jax.rmse`). The models and why each is hard: "
              "`csf_jax/problems/zoo.py`; lorenz63_gaps has 30% of its observation times "
              "removed. Seconds per step exclude compilation; the machine ran other jobs beside "
              "this one, so they are upper bounds."]
    return lines


DESCRIPTION = ("Benchmark CSF (defaults and csf_jax.ROBUST) against the PF, the EnKF and a "
               "near-exact reference on the zoo's unseen models; cache the runs and write "
               "results.json under --out and the markdown page to --page.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.zoo``."""
    p = parser("zoo", DESCRIPTION)
    p.add_argument("--models", type=name_list(tuple(problems.ZOO), "model"),
                   default=list(problems.ZOO), metavar="M,M,...",
                   help="comma-separated zoo models from: " + ", ".join(problems.ZOO)
                   + " (default: all)")
    p.add_argument("--methods", type=name_list(METHODS, "method"), default=list(METHODS),
                   metavar="M,M,...",
                   help="comma-separated methods from: " + ", ".join(METHODS) + " (default: all)")
    p.add_argument("--runs", type=positive_int, default=10,
                   help="runs per model (default %(default)s)")
    p.add_argument("--particles", type=int_at_least(2), default=1000,
                   help="N for CSF, PF and EnKF, at least 2 (default %(default)s)")
    p.add_argument("--reference-particles", type=int_at_least(2), default=100_000,
                   help="the reference particle filter's particles (default %(default)s)")
    p.add_argument("--seed", type=int_at_least(0), default=0,
                   help="seed of the runs (default %(default)s)")
    p.add_argument("--out", default=os.path.join("results", "zoo"),
                   help="folder for results.json and the cache (default %(default)s)")
    p.add_argument("--page", default=os.path.join("docs", "zoo.md"),
                   help="markdown page to write (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    cache = os.path.join(args.out, "cache")
    os.makedirs(cache, exist_ok=True)
    results = {"config": {"runs": args.runs, "particles": args.particles, "seed": args.seed,
                          "reference_particles": args.reference_particles,
                          "configs": {k: repr(v) for k, v in CONFIGS.items()}},
               "machine": machine(), "models": {}}
    for name in args.models:
        results["models"][name] = benchmark(name, args.runs, args.particles, args.seed,
                                            args.reference_particles, cache, args.methods)
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump(results, f, indent=1)
    command = "python -m experiments.zoo" + "".join(f" {a}" for a in (argv or sys.argv[1:]))
    write_page(args.page, page(results, command))


if __name__ == "__main__":
    main()
