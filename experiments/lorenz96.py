"""Lorenz-96: the local CSF in transform form against the LETKF, EnSF and the local iterative
smoother, tuned on runs of their own.

    python -m experiments.lorenz96 [--setups identity,arctan,ensf,ensf_calm] [--runs 10]
        [--out results/lorenz96] [--page docs/lorenz96.md]

Setups (``csf_jax.problems``):

* ``identity``: d = 40, every site observed with R = I, N = 10, 20 and 40, 1000 steps;
* ``arctan``: d = 40, an arctan sensor with noise std 0.05, N = 10, 20 and 40 started from the
  problem's initial ensemble, and N = 40 from the truth (``x_0 + N(0, 0.1^2 I)``);
* ``ensf`` and ``ensf_calm``: EnSF's setup (``lorenz96_ensf``: d = 100, arctan sensor, N = 20, an
  ``N(0, I)`` ensemble far from the truth), with its random shocks of the truth (and the same runs
  from the truth, ``x_0 + N(0, 0.1^2 I)``) and without.

Filters: the LETKF and the transform CSF at the radius and inflation with the least RMSE on two
tuning runs (runs 100 and 101, never tested on; the transform CSF takes the LETKF's choice on
d = 40, where with a linear sensor it is the LETKF), the transform CSF with its defaults
(``LocalTransformConfig()``, no tuning), the local iterative smoother (``csf_jax.ienks``, the
iterative baseline) tuned on the same grid and runs and at its defaults, and on EnSF's setup
EnSF (``ENSFConfig(clip=50)``, EnSF's own settings). A run's error is the time average of the RMSE over sites after the burn-in (200
steps on d = 40; analyses 101-150 on EnSF's setup); a run is lost when the filter diverged or
its error exceeds both ``LOST`` and ``FLOOR`` times the least error any filter of the table reaches
on that run from the truth, where the setup has a start at the truth (``lost_runs``): with jumps
the truth's later jumps alone, seen through the flat arctan, keep every filter near 1 on some
runs, from whatever start. Every run is a cached cell of ``experiments.harness``.

``--study adaptive``: the settings that adapt online, each alone (``ADAPTIVE_RUNS``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

import csf_jax
from csf_jax import problems
from csf_jax.problems.lorenz96 import obs_sites
from experiments import cells, cli, harness, interrupt

D40 = (("num_steps", 1000), ("burn_in", 200))
TRUTH_SPREAD = 0.1  # a start at the truth: x_0 + N(0, TRUTH_SPREAD^2 I)
CALM = (("shock_probs", ()), ("shock_sizes", ()))
SETUPS = {  # name: (test cases, d = 40 grid or EnSF grid)
    "identity": [harness.Case("lorenz96", D40, particles=n) for n in (10, 20, 40)],
    "arctan": [harness.Case("lorenz96_arctan", D40, particles=n) for n in (10, 20, 40)]
              + [harness.Case("lorenz96_arctan", D40, particles=40, start="truth",
                              spread=TRUTH_SPREAD)],
    "ensf": [harness.Case("lorenz96_ensf", particles=20),
             harness.Case("lorenz96_ensf", particles=20, start="truth", spread=TRUTH_SPREAD)],
    "ensf_calm": [harness.Case("lorenz96_ensf", CALM, particles=20)],
}
D40_GRID = [(r, i) for r in (2.0, 4.0, 8.0, 15.0) for i in (1.01, 1.02, 1.05, 1.1)]
ENSF_GRID = [(r, i) for r in (1.0, 2.0, 4.0, 8.0) for i in (1.05, 1.1, 1.2, 1.4)]
LOST, FLOOR = 1.0, 1.5
CONFIGS = {"letkf": csf_jax.LETKFConfig, "local_transform": csf_jax.LocalTransformConfig,
           "ienks": csf_jax.IEnKSConfig}
TUNE_RUNS, TUNE_FIRST = 2, 100


def _local(method: str, radius: float | None = None, inflation: float | None = None,
           **fields):
    """Builder settings of a local filter on the case's ring; None: the config's defaults; a
    given radius and inflation are fixed settings (no adaptive inflation unless ``fields`` sets
    one); a radius alone: the defaults at that radius; ``fields``: other config fields."""
    def settings(case, model):
        loc = csf_jax.ring_localization(model.dim, obs_sites(problems.config(
            case.problem, **dict(case.settings))))
        config = CONFIGS[method]()
        if inflation is not None:
            config = dataclasses.replace(config, radius=radius, inflation=inflation,
                                         adaptive=0.0)
        elif radius is not None:
            config = dataclasses.replace(config, radius=radius)
        return {"localization": loc, "config": dataclasses.replace(config, **fields)}

    return settings


def window(case: harness.Case) -> tuple:
    cfg = problems.config(case.problem, **dict(case.settings))
    return cfg.burn_in, cfg.num_steps


def errors(outcome, case) -> np.ndarray:
    """Per run, the time-averaged RMSE over sites in the case's window (inf: diverged)."""
    return np.asarray(harness.summary(outcome, harness.simulate(case),
                                      window(case))["window_rmse_per_run"])


