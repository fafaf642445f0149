"""How close a filter can come to the reference on the triple well: the exact filter under the
jump law a filter assumes.

    python -m experiments.exact_jumps [--runs 24] [--seeds 0,7,101,102] [--particles 1000]
        [--out results/exact_jumps] [--page docs/defaults.md]

The reference of the paper's well problems weighs the truth's own jumps: it knows that a jump
reflects the state (``x -> -x``) and how often one comes (``csf_jax.filters.reference``). A
filter that is not told either assumes a jump law of its own; CSF's is ``shock_hazard`` a step
(``MixtureConfig``) and a grid of widths around the ensemble. Which part of CSF's excess over the
reference is that assumption, and which its approximation, this measures with the exact Bayes filter of the
1-D model (``grid_filter``: the filtering density on a grid) under a generic jump law, ``x_{k+1}
= f(x_k) + N(0, q^2 + s^2)`` with probability ``hazard`` (s = ``JUMP_STD``), at the hazards of
``hazards``: none, CSF's, ten times it, and the truth's mean rate (one jump per run, at a step in
[0.2 K, 0.8 K)); and CSF at its default hazard and at ten times it. Same truths, observations and
initial ensembles as CSF, PAPER and the reference (``experiments.harness``, cached cells).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import problems
from csf_jax.ssm import log_likelihood
from experiments import cells, cli, defaults, harness, interrupt, zoo

PROBLEM = "triple_well"
JUMP_STD = 1.0
GRID = (-2.5, 2.5, 2001)
INITIAL_DRAWS = 1_000_000
TEN_TIMES = 10 * csf_jax.MixtureConfig().shock_hazard


def hazards(model) -> dict:
    """The hazards compared, by their rows' labels: none, CSF's default, ten times it, and the
    truth's mean rate over the steps where its jump can come (``WellConfig``: one in [0.2 K,
    0.8 K))."""
    default = csf_jax.MixtureConfig().shock_hazard
    rate = round(0.6 * model.num_steps)
    return {"exact, no jumps": 0.0, f"exact, hazard {default:g} (CSF's)": default,
            f"exact, hazard {TEN_TIMES:g}": TEN_TIMES,
            f"exact, hazard 1/{rate} (the truth's)": 1.0 / rate}


def initial_density(model, grid=GRID) -> np.ndarray:
    """The initial density on ``grid``: a histogram of ``INITIAL_DRAWS`` draws of
    ``model.initial_ensemble``, each bin a grid point's."""
    lo, hi, points = grid
    step = (hi - lo) / (points - 1)
    draws = np.asarray(model.initial_ensemble(jax.random.key(0), INITIAL_DRAWS))[:, 0]
    p0, _ = np.histogram(draws, bins=points, range=(lo - step / 2, hi + step / 2))
    return p0 / p0.sum()


def grid_filter(model, obs, hazard, p0, jump_std: float = JUMP_STD, grid=GRID):
    """Filtered means ``(K,)`` of a 1-D ``model`` (additive Gaussian process noise
    ``model.process_std``) from ``obs (K, 1)``, by the filtering density on ``grid = (lo, hi,
    points)``: the prior ``p_k = (1 - hazard) p_{k-1} K_q + hazard p_{k-1} K_j`` (``K_q``: the
    drift then ``N(0, q^2)``; ``K_j``: the drift then ``N(0, q^2 + jump_std^2)``), times the
    likelihood (``log_likelihood``: NaN missing), from the initial density ``p0 (points,)``
    (``initial_density``). The drift's image is clipped to the grid. Run it under
    ``jax.enable_x64``: without a jump law the density where the truth jumped to underflows
    float32."""
    lo, hi, points = grid
    g = jnp.linspace(lo, hi, points)
    f = jnp.clip(jax.vmap(model.drift)(g[:, None])[:, 0], lo, hi)

    def kernel(std):
        k = jnp.exp(-0.5 * ((g[None, :] - f[:, None]) / std) ** 2)
        return k / k.sum(1, keepdims=True)

    q = float(model.process_std)
    stay, jump = kernel(q), kernel(float(np.hypot(q, jump_std)))

    def update(p, y):
        prior = (1.0 - hazard) * (p @ stay) + hazard * (p @ jump)
        loglik = jax.vmap(lambda x: log_likelihood(model, y, x[None]))(g)
        post = prior * jnp.exp(loglik - loglik.max())
        post = post / post.sum()
        return post, post @ g

    return jax.lax.scan(update, jnp.asarray(p0, g.dtype), obs)[1]


