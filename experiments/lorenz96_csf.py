"""The local CSF on Lorenz-96: accuracy at d = 40 against the tuned baselines, and scaling in d.

    python -m experiments.lorenz96_csf [--runs R] [--steps K] [--dims D D ...]
        [--scaling-steps K] [--out docs/lorenz96_csf.md]

Accuracy: ``csf_jax.local_filter`` with N = 40 on the runs of ``python -m experiments.lorenz96``
(truth seed 0, ensemble seed 1, the same ``--runs`` and ``--steps``), so its LETKF, EnKF and
climatology figures (read from that sweep's cache, run if missing) are on the same trajectories:
the flow sampler over a few inflations (the stochastic ancestral sampler's limit diverges here:
``experiments.lorenz96_ablation``); a bootstrap particle filter with 1000 particles. Each cell is cached under ``runs/lorenz96_csf``.

Scaling: one run of ``--scaling-steps`` steps (3 beyond d = 1000: ``scaling_steps``) of the
flow sampler per d, in a fresh process each
(peak resident memory is the process's), float32, N = 40: seconds per filter step after
compilation, peak memory, and the RMSE over the second half of the steps (from step 150 of 300,
after the filter's spin-up, where there are that many).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib.util
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import problems
from csf_jax.filters.local_csf import LocalCSFConfig, local_filter
from csf_jax.problems.lorenz96 import obs_sites
from experiments import lorenz96 as baselines
from experiments._cli import multiple_of, parser, positive_int, write_page
from experiments._timing import timed
from experiments.run import machine

CACHE = os.path.join("runs", "lorenz96_csf")
N = 40
#: (setup, sampler, inflations) of the accuracy table.
GRID = (("lorenz96", "flow", (1.0, 1.01, 1.02)), ("lorenz96_arctan", "flow", (1.06,)))


def digest(config: LocalCSFConfig) -> str:
    """A stable short id of a config (Python's ``hash`` of a str differs between processes)."""
    return hashlib.sha1(json.dumps(dataclasses.asdict(config), sort_keys=True).encode()).hexdigest()[:8]


def config_for(sampler: str, inflation: float) -> LocalCSFConfig:
    """The table's settings: the defaults with the sampler and the inflation."""
    return dataclasses.replace(LocalCSFConfig(), sampler=sampler, inflation=inflation)


def _cached(path: str, compute) -> dict:
    """``compute()``'s JSON dict, kept at ``path + ".json"`` (written atomically: an interrupted run
    leaves no half-written cell)."""
    path = path + ".json"
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    out = compute()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".tmp", "w") as f:
        json.dump(out, f)
    os.replace(path + ".tmp", path)
    return out


def csf_cell(name: str, sampler: str, inflation: float, runs: int, steps: int) -> dict:
    """RMSE (time average after burn-in, runs averaged), spread, seconds per step of the local CSF;
    the RMSE per step ``(K,)`` averaged over runs is kept for the figure."""
    config = config_for(sampler, inflation)
    tag = f"{name}_csf_{sampler}_N{N}_R{runs}_K{steps}_infl{inflation}_{digest(config)}"

    def compute():
        cfg = problems.config(name, num_steps=steps)
        model, truth, obs, ens, keys = baselines.data(name, runs, steps, N)
        loc = csf_jax.ring_localization(model.dim, obs_sites(cfg))
        run = jax.jit(jax.vmap(lambda o, e, k: local_filter(
            o, e, problem=model, key=k, localization=loc, config=config, check_finite=False)))
        result, seconds, _ = timed(run, obs, ens, keys)
        per_step = jnp.sqrt(jnp.mean((result.mean - truth[:, 1:]) ** 2, -1))
        ok = bool(result.finite.all())
        return {"rmse": baselines.time_rmse(result.mean, truth, cfg.burn_in) if ok else float("inf"),
                "spread": float(jnp.sqrt(jnp.mean(result.std[:, cfg.burn_in:] ** 2))),
                "seconds_per_step": seconds / (runs * steps),
                "rmse_per_step": np.asarray(per_step.mean(0)).round(5).tolist()}

    out = _cached(os.path.join(CACHE, tag), compute)
    print(f"{name} CSF {sampler} inflation {inflation}: RMSE {out['rmse']:.4f}", file=sys.stderr,
          flush=True)
    return out


def pf_cell(name: str, runs: int, steps: int, particles: int = 1000) -> dict:
    """The bootstrap particle filter's RMSE on the same runs."""

    def compute():
        cfg = problems.config(name, num_steps=steps)
        model, truth, obs, ens, keys = baselines.data(name, runs, steps, particles)
        result = jax.jit(jax.vmap(lambda o, e, k: csf_jax.particle_filter(
            o, e, problem=model, key=k, check_finite=False)))(obs, ens, keys)
        return {"rmse": baselines.time_rmse(result.mean, truth, cfg.burn_in)}

    return _cached(os.path.join(CACHE, f"{name}_pf_N{particles}_R{runs}_K{steps}"), compute)


