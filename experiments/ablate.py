"""CSF ablations on a few runs of the table: one setting changed at a time, same data, same keys.

    python -m experiments.ablate cubic10_indep --runs 2 \
        --setting reverse_steps=20 --setting reverse_steps=20,prior_inflation=0.2 \
        [--out docs/ablation/cubic10_indep.json]

Each ``--setting`` is a comma-separated list of ``CSFConfig`` fields (``field=value``, values read as
Python literals; ``guidance.proposals=4`` sets a ``GuidanceConfig`` field; on top of ``CSFConfig()``,
not of the tables' per-problem ``experiments.run.CSF_OVERRIDES``); the pretrained prior of the problem, N = 1000 and the runs of
``experiments.run`` (seed 0: run i is the table's run i) are shared. EnKF on the same runs is the
first row. Prints a markdown table (RMSE over the runs, per run, seconds per filter step, measured
one run at a time after compilation) and appends the rows to ``--out`` (JSON, one object per row),
so that a page quoting them names this command. ``--render JSON`` prints the table of such a file
(each problem's EnKF row once, problems in order of first appearance): docs/ablation.md is made so.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import sys
import time

import jax
import numpy as np

import csf_jax
from csf_jax import CSFConfig, GuidanceConfig, problems
from csf_jax.pretrained import load_dir, load_pretrained
from csf_jax.prior import gaussian_prior
from experiments._cli import parser, positive_int
from experiments.run import PRIORS, _errors, machine, simulate_runs


def make_config(setting: dict) -> CSFConfig:
    """The ``CSFConfig`` of a parsed setting: ``guidance.<field>`` entries go to its
    ``GuidanceConfig``."""
    sub = {k.split(".", 1)[1]: v for k, v in setting.items() if k.startswith("guidance.")}
    top = {k: v for k, v in setting.items() if not k.startswith("guidance.")}
    return CSFConfig(**top, guidance=GuidanceConfig(**sub)) if sub else CSFConfig(**top)


def parse_setting(text: str) -> dict:
    """``"a=1,b=0.2"`` -> ``{"a": 1, "b": 0.2}``, checked against ``CSFConfig``'s fields
    (``guidance.<field>``: a ``GuidanceConfig`` field)."""
    fields = {f.name for f in dataclasses.fields(CSFConfig)}
    fields |= {"guidance." + f.name for f in dataclasses.fields(GuidanceConfig)}
    out = {}
    for part in filter(None, text.split(",")):
        name, sep, value = part.partition("=")
        if not sep or name.strip() not in fields:
            raise argparse.ArgumentTypeError(f"{part!r}: expected field=value with a CSFConfig "
                                             f"field ({', '.join(sorted(fields))})")
        try:
            out[name.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise argparse.ArgumentTypeError(f"{part!r}: the value is not a Python literal") from None
    try:
        make_config(out)
    except (ValueError, TypeError) as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return out


def ablate(name: str, runs: int, settings, particles: int = 1000, seed: int = 0,
           prior: str = "pretrained", model_dir: str | None = None):
    """Rows ``{"setting", "rmse", "rmse_per_run", "seconds_per_step"}``: EnKF first, then CSF per
    setting. ``prior``: the shipped model, the ensemble's Gaussian (``csf_jax.prior.gaussian_prior``)
    or the exact mixture. ``model_dir``: a trained model's folder (``experiments.train --export``)
    in place of the shipped one."""
    model = problems.get(name)
    trained = None
    if prior == "pretrained":
        trained = load_dir(model_dir) if model_dir else load_pretrained(name)
    truth, obs, _, ens, keys = simulate_runs(model, runs, particles, seed)
    truth = np.asarray(truth)
    K = obs.shape[1]

    def row(label, means, seconds, config=None):
        err = _errors(np.stack(means), truth)
        return {"problem": name, "setting": label, "runs": runs, "particles": particles,
                "config": None if config is None else dataclasses.asdict(config),
                "rmse": float(np.sqrt(err.mean())),
                "rmse_per_run": np.sqrt(err.mean(axis=1)).round(4).tolist(),
                "seconds_per_step": seconds / (runs * K)}

    enkf = jax.jit(jax.vmap(lambda o, e, k: csf_jax.ensemble_kalman_filter(o, e, problem=model,
                                                                            key=k)))
    compiled = enkf.lower(obs, ens, keys).compile()
    t0 = time.perf_counter()
    rows = [row("EnKF", list(np.asarray(compiled(obs, ens, keys).mean)), time.perf_counter() - t0)]
    print(table(rows[-1:], header=True), flush=True)
    for setting in settings:
        cfg = make_config(setting)
        source = gaussian_prior(cfg.sigma_max) if prior == "gaussian" else None
        fn = jax.jit(lambda o, e, k: csf_jax.filter(trained, o, e, problem=model, key=k, config=cfg,
                                                    prior=source, check_finite=False).mean)
        compiled = fn.lower(obs[0], ens[0], keys[0]).compile()
        t0 = time.perf_counter()
        means = [np.asarray(compiled(obs[i], ens[i], keys[i])) for i in range(runs)]
        label = ("CSF " if prior == "pretrained" else f"CSF ({prior} prior) ") + (
            f"[{model_dir}] " if model_dir and prior == "pretrained" else "")
        rows.append(row(label + (", ".join(f"{k}={v}" for k, v in setting.items()) or "default"),
                        means, time.perf_counter() - t0, cfg))
        print(table(rows[-1:]), flush=True)
    return rows


def table(rows, header: bool = False) -> str:
    lines = ["| problem | setting | runs | RMSE | per run | s / filter step |",
             "|---|---|---|---|---|---|"] if header else []
    for r in rows:
        lines.append(f"| {r['problem']} | {r['setting']} | {r['runs']} | {r['rmse']:.4f} | "
                     f"{', '.join(f'{v:.3f}' for v in r['rmse_per_run'])} | "
                     f"{r['seconds_per_step']:.4f} |")
    return "\n".join(lines)


def render(path: str) -> str:
    """The markdown table of the rows in ``path`` (a ``--out`` file); a row repeated (same problem,
    setting and number of runs) is kept once, the first."""
    with open(path) as f:
        rows = json.load(f)["rows"]
    seen, problems_seen, kept = set(), [], []
    for r in rows:
        if (r["problem"], r["setting"], r["runs"]) in seen:
            continue
        seen.add((r["problem"], r["setting"], r["runs"]))
        problems_seen += [r["problem"]] if r["problem"] not in problems_seen else []
        kept.append(r)
    kept.sort(key=lambda r: problems_seen.index(r["problem"]))
    return table(kept, header=True)


DESCRIPTION = ("CSF ablations on the first runs of the table: EnKF and CSF with each --setting "
               "on the same data and keys; print the markdown table and append the rows to --out "
               "(JSON).")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.ablate``."""
    p = parser("ablate", DESCRIPTION)
    p.add_argument("problem", nargs="?", choices=problems.NAMES, metavar="PROBLEM",
                   help="the problem, one of %(choices)s (not needed with --render)")
    p.add_argument("--runs", type=positive_int, default=2,
                   help="the table's first runs to filter (default %(default)s)")
    p.add_argument("--setting", type=parse_setting, action="append", default=None,
                   help="CSFConfig fields, e.g. reverse_steps=20,prior_inflation=0.2; "
                        "guidance.<field> sets a GuidanceConfig field (repeatable; default: one "
                        "row with the default config)")
    p.add_argument("--prior", choices=PRIORS, default="pretrained",
                   help="CSF's prior: 'pretrained' (the shipped model), 'gaussian' (the "
                        "ensemble's Gaussian) or 'exact' (the exact Gaussian mixture) (default "
                        "%(default)s)")
    p.add_argument("--model", default=None,
                   help="a trained model's folder (experiments.train --export) instead of the "
                        "shipped prior (default: the shipped prior)")
    p.add_argument("--out", default=None,
                   help="JSON file the rows are appended to (default: none)")
    p.add_argument("--render", default=None, metavar="JSON",
                   help="print the table of this JSON file and stop")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    if args.render is None and args.problem is None:
        p.error("the problem is required (or --render JSON)")
    if args.render is not None and not os.path.isfile(args.render):
        p.error(f"argument --render: no file {args.render!r}")
    if args.model is not None and not os.path.isdir(args.model):
        p.error(f"argument --model: no folder {args.model!r}")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.render:
        print(render(args.render))
        return
    rows = ablate(args.problem, args.runs, args.setting or [{}], prior=args.prior,
                  model_dir=args.model)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        old = json.load(open(args.out)) if os.path.exists(args.out) else {"rows": []}
        old["rows"].extend(rows)
        old["machine"] = machine()
        with open(args.out, "w") as f:
            json.dump(old, f, indent=1)
        print(f"appended {len(rows)} rows to {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
