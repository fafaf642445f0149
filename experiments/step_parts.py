"""Where the time of one CSF filter step goes: the parts of the default sampler, timed apart.

    python -m experiments.step_parts [--dim D] [--particles N] [--repeats R] [--out DIR]

The benchmark's case (``experiments.bench``: the cubic sensor ``cubic<d>_indep``, the shipped
models' network with random-init weights, ``CSFConfig()``: the ancestral sampler with Kalman
guidance, L = 20 levels, K = 8 proposals). Each part runs alone, compiled, L times in a
``fori_loop`` on inputs of the step's shapes; ``ms`` is the median over ``--repeats`` calls per
filter step (compilation excluded). ``share`` is the part over the whole step; the parts overlap
where one contains another (the normal draws are inside the proposals). Prints the table and writes
``step_parts.json`` to ``--out`` (default ``out/step_parts``).
"""

from __future__ import annotations

import functools
import json
import os
import statistics
import time

import jax
import jax.numpy as jnp

import csf_jax
from csf_jax import _linalg, guidance
from csf_jax.ssm import curvature
from experiments._cli import parser, particle_count, positive_int
from experiments._timing import compiled
from experiments.bench import csf_config, make_data, network
from experiments.run import machine


def _median_ms(fn, args, repeats: int) -> float:
    exe, _ = compiled(jax.jit(fn), *args)
    jax.block_until_ready(exe(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(exe(*args))
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def parts(dim: int, particles: int, repeats: int) -> list[dict]:
    """``[{"part", "ms"}]`` for one filter step at state dimension ``dim`` with ``particles``."""
    config = csf_config({"steps": 20, "guidance": "kalman"})
    levels, proposals = config.reverse_steps, config.guidance.proposals
    net = network()
    params = csf_jax.init_params(jax.random.key(0), net, dim)
    obs, ens = make_data(dim, particles, 1, 1)
    y, ens = jnp.asarray(obs[0, 0]), jnp.asarray(ens[0])
    model = csf_jax.problems.get("cubic10_indep", dim=dim)
    prior = csf_jax.learned_prior(net, config.encode_particles)
    context = prior.condition(params, ens, ens, model.process_std)
    precision = jnp.linalg.inv(jnp.cov(ens.T).reshape(dim, dim)) + jnp.eye(dim)
    loglik = functools.partial(csf_jax.log_likelihood, model, y)
    weights = functools.partial(curvature, model, y)
    u, chol = guidance.kalman_tweedie(ens, precision, loglik, model.observe, weights, ens, 1.0, 1)

    def repeat(body, init):
        return jax.lax.fori_loop(0, levels, body, init)

    def whole(p, o, e):
        return csf_jax.filter(p, o, e, problem=model, network=net, config=config,
                              key=jax.random.key(0), check_finite=False).mean

    cases = [
        ("whole filter step", whole, (params, obs[0], ens)),
        ("propagate + encode (once)", lambda p, e: prior.condition(
            p, e, jax.vmap(model.drift)(e), model.process_std), (params, ens)),
        (f"prior score x {levels}", lambda p, x: repeat(
            lambda i, x: x + 1e-3 * prior.score(p, context, x, 0.3), x), (params, ens)),
        (f"Kalman Tweedie (Jacobian, Cholesky, solve) x {levels}", lambda x: repeat(
            lambda i, x: guidance.kalman_tweedie(x, precision, loglik, model.observe, weights, x,
                                                 1.0, 1)[0], x), (ens,)),
        (f"  of which Cholesky (N, d, d) x {levels}", lambda a: repeat(
            lambda i, a: a + 1e-3 * _linalg.cholesky(a), a),
         (jnp.broadcast_to(precision, (particles, dim, dim)),)),
        (f"proposals and resampling (K = {proposals}) x {levels}", lambda x: repeat(
            lambda i, x: guidance.resample_posterior(jax.random.key(i), x, precision, u, chol,
                                                     loglik, 1.0, proposals), x), (ens,)),
        (f"  of which normal draws (K, N, d) x {levels}", lambda k: repeat(
            lambda i, s: s + jax.random.normal(jax.random.fold_in(k, i), s.shape),
            jnp.zeros((proposals, particles, dim))), (jax.random.key(0),)),
        (f"  of which triangular solves (K, N, d) x {levels}", lambda z: repeat(
            lambda i, z: _linalg.solve_lower_transposed(chol, z), z),
         (jnp.ones((proposals, particles, dim)),)),
    ]
    rows = [{"part": name, "ms": round(_median_ms(fn, args, repeats), 2)}
            for name, fn, args in cases]
    for row in rows:
        row["share"] = round(row["ms"] / rows[0]["ms"], 2)
    return rows


DESCRIPTION = ("Time the parts of one CSF filter step (encode, prior score, Kalman guidance, "
               "proposals, normal draws) apart; print the table and write step_parts.json to "
               "--out.")


def build_parser():
    """The command line of ``python -m experiments.step_parts``."""
    p = parser("step_parts", DESCRIPTION)
    p.add_argument("--dim", type=positive_int, default=10, help="state dimension d (default %(default)s)")
    p.add_argument("--particles", type=particle_count, default=1000,
                   help="ensemble size N (default %(default)s)")
    p.add_argument("--repeats", type=positive_int, default=20,
                   help="timed calls per part (default %(default)s)")
    p.add_argument("--out", default="out/step_parts", help="output folder (default %(default)s)")
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    rows = parts(args.dim, args.particles, args.repeats)
    print(f"d = {args.dim}, N = {args.particles}\n\n| part | ms per filter step | share |\n"
          "|---|---|---|")
    for row in rows:
        print(f"| {row['part']} | {row['ms']:.2f} | {row['share']:.2f} |")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "step_parts.json"), "w") as f:
        json.dump({"machine": machine(), "dim": args.dim, "particles": args.particles,
                   "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
