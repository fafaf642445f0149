"""The main job: CSF against its baselines on one of the paper's problems (paper Sec. 3).

    python -m experiments.run double_well [--methods CSF,EnKF,...] [--preset default|paper]
        [--runs 10] [--particles 1000] [--sf-runs R] [--seed 0] [--out DIR] [--quick]

``ENTRIES`` declares the filters (``experiments.harness``): CSF with the shipped pretrained prior
(``csf_jax.load_pretrained``; the triple well uses the double-well model, the paper's transfer
experiment) and ``--preset``'s config (``csf_jax.filters.csf.PRESETS``: "default",
``CSFConfig()``, or "paper", ``csf_jax.PAPER``; the same on every problem, recorded in the results
file), CSF-G (CSF's sampler with the ensemble's own Gaussian as the prior: what the learned
network has to beat), SF (a score net trained online at every step), the EnKF, the PF and the
near-exact reference filter (``csf_jax.reference_filter``, shocks modelled, started from the model's
initial law: the best achievable). Every filter gets the same runs; "RMSE / ref." is each one's RMSE
over the reference's on the same runs.

SF's online training makes it the slow row: on a CPU it runs on the first run only unless
``--sf-runs`` says otherwise. Cells are cached under ``--cache`` (default ``OUT/cache``: run the same
command again after an interruption and it resumes; a changed filter recomputes its own). ``--out`` writes ``results.json`` and the figures (``experiments.figures``,
matplotlib). The seven-problem table of the README is ``python -m experiments.table``.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import tempfile

import jax
import numpy as np

import csf_jax
from csf_jax import PAPER, CSFConfig, SFConfig, problems
from csf_jax.filters.csf import PRESETS
from experiments import cells, cli, harness, interrupt

RUNS, PARTICLES = 10, 1000  # the table's setting
QUICK = dict(runs=2, particles=100, num_steps=10)
# SF's sampler, the paper's online stage with a base inflation of 0.2 (its score net is trained
# online on one ensemble; without it SF loses the mirror well after a shock), the paper's own on
# the triple well. SF is the paper's baseline: its sampler does not follow CSF's preset.
SF_SAMPLER = dataclasses.replace(PAPER, inflation=csf_jax.InflationConfig(base=0.2, adaptive=True))
SF_SAMPLERS = {"triple_well": PAPER}


def csf_config(case: harness.Case, preset: str = "default") -> CSFConfig:
    """CSF's (and CSF-G's) config in the tables: ``PRESETS[preset]``, the same on every problem
    (``case`` names the problem for callers that vary it)."""
    return PRESETS[preset]


def csf_g_config(case: harness.Case, preset: str = "default") -> CSFConfig:
    """CSF-G's config: CSF's (``csf_config``), with the ensemble component's members drawn by the
    same reverse-diffusion sampler as CSF's (``MixtureConfig.ensemble_draws="sampler"``; with the
    ensemble's Gaussian the default transports them), so that CSF against CSF-G is the learned
    network against the Gaussian, nothing else."""
    config = csf_config(case, preset)
    if config.prior.mixture is None:
        return config
    mixture = dataclasses.replace(config.prior.mixture, ensemble_draws="sampler")
    return dataclasses.replace(config, prior=dataclasses.replace(config.prior, mixture=mixture))


def _csf(preset: str = "default"):
    def settings(case, model):
        return {"params": csf_jax.load_pretrained(case.problem),
                "config": csf_config(case, preset)}

    return settings


def _csf_gaussian(preset: str = "default"):
    def settings(case, model):
        config = csf_g_config(case, preset)
        return {"prior": csf_jax.gaussian_prior(config.sampler.sigma_max,
                                                config.prior.covariance), "config": config}

    return settings


def _sf(case, model):
    return {"config": SFConfig(), "sampler": SF_SAMPLERS.get(case.problem, SF_SAMPLER)}


def entries(sf_runs: int | None = None, reference=csf_jax.ReferenceConfig(),
            preset: str = "default") -> list:
    """The main job's filters, CSF and CSF-G with ``PRESETS[preset]``; SF on the first
    ``sf_runs`` runs (None: all)."""
    return [harness.Entry("CSF", "csf", _csf(preset), batch=2),
            harness.Entry("CSF-G", "csf", _csf_gaussian(preset), batch=2),
            harness.Entry("SF", "sf", _sf, runs=sf_runs, batch=1),
            harness.Entry("EnKF", "enkf"),
            harness.Entry("PF", "pf"),
            harness.Entry("Ref.", "reference", {"config": reference, "own_start": True})]


LABELS = [e.label for e in entries()]


def run_filters(case: harness.Case, chosen, cache: cells.Cache, progress: bool = True) -> dict:
    """``harness.run`` of ``chosen`` on ``case``, SF's runs beside the other filters' on a second
    thread: ``{(case, label): Outcome}``. SF trains a score network online at every step, so on
    a CPU its one run takes about as long as the other filters' compilations and runs together,
    and each side keeps about one core busy. The seconds per step and compile seconds each side
    measures are with the other running beside it; the paper's table (``experiments.table``)
    times one filter at a time."""
    slow = [e for e in chosen if e.method == "sf"]
    rest = [e for e in chosen if e.method != "sf"]
    if not slow or not rest:
        return harness.run([case], chosen, cache, progress=progress)
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        sides = [pool.submit(harness.run, [case], side, cache, progress=progress)
                 for side in (slow, rest)]
        return {k: v for side in sides for k, v in side.result().items()}


def add_preset(p) -> None:
    """``--preset``: CSF's named config (``csf_jax.filters.csf.PRESETS``)."""
    p.add_argument("--preset", choices=sorted(PRESETS), default="default",
                   help="CSF's config: default (CSFConfig(), the mixture prior) or paper "
                        "(csf_jax.PAPER, tuned to the paper's table); default %(default)s")
