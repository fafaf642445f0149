"""Lorenz-96: how often each filter catches the truth, against its start and its settings.

    python -m experiments.lorenz96_robustness [--setups ensf_calm,ensf] [--runs 10]
        [--out results/lorenz96] [--page docs/lorenz96.md]

On EnSF's setup without and with the truth's jumps (``experiments.lorenz96.SETUPS``: d = 100,
arctan sensor, N = 20), on runs of a seed of their own (``SEED``; neither the table's test runs nor
its tuning runs), a run *catches the truth* when it did not diverge and its time-averaged RMSE
over analyses 101-150 is at most ``experiments.lorenz96.LOST`` or at most ``FLOOR`` times the
least error of the filters' defaults started at the truth on that run (``lost_runs``). Two sweeps:

* the starting spread: the initial ensemble ``N(0, s^2 I)`` for s in ``SPREADS`` (EnSF's own start
  is s = 1; the truth's sites spread about 3.6 on the attractor), each filter at its defaults, as a
  user gets it: the LETKF (``LETKFConfig()``), the transform CSF (``LocalTransformConfig()``) and
  EnSF (``ENSFConfig(clip=50)``);
* the settings, from the setup's own start: the LETKF and the transform CSF at every radius and
  fixed inflation of ``experiments.lorenz96.ENSF_GRID`` (the table's tuning grid), and the
  transform CSF's defaults (the EnKF-N's inflation and the trust bound) at each radius of
  ``RADII``.

Every run is a cached cell of ``experiments.harness``. ``--out`` writes
``results_robustness.json``; ``--page`` rewrites the page's ``robustness`` block and draws
``lorenz96_robustness.png`` beside the page (matplotlib).
"""

from __future__ import annotations

import dataclasses
import pathlib

import csf_jax
from experiments import cells, cli, harness, interrupt
from experiments.lorenz96 import (
    ENSF_GRID,
    FLOOR,
    LOST,
    SETUPS,
    TRUTH_SPREAD,
    _local,
    entry_rows,
    lost_runs,
    parser,
)

SEED = 13
SPREADS = (0.1, 1.0, 4.0)
RADII = (1.0, 2.0, 4.0, 6.0, 8.0, 15.0)
ROBUST_SETUPS = {"ensf_calm": "without jumps", "ensf": "with jumps"}
FILTERS = {"LETKF": "letkf", "transform CSF": "local_transform"}


def default_entries() -> list:
    """Each filter at its defaults."""
    return ([harness.Entry(f"{name}, defaults", method, _local(method), batch=1)
             for name, method in FILTERS.items()]
            + [harness.Entry("EnSF", "ensf", {"config": csf_jax.ENSFConfig(clip=50.0)},
                             batch=1)])


def setting_grid() -> list:
    """``(label, method, radius, inflation)`` of the settings sweep: both local filters at every
    point of ``ENSF_GRID``, and the transform CSF's defaults at each radius of ``RADII``
    (inflation None: the EnKF-N's)."""
    return ([(f"{name}: {r:g} / {i:g}", method, r, i) for name, method in FILTERS.items()
             for r, i in ENSF_GRID]
            + [(f"transform CSF, defaults: {r:g}", "local_transform", r, None) for r in RADII])


def setting_entries() -> list:
    """The entries of ``setting_grid``."""
    return [harness.Entry(label, method, _local(method, r, i), batch=1)
            for label, method, r, i in setting_grid()]


def caught(row: dict) -> int:
    """The runs of a row that caught the truth."""
    return row["runs"] - row["lost"]


def rows(setups, runs: int, cache, progress) -> list:
    """Every row of both sweeps, each with ``sweep`` ("spread" or "settings"), ``spread``, and
    the settings sweep's ``radius`` and ``inflation`` (None elsewhere)."""
    settings = {label: {"radius": r, "inflation": i} for label, _, r, i in setting_grid()}
    none = {"radius": None, "inflation": None}
    out = []
    for name in setups:
        base = dataclasses.replace(SETUPS[name][0], runs=runs, seed=SEED)
        truth = dataclasses.replace(base, start="truth", spread=TRUTH_SPREAD)
        mine = [r | {"sweep": "truth", "spread": TRUTH_SPREAD} | none
                for r in entry_rows(name, truth, default_entries(), cache, progress)]
        for s in SPREADS:
            case = dataclasses.replace(base, start="standard", spread=s)
            mine += [r | {"sweep": "spread", "spread": s} | none
                     for r in entry_rows(name, case, default_entries(), cache, progress)]
        mine += [r | {"sweep": "settings", "spread": None} | settings[r["entry"]]
                 for r in entry_rows(name, base, setting_entries(), cache, progress)]
        out += lost_runs(mine)
    return out


def cell(row: dict | None) -> str:
    """A table cell: the runs caught of all, and the mean error of those runs."""
    if row is None:
        return "-"
    kept = "" if row["error_kept"] is None else f" ({harness.number(row['error_kept'], 3)})"
    return f"{caught(row)}/{row['runs']}{kept}"


