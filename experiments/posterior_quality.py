"""Posterior quality of one CSF filter step against the exact posterior.

    python -m experiments.posterior_quality --out docs/posterior/posterior_quality.json

One filter step whose prior is known exactly: the model's drift is the identity, so with the input
ensemble ``c_i`` the prior is the mixture ``(1/N) sum_i N(c_i, q^2 I)``, which is what CSF's exact
prior (``params=None``) scores. The ensembles hold M distinct centres (M = 1: the Gaussian
``N(m, q^2 I)``; M > 1: a Gaussian mixture). The truth is drawn from that prior, ``y = h(x) + w``
with ``h`` the identity (compared with the Kalman filter's closed form) or the cubic sensor
``x^3`` (noise std 0.1, or the Cauchy problem's Cauchy noise of scale 0.0544 in d = 5). The likelihood factorises over coordinates, so within each mixture component
the exact posterior is a product of 1-D posteriors, found by quadrature on a fine grid; the
components' weights are their evidences. Per case, sampler and step count it reports

* mean error ratio: ``RMSE(CSF mean - truth) / RMSE(exact mean - truth)`` (1 is exact),
* mean bias: ``RMS((CSF mean - exact mean) / exact std)``,
* spread ratio: ``mean(CSF std) / mean(exact std)`` over coordinates and trials (1 is exact),
* coverage: how often the truth lies in the ensemble's central 90% interval (exact: 0.9 on average),

over T trials, inflation 0 (the exact Bayes update), N = 1000.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import shlex
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import CSFConfig, GuidanceConfig, StateSpaceModel, cauchy_noise, gaussian_noise
from csf_jax.filters.csf import csf_filter
from experiments._cli import (
    int_list,
    name_list,
    nonnegative_int,
    parser,
    particle_count,
    positive_int,
)
from experiments._timing import timed


@dataclasses.dataclass(frozen=True)
class Case:
    """One posterior problem: d coordinates, M prior components of std q, a sensor and its noise."""

    name: str
    dim: int = 10
    prior_std: float = 1.0
    components: int = 1
    centre_std: float = 1.0
    sensor: str = "cubic"
    obs_std: float = 0.1
    noise: str = "gaussian"  # or "cauchy" (obs_std is then the scale)


CASES = (
    Case("linear d10 narrow", prior_std=0.3, sensor="linear"),
    Case("linear d10 broad", prior_std=1.0, sensor="linear"),
    Case("cubic d10 gauss narrow", prior_std=0.3),
    Case("cubic d10 gauss broad", prior_std=1.0),
    Case("cubic d20 gauss narrow", dim=20, prior_std=0.3),
    Case("cubic d20 gauss broad", dim=20, prior_std=1.0),
    Case("cubic d10 mixture narrow", prior_std=0.3, components=4),
    Case("cubic d10 mixture broad", prior_std=1.0, components=4),
    Case("cubic d20 mixture narrow", dim=20, prior_std=0.3, components=4),
    Case("cubic d20 mixture broad", dim=20, prior_std=1.0, components=4),
    Case("cubic d5 cauchy narrow", dim=5, prior_std=0.3, obs_std=0.0544, noise="cauchy"),
    Case("cubic d5 cauchy broad", dim=5, prior_std=1.0, obs_std=0.0544, noise="cauchy"),
)


class CaseData(NamedTuple):
    """centres: (T, N, d) the input ensembles.  truth: (T, d).  obs: (T, 1, d)."""

    centres: np.ndarray
    truth: np.ndarray
    obs: np.ndarray


class Exact(NamedTuple):
    """The exact posterior per trial and coordinate: mean, std, 5% and 95% quantiles, (T, d) each."""

    mean: np.ndarray
    std: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def observe_fn(sensor: str):
    if sensor == "linear":
        return lambda x: x
    if sensor == "cubic":
        return lambda x: x ** 3
    raise ValueError(f"unknown sensor {sensor!r}; use 'linear' or 'cubic'")


@functools.cache
def model_for(case: Case) -> StateSpaceModel:
    """Identity drift with process std q: the exact prior of the input ensemble's centres."""
    d = case.dim
    return StateSpaceModel(
        name=f"posterior_quality_{case.sensor}", dim=d, obs_dim=d, num_steps=1, dt=1.0,
        drift=lambda x: x, observe=observe_fn(case.sensor), process_std=case.prior_std,
        obs_noise=(cauchy_noise if case.noise == "cauchy" else gaussian_noise)(case.obs_std),
        initial_truth=lambda key: jnp.zeros((d,)),
        initial_ensemble=lambda key, n: jnp.zeros((n, d)))