REFERENCE = "Ref."


def rows(results: dict, cases, chosen) -> list:
    """The results rows of ``cases`` x ``chosen`` entries, with ``rmse_ratio`` over the reference
    where it ran."""
    out = []
    for case in cases:
        data = harness.simulate(case)
        ref = results.get((case, REFERENCE))
        for entry in chosen:
            outcome = results[(case, entry.label)]
            row = harness.describe(case, entry, outcome) | harness.summary(outcome, data)
            if ref is not None:
                runs = outcome.means.shape[0]
                row["rmse_ratio"] = row["rmse"] / float(csf_jax.rmse(
                    ref.means[:runs], data.truth[:runs, 1:]))
            out.append(row)
    return out


def print_table(rows_: list) -> None:
    header = ["filter", "runs", "RMSE", "RMSE / ref.", "before / after 1st shock",
              "s / step per run", "compile s"]
    body = [[r["entry"], r["runs"], harness.number(r["rmse"], 4),
             harness.number(r.get("rmse_ratio")),
             f"{harness.number(r.get('rmse_before_shock'))} / "
             f"{harness.number(r.get('rmse_after_shock'))}",
             f"{r['seconds_per_step']:.2g}", f"{r['compile_seconds']:.1f}"] for r in rows_]
    print("\n".join(harness.table(header, body)))


def figures(out: str, case: harness.Case, results: dict, chosen, preset: str = "default") -> None:
    """The main job's figures, or a line saying how to get matplotlib."""
    try:
        from experiments import figures as fig
    except ImportError as e:
        print(f"figures skipped ({e}); pip install matplotlib to get them")
        return
    data = harness.simulate(case)
    means = {e.label: results[(case, e.label)].means for e in chosen}
    paths = [fig.estimates(out, case.problem, data.truth, data.shocks, means),
             fig.rmse_over_time(out, case.problem, data.truth, data.shocks, means)]
    model = case.model
    if model.dim == 1 and "CSF" in means:
        key = harness.run_keys(case.seed, [0])[0]
        paths.append(fig.prior_vs_model(out, case.problem, model,
                                        csf_jax.load_pretrained(case.problem),
                                        csf_config(case, preset), data.ensembles[0], key[0],
                                        data.shocks[0]))
    print("figures: " + ", ".join(paths))