def scaling_row(dim: int, steps: int) -> dict:
    """One d, measured in this process: seconds per step after compilation, peak RSS, RMSE."""
    model = problems.get("lorenz96", dim=dim, num_steps=steps, burn_in=0)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), N)
    loc = csf_jax.ring_localization(dim, np.arange(dim))
    config = LocalCSFConfig()

    def run(o):
        return local_filter(o, ens, problem=model, key=jax.random.key(2), localization=loc,
                            config=config, check_finite=False)

    result, seconds, compile_s = timed(jax.jit(run), obs)
    seconds /= steps
    err = jnp.sqrt(jnp.mean((result.mean - truth[1:]) ** 2, -1))
    return {"dim": dim, "steps": steps, "seconds_per_step": seconds, "compile_s": compile_s,
            "device": str(jax.devices()[0]), "peak_rss_mib": peak_rss_mib(),
            "rmse_second_half": float(err[steps // 2:].mean())}


def peak_rss_mib() -> float:
    """This process's peak resident memory (``VmHWM``: reset at ``exec``, unlike ``ru_maxrss``,
    which a child started by ``subprocess`` inherits from its parent)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def letkf_curve(name: str, runs: int, steps: int, particles: int, radius: float,
                inflation: float) -> list:
    """The LETKF's per-step RMSE ``(K,)``, runs averaged, with the given settings (for the figure)."""
    cfg = problems.config(name, num_steps=steps)
    model, truth, obs, ens, keys = baselines._data(name, runs, steps, particles)
    result = baselines._letkf_runner(name, model, cfg, radius)(obs, ens, keys,
                                                               jnp.asarray(inflation, jnp.float32))
    return np.asarray(jnp.sqrt(jnp.mean((result.mean - truth[:, 1:]) ** 2, -1)).mean(0)).tolist()


def figure(path: str, curves: dict) -> None:
    """RMSE over time, one panel per setup: ``curves[setup] = {label: (K,) list}``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(6 * len(curves), 3.6), squeeze=False)
    for ax, (name, lines) in zip(axes[0], curves.items()):
        for label, values in lines.items():
            ax.plot(np.arange(1, len(values) + 1), values, lw=0.8, label=label)
        ax.set_yscale("log")
        ax.set_xlabel("filter step")
        ax.set_ylabel("RMSE (mean of runs)")
        ax.set_title(name)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def scaling_steps(dim: int, steps: int) -> int:
    """``steps`` filter steps up to d = 1000 (enough for an RMSE after spin-up), 3 beyond (a
    timing only): the table's CPU budget."""
    return steps if dim <= 1000 else 3


def scaling(dim: int, steps: int) -> dict:
    """``scaling_row`` in a fresh process (so that peak memory is this d's alone), cached."""

    def compute():
        out = subprocess.run([sys.executable, "-m", "experiments.lorenz96_csf", "--scaling-row",
                              str(dim), str(steps)], check=True, capture_output=True, text=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    tag = f"scaling_d{dim}_K{steps}_{digest(LocalCSFConfig())}"
    out = _cached(os.path.join(CACHE, tag), compute)
    print(f"scaling d={dim}: {out['seconds_per_step']:.2f} s/step", file=sys.stderr, flush=True)
    return out


DESCRIPTION = ("The local CSF on Lorenz-96: its accuracy at d = 40 against the tuned LETKF, EnKF, "
               "PF and climatology, and its time and memory per step as d grows; cache each cell "
               "under runs/lorenz96_csf and write the page and its RMSE figure to --out.")
DIM_STEP = 2 * LocalCSFConfig().block  # local_filter needs d to be a multiple of 2 x block
DIMS = (40, 1000, 10000)  # the scaling rows' d


def build_parser():
    """The command line of ``python -m experiments.lorenz96_csf``."""
    p = parser("lorenz96_csf", DESCRIPTION)
    baselines.add_run_arguments(p)
    p.add_argument("--dims", type=multiple_of(DIM_STEP, why=f"the local CSF's d must be a "
                                              f"multiple of 2 x its block of {DIM_STEP // 2} "
                                              f"sites"),
                   nargs="+", default=list(DIMS), metavar="D",
                   help=f"state dimensions of the scaling rows, each a multiple of {DIM_STEP} "
                        f"(default {' '.join(map(str, DIMS))})")
    p.add_argument("--scaling-steps", type=positive_int, default=300,
                   help="filter steps of a scaling row up to d = 1000 (beyond it 3: a timing "
                        "only) (default %(default)s)")
    p.add_argument("--scaling-row", type=int, nargs=2, help=argparse.SUPPRESS)
    p.add_argument("--out", default=os.path.join("docs", "lorenz96_csf.md"),
                   help="markdown page to write; the figure goes beside it "
                        "(default %(default)s)")
    return p


def parse_args(argv=None):
    p = build_parser()
    args = p.parse_args(argv)
    if not args.scaling_row:
        baselines.check_memory(p, args.runs, args.steps)
        if importlib.util.find_spec("matplotlib") is None:
            p.error("the page's RMSE figure needs matplotlib: pip install matplotlib")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.scaling_row:
        print(json.dumps(scaling_row(*args.scaling_row)))
        return
    rows = []
    for name, sampler, inflations in GRID:
        for infl in inflations:
            rows.append((name, sampler, infl, csf_cell(name, sampler, infl, args.runs, args.steps)))
    scale = [scaling(d, scaling_steps(d, args.scaling_steps)) for d in args.dims]
    write_page(args.out, page(args, rows, scale))


def page(args, rows, scale) -> list:
    """The markdown page."""
    cfg = LocalCSFConfig()
    lines = ["# The local CSF on Lorenz-96", "",
             f"Made by `python -m experiments.lorenz96_csf --runs {args.runs} --steps {args.steps} "
             f"--dims {' '.join(map(str, args.dims))} --scaling-steps {args.scaling_steps}` on "
             f"{machine().get('cpu')} (2 cores), float32. `csf_jax.local_filter` with N = {N}, "
             f"`LocalCSFConfig` defaults (half_width {cfg.half_width}, reverse_steps "
             f"{cfg.reverse_steps}, cg_iterations {cfg.cg_iterations}, block {cfg.block}, t_min "
             f"{cfg.t_min}) unless a column says otherwise. Time-averaged RMSE after 200 burn-in "
             f"steps, {args.runs} runs of {args.steps} steps: the runs of `docs/lorenz96.md`, whose "
             f"tuned baselines are repeated here.", ""]
    curves = {}
    for name in dict.fromkeys(r[0] for r in rows):
        c = problems.config(name)
        best_letkf = min((baselines.cell(name, "letkf", n, args.runs, args.steps, radius=r,
                                         inflation=i)["rmse"], n, r, i)
                         for n in (40, 20) for r in baselines.RADII for i in baselines.INFLATIONS)
        best_enkf = min((baselines.cell(name, "enkf", 40, args.runs, args.steps, inflation=i)["rmse"],
                         i) for i in baselines.INFLATIONS)
        lines += [f"## {name}: d = {c.dim}, sensor {c.sensor}, obs std {c.obs_std}", "",
                  "| filter | N | settings | RMSE | spread | s/step |", "|---|---|---|---|---|---|"]
        for rname, sampler, infl, r in rows:
            if rname == name:
                lines.append(f"| CSF, local, {sampler} sampler | {N} | inflation {infl} | "
                             f"{r['rmse']:.3f} | {r['spread']:.3f} | {r['seconds_per_step']:.3f} |")
        lines += [f"| LETKF (tuned) | {best_letkf[1]} | radius {best_letkf[2]}, inflation "
                  f"{best_letkf[3]} | {best_letkf[0]:.3f} | | |",
                  f"| stochastic EnKF (tuned) | 40 | inflation {best_enkf[1]} | {best_enkf[0]:.3f} | | |",
                  f"| bootstrap PF | 1000 | | {pf_cell(name, args.runs, args.steps)['rmse']:.3f} | | |",
                  f"| climatology | | | {baselines.climatology(name, args.runs, args.steps):.3f} | | |",
                  ""]
        best_csf = min((r for r in rows if r[0] == name), key=lambda r: r[3]["rmse"])
        curves[name] = {f"CSF, inflation {best_csf[2]}": best_csf[3]["rmse_per_step"],
                        f"LETKF, N = {best_letkf[1]}": letkf_curve(
                            name, args.runs, args.steps, best_letkf[1], best_letkf[2],
                            best_letkf[3])}
    png = os.path.splitext(args.out)[0] + "_rmse.png"
    figure(png, curves)
    lines += [f"![RMSE over time]({os.path.basename(png)})", "",
              "RMSE over time of the best CSF and the tuned LETKF above (mean of the runs).", ""]
    lines += ["## Scaling in d (flow sampler, identity sensor, N = 40, one run)", "",
              "| d | steps | s/step | compile s | peak RSS MiB | RMSE, 2nd half |",
              "|---|---|---|---|---|---|"]
    for s in scale:
        rmse = (f"{s['rmse_second_half']:.3f}" if s["steps"] >= 100
                else f"({s['steps']} steps: a timing, still spinning up)")
        lines.append(f"| {s['dim']} | {s['steps']} | {s['seconds_per_step']:.2f} | "
                     f"{s['compile_s']:.0f} | {s['peak_rss_mib']:.0f} | {rmse} |")
    return lines


if __name__ == "__main__":
    main()