def page(record: dict) -> list:
    """The generated block: runs caught, against the spread and against the settings."""
    m, all_rows = record["machine"], record["rows"]
    setups = list(dict.fromkeys(r["setup"] for r in all_rows))
    runs = all_rows[0]["runs"]
    spread = {(r["setup"], r["entry"], r["spread"]): r for r in all_rows
              if r["sweep"] == "spread"}
    found = {(r["setup"], r["entry"]): r for r in all_rows if r["sweep"] == "settings"}
    labels = list(dict.fromkeys(e for (_, e, _) in spread))
    body = [[e, *(cell(spread.get((s, e, v))) for s in setups for v in SPREADS)]
            for e in labels]
    lines = [f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). Seed {SEED}, N = 20; runs that caught the truth "
             f"(not diverged, and an error at most {record['lost_above']} or at most "
             f"{record['floor']} times the least error of the defaults started at the truth, "
             f"`x_0 + N(0, {TRUTH_SPREAD:g}^2 I)`, on the same run) of {runs}, and in brackets "
             f"their mean error.", "",
             "Against the starting spread s (`N(0, s^2 I)`), each filter at its defaults:", ""]
    lines += harness.table(["filter", *(f"{ROBUST_SETUPS[s]}, s = {v:g}" for s in setups
                                        for v in SPREADS)], body)
    inflations = sorted({i for _, i in ENSF_GRID})
    far = csf_jax.LocalTransformConfig()
    lines += ["", "Against the radius (columns) and a fixed inflation (rows), from the setup's "
              "own start; the last rows: the transform CSF's defaults (the EnKF-N's inflation, "
              f"the trust bound) at each radius, with radius {far.far_radius:g} in the steps whose "
              f"EnKF-N factor exceeds {far.far_factor:g} where the radius is larger:", ""]
    body = [[ROBUST_SETUPS[s], name, f"{i:g}",
             *(cell(found.get((s, f"{name}: {r:g} / {i:g}"))) for r in RADII)]
            for s in setups for name in FILTERS for i in inflations]
    body += [[ROBUST_SETUPS[s], "transform CSF, defaults", "EnKF-N",
              *(cell(found.get((s, f"transform CSF, defaults: {r:g}"))) for r in RADII)]
             for s in setups]
    lines += harness.table(["setup", "filter", "inflation", *(f"radius {r:g}" for r in RADII)],
                           body)
    return lines + ["", "![Runs that catch the truth](lorenz96_robustness.png)"]


def figure(record: dict, path: pathlib.Path) -> None:
    """``path``: per setup (rows), the runs caught against the spread, and against the radius
    for each inflation of both local filters and for the transform CSF's defaults."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    all_rows = record["rows"]
    setups = list(dict.fromkeys(r["setup"] for r in all_rows))
    fig, axes = plt.subplots(len(setups), 3, figsize=(13, 3.4 * len(setups)), squeeze=False,
                             sharey=True)
    for ax_row, s in zip(axes, setups):
        mine = [r for r in all_rows if r["setup"] == s]
        spread = [r for r in mine if r["sweep"] == "spread"]
        # widest first, so that filters with equal counts all show
        for k, label in enumerate(dict.fromkeys(r["entry"] for r in spread)):
            pts = sorted((r["spread"], caught(r)) for r in spread if r["entry"] == label)
            ax_row[0].plot(*zip(*pts), marker="os^D"[k % 4], lw=5.0 / (k + 1), ms=9 - 2 * k,
                           label=label)
        ax_row[0].set_xscale("log")
        ax_row[0].set_xlabel("starting spread s")
        ax_row[0].set_ylabel(f"{ROBUST_SETUPS[s]}: runs caught")
        for ax, name in zip(ax_row[1:], FILTERS):
            for i in sorted({i for _, i in ENSF_GRID}):
                pts = [(r["radius"], caught(r)) for r in mine
                       if r["entry"].startswith(f"{name}: ") and r["inflation"] == i]
                ax.plot(*zip(*sorted(pts)), marker="o", label=f"inflation {i:g}")
            if name == "transform CSF":
                pts = [(r["radius"], caught(r)) for r in mine
                       if r["entry"].startswith("transform CSF, defaults: ")]
                ax.plot(*zip(*sorted(pts)), marker="s", color="k", lw=2, label="defaults")
            ax.set_xlabel(f"{name}: radius")
    for ax in axes[0]:
        ax.legend(fontsize=7)
    for ax in axes.flat:
        ax.set_ylim(-0.5, all_rows[0]["runs"] + 0.5)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = parser("lorenz96_robustness", "How often the Lorenz-96 filters catch the truth, against "
               "the starting spread and the radius and inflation (cached, resumable); write "
               "results_robustness.json, the page's block and figure.", ROBUST_SETUPS)
    args = p.parse_args(argv)
    cli.check_outputs(p, args, "robustness")
    cache = cells.Cache(args.cache)
    found = rows(args.setups, args.runs, cache, not args.no_progress)
    record = harness.results_record("lorenz96_robustness",
                                    harness.command("lorenz96_robustness", argv), found, cache,
                                    harness.output(args, "results_robustness.json"), lost_above=LOST, floor=FLOOR)
    with interrupt.WRITING:
        harness.publish(args, record, page(record), "results_robustness.json", "robustness")
    if args.page:
        figure(record, pathlib.Path(args.page).with_name("lorenz96_robustness.png"))


if __name__ == "__main__":
    interrupt.main(main, "lorenz96_robustness", interrupt.CACHED)
