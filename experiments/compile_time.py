"""Compile time and step time of ``csf_jax.filter`` against the state dimension d.

    python -m experiments.compile_time [--dims 5,10,20,40,100] [--particles N] [--steps K]
        [--repeats R] [--out DIR]

For every d: the cubic sensor ``cubic<d>_indep`` with the default ``CSFConfig()`` and the
ensemble's own Gaussian as the prior (``gaussian_prior()``: the per-particle (d, d) Kalman
systems of the default sampler are the part whose compile cost depends on d), N particles,
K filter steps. ``compile_s`` is ``jit(...).lower(...).compile()`` (trace + lower + XLA
compile); ``step_s`` the median over ``--repeats`` timed calls of the compiled function, divided
by K (compilation excluded). Prints a table and writes ``compile_time.json`` to ``--out``
(default ``out/compile_time``).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp

import csf_jax
from experiments._cli import int_list, parser, positive_int
from experiments._timing import compiled


def measure(dim: int, particles: int, steps: int, repeats: int) -> dict:
    """One row: compile and per-step seconds of the default filter at state dimension ``dim``."""
    problem = csf_jax.problems.get("cubic10_indep", dim=dim, num_steps=steps)
    _, obs = csf_jax.simulate(problem, jax.random.key(0))
    ensemble = problem.initial_ensemble(jax.random.key(1), particles)
    prior = csf_jax.gaussian_prior()

    def run(obs, ensemble, key):
        return csf_jax.filter(None, obs, ensemble, problem=problem, key=key, prior=prior,
                              check_finite=False).mean

    exe, compile_s = compiled(jax.jit(run), obs, ensemble, jax.random.key(2))
    exe(obs, ensemble, jax.random.key(2)).block_until_ready()
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        exe(obs, ensemble, jax.random.key(3 + r)).block_until_ready()
        times.append((time.perf_counter() - t0) / steps)
    return {"d": dim, "N": particles, "K": steps, "compile_s": round(compile_s, 2),
            "step_s": round(statistics.median(times), 4)}


DESCRIPTION = ("Compile time and step time of csf_jax.filter (default config, Gaussian prior, "
               "cubic sensor) against the state dimension; print the table and write "
               "compile_time.json to --out.")


def build_parser():
    """The command line of ``python -m experiments.compile_time``."""
    p = parser("compile_time", DESCRIPTION)
    p.add_argument("--dims", type=int_list(1), default=[5, 10, 20, 40, 100],
                   help="state dimensions (default %(default)s)")
    p.add_argument("--particles", type=positive_int, default=200,
                   help="ensemble size N (default %(default)s)")
    p.add_argument("--steps", type=positive_int, default=10,
                   help="filter steps K per call (default %(default)s)")
    p.add_argument("--repeats", type=positive_int, default=3,
                   help="timed calls per d (default %(default)s)")
    p.add_argument("--out", default="out/compile_time", help="output folder (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    rows = []
    print("| d | N | K | compile s | step s |\n|---|---|---|---|---|", flush=True)
    for dim in args.dims:
        row = measure(dim, args.particles, args.steps, args.repeats)
        rows.append(row)
        print(f"| {row['d']} | {row['N']} | {row['K']} | {row['compile_s']:.2f} | "
              f"{row['step_s']:.4f} |", flush=True)
    os.makedirs(args.out, exist_ok=True)
    machine = {"platform": platform.platform(), "processor": platform.processor(),
               "cpus": os.cpu_count(), "jax": jax.__version__,
               "backend": jax.default_backend(), "dtype": str(jnp.zeros(()).dtype)}
    with open(os.path.join(args.out, "compile_time.json"), "w") as f:
        json.dump({"machine": machine, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