def tune(case: harness.Case, method: str, grid, cache, progress) -> tuple:
    """The grid point with the least mean error over the tuning runs of ``case``; and the
    scores."""
    short = (("num_steps", 500), ("burn_in", 200)) if case.settings == D40 else case.settings
    tuning = dataclasses.replace(case, settings=short, runs=TUNE_RUNS, first_run=TUNE_FIRST,
                                 start="model")
    entries = [harness.Entry(f"{method} {r:g}/{i:g}", method, _local(method, r, i), batch=1)
               for r, i in grid]
    found = harness.run([tuning], entries, cache, progress)
    scores = [float(errors(found[(tuning, e.label)], tuning).mean()) for e in entries]
    return grid[int(np.nanargmin(np.where(np.isfinite(scores), scores, np.nan)))], scores


def setup_rows(name: str, cases, cache, progress, extra=()) -> list:
    """The rows of one setup: each filter on each case, with its tuning."""
    rows = []
    for case in cases:
        grid = D40_GRID if case.problem != "lorenz96_ensf" else ENSF_GRID
        (r, i), scores = tune(case, "letkf", grid, cache, progress)
        chosen = {"LETKF": ("letkf", (r, i), scores)}
        ensf = case.problem == "lorenz96_ensf"
        if ensf:
            chosen["transform CSF"] = ("local_transform",) + tune(case, "local_transform", grid,
                                                                  cache, progress)
        else:
            chosen["transform CSF"] = ("local_transform", (r, i), scores)
        chosen["IEnKS"] = ("ienks",) + tune(case, "ienks", grid, cache, progress)
        entries = [harness.Entry(label, m, _local(m, *ri), batch=1)
                   for label, (m, ri, _) in chosen.items()]
        entries += [harness.Entry("transform CSF, defaults", "local_transform",
                                  _local("local_transform"), batch=1),
                    harness.Entry("IEnKS, defaults", "ienks", _local("ienks"), batch=1)]
        if ensf:
            entries.append(harness.Entry("EnSF", "ensf", {"config": csf_jax.ENSFConfig(clip=50.0)},
                                         batch=1))
        entries += list(extra)
        for row in entry_rows(name, case, entries, cache, progress):
            tuned = chosen.get(row["entry"])
            row["tuned"] = None if tuned is None else {"radius": tuned[1][0],
                                                       "inflation": tuned[1][1],
                                                       "grid_scores": tuned[2]}
            rows.append(row)
    return lost_runs(rows)


def lost_runs(rows) -> list:
    """``rows`` of one setup with ``lost`` and ``error_kept`` set: a run is lost when it diverged
    or its error exceeds ``LOST`` and ``FLOOR`` times the floor, the least error of any row
    started at the truth on the same run (same N); 0 where the setup has no such row."""
    floors = {}
    for r in rows:
        if r["case"]["start"] == "truth":
            err = np.asarray(r["window_rmse_per_run"], np.float64)
            n = r["case"]["particles"]
            floors[n] = np.fmin(floors.get(n, np.inf), np.where(np.isfinite(err), err, np.inf))
    out = []
    for r in rows:
        err = np.asarray(r["window_rmse_per_run"], np.float64)
        floor = floors.get(r["case"]["particles"], np.zeros_like(err))
        lost = ~np.isfinite(err) | (err > np.maximum(LOST, FLOOR * floor))
        out.append(r | {"lost": int(lost.sum()),
                        "error_kept": float(err[~lost].mean()) if (~lost).any() else None})
    return out


