"""CSF with few members: the Gaussian part's covariance estimators against the shipped prior.

    python -m experiments.small_ensembles [--problems cauchy,...] [--particles 50] [--runs 3]
        [--seed 7] [--out results/small_ensembles] [--page docs/small_ensembles.md]

On held-out runs of the paper's problems (seed 7; the tables use seed 0), with N members: CSF with
the shipped prior; CSF-G (CSF's sampler with the ensemble's Gaussian as the prior) with the sample
covariance, Ledoit-Wolf shrinkage, or Gaspari-Cohn localisation of half-width r (0.5: the diagonal)
(``CSFConfig.prior.covariance``: the Kalman guidance uses the same covariance); ``csf_jax.PAPER``
with the shipped prior; the EnKF, the PF and the reference. CSF's config is the table's
(``experiments.run.csf_config``). Cells are cached (``experiments.harness``).
"""

from __future__ import annotations

import dataclasses

import csf_jax
from csf_jax import CovarianceConfig
from experiments import cells, cli, harness, interrupt
from experiments import run as main_job

COLUMNS = ["cauchy", "cubic10_indep", "cubic10_corr", "cubic20_indep", "cubic20_corr"]
PROBLEMS = ["double_well", "triple_well"] + COLUMNS
ESTIMATORS = {"sample": CovarianceConfig(), "Ledoit-Wolf": CovarianceConfig("ledoit_wolf"),
              "diagonal": CovarianceConfig("localised", radius=0.5)} | {
    f"loc r={r:g}": CovarianceConfig("localised", radius=r) for r in (1.0, 2.0, 4.0)}


def _gaussian(covariance):
    def settings(case, model):
        config = main_job.csf_g_config(case)
        config = dataclasses.replace(config, prior=dataclasses.replace(config.prior,
                                                                       covariance=covariance))
        return {"prior": csf_jax.gaussian_prior(config.sampler.sigma_max, covariance),
                "config": config}

    return settings


def _paper(case, model):
    return {"params": csf_jax.load_pretrained(case.problem), "config": main_job.csf_config(
        case, "paper")}


ENTRIES = ([harness.Entry("CSF", "csf", main_job._csf())]
           + [harness.Entry(f"CSF-G {name}", "csf", _gaussian(c)) for name, c in
              ESTIMATORS.items()]
           + [harness.Entry("PAPER", "csf", _paper), harness.Entry("EnKF", "enkf"),
              harness.Entry("PF", "pf"),
              harness.Entry("Ref.", "reference", {"own_start": True})])


def main(argv=None):
    p = harness.parser("small_ensembles", "CSF's Gaussian part with few members: covariance "
                       "estimators against the shipped prior and the reference (cached).")
    harness.add_names(p, "--problems", PROBLEMS, COLUMNS, "problem")
    harness.add_names(p, "--filters", [e.label for e in ENTRIES], what="filter")
    harness.add_sizes(p, runs=3, particles=50, seed=7)
    harness.add_outputs(p, "results/small_ensembles", "docs/small_ensembles.md")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, f"N{args.particles}")
    cases = [harness.Case(n, runs=args.runs, particles=args.particles, seed=args.seed)
             for n in args.problems]
    chosen = [e for e in ENTRIES if e.label in args.filters or e.label == "Ref."]
    chosen += harness.extra_entries(args)
    cache = cells.Cache(args.cache)
    results = harness.run(cases, chosen, cache, not args.no_progress)
    rows = main_job.rows(results, cases, chosen)
    record = harness.results_record("small_ensembles", harness.command("small_ensembles", argv),
                                    rows, cache,
                                    harness.output(args, f"results_N{args.particles}.json"))
    by = {(r["case"]["problem"], r["entry"]): r for r in rows}
    body = [[e.label] + [harness.number(by[(c.problem, e.label)].get("rmse_ratio"))
                         for c in cases] for e in chosen if e.label != "Ref."]
    m = record["machine"]
    lines = ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
              f"cores). RMSE over the reference's on the same {args.runs} runs (seed "
              f"{args.seed}), N = {args.particles}:", ""]
             + harness.table(["filter"] + [c.problem for c in cases], body))
    with interrupt.WRITING:
        harness.publish(args, record, lines, f"results_N{args.particles}.json",
                        f"N{args.particles}")


if __name__ == "__main__":
    interrupt.main(main, "small_ensembles", interrupt.CACHED)