def make_data(case: Case, key, trials: int, particles: int) -> CaseData:
    """M centres per trial from ``N(0, centre_std^2 I)``, each held by N/M particles; the truth is a
    draw of the mixture prior; one observation of it."""
    k_c, k_pick, k_x, k_w = jax.random.split(key, 4)
    M, d = case.components, case.dim
    means = case.centre_std * jax.random.normal(k_c, (trials, M, d))
    centres = jnp.repeat(means, -(-particles // M), axis=1)[:, :particles]
    pick = jax.random.randint(k_pick, (trials,), 0, M)
    truth = means[jnp.arange(trials), pick] + case.prior_std * jax.random.normal(k_x, (trials, d))
    draw = jax.random.cauchy if case.noise == "cauchy" else jax.random.normal
    obs = observe_fn(case.sensor)(truth) + case.obs_std * draw(k_w, (trials, d))
    return CaseData(np.asarray(centres), np.asarray(truth), np.asarray(obs)[:, None, :])


def exact_posterior(case: Case, data: CaseData, grid_points: int = 20001) -> Exact:
    """Quadrature, per trial, coordinate and component, in float64 (see the module docstring)."""
    q, r = case.prior_std, case.obs_std
    h = observe_fn(case.sensor)
    T, d = data.truth.shape
    counts = [np.unique(c, axis=0, return_counts=True) for c in data.centres.astype(np.float64)]
    out = np.zeros((4, T, d))
    for t, (means, n_of) in enumerate(counts):
        y = data.obs[t, 0].astype(np.float64)
        lo, hi = means.min(0) - 7 * q, means.max(0) + 7 * q                     # (d,)
        grid = lo[:, None] + (hi - lo)[:, None] * np.linspace(0, 1, grid_points)  # (d, G)
        dx = (hi - lo) / (grid_points - 1)
        resid = (y[:, None] - h(grid)) / r                                      # (d, G)
        loglik = -np.log1p(resid ** 2) if case.noise == "cauchy" else -0.5 * resid ** 2
        logp = -0.5 * ((grid[None] - means[:, :, None]) / q) ** 2 + loglik[None]  # (M, d, G)
        shift = logp.max(axis=(0, 2), keepdims=True)
        dens = np.exp(logp - shift)
        z = dens.sum(-1) * dx[None]                                            # (M, d)
        log_w = np.log(n_of) + np.sum(np.log(z), axis=1)                       # (M,)
        w = np.exp(log_w - log_w.max())
        w /= w.sum()
        marg = np.einsum("m,mdg->dg", w, dens / z[:, :, None])                 # (d, G)
        mean = np.sum(marg * grid, -1) * dx
        var = np.sum(marg * (grid - mean[:, None]) ** 2, -1) * dx
        cdf = np.cumsum(marg, -1) * dx[:, None]
        out[0, t], out[1, t] = mean, np.sqrt(var)
        out[2, t] = [np.interp(0.05, cdf[j], grid[j]) for j in range(d)]
        out[3, t] = [np.interp(0.95, cdf[j], grid[j]) for j in range(d)]
    return Exact(*out)


def run_csf(case: Case, config: CSFConfig, data: CaseData, key):
    """One CSF step per trial (vmapped), exact prior; returns the posterior ensembles (T, N, d)
    and the seconds the compiled step took."""
    model = model_for(case)
    fn = functools.partial(csf_filter, None, problem=model, config=config, return_ensembles=True,
                           check_finite=False)
    keys = jax.random.split(key, data.truth.shape[0])
    res, seconds, _ = timed(jax.jit(jax.vmap(lambda o, e, k: fn(o, e, key=k))),
                            jnp.asarray(data.obs), jnp.asarray(data.centres), keys)
    return np.asarray(res.ensembles[:, 0], np.float64), seconds


def metrics(ens: np.ndarray, exact: Exact, truth: np.ndarray) -> dict:
    """Mean error ratio, mean bias in exact stds, spread ratio and 90% coverage (module docstring)."""
    mean, std = ens.mean(1), ens.std(1)
    finite = bool(np.all(np.isfinite(ens)))
    lo, hi = np.quantile(ens, 0.05, axis=1), np.quantile(ens, 0.95, axis=1)
    rmse = lambda e: float(np.sqrt(np.mean(e ** 2)))
    return {
        "finite": finite,
        "error_ratio": rmse(mean - truth) / rmse(exact.mean - truth),
        "bias": rmse((mean - exact.mean) / exact.std),
        "spread_ratio": float(np.mean(std) / np.mean(exact.std)),
        "coverage": float(np.mean((truth >= lo) & (truth <= hi))),
        "exact_coverage": float(np.mean((truth >= exact.lo) & (truth <= exact.hi))),
    }


SAMPLERS = {  # inflation 0, fixed: the exact Bayes update of the one step
    "kalman": lambda L: CSFConfig(reverse_steps=L, prior_inflation=0.0, adaptive_inflation=False),
    "dps clipped": lambda L: CSFConfig(reverse_steps=L, prior_inflation=0.0, adaptive_inflation=False,
                                       guidance=GuidanceConfig(mode="clipped")),
    "dps raw": lambda L: CSFConfig(reverse_steps=L, prior_inflation=0.0, adaptive_inflation=False,
                                   guidance=GuidanceConfig(mode="raw")),
    # heavy-tailed proposals (the Cauchy column's, experiments.run.CSF_OVERRIDES)
    "kalman t1x32": lambda L: CSFConfig(reverse_steps=L, prior_inflation=0.0, adaptive_inflation=False,
                                        guidance=GuidanceConfig(proposal_df=1, proposals=32)),
}


def evaluate(case: Case, sampler: str, steps: int, *, trials: int, particles: int, seed: int,
             config: CSFConfig | None = None) -> dict:
    """Metrics of one sampler setting on one case (data and exact posterior from ``seed``)."""
    data = make_data(case, jax.random.key(seed), trials, particles)
    exact = exact_posterior(case, data)
    config = config if config is not None else SAMPLERS[sampler](steps)
    ens, seconds = run_csf(case, config, data, jax.random.key(seed + 1))
    row = {"case": case.name, "sampler": sampler, "steps": steps, **metrics(ens, exact, data.truth),
           "seconds": seconds}
    return row


def table(rows) -> str:
    lines = ["| case | sampler | steps | mean error ratio | bias (exact stds) | spread ratio | "
             "90% coverage (exact) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        bad = "" if r["finite"] else " (non-finite)"
        lines.append(f"| {r['case']} | {r['sampler']}{bad} | {r['steps']} | {r['error_ratio']:.3f} | "
                     f"{r['bias']:.3f} | {r['spread_ratio']:.3f} | {r['coverage']:.3f} "
                     f"({r['exact_coverage']:.3f}) |")
    return "\n".join(lines)


def sampler_plan(text: str) -> list[tuple[str, int]]:
    """``'name:steps,steps;name:steps'`` -> ``[(name, steps), ...]`` (an argparse ``type``)."""
    plan = []
    for part in text.split(";"):
        name, _, steps = part.partition(":")
        if name not in SAMPLERS or not steps:
            raise argparse.ArgumentTypeError(f"bad entry {part!r}; expected name:steps,... with "
                                             f"name in {', '.join(SAMPLERS)}")
        plan += [(name, s) for s in int_list(2)(steps)]
    return plan


def _row_key(row) -> tuple:
    return row["case"], row["sampler"], row["steps"]


def write(path: str, command: str, args, rows) -> None:
    """The JSON record (atomically replaced) and its markdown table beside it (``.md``)."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    record = {"command": command, "trials": args.trials, "particles": args.particles,
              "seed": args.seed, "inflation": 0.0, "machine": platform.processor() or
              platform.machine(), "rows": rows}
    with open(path + ".tmp", "w") as f:
        json.dump(record, f, indent=1)
    os.replace(path + ".tmp", path)
    made = sorted({r.get("command", command) for r in rows})
    with open(os.path.splitext(path)[0] + ".md", "w") as f:
        f.write(f"Made by {', then '.join(f'`{c}`' for c in made)} ({args.trials} trials, "
                f"N = {args.particles}, inflation 0, seed {args.seed}; rows already in the file "
                f"are kept, not rerun).\n\n{table(rows)}\n")


DESCRIPTION = ("Measure one CSF filter step against the exact posterior (quadrature) per case "
               "and sampler: mean error ratio, bias, spread ratio and 90% coverage; write the "
               "JSON record to --out and its markdown table beside it.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.posterior_quality``."""
    parser_ = parser("posterior_quality", DESCRIPTION)
    parser_.add_argument("--out", default="docs/posterior/posterior_quality.json",
                         help="JSON record; the markdown table goes beside it (.md). Rows already "
                              "in it (same trials, particles, seed) are kept, not rerun (default "
                              "%(default)s)")
    parser_.add_argument("--trials", type=positive_int, default=16,
                         help="trials per case (default %(default)s)")
    parser_.add_argument("--particles", type=particle_count, default=1000,
                         help="ensemble size N, at least 2 (default %(default)s)")
    parser_.add_argument("--seed", type=nonnegative_int, default=0,
                         help="seed of the data and the sampling (default %(default)s)")
    parser_.add_argument("--samplers", type=sampler_plan,
                         default="kalman:10,20,50;dps clipped:50,500;dps raw:500",
                         help="'name:steps,steps;name:steps' with names from: "
                              + ", ".join(SAMPLERS) + " (default '%(default)s')")
    parser_.add_argument("--cases", type=name_list([c.name for c in CASES], "case"),
                         default=[c.name for c in CASES], metavar="CASE,CASE,...",
                         help="comma-separated case names from: "
                              + ", ".join(c.name for c in CASES) + " (default: all)")
    return parser_


def main(argv=None):
    args = build_parser().parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    command = shlex.join(["python", "-m", "experiments.posterior_quality", *argv])
    done = {}
    if os.path.exists(args.out):
        with open(args.out) as f:
            old = json.load(f)
        if (old["trials"], old["particles"], old["seed"]) == (args.trials, args.particles,
                                                               args.seed):
            done = {_row_key(r): {**r, "command": r.get("command", old["command"])}
                    for r in old["rows"]}
    rows = []
    for case in (c for c in CASES if c.name in args.cases):
        for name, steps in args.samplers:
            row = done.get((case.name, name, steps))
            if row is None:
                row = evaluate(case, name, steps, trials=args.trials, particles=args.particles,
                               seed=args.seed) | {"command": command}
            rows.append(row)
            print(table([row]).splitlines()[-1], flush=True)
            write(args.out, command, args, rows + [r for k, r in done.items()
                                                   if k not in map(_row_key, rows)])
    write(args.out, command, args, rows)
    print(table(rows))


if __name__ == "__main__":
    main()