def entry_rows(name: str, case: harness.Case, entries, cache, progress) -> list:
    """Each entry's row on ``case`` of setup ``name``: its summary and the mean error over runs
    (``lost_runs`` adds the lost runs)."""
    found = harness.run([case], entries, cache, progress)
    data = harness.simulate(case)
    rows = []
    for entry in entries:
        outcome = found[(case, entry.label)]
        rows.append(harness.describe(case, entry, outcome)
                    | harness.summary(outcome, data, window(case))
                    | {"setup": name, "error": float(errors(outcome, case).mean())})
    return rows


# The settings that adapt online, each alone (``--study adaptive``): each filter at radius 4 with
# the fixed inflation 1.05, with the EnKF-N's inflation (``adaptive``, no fixed inflation) at two
# certainties, the LETKF with the radius chosen online from ``ADAPTIVE_RADII`` (``radii``), alone
# and with the inflation, the transform CSF without its trust bound (``trust=0``), with its
# defaults (radius 15, 6 in the steps far from the observations, the EnKF-N's inflation at
# certainty 2, the bound), and with its defaults at one radius throughout (15 or 6); on runs of a
# seed of their own, apart from the tuned rows' test runs (and from the truth where the table
# has that start, for the lost runs' floor).
ADAPTIVE_SEED = 11
ADAPTIVE_RUNS = {"ensf_calm": 10, "ensf": 10, "identity": 5, "arctan": 3}
ADAPTIVE_PARTICLES = {"ensf_calm": 20, "ensf": 20, "identity": 20, "arctan": 40}
ADAPTIVE_CERTAINTIES = (2.0, 4.0)
ADAPTIVE_RADII = (2.0, 4.0, 8.0, 16.0)


def adaptive_rows(cache, progress) -> list:
    """The rows of the adaptive-inflation study (``ADAPTIVE_RUNS``)."""
    entries = []
    for method, name in (("letkf", "LETKF"), ("local_transform", "transform CSF")):
        entries.append(harness.Entry(f"{name}, fixed", method, _local(method, 4.0, 1.05),
                                     batch=1))
        entries += [harness.Entry(f"{name}, EnKF-N {x:g}", method,
                                  _local(method, 4.0, 1.0, adaptive=x), batch=1)
                    for x in ADAPTIVE_CERTAINTIES]
        if method == "local_transform":
            entries += [harness.Entry(f"{name}, fixed, unbounded", method,
                                      _local(method, 4.0, 1.05, trust=0.0), batch=1),
                        harness.Entry(f"{name}, EnKF-N 2, unbounded", method,
                                      _local(method, 4.0, 1.0, adaptive=2.0,
                                             trust=0.0), batch=1),
                        harness.Entry(f"{name}, defaults", method, _local(method), batch=1),
                        harness.Entry(f"{name}, defaults, radius 15 throughout", method,
                                      _local(method, far_radius=0.0), batch=1),
                        harness.Entry(f"{name}, defaults, radius 6 throughout", method,
                                      _local(method, 6.0), batch=1)]
        if method == "letkf":
            entries += [harness.Entry(f"{name}, radii", method,
                                      _local(method, radii=ADAPTIVE_RADII), batch=1),
                        harness.Entry(f"{name}, EnKF-N 2, radii", method,
                                      _local(method, 4.0, 1.0, adaptive=2.0, radii=ADAPTIVE_RADII),
                                      batch=1)]
    cases = {name: next(c for c in SETUPS[name]
                        if c.particles == ADAPTIVE_PARTICLES[name] and c.start == "model")
             for name in ADAPTIVE_RUNS}
    rows = []
    for name, runs in ADAPTIVE_RUNS.items():
        case = dataclasses.replace(cases[name], runs=runs, seed=ADAPTIVE_SEED)
        mine = entry_rows(name, case, entries, cache, progress)
        if any(c.start == "truth" for c in SETUPS[name]):
            truth = dataclasses.replace(case, start="truth", spread=TRUTH_SPREAD)
            mine += entry_rows(name, truth, entries, cache, progress)
        rows += lost_runs(mine)
    return rows


