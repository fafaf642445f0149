"""The full table: every problem, every method, 10 runs; writes the results page.

    python -m experiments.table [--problems double_well,...] [--out results] [--runs 10]
        [--sf-runs 5 | --sf-runs cubic20_corr=5,...] [--docs docs/results.md] [--write-only]

Runs ``experiments.run`` (N=1000, seed 0, pretrained priors, ``--guidance``/``--steps``: the
sampler, default CSFConfig's) on each problem into
``OUT/<problem>/`` (``results.json``, figures and the per-batch cache), then rewrites the generated
part of the results page (between its ``<!-- table:start -->`` and ``<!-- table:end -->`` markers)
from every ``results.json`` found, beside the paper's values. Resumable: run it again after an
interruption and finished runs are reused. ``--sf-runs`` runs SF on the first R runs only (all
problems, or the problems named; R <= ``--runs``): its online training is what a CPU budget
cannot afford; the page marks such cells. ``--write-only`` only rewrites the page.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

from csf_jax import problems  # noqa: E402  (isort: after run_mod on purpose)
from experiments import run as run_mod  # first: it sets XLA's host devices before jax loads
from experiments._cli import name_list, parser, particle_count, positive_int  # noqa: E402

# The paper's Table (RMSE over 10 runs) and its per-step time table (s, RTX 4090).
PAPER_RMSE = {  # as printed in the paper
    "csf": ["0.038", "0.185", "0.217", "0.748", "0.627", "0.764", "0.5978"],
    "sf": ["0.040", "0.176", "0.285", "0.750", "0.667", "0.868", "0.661"],
    "enkf": ["0.474", "0.249", "2.418", "1.481", "1.108", "1.338", "1.178"],
    "pf": ["1.117", "0.317", "1.162", "1.928", "1.489", "2.534", "1.937"],
    "csf_gaussian": [None] * 7,  # ours only: CSF's sampler with the ensemble's Gaussian prior
    "reference": [None] * 7,  # ours only: the near-exact per-coordinate filter
}
COLUMNS = ["double_well", "triple_well", "cauchy", "cubic10_indep", "cubic10_corr",
           "cubic20_indep", "cubic20_corr"]
HEADERS = ["Double Well", "Triple Well", "Cauchy", "10D I", "10D C", "20D I", "20D C"]
PAPER_TIME = {"csf": {"double_well": 1.25, "cauchy": 1.55, "10D": 1.61, "20D": 1.65},
              "sf": {"double_well": 5.85, "cauchy": 7.88, "10D": 7.95, "20D": 8.06}}
TIME_COLUMNS = [("Double Well", "double_well", "double_well"), ("Cauchy", "cauchy", "cauchy"),
                ("10D", "10D", "cubic10_corr"), ("20D", "20D", "cubic20_corr")]
START, END = "<!-- table:start -->", "<!-- table:end -->"


def load_results(out: str) -> dict:
    """``{problem: results dict}`` for every ``OUT/<problem>/results.json`` present."""
    found = {}
    for name in COLUMNS:
        path = os.path.join(out, name, "results.json")
        if os.path.exists(path):
            with open(path) as f:
                found[name] = json.load(f)
    return found


def _num(v: float) -> str:
    """3 decimals, 4 below 0.1 (the double-well errors differ in the fourth)."""
    return f"{v:.4f}" if abs(v) < 0.1 else f"{v:.3f}"


def _seconds(v: float) -> str:
    return f"{v:.3f}" if v >= 0.001 else f"{v * 1e3:.2f} ms"


def render(results: dict, command: str) -> str:
    """The generated markdown: RMSE table, per-step time table, shock split, machine."""
    lines = [f"Made by `{command}`.", "",
             "RMSE (Eq. rmse, 10 runs unless marked), ours with the paper's in brackets; bold: the "
             "best of ours in the column (the reference apart); `-`: not run yet. Ref.: the "
             "near-exact reference filter (`csf_jax.reference_filter`, shocks modelled; why it "
             "is near-exact: below the table). CSF-G: CSF's sampler and config with the ensemble's "
             "own Gaussian as the prior (`csf_jax.gaussian_prior()`, no network): CSF against "
             "CSF-G is the learned correction's worth. SF: its sampler has base inflation 0.2 "
             "(`experiments.run.SF_SAMPLER_BASE`), the setting its cached runs were made with; "
             "on the triple well CSF's (0).", "",
             "| method | " + " | ".join(HEADERS) + " |", "|---" * (len(HEADERS) + 1) + "|"]
    best = {}
    for name, res in results.items():
        ours = [v for m, v in res["rmse"].items() if m != "reference"]
        best[name] = min(ours) if ours else None
    for m in run_mod.METHODS:
        cells = []
        for j, name in enumerate(COLUMNS):
            res = results.get(name)
            paper = PAPER_RMSE[m][j]
            if res is None or m not in res["rmse"]:
                cells.append("-" if paper is None else f"- ({paper})")
                continue
            v = res["rmse"][m]
            text = _num(v)
            if v == best[name] and m != "reference":
                text = f"**{text}**"
            runs = res["runs_used"][m]
            note = f"{runs} runs" if runs != res["config"]["runs"] or runs != 10 else ""
            bracket = ", ".join(x for x in (paper, note) if x)
            cells.append(f"{text} ({bracket})" if bracket else text)
        lines.append(f"| {run_mod.LABELS[m]} | " + " | ".join(cells) + " |")
    differ = _config_differences(results)
    if differ:
        lines += ["", "CSF (and CSF-G) settings other than `CSFConfig()`'s, per column "
                  "(`experiments.run.CSF_OVERRIDES`): " + "; ".join(differ) + "."]
    if any("rmse_ratio" in r for r in results.values()):
        lines += ["", "RMSE over the reference's RMSE on the same runs (1 is the best achievable):",
                  "", "| method | " + " | ".join(HEADERS) + " |",
                  "|---" * (len(HEADERS) + 1) + "|"]
        for m in run_mod.METHODS:
            if m == "reference":
                continue
            cells = [f"{results[n]['rmse_ratio'][m]:.2f}"
                     if n in results and m in results[n].get("rmse_ratio", {}) else "-"
                     for n in COLUMNS]
            lines.append(f"| {run_mod.LABELS[m]} | " + " | ".join(cells) + " |")
    lines += ["", "RMSE before / after the first shock of each run (where the error comes from):",
              "", "| method | " + " | ".join(HEADERS) + " |", "|---" * (len(HEADERS) + 1) + "|"]
    fmt = lambda v: "-" if v is None else _num(v)
    for m in run_mod.METHODS:
        cells = []
        for name in COLUMNS:
            res = results.get(name)
            if res is None or m not in res["rmse"]:
                cells.append("-")
            else:
                cells.append(f"{fmt(res['rmse_before_shock'][m])} / "
                             f"{fmt(res['rmse_after_shock'][m])}")
        lines.append(f"| {run_mod.LABELS[m]} | " + " | ".join(cells) + " |")
    lines += ["", "Seconds per filter step per run (ours: compile excluded; the paper's: RTX 4090):",
              "", "| method | " + " | ".join(h for h, _, _ in TIME_COLUMNS) + " |",
              "|---" * (len(TIME_COLUMNS) + 1) + "|"]
    for m in ("csf", "csf_gaussian", "sf", "enkf", "pf", "reference"):
        cells = []
        for _, paper_key, name in TIME_COLUMNS:
            res = results.get(name)
            ours = "-" if res is None or m not in res["seconds_per_step"] else \
                _seconds(res["seconds_per_step"][m])
            paper = PAPER_TIME.get(m, {}).get(paper_key)
            cells.append(ours + ("" if paper is None else f" ({paper})"))
        lines.append(f"| {run_mod.LABELS[m]} | " + " | ".join(cells) + " |")
    at_once = {}
    for _, _, name in TIME_COLUMNS:
        for m, r in results.get(name, {}).get("runs_at_once", {}).items():
            at_once.setdefault(m, set()).add(r)
    lines += ["", "Per run: the wall-clock time of all runs over runs x filter steps; runs at once: " +
              ", ".join(f"{run_mod.LABELS[m]} {'/'.join(map(str, sorted(v)))}"
                        for m, v in at_once.items()) + "."]
    machines = sorted({f"{m['cpu']} ({m['cpu_count']} cores, jax backend {m['jax_backend']})"
                       for m in (r["machine"] for r in results.values())})
    lines += ["", "Measured on: " + "; ".join(machines) + "."]
    return "\n".join(lines)


def _config_differences(results: dict) -> list:
    """``["cauchy: guidance.proposals=32", ...]``: each column's CSF config fields that differ
    from ``CSFConfig()`` (reverse steps and guidance mode apart: the page's command names those)."""
    default = dataclasses.asdict(run_mod.CSFConfig())
    out = []
    for name in COLUMNS:
        if name not in results:
            continue
        used = results[name]["config"]["csf"]
        fields = [f"{k}={used[k]}" for k in default
                  if k not in ("reverse_steps", "guidance") and k in used and used[k] != default[k]]
        guidance = used.get("guidance", {})
        fields += [f"guidance.{k}={guidance[k]}" for k in default["guidance"]
                   if k != "mode" and guidance.get(k, default["guidance"][k]) != default["guidance"][k]]
        if fields:
            out.append(f"{name}: {', '.join(fields)}")
    return out


def write_page(path: str, body: str) -> None:
    """Replace the text between the markers of ``path`` (created if missing) with ``body``."""
    text = f"# Results\n\n{START}\n{END}\n"
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
    if START not in text or END not in text:
        raise SystemExit(f"{path} lacks the {START} / {END} markers")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w") as f:
        f.write(f"{head}{START}\n{body}\n{END}{tail}")


def parse_sf_runs(text, names, runs: int | None = None) -> dict:
    """``--sf-runs``: ``"5"`` -> ``{name: 5 for names}``; ``"a=5,b=3"`` -> ``{"a": 5, "b": 3}``.

    Raises ``argparse.ArgumentTypeError`` for a malformed value, an unknown problem, or an R below
    1 or above ``runs``."""
    if not text:
        return {}
    try:
        if "=" not in text:
            out = {n: int(text) for n in names}
        else:
            pairs = [item.split("=") for item in text.split(",") if item.strip()]
            out = {k.strip(): int(v) for k, v in pairs}
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected R or problem=R,..., got {text!r}") from None
    unknown = [n for n in out if n not in problems.NAMES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown problem {', '.join(map(repr, unknown))}; "
                                         f"choose from {', '.join(problems.NAMES)}")
    for n, r in out.items():
        if r < 1:
            raise argparse.ArgumentTypeError(f"R must be >= 1, got {r}" + (
                f" for {n}" if "=" in text else ""))
        if runs is not None and r > runs:
            raise argparse.ArgumentTypeError(f"{r} exceeds the {runs} runs (--runs)" + (
                f" for {n}" if "=" in text else ""))
    return out


DESCRIPTION = ("Run the main job (experiments.run) on every problem into OUT/<problem>/ "
               "(results.json, figures, cache; resumable) and rewrite the generated table of the "
               "results page beside the paper's values.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.table``."""
    p = parser("table", DESCRIPTION)
    p.add_argument("--problems", type=name_list(problems.NAMES, "problem"), default=list(COLUMNS),
                   metavar="P,P,...",
                   help=f"comma-separated problems from: {', '.join(COLUMNS)} (default: all)")
    p.add_argument("--out", default="results",
                   help="folder of the per-problem results (default %(default)s)")
    p.add_argument("--runs", type=positive_int, default=10,
                   help="independent runs per problem (default %(default)s)")
    p.add_argument("--sf-runs", default=None, metavar="R|P=R,...",
                   help="run SF on fewer runs (CPU budget), at most --runs: R for every problem, "
                        "or problem=R,... for those named (default: all runs)")
    p.add_argument("--steps", type=particle_count, default=run_mod.CSFConfig().reverse_steps,
                   help="CSF's and SF's reverse steps L (default %(default)s)")
    p.add_argument("--guidance", choices=run_mod.MODES, default=run_mod.GuidanceConfig().mode,
                   help="CSF's and SF's sampler, one of %(choices)s (the paper's: --guidance "
                        "clipped --steps 500) (default %(default)s)")
    p.add_argument("--docs", default=os.path.join("docs", "results.md"),
                   help="the results page to rewrite (default %(default)s)")
    p.add_argument("--write-only", action="store_true",
                   help="only rewrite the results page from the results found under --out")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    """The checked arguments; ``sf_runs`` parsed to ``{problem: R}``."""
    p = build_parser()
    args = p.parse_args(argv)
    args.sf_text = args.sf_runs
    try:
        args.sf_runs = parse_sf_runs(args.sf_runs, args.problems, args.runs)
    except argparse.ArgumentTypeError as e:
        p.error(f"argument --sf-runs: {e}")
    return args


def main(argv=None):
    args = parse_args(argv)
    names, sf_runs = args.problems, args.sf_runs
    command = "python -m experiments.table" + (f" --sf-runs {args.sf_text}" if args.sf_text else "")
    if (args.steps, args.guidance) != (run_mod.CSFConfig().reverse_steps,
                                       run_mod.GuidanceConfig().mode):
        command += f" --guidance {args.guidance} --steps {args.steps}"
    if not args.write_only:
        for n in names:
            t0 = time.perf_counter()
            print(f"== {n}", file=sys.stderr, flush=True)
            res = run_mod.run(n, run_mod.METHODS, runs=args.runs, out=os.path.join(args.out, n),
                              method_runs={"sf": sf_runs[n]} if n in sf_runs else None,
                              steps=args.steps, guidance=args.guidance)
            print(run_mod.table(res), flush=True)
            print(f"== {n} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
            write_page(args.docs, render(load_results(args.out), command))
    write_page(args.docs, render(load_results(args.out), command))
    print(f"wrote {args.docs}", file=sys.stderr)


if __name__ == "__main__":
    main()
