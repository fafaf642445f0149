"""The paper's table: the main job's filters on the seven problems, 10 runs each, N = 1000.

    python -m experiments.table [--problems double_well,...] [--preset default|paper]
        [--sf-runs 5] [--out DIR] [--page PAGE] [--readme README]

The cases and filters are ``experiments.run``'s (seed 0). Prints the tables; with ``--out``
writes ``OUT/results.json`` and each problem's figures under ``OUT/<problem>/``, with ``--page``
and ``--readme`` rewrites the generated blocks of those pages (between their
``<!-- results:start -->`` / ``<!-- results:end -->`` markers). The committed ones:
``--out results/table --page docs/results.md --readme README.md``. Resumable: every run of every
filter is a cached cell.
"""

from __future__ import annotations

import os

import jax

from experiments import cells, cli, harness, interrupt
from experiments import run as main_job

COLUMNS = ["double_well", "triple_well", "cauchy", "cubic10_indep", "cubic10_corr",
           "cubic20_indep", "cubic20_corr"]
HEADERS = ["Double Well", "Triple Well", "Cauchy", "10D I", "10D C", "20D I", "20D C"]
PAPER = {"CSF": ["0.038", "0.185", "0.217", "0.748", "0.627", "0.764", "0.598"],
         "SF": ["0.040", "0.176", "0.285", "0.750", "0.667", "0.868", "0.661"],
         "EnKF": ["0.474", "0.249", "2.418", "1.481", "1.108", "1.338", "1.178"],
         "PF": ["1.117", "0.317", "1.162", "1.928", "1.489", "2.534", "1.937"]}
PAPER_SECONDS = {"CSF": {"double_well": 1.25, "cauchy": 1.55, "cubic10_corr": 1.61,
                         "cubic20_corr": 1.65},
                 "SF": {"double_well": 5.85, "cauchy": 7.88, "cubic10_corr": 7.95,
                        "cubic20_corr": 8.06}}


def _grid(rows: list, cell, labels) -> list:
    """Markdown rows ``label | cell(row of that column) ...`` over the columns present."""
    by = {(r["case"]["problem"], r["entry"]): r for r in rows}
    names = [c for c in COLUMNS if any(p == c for p, _ in by)]
    return harness.table(["filter"] + [HEADERS[COLUMNS.index(c)] for c in names],
                         [[label] + [cell(by.get((c, label)), label, j) for j, c in
                                     enumerate(names)] for label in labels])


def render(record: dict) -> str:
    """The generated block: RMSE beside the paper's, over the reference, before and after the
    first shock, seconds per step, the command and the machine."""
    rows = record["rows"]
    labels = list(dict.fromkeys(r["entry"] for r in rows))  # the main job's, then any --with
    m = record["machine"]

    def rmse(r, label, j):
        if r is None:
            return "-"
        paper = PAPER.get(label, [None] * 7)[COLUMNS.index(r["case"]["problem"])]
        runs = "" if r["runs"] == 10 else f"{r['runs']} runs"
        note = ", ".join(x for x in (paper, runs) if x)
        return harness.number(r["rmse"]) + (f" ({note})" if note else "")

    ratio = lambda r, label, j: "-" if r is None else harness.number(r.get("rmse_ratio"))
    shock = lambda r, label, j: "-" if r is None else (
        f"{harness.number(r.get('rmse_before_shock'))} / "
        f"{harness.number(r.get('rmse_after_shock'))}")

    def seconds(r, label, j):
        if r is None:
            return "-"
        paper = PAPER_SECONDS.get(label, {}).get(r["case"]["problem"])
        return f"{r['seconds_per_step']:.2g}" + (f" ({paper})" if paper else "")

    return "\n".join(
        [f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
         f"cores, jax {m['jax_backend']}). RMSE over 10 runs unless marked, the paper's in "
         f"brackets:", ""] + _grid(rows, rmse, labels)
        + ["", "RMSE over the reference's on the same runs (1 is the best achievable):", ""]
        + _grid(rows, ratio, [x for x in labels if x != main_job.REFERENCE])
        + ["", "RMSE before / after the first shock of each run:", ""]
        + _grid(rows, shock, labels)
        + ["", "Seconds per filter step per run, compilation excluded (the paper's, RTX 4090, in "
           "brackets):", ""] + _grid(rows, seconds, labels))


def readme_block(record: dict) -> str:
    """The README's table: RMSE with the ratio to the reference in brackets."""
    labels = ["CSF", "EnKF", "PF", main_job.REFERENCE]

    def cell(r, label, j):
        if r is None:
            return "-"
        ratio = r.get("rmse_ratio")
        return harness.number(r["rmse"]) + ("" if ratio is None or label == main_job.REFERENCE
                                            else f" ({ratio:.2f})")

    names = [c for c in COLUMNS if any(r["case"]["problem"] == c for r in record["rows"])]
    paper = "| paper's CSF | " + " | ".join(PAPER["CSF"][COLUMNS.index(c)] for c in names) + " |"
    return "\n".join(_grid(record["rows"], cell, labels) + [paper])


def main(argv=None):
    p = harness.parser("table", "Run the main job's filters on every problem of the paper's "
                       "table (cached, resumable); write results.json and figures under --out "
                       "and the generated blocks of the results page and the README.")
    harness.add_names(p, "--problems", COLUMNS, what="problem")
    p.add_argument("--sf-runs", type=harness.int_at_least(1), default=None,
                   help="run SF on the first R runs of each problem (default: all on a GPU, 5 "
                        "on a CPU)")
    main_job.add_preset(p)
    harness.add_outputs(p, "results/table", "docs/results.md")
    p.add_argument("--readme", default=None,
                   help="a README whose table block is rewritten (the committed one: README.md)")
    args = p.parse_args(argv)
    cli.check_outputs(p, args)
    cli.check_page(p, "--readme", args.readme)
    sf_runs = args.sf_runs or (5 if jax.default_backend() == "cpu" else None)
    cases = [harness.Case(name) for name in args.problems]
    chosen = main_job.entries(sf_runs, preset=args.preset) + harness.extra_entries(args)
    cache = cells.Cache(args.cache)
    results = harness.run(cases, chosen, cache, not args.no_progress)
    rows = main_job.rows(results, cases, chosen)
    record = harness.results_record("table", harness.command("table", argv), rows, cache,
                                    harness.output(args), preset=args.preset)
    if args.out:
        with interrupt.WRITING:
            harness.write_results(os.path.join(args.out, "results.json"), record)
        for case in cases:
            os.makedirs(os.path.join(args.out, case.problem), exist_ok=True)
            main_job.figures(os.path.join(args.out, case.problem), case, results, chosen,
                             args.preset)
    with interrupt.WRITING:
        if args.page:
            harness.replace_section(args.page, render(record))
        if args.readme:
            harness.replace_section(args.readme, readme_block(record))
    print(render(record))


if __name__ == "__main__":
    interrupt.main(main, "table", interrupt.CACHED)
