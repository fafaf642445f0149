"""Run the filters on one of the paper's problems and print the RMSE table.

    python -m experiments.run double_well [--methods csf,enkf,pf] [--runs 10] [--particles 1000]
        [--steps 500] [--seed 0] [--out DIR] [--quick]

Simulates ``--runs`` independent truth/observation trajectories (seeded), runs every method on the
same data (vmapped over runs), and prints RMSE (the paper's Eq. rmse, full norm), RMSE per
coordinate, and seconds per filter step with the compile time apart. ``--out DIR`` writes
``results.json``.

CSF uses the shipped pretrained prior of the problem (``csf_jax.load_pretrained``; triple_well uses
the double-well model). ``--prior exact`` uses the exact Gaussian-mixture prior instead (the score of
the propagated ensemble in closed form, no network): it separates the learned prior's error from the
sampler's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import CSFConfig, problems
from csf_jax.pretrained import load_pretrained

METHODS = ("csf", "enkf", "pf")


def _runner(method: str, model, config: CSFConfig, pretrained):
    """``(obs (R, K, m), ens (R, N, d), keys (R,)) -> FilterResult`` batched over runs, jitted.

    pretrained: a ``csf_jax.pretrained.Pretrained`` for CSF, or None for the exact mixture prior.
    """
    if method == "csf":
        params = None if pretrained is None else pretrained.params
        network = None if pretrained is None else pretrained.network
        one = lambda o, e, k: csf_jax.filter(params, o, e, problem=model, key=k, config=config,
                                             network=network)
    elif method == "enkf":
        one = lambda o, e, k: csf_jax.ensemble_kalman_filter(o, e, problem=model, key=k)
    elif method == "pf":
        one = lambda o, e, k: csf_jax.particle_filter(o, e, problem=model, key=k)
    else:
        raise SystemExit(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return jax.jit(jax.vmap(one))


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return out, time.perf_counter() - t0


def run(name: str, methods, runs: int, particles: int, steps: int, seed: int,
        num_steps: int | None = None, prior: str = "pretrained"):
    """Simulate ``runs`` trajectories and run ``methods``; returns a results dict."""
    model = problems.get(name) if num_steps is None else problems.get(name, num_steps=num_steps)
    pretrained = load_pretrained(name) if prior == "pretrained" and "csf" in methods else None
    config = CSFConfig(reverse_steps=steps)
    keys = jax.random.split(jax.random.key(seed), 3 * runs).reshape(3, runs)
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(keys[0])
    ens = jax.vmap(lambda k: model.initial_ensemble(k, particles))(keys[1])
    K = obs.shape[1]
    out = {"problem": name, "config": {"runs": runs, "particles": particles,
                                        "reverse_steps": steps, "seed": seed, "num_steps": K,
                                        "problem": dataclasses.asdict(problems.config(name)),
                                        "csf": repr(config), "csf_prior": prior},
           "rmse": {}, "rmse_per_dim": {}, "seconds_per_step": {}, "compile_seconds": {},
           "rmse_per_run": {}}
    for method in methods:
        fn = _runner(method, model, config, pretrained)
        lowered = fn.lower(obs, ens, keys[2])
        t0 = time.perf_counter()
        compiled = lowered.compile()
        compile_s = time.perf_counter() - t0
        result, run_s = _timed(compiled, obs, ens, keys[2])
        mean = np.asarray(result.mean)
        err = np.sum((mean - np.asarray(truth[:, 1:])) ** 2, axis=-1)
        out["rmse"][method] = float(np.sqrt(err.mean()))
        out["rmse_per_dim"][method] = float(np.sqrt(err.mean() / model.dim))
        out["rmse_per_run"][method] = np.sqrt(err.mean(axis=1)).tolist()
        out["seconds_per_step"][method] = run_s / (runs * K)
        out["compile_seconds"][method] = compile_s
        print(f"  {method:5s} RMSE {out['rmse'][method]:.3f}  ({run_s:.1f} s for {runs} runs, "
              f"compile {compile_s:.1f} s)", file=sys.stderr, flush=True)
    out["machine"] = {"platform": platform.platform(), "processor": platform.processor(),
                      "cpu_count": os.cpu_count(), "jax_devices": [str(d) for d in jax.devices()]}
    out["versions"] = {"python": platform.python_version(), "jax": jax.__version__,
                       "csf_jax": csf_jax.__version__}
    return out


def table(results) -> str:
    """Markdown table of a results dict."""
    rows = ["| method | RMSE | RMSE per dim | s / filter step (per run) | compile s |",
            "|---|---|---|---|---|"]
    for m in results["rmse"]:
        rows.append(f"| {m} | {results['rmse'][m]:.3f} | {results['rmse_per_dim'][m]:.3f} | "
                    f"{results['seconds_per_step'][m]:.4f} | {results['compile_seconds'][m]:.1f} |")
    return "\n".join(rows)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.run", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("problem", choices=problems.NAMES)
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--runs", type=int, default=None, help="independent runs (default 10; 2 quick)")
    p.add_argument("--particles", type=int, default=None, help="N (default 1000; 200 quick)")
    p.add_argument("--steps", type=int, default=None, help="reverse steps L (default 500; 200 quick)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="directory for results.json")
    p.add_argument("--prior", choices=("pretrained", "exact"), default="pretrained",
                   help="CSF prior: the shipped model (default) or the exact Gaussian mixture")
    p.add_argument("--quick", action="store_true",
                   help="small and fast: 2 runs, 200 particles, 200 reverse steps, 20 filter steps")
    args = p.parse_args(argv)
    quick = args.quick
    runs = args.runs or (2 if quick else 10)
    particles = args.particles or (200 if quick else 1000)
    steps = args.steps or (200 if quick else 500)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    print(f"{args.problem}: {runs} runs, N={particles}, L={steps}, methods {methods}",
          file=sys.stderr)
    results = run(args.problem, methods, runs, particles, steps, args.seed,
                  num_steps=20 if quick else None, prior=args.prior)
    print(table(results))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "results.json"), "w") as f:
            json.dump(results, f, indent=2)
        print(f"wrote {os.path.join(args.out, 'results.json')}", file=sys.stderr)


if __name__ == "__main__":
    main()
