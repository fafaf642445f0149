"""EnSF against the LETKF on EnSF's Lorenz-96 setup (``lorenz96_ensf``).

    python -m experiments.ensf_l96 [--dim 100] [--particles 20] [--runs 5] [--tune-runs 2]
        [--out DIR]

Two setups: ``shocks`` (``lorenz96_ensf`` as registered: random relative shocks of the truth) and
``no_shocks`` (the same without shocks: the setup of EnSF's d = 100 tuning sweep, whose stored
results are the published reference). Run r of a setup draws truth and observations from key r and
the ``N(0, I)`` initial ensemble of ``--particles`` members from key 1000 + r. Filters:

* ``ensf``: ``csf_jax.ensf`` with ``ENSFConfig()`` (the full Monte-Carlo score over all N members);
* ``ensf_j1``: the same with ``batch=1``, each particle scored against one member (the form of
  EnSF's released scripts);
* ``letkf``: ``csf_jax.letkf`` on ``ring_localization(d, range(d))`` at the radius and inflation
  of ``GRID`` with the least RMSE over ``--tune-runs`` separate runs (keys 10000 + r).

Both EnSF rows clip the forecast at 50, as EnSF's Lorenz-96 scripts do. The error of a run is the
RMSE over sites of the analysis mean, ``sqrt(mean_i (mean_i - x_i)^2)``, averaged over analyses
``burn_in + 1 .. K`` (101 .. 150), as EnSF's results summary does. A run whose mean turns non-finite
counts as diverged and is left out of the average. Prints a markdown table (mean and standard error
over runs, run seconds without compilation) and writes ``ensf_l96.json`` to ``--out`` (default
``out/ensf_l96``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax.filters.ensf import ENSFConfig, ensf
from experiments._cli import int_at_least, parser, particle_count, positive_int

SETUPS = {"shocks": {}, "no_shocks": {"shock_probs": (), "shock_sizes": ()}}
GRID = tuple((radius, inflation) for radius in (1.0, 2.0, 4.0, 8.0)
             for inflation in (1.05, 1.1, 1.2, 1.4))
CLIP = 50.0
ENSF_ROWS = {"ensf": ENSFConfig(clip=CLIP), "ensf_j1": ENSFConfig(batch=1, clip=CLIP)}


def run_error(mean, truth, burn_in: int) -> float:
    """Time-averaged RMSE of ``mean (K, d)`` against ``truth (K+1, d)`` over steps after
    ``burn_in``; NaN for a diverged run."""
    err = np.sqrt(np.mean((np.asarray(mean) - np.asarray(truth)[1:]) ** 2, axis=-1))
    return float(err[burn_in:].mean())


def data(model, run: int, particles: int):
    """Truth ``(K+1, d)``, observations ``(K, m)`` and the initial ensemble ``(N, d)`` of ``run``."""
    truth, obs = csf_jax.simulate(model, jax.random.key(run))
    return truth, obs, model.initial_ensemble(jax.random.key(1000 + run), particles)


def letkf_runner(model):
    """``(obs, ensemble, key, radius, inflation) -> mean (K, d)`` for the LETKF on the full ring."""
    loc = csf_jax.ring_localization(model.dim, range(model.dim))

    def go(obs, ens, key, radius, inflation):
        return csf_jax.letkf(obs, ens, problem=model, key=key, localization=loc,
                             config=csf_jax.LETKFConfig(radius=radius, inflation=inflation),
                             check_finite=False).mean

    return go


def timed_mean(fn, *args):
    """``(mean, seconds)``: ``fn(*args)`` waited for (``evaluate`` compiles before the clock)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def tune_letkf(model, cfg, runs: int, particles: int) -> tuple[float, float, list]:
    """The ``GRID`` point with the least mean RMSE over ``runs`` tuning runs (keys 10000 + r)."""
    go = letkf_runner(model)
    scores = []
    for radius, inflation in GRID:
        errs = []
        for r in range(runs):
            truth, obs, ens = data(model, 10000 + r, particles)
            mean = go(obs, ens, jax.random.key(20000 + r), radius, inflation)
            errs.append(run_error(mean, truth, cfg.burn_in))
        score = float(np.mean(errs)) if np.isfinite(errs).all() else math.inf
        scores.append({"radius": radius, "inflation": inflation, "rmse": score})
        print(f"  tune letkf radius {radius:g} inflation {inflation:g}: {score:.3f}", flush=True)
    best = min(scores, key=lambda s: s["rmse"])
    return best["radius"], best["inflation"], scores


