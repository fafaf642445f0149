"""Where CSF's default filter step spends its time: each stage of one step, timed alone.

    python -m experiments.profile [--out results/profile] [--page docs/benchmark.md]

Prints one table per route (``params=None``: the mixture prior with the transported ensemble
component; the shipped trained prior: the same with the reverse-diffusion sampler) whose rows are
the stages of ``csf_jax.filters.csf._step`` and of ``csf_jax.mixture.select`` and whose columns
are the cases (d = 1 ``double_well``, d = 10 ``cubic10_indep``, d = 20 ``cubic20_indep``; N = 1000
and 50), in milliseconds with each stage's share of the whole step. ``--out`` writes
``results.json`` there and ``--page`` rewrites the page's generated block (markers
``results:profile:start`` / ``:end``).

How a case is measured (``profile_case``), at ``CSFConfig()``:

* the inputs of a real step: ``WARM_STEPS`` filter steps run from the model's initial ensemble
  (the step jitted alone, the keys and step indices of ``csf_jax.filter``'s scan), then the next
  step's ensemble, memory, observation, key and index;
* each stage (``STAGES``) is its own ``jax.jit`` of the library's code for that stage, called on
  these inputs, the outputs of one stage feeding the next (``stage_pipeline``; its posterior is
  the step's, ``tests/test_profile.py``); each is compiled first, called once to warm up, then
  timed with ``jax.block_until_ready``: the median of up to ``--repeats`` calls, fewer where they
  would take more than ``--budget`` seconds;
* the whole step: ``csf._step`` jitted alone on the same inputs (its compile seconds printed and
  recorded), and the per-step seconds of a ``csf_jax.filter`` run over K = ``RUN_STEPS`` steps
  (one ``jax.jit`` of the call: its scan). "other" is the whole step minus the stages: what the
  stages' own jits do not see (fusion across stages, the step's glue) and the stages' call
  overheads taken back;
* with the trained prior, its score network alone (``network_time``): the encoder and the
  sampler's L evaluations of ``s(x, t; c)`` on all N members, what the network costs a step
  where the sampler runs on every member, against the whole step.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import statistics
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

import csf_jax
from csf_jax import _linalg, mixture, problems
from csf_jax.filters import csf
from csf_jax.prior import ensemble_moments
from csf_jax.ssm import (
    Step,
    log_normalizer,
    process_cov,
    process_draws,
    tail_df,
)
from experiments import cli, harness, interrupt

PROBLEMS = {1: "double_well", 10: "cubic10_indep", 20: "cubic20_indep"}
PARTICLES = (1000, 50)
ROUTES = ("none", "trained")
ROUTE_TITLE = {"none": "`csf_jax.filter(None, ...)`: the ensemble component transported",
               "trained": "`csf_jax.filter(csf_jax.load_pretrained(name), ...)`: the ensemble "
                          "component sampled by the reverse diffusion"}
WARM_STEPS = 5
RUN_STEPS = 20

STAGES = {
    "propagation": "propagation (drift + process noise, wild members dropped)",
    "moments": "ensemble moments (covariance; trained: and the sampler's precision)",
    "ensemble_evidence": "ensemble + shock components' evidence (1 + G Laplace fits)",
    "particle_evidence": "particle components' evidence (N Laplace fits + weights)",
    "selection": "resampling / selection bookkeeping",
    "shock_draws": "shock draws (importance resampling)",
    "transport": "transport (`flow_transport`)",
    "sampler": "encoder + reverse-diffusion sampler (`prior.condition`, `sample`)",
}


class StepInputs(NamedTuple):
    """What one call of ``csf._step`` reads: the bound model and ``CSFStatic``, the raw params
    (None without a network), the state ``(ensemble (N, d), memory ())``, ``y (m,)``, the step's
    key and its index ``k`` (an int32 scalar)."""

    model: object
    static: csf.CSFStatic
    params: object
    ens: jax.Array
    memory: jax.Array
    y: jax.Array
    key: jax.Array
    k: jax.Array


class Timing(NamedTuple):
    """A timed function: median seconds per call, compile seconds, calls timed, its output."""

    seconds: float
    compile_seconds: float
    calls: int
    output: object


def compiled(fn: Callable, args: tuple) -> tuple:
    """``(fn`` compiled for ``args`` as one ``jax.jit``, its compile seconds)."""
    t0 = time.perf_counter()
    done = jax.jit(fn).lower(*args).compile()
    return done, time.perf_counter() - t0


def timed(fn: Callable, args: tuple, repeats: int, budget: float,
          ready: tuple | None = None) -> Timing:
    """``fn(*args)`` as one ``jax.jit`` (``ready``: already compiled, ``compiled``'s pair):
    compiled ahead (timed), called once to warm up, then the median over up to ``repeats``
    calls, fewer where they would pass ``budget`` seconds."""
    call, compile_seconds = ready or compiled(fn, args)
    out = jax.block_until_ready(call(*args))
    calls = []
    while len(calls) < repeats and (not calls or sum(calls) + calls[0] <= budget):
        t0 = time.perf_counter()
        jax.block_until_ready(call(*args))
        calls.append(time.perf_counter() - t0)
    return Timing(statistics.median(calls), compile_seconds, len(calls), out)


def user_params(problem: str, route: str):
    """The ``params`` a user passes for ``route``: None, or the shipped trained prior."""
    return None if route == "none" else csf_jax.load_pretrained(problem)


def case_data(problem: str, particles: int, seed: int, steps: int = RUN_STEPS):
    """``(model, obs (K, m), initial ensemble (N, d), filter key)`` of a case."""
    model = problems.get(problem, num_steps=steps)
    k_sim, k_ens, k_run = jax.random.split(jax.random.key(seed), 3)
    _, obs = csf_jax.simulate(model, k_sim)
    return model, obs, model.initial_ensemble(k_ens, particles), k_run


def bind(model, params, ensemble):
    """``(model, CSFStatic, raw params)`` as ``csf_jax.filter`` binds them at ``CSFConfig()``."""
    method = csf.method(params)
    model, static, raw, _ = csf.CSF.bind(model, method.config, method.params, ensemble)
    return model, static, raw


def whole_step(model, static: csf.CSFStatic) -> Callable:
    """``(params, ens, memory, y, key, k) -> ((post, memory), StepOutput)``: ``csf._step``."""
    return lambda params, ens, memory, y, key, k: csf._step(model, static, params, (ens, memory),
                                                            y, key, Step(k))


def step_inputs(model, static, raw, obs, ensemble, key, warm: int = WARM_STEPS,
                step: Callable | None = None) -> StepInputs:
    """The inputs of step ``warm + 1`` of a run: ``warm`` steps of the jitted ``csf._step``
    (``step``: the one compiled already) with the scan's keys (``split(key, K)``), observations
    and indices."""
    step = step or jax.jit(whole_step(model, static))
    keys = jax.random.split(key, obs.shape[0])
    ens, memory = ensemble, jnp.zeros((), ensemble.dtype)
    for i in range(warm):
        (ens, memory), _ = step(raw, ens, memory, obs[i], keys[i], jnp.int32(i + 1))
    return StepInputs(model, static, raw, ens, memory, obs[warm], keys[warm], jnp.int32(warm + 1))


def stage_functions(inp: StepInputs) -> tuple:
    """``({stage: function}, config)``: ``csf._step`` and ``mixture.select`` cut into their
    stages, each a pure function of arrays (the model and config closed over), in the order they
    run, and the config the step runs (with a heavy-tailed noise's proposals, as ``_step`` sets
    them). The stages not on the route (``transport`` under a trained prior, ``sampler``
    without one) are left out."""
    model, static = inp.model, inp.static
    config, prior = static.config, static.prior
    if (csf.uses_kalman(config) and config.sampler.guidance.proposal_df is None
            and tail_df(model) is not None):
        guidance = dataclasses.replace(config.sampler.guidance, proposal_df=tail_df(model))
        config = dataclasses.replace(config, sampler=dataclasses.replace(config.sampler,
                                                                         guidance=guidance))
    mix = config.prior.mixture
    transport = mixture.transports(mix, prior.name)
    sample = csf.particle_sampler(model, prior, config, static.shards)

    def propagation(ens, k_prop, k_wild):
        centers = jax.vmap(model.drift)(ens)
        prior_ens = centers + process_draws(model, k_prop, ens.shape, ens.dtype)
        wild = mixture.wild_members(prior_ens, mix.wild_ranges)
        return mixture.tame(k_wild, wild, centers, prior_ens)[0]

    def moments(prior_ens, k_init, y, guide):
        cov = ensemble_moments(prior_ens, covariance=config.prior.covariance).cov
        if transport:  # the sampler's start is unused there (the scan drops it)
            return cov, None, None
        x_init, start = csf.sampler_start(config, prior_ens, k_init, y, model, guide)
        return cov, x_init, start.precision

    @_linalg.precise
    def ensemble_evidence(y, k_ens, prior_ens, cov, tau2, guide):
        n, d = prior_ens.shape
        mean = prior_ens.mean(0)
        scales = jnp.asarray(mix.shock_scales, prior_ens.dtype)
        shock_tau2 = jnp.trace(cov) / d * scales
        inflation = jnp.concatenate([jnp.reshape(jnp.asarray(tau2, prior_ens.dtype), (1,)),
                                     shock_tau2 if mix.shock_hazard > 0
                                     else jnp.zeros((0,), prior_ens.dtype)])
        shapes = mixture.inflation_shapes(model, mix, y, prior_ens, inflation.shape[0])
        precisions = mixture.precision(cov[None] + inflation[:, None, None] * shapes)
        keys = jax.random.split(k_ens, precisions.shape[0])
        log_z, _, u, chol = jax.vmap(lambda p, k: mixture._component_evidence(
            model, y, k, mean[None], p, mix.ensemble_iterations, mix.ensemble_proposals,
            guide))(precisions, keys)
        return log_z[:, 0], precisions, u[:, 0], chol[:, 0]

    @_linalg.precise
    def particle_evidence(y, k_part, centers, cov, guide):
        n, d = centers.shape
        kernels, q_cov = centers, process_cov(model, centers.dtype)
        if mix.particle_kernel > 0:
            h2 = mix.particle_kernel * mixture.silverman(n, d) ** 2
            centre = centers.mean(0)
            kernels, q_cov = centre + math.sqrt(1.0 - h2) * (centers - centre), q_cov + h2 * cov
        q_prec = mixture.precision(q_cov + 1e-12 * jnp.eye(d, dtype=centers.dtype))
        log_z, draws, _, _ = mixture._component_evidence(
            model, y, k_part, kernels, q_prec, mix.iterations, mix.proposals, guide)
        return jnp.where(jnp.isfinite(log_z), log_z, -jnp.inf), draws

    @_linalg.precise
    def selection(y, k_res, prior_ens, log_z_part, log_z_ens, draws, memory, guide):
        n, d = prior_ens.shape
        dtype = prior_ens.dtype
        informed = mixture.informative(y, guide)
        hazard = jnp.asarray(mix.shock_hazard, dtype)
        log_hazard = jnp.where(informed, jnp.log(hazard), -jnp.inf)
        log_calm = jnp.where(informed, jnp.log1p(-hazard), 0.0)
        odds = mix.particle_logodds + memory
        log_bf = logsumexp(log_z_part) - jnp.log(n) - log_z_ens[0]
        if mix.particle_ess > 0:
            penalty = mixture.ess_penalty(log_z_part, min(mix.particle_ess * d, n))
            odds, log_bf = odds - penalty, log_bf - penalty
        log_calm_w = jnp.concatenate([log_calm + jax.nn.log_sigmoid(odds) - jnp.log(n)
                                      + log_z_part,
                                      log_calm + jax.nn.log_sigmoid(-odds) + log_z_ens[:1]])
        log_shock_w = log_hazard - jnp.log(len(mix.shock_scales)) + log_z_ens[1:]
        if mix.shock_gate > 0:
            gate = math.log(mix.shock_gate) - math.log1p(-mix.shock_gate)
            log_odds = logsumexp(log_shock_w) - logsumexp(log_calm_w)
            log_shock_w = jnp.where(log_odds >= gate, log_shock_w, -jnp.inf)
        log_w = jnp.concatenate([log_calm_w, log_shock_w])
        log_w = jnp.where(jnp.isnan(log_w), -jnp.inf, log_w)
        idx = mixture._systematic(k_res, log_w, n)
        kind = jnp.where(idx < n, 0, idx - n + 1).astype(jnp.int32)
        weights = jnp.exp(log_w - logsumexp(log_w))
        draws = draws[jnp.clip(idx, 0, n - 1)]
        log_bf = jnp.where(informed & jnp.isfinite(log_bf), log_bf, 0.0)
        # the step's end: the blind step's fallbacks, the evidence, the memory and the output
        kind_out = jnp.where(informed, kind, 0)
        post = jnp.where(informed, draws, prior_ens)
        const = log_normalizer(model, y)
        calm = logsumexp(jnp.where(jnp.isnan(log_calm_w), -jnp.inf, log_calm_w)) - log_calm
        log_ev = None if const is None else jnp.where(
            informed, calm + mixture.proposal_constant(d, tail_df(model), dtype) + const, 0.0)
        memory, _ = mixture.next_odds(mix, memory, log_bf, informed)
        out = csf._output(post, jnp.all(jnp.isfinite(prior_ens)),
                          {"particle_weight": jnp.where(informed, weights[:n].sum(), 1.0),
                           "shock_weight": weights[n + 1:].sum()}, log_ev)
        return kind, kind_out, draws, memory, out

    @_linalg.precise
    def shock_draws(y, k_shock, prior_ens, precisions, u_ens, chol_ens, kind, draws, guide):
        return mixture.shock_draws(model, mix, k_shock, y, prior_ens.mean(0), precisions, u_ens,
                                   chol_ens, kind, draws, guide)

    @_linalg.precise
    def transport_stage(y, k_res, prior_ens, cov, u_ens, chol_ens, precisions, kind, draws,
                        guide):
        return mixture.transported(model, mix, k_res, y, prior_ens, cov, u_ens[0], chol_ens[0],
                                   precisions[0], kind, draws, guide)

    def sampler(params, y, k_rev, centers, prior_ens, x_init, start_precision, kind, draws,
                guide, *, tau):
        context = prior.condition(params, centers, prior_ens, model.process_std)
        start = csf.SamplerStart(start_precision, tau)

        def fill(idx):
            return sample(params, context, y, jnp.take(x_init, idx, axis=0, mode="clip"), start,
                          k_rev, guide)

        return mixture.fill_rows(kind == 1, fill, draws, mixture.row_block(draws.shape[0]))

    stages = {"propagation": propagation, "moments": moments,
              "ensemble_evidence": ensemble_evidence, "particle_evidence": particle_evidence,
              "selection": selection, "shock_draws": shock_draws}
    if mix.shock_hazard == 0:
        del stages["shock_draws"]
    if transport:
        stages["transport"] = transport_stage
    else:
        stages["sampler"] = sampler
    return stages, config


def stage_pipeline(inp: StepInputs, repeats: int = 1, budget: float = 0.0) -> tuple:
    """Each stage of ``stage_functions`` timed on ``inp``, fed by the stages before it:
    ``({stage: Timing}, posterior ensemble (N, d), kind (N,))``. The posterior and the members'
    components are the step's (the particles' draws, then the shocks', then the ensemble
    component's)."""
    fns, config = stage_functions(inp)
    k_prop, k_init, k_rev = jax.random.split(inp.key, 3)
    k_part, k_ens, k_res, k_shock = jax.random.split(jax.random.fold_in(inp.key, 3), 4)
    guide = jnp.where((inp.k > 1) | config.sampler.assimilate_first, 1.0, 0.0).astype(
        inp.ens.dtype)
    out = {}

    def run(name, *args):
        out[name] = timed(fns[name], args, repeats, budget)
        return out[name].output

    centers, prior_ens = run("propagation", inp.ens, k_prop, jax.random.fold_in(inp.key, 4))
    tau = csf.step_inflation(config, prior_ens, inp.y, inp.model, guide)
    tau2 = jnp.square(jnp.asarray(tau, prior_ens.dtype))
    cov, x_init, start_precision = run("moments", prior_ens, k_init, inp.y, guide)
    log_z_ens, precisions, u_ens, chol_ens = run("ensemble_evidence", inp.y, k_ens, prior_ens,
                                                 cov, tau2, guide)
    log_z_part, draws = run("particle_evidence", inp.y, k_part, centers, cov, guide)
    kind, kind_out, draws, _, _ = run("selection", inp.y, k_res, prior_ens, log_z_part,
                                      log_z_ens, draws, inp.memory, guide)
    if "shock_draws" in fns:
        draws = run("shock_draws", inp.y, k_shock, prior_ens, precisions, u_ens, chol_ens, kind,
                    draws, guide)
    if "transport" in fns:
        draws = run("transport", inp.y, k_res, prior_ens, cov, u_ens, chol_ens, precisions, kind,
                    draws, guide)
    else:
        # tau closed over, as the step has it: a Python float keeps the samplers' static
        # shortcut for 0 (an adaptive inflation is a concrete scalar here)
        fns["sampler"] = functools.partial(fns["sampler"], tau=tau)
        draws = run("sampler", inp.params, inp.y, k_rev, centers, prior_ens, x_init,
                    start_precision, kind, draws, guide)
    informed = mixture.informative(inp.y, guide)
    return out, jnp.where(informed, draws, prior_ens), kind_out


def network_time(inp: StepInputs, propagated: tuple, repeats: int, budget: float) -> Timing:
    """The score network alone, as the trained sampler evaluates it in a step where it runs on
    all N members: the encoder once, then ``reverse_steps`` evaluations of ``s(x, t; c)`` on
    ``(N, d)`` (a scan, each step's input the last one's output nudged, so none is hoisted)."""
    config, prior = inp.static.config, inp.static.prior
    centers, prior_ens = propagated
    steps = config.sampler.reverse_steps

    def network(params, centers, prior_ens):
        context = prior.condition(params, centers, prior_ens, inp.model.process_std)

        def evaluate(x, t):
            return x + 1e-3 * prior.score(params, context, x, t), None

        return jax.lax.scan(evaluate, prior_ens, jnp.linspace(1.0, 1e-3, steps,
                                                              dtype=prior_ens.dtype))[0]

    return timed(network, (inp.params, centers, prior_ens), repeats, budget)


def profile_case(problem: str, particles: int, route: str, repeats: int, budget: float,
                 seed: int, warm: int = WARM_STEPS, steps: int = RUN_STEPS) -> dict:
    """One case's results row: the stages' milliseconds, the whole step's (and its compile
    seconds), the per-step milliseconds of a K = ``steps`` run, and the calls timed."""
    model, obs, ensemble, key = case_data(problem, particles, seed, steps)
    params = user_params(problem, route)
    bound, static, raw = bind(model, params, ensemble)
    step = whole_step(bound, static)
    first = (raw, ensemble, jnp.zeros((), ensemble.dtype), obs[0], key, jnp.int32(1))
    ready = compiled(step, first)
    inp = step_inputs(bound, static, raw, obs, ensemble, key, warm, ready[0])
    stages, _, kind = stage_pipeline(inp, repeats, budget)
    network = (None if route == "none" else
               network_time(inp, stages["propagation"].output, repeats, budget).seconds * 1e3)
    members = [int(v) for v in jnp.bincount(jnp.minimum(kind, 2), length=3)]
    whole = timed(step, (inp.params, inp.ens, inp.memory, inp.y, inp.key, inp.k), repeats, budget,
                  ready)
    run = timed(lambda y, e, k: csf_jax.filter(params, y, e, model=model, key=k),
                (obs, ensemble, key), repeats, budget)
    return {"problem": problem, "dim": model.dim, "particles": particles, "route": route,
            "stages_ms": {name: t.seconds * 1e3 for name, t in stages.items()},
            "stage_calls": {name: t.calls for name, t in stages.items()},
            "members": dict(zip(("particle", "ensemble", "shock"), members)),
            "network_ms": network,
            "whole_step_ms": whole.seconds * 1e3, "whole_step_calls": whole.calls,
            "whole_step_compile_seconds": whole.compile_seconds,
            "run_steps": steps, "run_ms_per_step": run.seconds / steps * 1e3,
            "run_calls": run.calls, "run_compile_seconds": run.compile_seconds}


def ms(v: float) -> str:
    """Milliseconds for the table: 3 significant figures."""
    return f"{v:.3g}"


def cell(v: float, whole: float) -> str:
    """``12.3 (45%)``: milliseconds and the share of the whole step."""
    return f"{ms(v)} ({100 * v / whole:.0f}%)"


def route_table(rows: list) -> list:
    """The markdown table of one route's rows (one per case, in column order)."""
    header = ["stage, ms (share of the whole step)"] + [
        f"d = {r['dim']}, N = {r['particles']}" for r in rows]
    names = [s for s in STAGES if any(s in r["stages_ms"] for r in rows)]
    lines = []
    for name in names:
        lines.append([STAGES[name]] + [cell(r["stages_ms"][name], r["whole_step_ms"])
                                       if name in r["stages_ms"] else "-" for r in rows])
    parts = [sum(r["stages_ms"].values()) for r in rows]
    lines.append(["sum of the stages"] + [cell(p, r["whole_step_ms"]) for p, r in zip(parts, rows)])
    lines.append(["other (whole step - stages)"] + [cell(r["whole_step_ms"] - p, r["whole_step_ms"])
                                                    for p, r in zip(parts, rows)])
    lines.append(["**whole step** (`csf._step`, one jit)"] + [f"**{ms(r['whole_step_ms'])}**"
                                                               for r in rows])
    if any(r.get("network_ms") is not None for r in rows):
        lines.append(["of the sampler: the score network alone (the encoder and L evaluations "
                      "on all N members)"]
                     + [cell(r["network_ms"], r["whole_step_ms"]) for r in rows])
    lines.append([f"per step of a K = {rows[0]['run_steps']} `csf_jax.filter` run (the scan)"]
                 + [ms(r["run_ms_per_step"]) for r in rows])
    lines.append(["members drawn from the particle / ensemble / shock components"]
                 + [" / ".join(str(r["members"][k]) for k in ("particle", "ensemble", "shock"))
                    for r in rows])
    lines.append(["whole step's compile, s"] + [f"{r['whole_step_compile_seconds']:.1f}"
                                                for r in rows])
    return harness.table(header, lines)


def page(record: dict) -> list:
    """The generated block: a table per route, then how it was made."""
    lines = []
    for route in ROUTES:
        rows = [r for r in record["rows"] if r["route"] == route]
        if rows:
            lines += [f"**{ROUTE_TITLE[route]}**", "", *route_table(rows), ""]
    m = record["machine"]
    calls = sorted({c for r in record["rows"] for c in (*r["stage_calls"].values(),
                                                           r["whole_step_calls"])})
    counts = str(calls[0]) if calls[0] == calls[-1] else f"{calls[0]}-{calls[-1]}"
    lines.append(f"Made by `{record['command']}` on {record['date']}, {m['cpu']} "
                 f"({m['cpu_count']} cores, jax {m['jax_backend']}); step {record['warm_steps'] + 1}"
                 f" of a run, the median of {counts} timed calls per figure after a warm-up.")
    return lines


def main(argv=None):
    p = harness.parser("profile", "Time each stage of one CSF filter step at CSFConfig() (the "
                       "evidence of the mixture's components, the transport or the sampler, ...) "
                       "against the whole step, for d = 1, 10, 20 and N = 1000, 50.", cache=False)
    harness.add_outputs(p, "results/profile", "docs/benchmark.md")
    p.add_argument("--repeats", type=harness.int_at_least(1), default=5,
                   help="timed calls per figure after a warm-up (default %(default)s)")
    p.add_argument("--budget", type=float, default=4.0,
                   help="seconds of timed calls per figure, past which fewer calls are timed "
                        "(default %(default)s)")
    p.add_argument("--dims", type=harness.int_list(1), default=list(PROBLEMS),
                   help="state dimensions, of " + ", ".join(map(str, PROBLEMS))
                        + " (default: all)")
    p.add_argument("--particles", type=harness.int_list(2), default=list(PARTICLES),
                   help="ensemble sizes N (default: 1000,50)")
    p.add_argument("--routes", type=harness.name_list(ROUTES, "route"), default=list(ROUTES),
                   help="none (params=None), trained (the shipped prior) (default: both)")
    p.add_argument("--seed", type=harness.int_at_least(0), default=0,
                   help="seed of the data and the filter (default %(default)s)")
    args = p.parse_args(argv)
    cli.check_outputs(p, args, "profile")
    unknown = [d for d in args.dims if d not in PROBLEMS]
    if unknown:
        p.error(f"argument --dims: no problem of dimension {unknown[0]}; use "
                f"{', '.join(map(str, PROBLEMS))}")
    rows = []
    for route in args.routes:
        for d in args.dims:
            for n in args.particles:
                t0 = time.perf_counter()
                r = profile_case(PROBLEMS[d], n, route, args.repeats, args.budget, args.seed)
                rows.append(r)
                if not args.no_progress:
                    print(f"{route}, d = {d}, N = {n}: whole step {ms(r['whole_step_ms'])} ms "
                          f"(compile {r['whole_step_compile_seconds']:.1f} s), run "
                          f"{ms(r['run_ms_per_step'])} ms per step, stages "
                          + ", ".join(f"{k} {ms(v)}" for k, v in r["stages_ms"].items())
                          + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    record = harness.results_record("profile", harness.command("profile", argv), rows,
                                    warm_steps=WARM_STEPS, config="CSFConfig()")
    harness.publish(args, record, page(record), tag="profile")


if __name__ == "__main__":
    interrupt.main(main, "profile")