def main(argv=None):
    p = harness.parser("run", "Run CSF, CSF-G, SF, the EnKF, the PF and the reference filter on "
                       "one of the paper's problems; print the RMSE table, and with --out write "
                       "results.json and the figures.", cache=None)
    p.add_argument("problem", choices=problems.NAMES, metavar="PROBLEM",
                   help="one of: %(choices)s")
    p.add_argument("--methods", type=harness.name_list(LABELS, "filter"), default=LABELS,
                   help=f"comma-separated filters from {','.join(LABELS)} (default: all)")
    add_preset(p)
    p.add_argument("--runs", type=harness.int_at_least(1), default=None,
                   help=f"independent runs (default {RUNS}; {QUICK['runs']} with --quick)")
    p.add_argument("--particles", type=harness.int_at_least(2), default=None,
                   help=f"ensemble size N (default {PARTICLES}; {QUICK['particles']} with "
                        f"--quick)")
    harness.add_sizes(p, seed=0)
    p.add_argument("--sf-runs", type=harness.int_at_least(1), default=None,
                   help="run SF on the first R runs only (default: all on a GPU, 1 on a CPU)")
    p.add_argument("--out", default=None, help="folder for results.json and the figures")
    p.add_argument("--quick", action="store_true",
                   help=f"a first look: {QUICK['runs']} runs, N = {QUICK['particles']}, "
                        f"{QUICK['num_steps']} filter steps, a smaller reference (--runs and "
                        f"--particles, if given, win)")
    args = p.parse_args(argv)
    quick = QUICK if args.quick else {}
    cli.fill(args, {"runs": RUNS, "particles": PARTICLES}, quick)
    cli.check_outputs(p, args)
    runs = args.runs
    sf_runs = args.sf_runs or (1 if jax.default_backend() == "cpu" else None)
    if sf_runs is not None and sf_runs > runs:
        p.error(f"argument --sf-runs: {sf_runs} exceeds the {runs} runs (--runs)")
    case = harness.Case(args.problem, runs=runs, seed=args.seed, particles=args.particles,
                        settings=(("num_steps", quick["num_steps"]),) if quick else ())
    reference = (csf_jax.ReferenceConfig(particles=2000, shock_draws=256) if quick
                 else csf_jax.ReferenceConfig())
    chosen = [e for e in entries(sf_runs, reference, args.preset) if e.label in args.methods]
    chosen += harness.extra_entries(args)
    cache = args.cache or os.path.join(args.out or tempfile.mkdtemp(prefix="csf_run_"), "cache")
    store = cells.Cache(cache)
    results = run_filters(case, chosen, store, progress=not args.no_progress)
    table = rows(results, [case], chosen)
    print_table(table)
    if any(e.method == "sf" for e in chosen) and len(chosen) > 1:
        print("SF ran beside the other filters, on a second thread: each side's seconds are "
              "measured with the other running (python -m experiments.table times one filter at "
              "a time).")
    if args.out:
        with interrupt.WRITING:
            harness.write_results(f"{args.out}/results.json", harness.results_record(
                "run", harness.command("run", argv), table, store, harness.output(args),
                preset=args.preset))
        figures(args.out, case, results, chosen, args.preset)
    if sf_runs is not None and "SF" in args.methods and sf_runs < runs:
        print(f"SF ran on {sf_runs} of {runs} runs (its online training is the slow part on a "
              f"CPU); --sf-runs {runs} for all.")
    if np.isfinite([r["rmse"] for r in table]).all() and (runs, case.particles) != (RUNS,
                                                                                     PARTICLES):
        print(f"This is not the table's setting ({RUNS} runs, N = {PARTICLES}).")


if __name__ == "__main__":
    interrupt.main(main, "run", interrupt.CACHED)