def summarise(errs: list, seconds: list) -> dict:
    """Mean and standard error of the finite run errors, the diverged count, the median seconds."""
    ok = np.asarray([e for e in errs if np.isfinite(e)])
    se = float(ok.std(ddof=1) / np.sqrt(ok.size)) if ok.size > 1 else math.nan
    return {"rmse": float(ok.mean()) if ok.size else math.nan, "se": se,
            "diverged": len(errs) - int(ok.size), "runs": len(errs), "errors": errs,
            "run_s": float(np.median(seconds)) if seconds else math.nan}


def evaluate(setup: str, args) -> list[dict]:
    """Every filter's row on ``setup``."""
    cfg = csf_jax.problems.config("lorenz96_ensf", dim=args.dim, **SETUPS[setup])
    model = csf_jax.problems.build(cfg)
    radius, inflation, scores = tune_letkf(model, cfg, args.tune_runs, args.particles)
    runners = {name: (lambda obs, ens, key, c=c: ensf(obs, ens, problem=model, key=key, config=c,
                                                     check_finite=False).mean)
               for name, c in ENSF_ROWS.items()}
    go = letkf_runner(model)
    runners["letkf"] = lambda obs, ens, key: go(obs, ens, key, radius, inflation)
    rows = []
    for name, fn in runners.items():
        errs, seconds = [], []
        for r in range(args.runs):
            truth, obs, ens = data(model, r, args.particles)
            key = jax.random.key(2000 + r)
            if r == 0:
                fn(obs, ens, key)  # compile outside the clock
            mean, sec = timed_mean(fn, obs, ens, key)
            errs.append(run_error(mean, truth, cfg.burn_in))
            seconds.append(sec)
        row = {"setup": setup, "filter": name, "d": args.dim, "N": args.particles,
               **summarise(errs, seconds)}
        if name == "letkf":
            row.update(radius=radius, inflation=inflation, tuning=scores)
        rows.append(row)
        print(f"| {setup} | {name} | {_fmt(row)} | {row['diverged']}/{row['runs']} | "
              f"{row['run_s']:.1f} |", flush=True)
    return rows


def _fmt(row: dict) -> str:
    return f"{row['rmse']:.3f} ± {row['se']:.3f}" if np.isfinite(row["se"]) \
        else f"{row['rmse']:.3f}"


DESCRIPTION = ("EnSF (full Monte-Carlo score, and one member per particle) against a tuned LETKF "
               "on EnSF's Lorenz-96 setup, with and without shocks; print the table and write "
               "ensf_l96.json to --out.")


def build_parser():
    """The command line of ``python -m experiments.ensf_l96``."""
    p = parser("ensf_l96", DESCRIPTION)
    p.add_argument("--dim", type=int_at_least(4, why="Lorenz-96 needs 4 sites"), default=100,
                   help="state dimension d (default %(default)s)")
    p.add_argument("--particles", type=particle_count, default=20,
                   help="ensemble size N (default %(default)s)")
    p.add_argument("--runs", type=positive_int, default=5,
                   help="runs per setup and filter (default %(default)s)")
    p.add_argument("--tune-runs", type=positive_int, default=2,
                   help="separate runs scoring each LETKF setting (default %(default)s)")
    p.add_argument("--setups", nargs="+", choices=tuple(SETUPS), default=list(SETUPS),
                   help="setups to run (default: all)")
    p.add_argument("--out", default="out/ensf_l96", help="output folder (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    print("| setup | filter | RMSE (mean ± se over runs) | diverged | run s |\n"
          "|---|---|---|---|---|", flush=True)
    rows = [row for setup in args.setups for row in evaluate(setup, args)]
    os.makedirs(args.out, exist_ok=True)
    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "jax": jax.__version__,
               "backend": jax.default_backend(), "dtype": str(jnp.zeros(()).dtype)}
    with open(os.path.join(args.out, "ensf_l96.json"), "w") as f:
        json.dump({"machine": machine, "args": {k: v for k, v in vars(args).items()},
                   "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
