"""What each filter of the filter-choice page costs: its first call and its seconds per step.

    python -m experiments.costs [--out results/costs] [--page docs/choosing.md]

Prints the table of docs/choosing.md ("In short"), with two cost columns; ``--out`` writes
``results.json`` there and ``--page`` rewrites the page's generated block (markers
``results:costs:start`` / ``:end``).

Each row's filter runs at its builder's defaults on one small model (``ROWS``): the Kalman filter
on ``linear20`` (d = 20), the EnKF, the particle filter and CSF (``params=None``) on the zoo's
pendulum (d = 2, N = 200), the local filters on Lorenz-96 (d = 40, N = 20, every site seen), each
for K = 50 steps. A filter is one ``jax.jit`` of ``csf_jax.run``, fresh in every row:

* **first call**: the wall seconds of the first call, tracing and compilation included (what a
  user waits for the first time a model, config and array shapes meet);
* **per step**: the median over ``--repeats`` further calls of their wall seconds over K.

The sharded LETKF's row has no figures: it needs a mesh of several devices. The whole command
takes about a minute on a 2-core CPU.

``--paper`` times instead, on the paper's 10-D and 20-D columns (``cubic10_indep``,
``cubic20_indep``, N = 1000, K = ``PAPER_STEPS``), the EnKF, the README's call (``params=None``)
and the shipped trained prior, each a fresh ``jax.jit`` in the same process, and writes
``results_paper.json`` and the block ``costs_paper`` of docs/benchmark.md: each one's first call,
its seconds per step and their ratio to the EnKF's (about 2 minutes).
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Callable

import jax

import csf_jax
from csf_jax import methods, problems
from csf_jax.problems.lorenz96 import obs_sites
from experiments import cli, harness, interrupt

STEPS = 50


@dataclasses.dataclass(frozen=True)
class Row:
    """A row of the filter-choice table: when to use the filter, its name, its builder as the
    page writes it, its short name, and what it is timed on (None: not timed).

    problem: a name of ``csf_jax.problems``; particles: N (None: the filter takes no ensemble).
    build: ``model -> Method``, the builder at its defaults.
    settings: other fields of the problem's config, as ``(name, value)`` pairs.
    """

    when: str
    name: str
    builder: str
    label: str
    problem: str | None = None
    particles: int | None = None
    build: Callable | None = None
    settings: tuple = ()


PAPER_STEPS = 40
PAPER_COLUMNS = ("cubic10_indep", "cubic20_indep")


def _ring(model) -> csf_jax.Localization:
    """The ring localisation of a Lorenz-96 model whose every site is seen."""
    return csf_jax.ring_localization(model.dim, obs_sites(problems.config("lorenz96")))


ROWS = (
    Row("linear and Gaussian", "the Kalman filter (exact)", "methods.kalman()", "Kalman",
        "linear20", None, lambda m: methods.kalman()),
    Row("sensor close to linear over the ensemble's spread, noises close to Gaussian",
        "the EnKF", "methods.enkf()", "EnKF", "pendulum", 200, lambda m: methods.enkf()),
    Row("a few state dimensions, any sensor, noise or likelihood", "the particle filter",
        "methods.pf()", "PF", "pendulum", 200, lambda m: methods.pf()),
    Row("a nonlinear sensor, a multimodal or heavy-tailed posterior, or jumps the model lacks; "
        "up to a few tens of dimensions", "CSF", "methods.csf()", "CSF", "pendulum", 200,
        lambda m: methods.csf()),
    Row("many dimensions coupled locally (sites on a ring)", "the LETKF", "methods.letkf(loc)",
        "LETKF", "lorenz96", 20, lambda m: methods.letkf(_ring(m)), (("burn_in", 0),)),
    Row("the same, with a nonlinear point sensor", "the local CSF in transform form",
        "methods.local_transform(loc)", "local CSF", "lorenz96", 20,
        lambda m: methods.local_transform(_ring(m)), (("burn_in", 0),)),
    Row("the same, over several devices or hosts", "the sharded LETKF",
        "methods.sharded_letkf(loc, mesh=mesh)", "sharded LETKF"),
)


def paper_rows() -> tuple:
    """The ``--paper`` rows: the EnKF, the README's call and the trained prior on each column."""
    rows = []
    for problem in PAPER_COLUMNS:
        rows += [Row(problem, "the EnKF", "methods.enkf()", "EnKF", problem, 1000,
                     lambda m: methods.enkf()),
                 Row(problem, "CSF, the README's call", "csf_jax.filter(None, ...)",
                     "CSF params=None", problem, 1000, lambda m: methods.csf()),
                 Row(problem, "CSF, the shipped trained prior",
                     f'csf_jax.filter(load_pretrained("{problem}"), ...)', "CSF trained",
                     problem, 1000, lambda m, p=problem: methods.csf(csf_jax.load_pretrained(p)))]
    return tuple(rows)


