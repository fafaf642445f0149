"""The zoo: CSF on models it was not tuned for, against the PF, the EnKF and a near-exact reference.

    python -m experiments.zoo [--models pendulum,...] [--particles 1000] [--runs 10]
        [--out results/zoo] [--page docs/zoo.md]

Prints the table; ``--out`` writes ``results_N<N>.json`` there and ``--page`` rewrites the page's
generated block for this N (the committed command names both).

Every filter gets the same N particles, trajectories and initial ensembles (``experiments.harness``,
seed 0); CSF needs no training (``params=None``): "CSF" is ``CSFConfig()``, the same call on
every model (with ``csf_jax.gaussian_prior()`` where the
process noise is not i.i.d.: the exact mixture prior needs it). The reference is the Kalman filter
for the linear model and a bootstrap PF with 10^5 particles for the others with d <= 4; the
models of moderate dimension (``zoo.MODERATE``, d = 16 to 40) have none. The models and why each
is hard: ``csf_jax/problems/zoo.py``; lorenz63_gaps loses 30% of its
observation times, and the models of ``OUTAGES`` run again with an outage of several steps.
"""

from __future__ import annotations

import dataclasses

import csf_jax
from csf_jax import problems
from csf_jax.problems.zoo import MODERATE, ZOO_GAPS
from experiments import cells, cli, harness, interrupt

MODELS = list(problems.ZOO)
REFERENCE_PARTICLES = 100_000


def _csf(config):
    def settings(case, model):
        prior = None if model.process_noise is None else csf_jax.gaussian_prior()
        return {"config": config, "prior": prior}

    return settings


ENTRIES = [harness.Entry("CSF", "csf", _csf(csf_jax.CSFConfig())),
           harness.Entry("PF", "pf"), harness.Entry("EnKF", "enkf")]


# Observation outages (no observation at steps a .. b-1) on top of a model's own gaps: after one,
# a filter must find the truth again from an ensemble that only the dynamics have moved.
OUTAGES = {"pendulum": (15, 30), "lorenz63_gaps": (60, 100), "ungm": (40, 50)}


def cases(models, runs: int, particles: int) -> list:
    """The zoo's cases: each model with its benchmark gaps, and those of ``OUTAGES`` again with
    their outage."""
    plain = [harness.Case(name, runs=runs, particles=particles,
                          whole_steps=ZOO_GAPS.get(name, 0.0)) for name in models]
    return plain + [dataclasses.replace(c, outage=OUTAGES[c.problem]) for c in plain
                    if c.problem in OUTAGES]


def label(case: dict) -> str:
    """A case's row name: the model, and its outage if it has one."""
    outage = case.get("outage")
    return case["problem"] + ("" if not outage else f", no obs. {outage[0]}-{outage[1] - 1}")


def reference(case: harness.Case) -> tuple | None:
    """``(case, entry)`` of the reference of ``case``: the Kalman filter (linear20) or a PF with
    10^5 particles from the model's initial law, one run at a time (same truth and
    observations: they do not depend on N); None for the models of moderate dimension, where a
    PF of any affordable size collapses."""
    if case.problem in MODERATE:
        return None
    if case.problem == "linear20":
        return case, harness.Entry("reference", "kalman")
    return (dataclasses.replace(case, particles=REFERENCE_PARTICLES),
            harness.Entry("reference", "pf", batch=1))


def page(record: dict) -> list:
    """The generated block of the zoo's page: accuracy, then cost."""
    rows = {(label(r["case"]), r["entry"]): r for r in record["rows"]}
    m = record["machine"]
    filters = tuple(dict.fromkeys(r["entry"] for r in record["rows"] if r["entry"] != "reference"))
    accuracy, cost = [], []
    for name in dict.fromkeys(p for p, _ in rows):
        r = {label: rows.get((name, label)) for label in filters + ("reference",)}
        best = min(r[k]["rmse"] for k in ("PF", "EnKF"))
        ref = r["reference"]["rmse"] if r["reference"] else None
        others = [k for k in filters if k not in ("PF", "EnKF")]
        accuracy.append([name, r["CSF"]["case"]["particles"]]
                        + [harness.number(r[k]["rmse"]) if r[k] else "-" for k in r]
                        + [harness.number(r[k]["rmse"] / best) for k in others]
                        + [harness.number(r[k]["rmse"] / ref) if ref else "-" for k in others])
        cost.append([name] + [f"{r[k]['seconds_per_step']:.2g}" for k in filters]
                    + [f"{r[k]['compile_seconds']:.1f}" for k in filters])
    return ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). RMSE (`csf_jax.rmse`, over the runs and steps) of "
             f"CSF (`CSFConfig()`), the PF, the EnKF and the "
             f"reference; CSF over the better of PF and EnKF (\"/ best\") and over the reference "
             f"(\"/ ref.\"):", ""]
            + harness.table(["model", "N", *filters, "reference"]
                            + [f"{k} / best" for k in filters if k not in ("PF", "EnKF")]
                            + [f"{k} / ref." for k in filters if k not in ("PF", "EnKF")],
                            accuracy)
            + ["", "Seconds per filter step per run (all runs at once, compilation excluded) and "
               "seconds to compile:", ""]
            + harness.table(["model"] + [f"{k} s / step" for k in filters]
                            + [f"{k} compile s" for k in filters], cost))


def main(argv=None):
    p = harness.parser("zoo", "Benchmark CSF (its defaults) against the PF, the EnKF and "
                       "a near-exact reference on the zoo's models (cached, resumable); write "
                       "results.json and the markdown page.")
    harness.add_names(p, "--models", MODELS, what="model")
    harness.add_sizes(p, runs=10, particles=1000)
    harness.add_outputs(p, "results/zoo", "docs/zoo.md")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, f"N{args.particles}")
    cache = cells.Cache(args.cache)
    cases_ = cases(args.models, args.runs, args.particles)
    entries = ENTRIES + harness.extra_entries(args)
    results = harness.run(cases_, entries, cache, not args.no_progress)
    rows = []
    for case in cases_:
        data = harness.simulate(case)
        extra = [reference(case)] if reference(case) is not None else []
        found = results | harness.run([c for c, _ in extra], [e for _, e in extra], cache,
                                      not args.no_progress)
        for c, entry in [(case, e) for e in entries] + extra:
            outcome = found[(c, entry.label)]
            rows.append(harness.describe(c, entry, outcome) | harness.summary(outcome, data))
    record = harness.results_record("zoo", harness.command("zoo", argv), rows, cache,
                                    harness.output(args, f"results_N{args.particles}.json"))
    with interrupt.WRITING:
        harness.publish(args, record, page(record), f"results_N{args.particles}.json",
                        f"N{args.particles}")


if __name__ == "__main__":
    interrupt.main(main, "zoo", interrupt.CACHED)