def adaptive_page(record: dict) -> list:
    """The generated block of the adaptive-inflation study."""
    m = record["machine"]
    body = [[r["setup"], r["case"]["particles"], r["case"]["start"], r["entry"],
             harness.number(r["error"], 4), f"{r['lost']}/{r['runs']}",
             harness.number(r["error_kept"], 4)] for r in record["rows"]]
    return ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). Seed {ADAPTIVE_SEED}; \"fixed\": radius 4, "
             f"inflation 1.05; \"EnKF-N x\": radius 4, `adaptive=x`, `inflation=1`; \"radii\": "
             f"`radii={ADAPTIVE_RADII}`; \"unbounded\": `trust=0`; \"defaults\": "
             f"`LocalTransformConfig()` (radius 15, radius 6 in a step whose EnKF-N factor "
             f"exceeds 1.5, `adaptive=2`, `inflation=1`, `trust=6`); \"radius 15 throughout\": "
             f"`far_radius=0`; \"radius 6 throughout\": `radius=6`. Error, lost and kept as in "
             f"the table above.", ""]
            + harness.table(["setup", "N", "start", "filter", "error", "lost",
                             "error of kept runs"], body))


def page(record: dict) -> list:
    """The generated block of the Lorenz-96 page."""
    m = record["machine"]
    body = []
    for r in record["rows"]:
        c, t = r["case"], r["tuned"]
        body.append([r["setup"], c["particles"], c["start"] if c["start"] != "model" else "model",
                     r["entry"], "-" if t is None else f"{t['radius']:g} / {t['inflation']:g}",
                     harness.number(r["error"], 4), f"{r['lost']}/{r['runs']}",
                     harness.number(r["error_kept"], 4), f"{r['seconds_per_step']:.2g}"])
    return ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). Error: per run, the time-averaged RMSE over sites "
             f"after the burn-in, then the mean over runs (\"diverged\" if a run diverged); lost: "
             f"runs that diverged or are above {LOST} and above {FLOOR} times the least error of "
             f"the filters started at the truth on the same run (where the setup has that "
             f"start); kept: the mean over the other runs. Radius / inflation: chosen on "
             f"{TUNE_RUNS} tuning runs of their own.", ""]
            + harness.table(["setup", "N", "start", "filter", "radius / inflation", "error",
                             "lost", "error of kept runs", "s / step"], body))


def parser(module: str, description: str, setups):
    """A Lorenz-96 job's command line: ``--setups`` (names of ``setups``), ``--runs`` (10), the
    cache and the outputs (results/lorenz96, docs/lorenz96.md)."""
    p = harness.parser(module, description)
    harness.add_names(p, "--setups", setups, what="setup")
    harness.add_sizes(p, runs=10)
    harness.add_outputs(p, "results/lorenz96", "docs/lorenz96.md")
    return p


def main(argv=None):
    p = parser("lorenz96", "The transform CSF against the LETKF and EnSF on Lorenz-96 (tuned on "
               "separate runs; cached, resumable); write results.json and the generated block of "
               "the Lorenz-96 page.", SETUPS)
    p.add_argument("--study", choices=["adaptive"], default=None,
                   help="instead of the setups, the adaptive-inflation study (ADAPTIVE_RUNS), "
                        "with its own block and results_adaptive.json")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, args.study)
    cache, rows = cells.Cache(args.cache), []
    if args.study == "adaptive":
        record = harness.results_record("lorenz96", harness.command("lorenz96", argv),
                                        adaptive_rows(cache, not args.no_progress), cache,
                                        harness.output(args, "results_adaptive.json"))
        with interrupt.WRITING:
            harness.publish(args, record, adaptive_page(record), "results_adaptive.json",
                            "adaptive")
        return
    for name in args.setups:
        cases = [dataclasses.replace(c, runs=args.runs) for c in SETUPS[name]]
        rows += setup_rows(name, cases, cache, not args.no_progress, harness.extra_entries(args))
    record = harness.results_record("lorenz96", harness.command("lorenz96", argv), rows, cache,
                                    harness.output(args))
    with interrupt.WRITING:
        harness.publish(args, record, page(record))


if __name__ == "__main__":
    interrupt.main(main, "lorenz96", interrupt.CACHED)