def paper_page(record: dict) -> list:
    """The ``costs_paper`` block: per column, each filter's first call, seconds per step and
    ratios to the EnKF's."""
    enkf = {r["problem"]: r for r in record["rows"] if r["filter"] == "EnKF"}
    lines = []
    for r in record["rows"]:
        e = enkf[r["problem"]]
        lines.append([f"`{r['problem']}` (d = {r['dim']})", f"`{r['builder']}`",
                      seconds(r["first_call_seconds"]), seconds(r["seconds_per_step"]),
                      f"{r['seconds_per_step'] / e['seconds_per_step']:.3g}x",
                      f"{r['first_call_seconds'] / e['first_call_seconds']:.3g}x"])
    m = record["machine"]
    return (harness.table(["column", "call", "first call", "per step", "per step / EnKF's",
                           "first call / EnKF's"], lines)
            + ["", f"Made by `{record['command']}` on {record['date']}, {m['cpu']} "
               f"({m['cpu_count']} cores, jax {m['jax_backend']}): N = "
               f"{record['rows'][0]['particles']}, K = {record['rows'][0]['steps']} steps, each "
               f"call a fresh `jax.jit` of `csf_jax.run` in one process; the first call includes "
               f"its compilation, the per-step figure is the median of the further calls."])


def inputs(row: Row, steps: int, seed: int):
    """``(model, obs (K, m), ensemble (N, d) or None, key)`` of a row's timing run."""
    model = problems.get(row.problem, num_steps=steps, **dict(row.settings))
    k_sim, k_ens, k_run = jax.random.split(jax.random.key(seed), 3)
    _, obs = csf_jax.simulate(model, k_sim)
    ensemble = None if row.particles is None else model.initial_ensemble(k_ens, row.particles)
    return model, obs, ensemble, k_run


def time_row(row: Row, steps: int, repeats: int, seed: int) -> dict:
    """The seconds of a row's first call (compile included) and its median seconds per step."""
    model, obs, ensemble, key = inputs(row, steps, seed)
    method = row.build(model)
    fn = jax.jit(lambda m, y, e, k: csf_jax.run(m, y, e, model=model, key=k))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(method, obs, ensemble, key))
    first = time.perf_counter() - t0
    calls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(method, obs, ensemble, key))
        calls.append(time.perf_counter() - t0)
    return {"filter": row.label, "builder": row.builder, "problem": row.problem,
            "dim": model.dim, "particles": row.particles, "steps": steps,
            "first_call_seconds": first, "seconds_per_step": statistics.median(calls) / steps}


def seconds(v: float) -> str:
    """A duration for the table: 21 s, 8.3 s, 0.82 ms, 0.016 ms (a no-break space before the
    unit, so that a narrow column does not split them)."""
    if v >= 10:
        return f"{v:.0f}&nbsp;s"
    if v >= 0.1:
        return f"{v:.1f}&nbsp;s"
    return f"{v * 1e3:.2g}&nbsp;ms"


def page(record: dict) -> list:
    """The generated block of the filter-choice page: the table, then how its costs were made."""
    timed = {r["filter"]: r for r in record["rows"]}
    lines = []
    for row in ROWS:
        r = timed.get(row.label)
        cost = [seconds(r["first_call_seconds"]), seconds(r["seconds_per_step"])] if r else ["-", "-"]
        lines.append([row.when, row.name, f"`{row.builder}`", *cost])
    m = record["machine"]
    models = {}
    for r in record["rows"]:
        size = f"d = {r['dim']}" + (f", N = {r['particles']}" if r["particles"] else "")
        models.setdefault(f"`{r['problem']}` ({size})", []).append(r["filter"])
    on = "; ".join(f"{', '.join(names)} on {name}" for name, names in models.items())
    return (harness.table(["your model", "start with", "builder", "first call", "per step"],
                          lines)
            + ["", f"Made by `{record['command']}` on {record['date']}, {m['cpu']} "
               f"({m['cpu_count']} cores, jax {m['jax_backend']}), each filter at its defaults "
               f"for K = {record['rows'][0]['steps']} steps: {on}. The sharded LETKF needs "
               f"several devices: [scale-out](scale_out.md)."])


def main(argv=None):
    p = harness.parser("costs", "Time each filter of docs/choosing.md's table on one small "
                       "model: its first call (compile included) and seconds per step.",
                       cache=False)
    harness.add_outputs(p, "results/costs", "docs/choosing.md")
    p.add_argument("--repeats", type=harness.int_at_least(1), default=3,
                   help="timed calls after the first (default %(default)s)")
    p.add_argument("--steps", type=harness.int_at_least(1), default=None,
                   help=f"filter steps K per call (default {STEPS}; {PAPER_STEPS} with --paper)")
    p.add_argument("--paper", action="store_true",
                   help="time the EnKF, the README's call and the trained prior on the paper's "
                        "10-D and 20-D columns (docs/benchmark.md's costs_paper block)")
    p.add_argument("--seed", type=harness.int_at_least(0), default=0,
                   help="seed of the runs (default %(default)s)")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, "costs_paper" if args.paper else "costs")
    steps = args.steps or (PAPER_STEPS if args.paper else STEPS)
    rows = []
    for row in paper_rows() if args.paper else ROWS:
        if row.build is None:
            continue
        rows.append(time_row(row, steps, args.repeats, args.seed))
        if not args.no_progress:
            r = rows[-1]
            print(f"{row.problem} {row.label}: first call {r['first_call_seconds']:.1f} s, "
                  f"{r['seconds_per_step'] * 1e3:.3g} ms per step", flush=True)
    record = harness.results_record("costs", harness.command("costs", argv), rows)
    if args.paper:
        harness.publish(args, record, paper_page(record), "results_paper.json", "costs_paper")
    else:
        harness.publish(args, record, page(record), tag="costs")


if __name__ == "__main__":
    interrupt.main(main, "costs")
