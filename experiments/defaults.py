"""Which default: candidate CSF configs, each change alone, on held-out runs of the paper's
problems and on the zoo.

    python -m experiments.defaults [--candidates CSF,PAPER,...] [--groups table,zoo,moderate]
        [--particles 1000] [--seed 7] [--out results/defaults] [--page docs/defaults.md]

A candidate is a ``CSFConfig`` (``CANDIDATES``), called as a user would on a model of their own:
``params=None`` (no network: the exact particle mixture without the mixture prior, the ensemble's
Gaussian for its ensemble component with it; ``csf_jax.gaussian_prior()`` where the process noise
is not i.i.d.), no per-model setting, as the zoo calls CSF. Three groups of cases (``GROUPS``):

* ``table``: the paper's problems whose columns the candidates disagree on, against the near-exact
  reference on the same runs;
* ``zoo``: the zoo's nine small models (and its outages), against the better of PF and EnKF;
* ``moderate``: the zoo's three models of moderate dimension, against the better of PF and EnKF.

The runs are held out: seed 7, where the committed tables use seed 0, so that no committed
figure is a run a default was chosen on. Cells are cached (``experiments.harness``).
"""

from __future__ import annotations

import dataclasses

import csf_jax
from csf_jax import PriorConfig
from csf_jax.mixture import MixtureConfig
from csf_jax.problems.zoo import MODERATE, ZOO_GAPS
from experiments import cells, cli, harness, interrupt, zoo


def _mixture(**settings) -> csf_jax.CSFConfig:
    """``CSFConfig()`` with ``MixtureConfig(**settings)``."""
    return dataclasses.replace(csf_jax.CSFConfig(),
                               prior=PriorConfig(mixture=MixtureConfig(**settings)))


CANDIDATES = {
    # the learned (here Gaussian) prior alone with the innovation-triggered inflation
    "PAPER": csf_jax.PAPER,
    # the mixture prior with point particle components and no discount
    "mixture": _mixture(particle_ess=0.0, particle_kernel=0.0),
    # the particle reading discounted where its evidence weights have fewer than 2.5 d
    # effective particles
    "mixture+ess": _mixture(particle_kernel=0.0),
    # the particle components widened to a regularised particle filter's kernels
    "mixture+kernel": _mixture(particle_ess=0.0),
    # both: the default
    "CSF": csf_jax.CSFConfig(),
    # the default with shock members only where a jump is the more probable reading
    # (``MixtureConfig.shock_gate``)
    "gated": _mixture(shock_gate=0.5),
    # the same at a jump probability of 2%: shock members only where a jump is not a long shot
    "gated0.02": _mixture(shock_gate=0.02),
    # the default with shocks widened along every direction, also those the sensor does not
    # see (``MixtureConfig.shock_span``)
    "isotropic": _mixture(shock_span="isotropic"),
    # the default with the ensemble component's members drawn afresh by the reverse-diffusion
    # sampler instead of transported (``MixtureConfig.ensemble_draws``)
    "sampler": _mixture(ensemble_draws="sampler"),
    # the default with the transport's Gauss-Newton steps taken with the curvature at the
    # posterior's mode, shared by every member, instead of each member's own
    # (``MixtureConfig.transport_flow``)
    "mode_flow": _mixture(transport_flow="mode"),
    # the default with each member moved from its Tweedie estimate by the exact flow of a
    # Gaussian posterior, instead of about the centre of the Gaussian linearised there
    "member_flow": _mixture(transport_flow="member"),
    # the default with the particle reading a mixture over point and kernel components, each
    # width weighed by how well it describes the forecast and by its evidence
    # (``MixtureConfig.particle_kernel`` a tuple, ``kernel_choice="loo"``)
    "kernel_loo": _mixture(particle_kernel=(0.0, 1.0)),
}

# (problem, runs): the table's columns where the candidates differ most, few runs each; the 20-D
# ones are where the transport's flow matters most
TABLE = (("triple_well", 4), ("double_well", 2), ("cauchy", 2), ("cubic10_corr", 2),
         ("cubic20_indep", 2), ("cubic20_corr", 2))
SMALL = [m for m in zoo.MODELS if m not in MODERATE]
GROUPS = ("table", "zoo", "moderate")


