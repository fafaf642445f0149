"""The transform-form local CSF against the LETKF and EnSF on Lorenz-96.

    python -m experiments.lorenz96_transform [--parts standard arctan ensf scaling] [--runs 10]
        [--steps 1000] [--tune-runs 2] [--scaling-dims 10000 100000] [--out results]

Parts (each cell cached in ``runs/lorenz96_transform``, so an interrupted job resumes):

* ``standard``: d = 40, identity sensor, R = I, N = 20 and 40;
* ``arctan``: d = 40, arctan sensor, obs std 0.05, N = 40, started from the problem's initial
  ensemble (around the attractor point, spread 1) and from the truth (``x_0 + N(0, 0.1^2 I)``);
* ``ensf``: EnSF's setup (``lorenz96_ensf``, d = 100, N = 20, shocks), the runs of
  ``experiments.ensf_l96`` (truth key r, ensemble key 1000 + r); its EnSF rows are read from
  ``docs/lorenz96_ensf.json``, made on the same runs;
* ``scaling``: seconds per analysis (compilation excluded) and peak memory at large d on the
  EnSF setup.

Tuning never sees the test runs. On d = 40 the LETKF's radius and inflation are chosen on
``--tune-runs`` runs of their own (truth key 100 + r, 500 steps) over ``RADII x INFLATIONS``, and
the transform CSF runs at the LETKF's choice (with a linear sensor it is the LETKF). On the EnSF
setup both are tuned on ``experiments.ensf_l96``'s ``GRID`` and tuning runs. A run is lost when
its time-averaged RMSE exceeds ``LOST`` on d = 40 (the observation std of the identity sensor;
climatology is 3.6); on the EnSF setup, whose shocks throw every filter off for a while, only a
diverged (non-finite) run is lost. Writes ``results/lorenz96{,_arctan,_ensf}/results.json`` (``rmse`` per method) and prints
markdown tables.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import problems
from csf_jax.filters import driver
from csf_jax.filters.letkf import LETKF, LETKFStatic
from csf_jax.filters.local_transform import (
    LOCAL_TRANSFORM,
    LocalTransformConfig,
    TransformStatic,
)
from csf_jax.problems.lorenz96 import obs_sites
from experiments import ensf_l96
from experiments._cli import parser, positive_int
from experiments._timing import timed

CACHE = os.path.join("runs", "lorenz96_transform")
RADII = (2.0, 4.0, 8.0, 15.0)
INFLATIONS = (1.01, 1.02, 1.05, 1.1)
LOST = 1.0
TRUTH_START_STD = 0.1
PARTS = ("standard", "arctan", "ensf", "scaling")


def _cached(tag: str, compute) -> dict:
    path = os.path.join(CACHE, tag + ".json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    out = compute()
    os.makedirs(CACHE, exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f)
    return out


def d40_data(name: str, runs: int, steps: int, particles: int, start: str, seed: int):
    """Truth ``(R, K+1, d)``, obs, initial ensembles ``(R, N, d)`` and filter keys of d = 40 runs:
    truth key ``seed``, ensemble key ``seed + 1`` (the runs of ``experiments.lorenz96`` for seed 0)."""
    model = problems.get(name, num_steps=steps, burn_in=min(200, steps // 2))
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(
        jax.random.split(jax.random.key(seed), runs))
    k_ens = jax.random.key(seed + 1)
    if start == "truth":
        ens = truth[:, :1] + TRUTH_START_STD * jax.random.normal(k_ens, (runs, particles, model.dim))
    else:
        ens = jax.vmap(lambda k: model.initial_ensemble(k, particles))(
            jax.random.split(k_ens, runs))
    return model, truth, obs, ens, jax.random.split(jax.random.key(seed + 2), runs)


def _runner(model, method: str, localization, radius: float, config: LocalTransformConfig):
    if method == "letkf":
        m, static = LETKF, LETKFStatic(float(radius), localization)
    else:
        m = LOCAL_TRANSFORM
        static = TransformStatic(dataclasses.replace(config, radius=radius, inflation=1.0),
                                 localization)
    return jax.jit(lambda o, e, k, infl: driver.run(
        m, o, e, model=model, key=k, config=static, params=infl, check_finite=False).mean)


def run_errors(mean, truth, burn_in: int) -> list:
    """Per run, the time-averaged RMSE over sites after ``burn_in`` (inf for a diverged run)."""
    err = jnp.sqrt(jnp.mean((mean - truth[:, 1:]) ** 2, -1))[:, burn_in:].mean(1)
    return [float(e) if math.isfinite(float(e)) else math.inf for e in np.asarray(err)]


def d40_cell(name, method, particles, runs, steps, start, radius, inflation, seed=0,
             config=LocalTransformConfig()) -> dict:
    tag = (f"{name}_{method}_N{particles}_R{runs}_K{steps}_{start}_s{seed}_r{radius}"
           f"_i{inflation}")

    def compute():
        model, truth, obs, ens, keys = d40_data(name, runs, steps, particles, start, seed)
        cfg = problems.config(name)
        loc = csf_jax.ring_localization(model.dim, obs_sites(cfg))
        run = _runner(model, method, loc, radius, config)
        infl = jnp.asarray(inflation, jnp.float32)
        means, seconds = [], 0.0
        for r in range(runs):           # one run at a time: vmapped, the batched solves crawl
            mean, sec, _ = timed(run, obs[r], ens[r], keys[r], infl)
            means.append(mean)
            seconds += sec
        errs = run_errors(jnp.stack(means), truth, min(200, steps // 2))
        return {"errors": errs, "seconds_per_step": seconds / (runs * steps)}

    return _cached(tag, compute)


def summary(errs: list, lost_above: float = LOST) -> dict:
    """Mean over all runs (inf if one diverged) and over the kept runs, standard error, and the
    lost runs (RMSE above ``lost_above``, or non-finite)."""
    e = np.asarray(errs, np.float64)
    kept = e[np.isfinite(e) & (e <= lost_above)]
    return {"rmse": float(np.mean(np.where(np.isfinite(e), e, np.nan))) if np.isfinite(e).all()
            else math.inf,
            "rmse_kept": float(kept.mean()) if kept.size else math.nan,
            "se": float(e.std(ddof=1) / np.sqrt(e.size)) if np.isfinite(e).all() and e.size > 1
            else math.nan,
            "lost": int(e.size - kept.size), "runs": int(e.size), "errors": errs}


def tune_letkf_d40(name: str, particles: int, tune_runs: int) -> tuple[float, float]:
    best = None
    for radius in RADII:
        for inflation in INFLATIONS:
            cell = d40_cell(name, "letkf", particles, tune_runs, 500, "attractor", radius,
                            inflation, seed=100)
            score = summary(cell["errors"])["rmse"]
            if best is None or score < best[0]:
                best = (score, radius, inflation)
    return best[1], best[2]


def part_d40(name: str, particles_list, starts, args) -> dict:
    rows = []
    for particles in particles_list:
        radius, inflation = tune_letkf_d40(name, particles, args.tune_runs)
        for start in starts:
            for method in ("letkf", "transform"):
                cell = d40_cell(name, method, particles, args.runs, args.steps, start, radius,
                                inflation)
                row = {"filter": method, "N": particles, "start": start, "radius": radius,
                       "inflation": inflation, "seconds_per_step": cell["seconds_per_step"],
                       **summary(cell["errors"])}
                rows.append(row)
                print(f"| {name} | {start} | {method} | {particles} | {radius:g}, {inflation:g} | "
                      f"{row['rmse']:.4f} | {row['lost']}/{row['runs']} | "
                      f"{row['seconds_per_step']:.4f} |", flush=True)
    return {"problem": name, "rows": rows}


def ensf_cell(setup, method, runs, radius, inflation, tune: bool, particles=20) -> dict:
    tag = f"ensf_{setup}_{method}_R{runs}_{'tune' if tune else 'test'}_r{radius}_i{inflation}"

    def compute():
        cfg = problems.config("lorenz96_ensf", **ensf_l96.SETUPS[setup])
        model = problems.build(cfg)
        loc = csf_jax.ring_localization(model.dim, range(model.dim))
        errs, seconds = [], []
        if method == "letkf":
            config = csf_jax.LETKFConfig(radius=radius, inflation=inflation)

            def go(o, e, k):
                return csf_jax.letkf(o, e, problem=model, key=k, localization=loc, config=config,
                                     check_finite=False).mean
        else:
            config = LocalTransformConfig(radius=radius, inflation=inflation)

            def go(o, e, k):
                return csf_jax.local_transform_filter(o, e, problem=model, key=k,
                                                      localization=loc, config=config,
                                                      check_finite=False).mean
        go = jax.jit(go)
        for r in range(runs):
            run = 10000 + r if tune else r
            truth, obs, ens = ensf_l96.data(model, run, particles)
            key = jax.random.key(20000 + r if tune else 2000 + r)
            mean, sec, _ = timed(go, obs, ens, key)
            errs.append(ensf_l96.run_error(mean, truth, cfg.burn_in))
            seconds.append(sec)
        return {"errors": [e if math.isfinite(e) else math.inf for e in errs],
                "run_s": float(np.median(seconds))}

    return _cached(tag, compute)


def part_ensf(args) -> dict:
    setup = "shocks"
    rows = []
    for method in ("letkf", "transform"):
        scores = []
        for radius, inflation in ensf_l96.GRID:
            e = np.asarray(ensf_cell(setup, method, args.tune_runs, radius, inflation, True)
                           ["errors"])
            scores.append((float(e.mean()) if np.isfinite(e).all() else math.inf, radius,
                           inflation))
        _, radius, inflation = min(scores)
        cell = ensf_cell(setup, method, args.runs, radius, inflation, False)
        row = {"filter": method, "N": 20, "radius": radius, "inflation": inflation,
               "run_s": cell["run_s"], **summary(cell["errors"], math.inf),
               "tuning": [{"radius": r, "inflation": i, "rmse": s} for s, r, i in scores]}
        rows.append(row)
    with open(os.path.join("docs", "lorenz96_ensf.json")) as f:
        stored = json.load(f)
    for row in stored["rows"]:
        if row["setup"] == setup and row["filter"] in ("ensf", "ensf_j1"):
            if row["runs"] != args.runs:
                continue
            rows.append({"filter": row["filter"], "N": row["N"], "run_s": row["run_s"],
                         "source": "docs/lorenz96_ensf.json (python -m experiments.ensf_l96)",
                         **summary(row["errors"], math.inf)})
    for row in rows:
        print(f"| lorenz96_ensf | {row['filter']} | {row.get('radius', '')} | "
              f"{row.get('inflation', '')} | {row['rmse']:.3f} | {row['rmse_kept']:.3f} | "
              f"{row['lost']}/{row['runs']} | "
              f"{row['run_s']:.1f} |", flush=True)
    return {"problem": "lorenz96_ensf", "setup": setup, "rows": rows}


def scaling_cell(dim: int, steps: int, radius: float, inflation: float) -> dict:
    """One d of the EnSF setup, in a subprocess of its own (peak memory per d)."""
    tag = f"scaling_d{dim}_K{steps}_r{radius}_i{inflation}"

    def compute():
        code = (f"import json; from experiments.lorenz96_transform import _scale; "
                f"print(json.dumps(_scale({dim}, {steps}, {radius}, {inflation})))")
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                             text=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    return _cached(tag, compute)


def _scale(dim: int, steps: int, radius: float, inflation: float) -> dict:
    from experiments.lorenz96_csf import peak_rss_mib
    cfg = problems.config("lorenz96_ensf", dim=dim, num_steps=steps, burn_in=0)
    model = problems.build(cfg)
    truth, obs, ens = ensf_l96.data(model, 0, 20)
    loc = csf_jax.ring_localization(dim, range(dim))
    config = LocalTransformConfig(radius=radius, inflation=inflation)
    go = jax.jit(lambda o: csf_jax.local_transform_filter(
        o, ens, problem=model, key=jax.random.key(2000), localization=loc, config=config,
        check_finite=False))
    result, seconds, compile_s = timed(go, obs)
    err = np.sqrt(np.mean((np.asarray(result.mean) - np.asarray(truth)[1:]) ** 2, -1))
    return {"dim": dim, "steps": steps, "seconds_per_analysis": seconds / steps,
            "compile_s": compile_s, "peak_rss_mib": peak_rss_mib(),
            "rmse_last": float(err[-1]), "device": str(jax.devices()[0])}


def part_scaling(args, ensf_part: dict | None) -> dict:
    radius, inflation = 1.0, 1.4
    if ensf_part is not None:
        row = next(r for r in ensf_part["rows"] if r["filter"] == "transform")
        radius, inflation = row["radius"], row["inflation"]
    rows = [scaling_cell(dim, args.scaling_steps, radius, inflation) for dim in args.scaling_dims]
    for row in rows:
        print(f"| {row['dim']} | {row['steps']} | {row['seconds_per_analysis']:.2f} | "
              f"{row['compile_s']:.0f} | {row['peak_rss_mib']:.0f} |", flush=True)
    return {"radius": radius, "inflation": inflation, "rows": rows}


def machine() -> dict:
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "jax": jax.__version__,
            "backend": jax.default_backend(), "dtype": "float32"}


def write(out: str, name: str, payload: dict, command: str) -> None:
    folder = os.path.join(out, name)
    os.makedirs(folder, exist_ok=True)
    rmse = {}
    for row in payload.get("rows", []):
        key = "_".join(str(x) for x in (row["filter"], f"N{row['N']}", row.get("start", ""))
                       if x).rstrip("_")
        rmse[key] = row["rmse"]
    with open(os.path.join(folder, "results.json"), "w") as f:
        json.dump({"command": command, "machine": machine(), "lost_above": LOST,
                   "rmse": rmse, **payload}, f, indent=1)


DESCRIPTION = ("The transform-form local CSF against the tuned LETKF (and EnSF on its setup) on "
               "Lorenz-96; writes results/lorenz96*/results.json.")


def build_parser():
    p = parser("lorenz96_transform", DESCRIPTION)
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS),
                   help="which tables to make (default: %(default)s)")
    p.add_argument("--runs", type=positive_int, default=10,
                   help="test runs per cell (default: %(default)s)")
    p.add_argument("--steps", type=positive_int, default=1000,
                   help="filter steps per d = 40 run (default: %(default)s)")
    p.add_argument("--tune-runs", type=positive_int, default=2,
                   help="tuning runs per grid point, apart from the test runs "
                        "(default: %(default)s)")
    p.add_argument("--scaling-dims", type=positive_int, nargs="+", default=[10000, 100000],
                   help="d of the scaling table (default: %(default)s)")
    p.add_argument("--scaling-steps", type=positive_int, default=3,
                   help="analyses timed per d (default: %(default)s)")
    p.add_argument("--out", default="results",
                   help="folder of the results/<problem>/results.json files "
                        "(default: %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    command = "python -m experiments.lorenz96_transform " + " ".join(
        argv if argv is not None else sys.argv[1:])
    t0 = time.time()
    ensf_part = None
    if "standard" in args.parts:
        write(args.out, "lorenz96", part_d40("lorenz96", (20, 40), ("attractor",), args), command)
    if "arctan" in args.parts:
        write(args.out, "lorenz96_arctan",
              part_d40("lorenz96_arctan", (40,), ("attractor", "truth"), args), command)
    if "ensf" in args.parts:
        ensf_part = part_ensf(args)
        write(args.out, "lorenz96_ensf", ensf_part, command)
    if "scaling" in args.parts:
        scaling = part_scaling(args, ensf_part)
        folder = os.path.join(args.out, "lorenz96_ensf")
        os.makedirs(folder, exist_ok=True)
        with open(os.path.join(folder, "scaling.json"), "w") as f:
            json.dump({"command": command, "machine": machine(), **scaling}, f, indent=1)
    print(f"done in {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