ENTRIES = [defaults.entry("CSF"),
           harness.Entry(f"CSF, hazard {TEN_TIMES:g}", "csf",
                         zoo._csf(defaults._mixture(shock_hazard=TEN_TIMES))),
           defaults.entry("PAPER"), defaults.REFERENCE]


def page(record: dict) -> list:
    """The generated block: per seed, the reference's RMSE, then each filter's over it."""
    labels = list(dict.fromkeys(r["entry"] for r in record["rows"] if r["entry"] != "reference"))
    by_seed: dict = {}
    for r in record["rows"]:
        by_seed.setdefault(r["case"]["seed"], {})[r["entry"]] = r["rmse"]
    body = []
    for seed, rm in by_seed.items():
        ref = rm["reference"]
        body.append([str(seed), harness.number(ref)] + [harness.number(rm[k] / ref)
                                                       for k in labels])
    m = record["machine"]
    runs = record["rows"][0]["runs"]
    return ([f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
             f"cores, jax {m['jax_backend']}). The triple well, {runs} runs per seed, N = "
             f"{record['rows'][0]['case']['particles']}: the reference's RMSE, and each filter's "
             f"over it; \"exact, hazard h\": the exact filter whose jump law is a jump of std "
             f"{JUMP_STD:g} with probability h a step (module docstring):", ""]
            + harness.table(["seed", "reference RMSE"] + [f"{k} / ref." for k in labels], body))


def main(argv=None):
    p = harness.parser("exact_jumps", "The triple well: CSF, PAPER and the exact filter under a "
                       "generic jump law at several hazards, against the reference (cached, "
                       "resumable).")
    harness.add_sizes(p, runs=24, particles=1000)
    p.add_argument("--seeds", type=harness.int_list(0), default=[0, 7, 101, 102],
                   help="seeds of the runs (default: 0,7,101,102)")
    harness.add_outputs(p, "results/exact_jumps", "docs/defaults.md")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, "jumps")
    cache = cells.Cache(args.cache)
    cases = [harness.Case(PROBLEM, runs=args.runs, particles=args.particles, seed=s)
             for s in args.seeds]
    results = harness.run(cases, ENTRIES, cache, not args.no_progress)
    model = problems.get(PROBLEM)
    p0 = initial_density(model)
    exact = jax.jit(jax.vmap(lambda obs, hazard: grid_filter(model, obs, hazard, p0),
                             in_axes=(0, None)))
    rows = []
    for case in cases:
        data = harness.simulate(case)
        for entry in ENTRIES:
            outcome = results[(case, entry.label)]
            rows.append(harness.describe(case, entry, outcome) | harness.summary(outcome, data))
        truth = np.asarray(data.truth)[:, 1:, 0]
        for label, hazard in hazards(model).items():
            with jax.enable_x64(True):  # the tails a jump lands in underflow float32
                mean = np.asarray(exact(np.asarray(data.obs, np.float64), hazard))
            rmse = float(np.sqrt(np.mean((mean - truth) ** 2)))
            rows.append({"case": rows[-1]["case"],
                         "entry": label, "rmse": rmse, "runs": case.runs})
    record = harness.results_record("exact_jumps", harness.command("exact_jumps", argv), rows,
                                    cache, harness.output(args), jump_std=JUMP_STD, grid=list(GRID))
    with interrupt.WRITING:
        harness.publish(args, record, page(record), "results.json", "jumps")


if __name__ == "__main__":
    interrupt.main(main, "exact_jumps", interrupt.CACHED)