def entry(label: str):
    """The candidate ``label`` as the zoo calls CSF (``experiments.zoo._csf``), all runs of a case
    in one compiled call."""
    return harness.Entry(label, "csf", zoo._csf(CANDIDATES[label]))


def cases(groups, particles: int, seed: int) -> list:
    """The cases of ``groups`` with N = ``particles`` and held-out seed ``seed``."""
    out = []
    if "table" in groups:
        out += [harness.Case(p, runs=r, particles=particles, seed=seed) for p, r in TABLE]
    if "zoo" in groups:
        plain = [harness.Case(m, runs=3, particles=particles, seed=seed,
                              whole_steps=ZOO_GAPS.get(m, 0.0)) for m in SMALL]
        out += plain + [dataclasses.replace(c, outage=zoo.OUTAGES[c.problem]) for c in plain
                        if c.problem in zoo.OUTAGES]
    if "moderate" in groups:
        out += [harness.Case(m, runs=2, particles=particles, seed=seed) for m in MODERATE]
    return out


REFERENCE = harness.Entry("reference", "reference",
                          {"config": csf_jax.ReferenceConfig(), "own_start": True})
CLASSICAL = [harness.Entry("PF", "pf"), harness.Entry("EnKF", "enkf")]


def page(record: dict, candidates) -> list:
    """The generated block: each candidate's RMSE over the better of PF and EnKF, and over the
    reference where the case has one."""
    rows = {}
    for r in record["rows"]:
        rows.setdefault(zoo.label(r["case"]), {})[r["entry"]] = r
    body = []
    for name, r in rows.items():
        best = min(r[k]["rmse"] for k in ("PF", "EnKF"))
        ref = r.get("reference", {}).get("rmse")
        body.append([name, str(r["PF"]["runs"])]
                    + [harness.number(r[c]["rmse"] / best) for c in candidates]
                    + [harness.number(r[c]["rmse"] / ref) if ref else "-" for c in candidates]
                    + [str(sum(r[c]["diverged"] for c in candidates))])
    m = record["machine"]
    return ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). RMSE over the better of PF and EnKF (\"/ best\", "
             f"below 1: better than both) and over the reference (\"/ ref.\"), held-out runs:",
             ""]
            + harness.table(["case", "runs"] + [f"{c} / best" for c in candidates]
                            + [f"{c} / ref." for c in candidates] + ["diverged runs"], body))


def main(argv=None):
    p = harness.parser("defaults", "Candidate default CSF configs, each change alone, on held-out "
                       "runs of the paper's problems and the zoo (cached, resumable).")
    harness.add_names(p, "--candidates", list(CANDIDATES), what="candidate")
    harness.add_names(p, "--groups", GROUPS, what="group")
    harness.add_sizes(p, particles=1000, seed=7)
    harness.add_outputs(p, "results/defaults", "docs/defaults.md")
    p.add_argument("--tag", default=None,
                   help="the page's block and the results file's suffix (default N<particles>)")
    args = p.parse_args(argv)
    tag = args.tag or f"N{args.particles}"
    cli.check_outputs(p, args, tag)
    cache = cells.Cache(args.cache)
    cases_ = cases(args.groups, args.particles, args.seed)
    entries = [entry(c) for c in args.candidates] + CLASSICAL
    results = harness.run(cases_, entries, cache, not args.no_progress)
    table_cases = [c for c in cases_ if c.problem in dict(TABLE)]
    results |= harness.run(table_cases, [REFERENCE], cache, not args.no_progress)
    rows = []
    for case in cases_:
        data = harness.simulate(case)
        for e in entries + ([REFERENCE] if case in table_cases else []):
            outcome = results[(case, e.label)]
            rows.append(harness.describe(case, e, outcome) | harness.summary(outcome, data))
    record = harness.results_record("defaults", harness.command("defaults", argv), rows, cache,
                                    harness.output(args, f"results_{tag}.json"))
    with interrupt.WRITING:
        harness.publish(args, record, page(record, args.candidates),
                        f"results_{tag}.json", tag)


if __name__ == "__main__":
    interrupt.main(main, "defaults", interrupt.CACHED)
