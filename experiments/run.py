"""The main job: run CSF, SF, EnKF and PF, and the near-exact reference, on one of the paper's
problems (paper Sec. 3).

    python -m experiments.run double_well [--methods csf,sf,enkf,pf,reference] [--runs R]
        [--particles N] [--steps L] [--guidance kalman] [--seed 0] [--out DIR] [--batch B]
        [--prior pretrained|exact|gaussian] [--quick]

Simulates ``--runs`` independent truth/observation trajectories (run i uses the key
``fold_in(key(seed), i)``, so a run does not depend on how many others there are), runs every method
on the same data and prints a table: RMSE (the paper's Eq. rmse, full norm), RMSE per coordinate,
RMSE before and after the first shock, seconds per filter step per run (the wall-clock time of all
runs over runs x filter steps, compile time apart; "at once" says how many runs shared that time).

CSF uses the shipped pretrained prior (``csf_jax.load_pretrained``; triple_well uses the double-well
model: the paper's transfer experiment); ``--prior exact`` uses the exact Gaussian-mixture prior,
``--prior gaussian`` the Gaussian with the propagated ensemble's mean and covariance.
SF trains its score net online (``csf_jax.SFConfig``: the per-step budget is printed).
The reference (``csf_jax.filters.reference``: 20000 particles per coordinate, shocks modelled,
started from the model's initial law) is the best achievable on these problems; the table's
"RMSE / reference" column is each method's RMSE over its RMSE on the same runs.

``--out DIR`` writes ``results.json`` and PNG figures (``experiments.figures``; they need
matplotlib: ``pip install matplotlib``), and caches every finished run under ``DIR/cache``: an
interrupted job, run again with the same arguments, resumes at the first unfinished run. Runs are
batched, ``--batch`` at a time (default: all runs for EnKF/PF and on GPU; on CPU one run per core
for CSF/SF). On a CPU a vmapped batch runs no faster per run than one run, so the job asks XLA for
one host device per core (``--xla_force_host_platform_device_count``, unless ``XLA_FLAGS`` already
sets it or jax was imported first) and spreads a batch's runs over them with ``shard_map``. Runs
are independent, so only the wall-clock time changes: on the 2-core dev machine 1.07x faster for
CSF (XLA already keeps both cores busy on one run), 1.39x for SF.

SF's online training makes it the slow column on a CPU: there the default is SF on the first run,
its training batch split over the cores (``csf_jax.score_filter(..., shards=)``; the page and the
table say so); ``--sf-runs 10`` runs it on all.

The full seven-problem table of the README is ``python -m experiments.table``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import json
import os
import platform
import sys
import time


def _one_host_device_per_core() -> None:
    """Ask XLA for one CPU device per core, before jax is imported (see the module doc)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "jax" not in sys.modules and "host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_force_host_platform_device_count="
                                   f"{os.cpu_count() or 1}").strip()


_one_host_device_per_core()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import csf_jax  # noqa: E402
from csf_jax import CSFConfig, GuidanceConfig, SFConfig, problems  # noqa: E402
from csf_jax.filters.reference import ReferenceConfig, reference_filter  # noqa: E402
from csf_jax.guidance import MODES  # noqa: E402
from csf_jax.pretrained import load_pretrained  # noqa: E402
from csf_jax.prior import gaussian_prior  # noqa: E402
from experiments._cli import (  # noqa: E402
    name_list,
    nonnegative_int,
    parser,
    particle_count,
    positive_int,
)

METHODS = ("csf", "csf_gaussian", "sf", "enkf", "pf", "reference")
LABELS = {"csf": "CSF", "csf_gaussian": "CSF-G", "sf": "SF", "enkf": "EnKF", "pf": "PF",
          "reference": "Ref."}
METHOD_HELP = {"csf": "CSF with the --prior prior", "csf_gaussian": "CSF-G: CSF's sampler with the "
               "ensemble's own Gaussian as the prior", "sf": "the score filter, trained online",
               "enkf": "ensemble Kalman filter", "pf": "bootstrap particle filter",
               "reference": "the near-exact per-coordinate reference filter"}
RUNS, PARTICLES = 10, 1000  # the table's setting
# csf_gaussian: CSF's sampler with the ensemble's own Gaussian as the prior (csf_jax.gaussian_prior,
# no network, all N particles for the moments): the baseline a learned prior has to beat. It runs
# with CSF's config of the column, so that CSF against CSF-G isolates the learned correction.
# The near-exact reference filter (csf_jax.filters.reference) of the tables: M particles per
# coordinate, shocks modelled, started from the model's initial law (not the N-particle ensemble).
REFERENCE = ReferenceConfig()
QUICK_REFERENCE = ReferenceConfig(particles=2000, shock_draws=256)
QUICK = dict(runs=2, particles=100, steps=20, num_steps=10)
QUICK_SF = SFConfig(train_steps=20, warmup_steps=100)
PRIORS = ("pretrained", "exact", "gaussian")  # CSF's prior: --prior
CPU_SF_RUNS = 1  # the CLI's default SF runs on a CPU (module doc)
# Per-problem CSFConfig fields of the tables, on top of the defaults; a "guidance" entry holds
# GuidanceConfig fields. Cauchy noise has heavy tails, and so has the posterior: the Laplace
# proposals (Gaussian around the mode) never propose its tails and the resampled ensemble comes out
# too narrow (docs/ablation.md). Student-t proposals with one degree of freedom, the noise's own
# tail, and 32 of them per particle (runs 0-2: 0.264 against 0.303 with 8 Gaussian ones).
CSF_OVERRIDES = {"cauchy": {"guidance": {"proposal_df": 1, "proposals": 32}}}
# SF's sampler in the tables: base inflation 0.2, the config of SF's cached runs (SF's runs cost
# hours, so they are not remade for each change of CSF's sampler); on the triple well, whose SF
# runs are cheap, CSF's own sampler (base 0).
SF_SAMPLER_BASE = {"prior_inflation": 0.2}
SF_SAMPLER_OVERRIDES = {"triple_well": {"prior_inflation": 0.0}}


class Progress:
    """A one-line progress bar on stderr over ``total`` filter steps, fed by the filters' host
    callback (``progress=`` of ``csf_jax.filter`` / ``csf_jax.score_filter``).

    One instance per method: the filters take it as a static argument, so every batch of runs
    reuses one compilation. ``offset`` says how many filter steps the batches before the current one
    covered, ``width`` how many runs the current batch holds (the callback fires once per step for the whole batch).
    """

    def __init__(self, label: str, total: int, enabled: bool = True):
        self.label, self.total, self.enabled = label, total, enabled
        self.offset, self.width, self.t0, self._last = 0, 1, time.perf_counter(), 0.0

    def __call__(self, k) -> None:
        if not self.enabled:
            return
        done = self.offset + (int(k) + 1) * self.width
        now = time.perf_counter()
        if now - self._last < 1.0 and done < self.total:
            return
        self._last = now
        frac = done / self.total
        bar = "#" * int(30 * frac)
        elapsed = now - self.t0
        eta = elapsed * (1 - frac) / max(frac, 1e-9)
        print(f"\r  {self.label:5s} [{bar:30s}] {done}/{self.total} filter steps  {elapsed:.0f} s"
              f"  ETA {eta:.0f} s ", end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled:
            print("\r" + " " * 90 + "\r", end="", file=sys.stderr, flush=True)


def run_keys(seed: int, runs: int):
    """Per-run keys ``(3, runs)``: truth/observations, initial ensemble, filter."""
    keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(jax.random.key(seed), i), 3))(
        jnp.arange(runs))
    return keys.T


@functools.partial(jax.jit, static_argnames=("model", "particles"))
def _simulate(model, k_sim, k_ens, particles: int):
    truth, obs = jax.vmap(lambda k: csf_jax.simulate(model, k))(k_sim)
    shocks = jax.vmap(lambda k: csf_jax.shock_steps(model, k))(k_sim)
    ens = jax.vmap(lambda k: model.initial_ensemble(k, particles))(k_ens)
    return truth, obs, shocks, ens


def simulate_runs(model, runs: int, particles: int, seed: int):
    """``truth (R, K+1, d)``, ``obs (R, K, m)``, ``shocks (R, K)`` bool, ``ens (R, N, d)``, filter
    keys ``(R,)``. One compiled computation (op by op it would compile ~50 small ones; the numbers
    of the two ways differ in the last bits)."""
    k_sim, k_ens, k_filt = run_keys(seed, runs)
    return (*_simulate(model, k_sim, k_ens, particles), k_filt)


def method_fn(method: str, model, config: CSFConfig, sf: SFConfig, pretrained, progress,
              return_ensembles: bool = False, sf_shards: int = 1,
              reference: ReferenceConfig = REFERENCE, prior=None,
              sf_sampler: CSFConfig | None = None):
    """``(obs (K, m), ens (N, d), key) -> FilterResult`` for one run of ``method``.

    pretrained: a ``csf_jax.pretrained.Pretrained`` for CSF (passed whole: the filter checks it
    was trained for ``model``), or None for the exact mixture prior.
    prior: CSF's ``PriorScore`` when not the pretrained or exact one (``gaussian_prior()``).
    sf_shards: SF's training batch split over this many local devices (``score_filter``).
    sf_sampler: SF's sampler (default ``config``; the tables pass ``sf_sampler_config``).
    reference: the reference filter's settings; it draws ``reference.particles`` from the model's
    initial law (with ``fold_in(key, 1)``) instead of using ``ens``.
    """
    if method == "csf":
        return lambda o, e, k: csf_jax.filter(pretrained, o, e, problem=model, key=k, config=config,
                                              prior=prior, progress=progress,
                                              return_ensembles=return_ensembles)
    if method == "csf_gaussian":
        return lambda o, e, k: csf_jax.filter(None, o, e, problem=model, key=k, config=config,
                                              prior=gaussian_prior(config.sigma_max,
                                                                   config.covariance),
                                              progress=progress,
                                              return_ensembles=return_ensembles)
    if method == "sf":
        return lambda o, e, k: csf_jax.score_filter(o, e, problem=model, key=k, config=sf,
                                                    sampler=sf_sampler or config,
                                                    progress=progress,
                                                    return_ensembles=return_ensembles,
                                                    shards=sf_shards)
    if method == "enkf":
        return lambda o, e, k: csf_jax.ensemble_kalman_filter(o, e, problem=model, key=k)
    if method == "pf":
        return lambda o, e, k: csf_jax.particle_filter(o, e, problem=model, key=k)
    if method == "reference":
        return lambda o, e, k: reference_filter(
            o, model.initial_ensemble(jax.random.fold_in(k, 1), reference.particles).astype(e.dtype),
            problem=model, key=k, config=reference, check_finite=False)
    raise SystemExit(f"unknown method {method!r}; choose from {', '.join(METHODS)}")


# Config fields whose value here leaves the method's computation as it is without the field: left
# out of fingerprints at that value, so that adding such a field does not invalidate cached runs.
NEUTRAL_FIELDS = {"base": "none",  # NetworkConfig.base (SFConfig.network): no Gaussian base
                  "proposal_df": None,  # GuidanceConfig.proposal_df: Gaussian proposals
                  "mixture": None,  # CSFConfig.mixture: no mixture prior
                  "covariance": {"estimator": "sample", "radius": 2.0,  # CSFConfig.covariance:
                                 "periodic": False}}  # the sample covariance


def _neutral(obj):
    if isinstance(obj, dict):
        return {k: _neutral(v) for k, v in obj.items()
                if not (k in NEUTRAL_FIELDS and v == NEUTRAL_FIELDS[k])}
    if isinstance(obj, (list, tuple)):
        return [_neutral(v) for v in obj]
    return obj


def _fingerprint(obj) -> str:
    """A short hash of a JSON-able config (``NEUTRAL_FIELDS`` at their neutral value left out)."""
    return hashlib.sha256(json.dumps(_neutral(obj), sort_keys=True,
                                     default=repr).encode()).hexdigest()[:16]


def method_ident(method: str, name: str, cfg: dict, reference: ReferenceConfig) -> str:
    """The cache fingerprint of ``method``'s runs of problem ``name`` under the run config ``cfg``
    (``run``'s ``results.json["config"]``): the problem, N, seed, and what the method's results
    depend on (CSF: its config, prior and model; SF: its config and sampler)."""
    config = ({"csf": cfg["csf"], "prior": cfg["csf_prior"], "model": cfg["csf_model_id"]}
              if method == "csf" else
              {"csf": cfg["csf"]} if method == "csf_gaussian" else
              {"sf": cfg["sf"], "csf": cfg["sf_sampler"]} if method == "sf" else
              {"reference": reference._asdict()} if method == "reference" else None)
    return _fingerprint({"problem": cfg["problem"], "name": name, "particles": cfg["particles"],
                         "seed": cfg["seed"], "method": method, "config": config})


def _cached(cache_dir, method, lo, hi, ident):
    """``(mean (hi-lo, K, d), seconds, compile s, runs at once)`` of runs ``[lo, hi)`` from the
    cache, or None.

    A batch is stored one file per run (``<method>-<i>-<i+1>-<ident>.npz``, its share of the
    batch's seconds), so a cache is reused whatever the batch size; a whole-batch file
    ``<method>-<lo>-<hi>-<ident>.npz`` (EnKF/PF) is looked up first.
    """
    if cache_dir is None:
        return None
    name = lambda a, b: os.path.join(cache_dir, f"{method}-{a}-{b}-{ident}.npz")
    paths = [name(lo, hi)] if os.path.exists(name(lo, hi)) else [name(i, i + 1)
                                                                 for i in range(lo, hi)]
    if not all(os.path.exists(q) for q in paths):
        return None
    means, seconds, compile_s, at_once = [], 0.0, 0.0, 1
    for q in paths:
        with np.load(q) as f:
            means.append(f["mean"])
            seconds += float(f["seconds"])
            compile_s = max(compile_s, float(f["compile_seconds"]))
            at_once = max(at_once, int(f["at_once"]) if "at_once" in f else len(f["mean"]))
    return np.concatenate(means), seconds, compile_s, at_once


def _save(cache_dir, method, lo, ident, mean, seconds, compile_s):
    """Write each run of a finished batch to its own cache file (atomically)."""
    width = mean.shape[0]
    for j in range(width):
        path = os.path.join(cache_dir, f"{method}-{lo + j}-{lo + j + 1}-{ident}.npz")
        tmp = path + ".tmp.npz"
        np.savez(tmp, mean=mean[j:j + 1], seconds=seconds / width, compile_seconds=compile_s,
                 at_once=width)
        os.replace(tmp, path)


def _filter_runs(method, fn, obs, ens, keys, batch, cache_dir, ident, progress):
    """Run ``fn`` over all runs in batches; returns means (R, K, d), seconds, compile s, and how
    many runs ran at once (the largest batch).

    seconds: the wall-clock time of all batches (runs of a batch run at once, vmapped or spread
    over devices). Finished runs are cached under ``cache_dir`` and reused (``_cached``).
    """
    R, K = obs.shape[:2]
    plain, spread = jax.jit(jax.vmap(fn)), _over_devices(fn, batch)
    compiled, compile_s = None, 0.0
    means, seconds, at_once = [], 0.0, 1
    for lo in range(0, R, batch):
        hi = min(R, lo + batch)
        progress.offset, progress.width = lo * K, hi - lo
        hit = _cached(cache_dir, method, lo, hi, ident)
        if hit is not None:
            means.append(hit[0])
            seconds += hit[1]
            compile_s = max(compile_s, hit[2])
            at_once = max(at_once, hit[3])
            continue
        args = (obs[lo:hi], ens[lo:hi], keys[lo:hi])
        if compiled is None or hi - lo != batch:
            batched = spread if hi - lo == batch and spread is not None else plain
            t0 = time.perf_counter()
            compiled = batched.lower(*args).compile()
            compile_s = max(compile_s, time.perf_counter() - t0)
        t0 = time.perf_counter()
        result = jax.block_until_ready(compiled(*args))
        run_s = time.perf_counter() - t0
        mean = np.asarray(result.mean)
        if not np.all(np.isfinite(mean)):
            bad = np.argwhere(~np.all(np.isfinite(mean), axis=-1))[0]
            print(f"\n  warning: {method} run {lo + bad[0]} is not finite from filter step "
                  f"{bad[1]} on", file=sys.stderr)
        means.append(mean)
        seconds += run_s
        at_once = max(at_once, hi - lo)
        if cache_dir is not None:
            _save(cache_dir, method, lo, ident, mean, run_s, compile_s)
    progress.close()
    return np.concatenate(means), seconds, compile_s, at_once


def _over_devices(fn, batch: int):
    """``jit(shard_map(vmap(fn)))`` with a batch's runs split over ``batch`` local devices, or None
    when fewer devices (or a batch of 1): then the batch is vmapped on one device."""
    devices = jax.local_devices()
    if batch < 2 or len(devices) < batch:
        return None
    mesh = jax.sharding.Mesh(np.array(devices[:batch]), ("runs",))
    spec = jax.sharding.PartitionSpec("runs")
    return jax.jit(jax.shard_map(jax.vmap(fn), mesh=mesh, in_specs=(spec, spec, spec),
                                 out_specs=spec, check_vma=False))


def _errors(mean, truth):
    """Squared error ``(R, K)`` of the filtered means ``(R, K, d)`` against ``truth (R, K+1, d)``."""
    return np.sum((mean - truth[:, 1:]) ** 2, axis=-1)


def summarize(err, shocks, dim: int) -> dict:
    """RMSE figures of one method from squared errors ``(R, K)`` and shock flags ``(R, K)``."""
    R, K = err.shape
    first = np.where(shocks.any(axis=1), shocks.argmax(axis=1), K)
    before = np.arange(K)[None, :] < first[:, None]
    with np.errstate(invalid="ignore"):
        return {
            "rmse": float(np.sqrt(err.mean())),
            "rmse_per_dim": float(np.sqrt(err.mean() / dim)),
            "rmse_per_run": np.sqrt(err.mean(axis=1)).tolist(),
            "rmse_over_time": np.sqrt(err.mean(axis=0)).tolist(),
            "rmse_before_shock": float(np.sqrt(err[before].mean())) if before.any() else None,
            "rmse_after_shock": float(np.sqrt(err[~before].mean())) if (~before).any() else None,
        }


def reference_ratios(means: dict, truth) -> dict:
    """``{method: RMSE / reference RMSE}``, both over the method's runs (the first R_m); ``means``
    holds ``(R_m, K, d)`` per method, the reference's over all runs."""
    ref = _errors(means["reference"], truth[:means["reference"].shape[0]])
    out = {}
    for m, mean in means.items():
        r = mean.shape[0]
        err = _errors(mean, truth[:r])
        out[m] = float(np.sqrt(err.mean() / ref[:r].mean()))
    return out


def default_batch(method: str, runs: int) -> int:
    """Runs per batch: all for EnKF/PF and on accelerators, else one per local CPU device (see
    the module doc)."""
    if method in ("enkf", "pf", "reference") or jax.default_backend() != "cpu":
        return runs
    return max(1, min(runs, jax.local_device_count()))


def csf_config(name: str, steps: int = CSFConfig().reverse_steps,
               guidance: str = GuidanceConfig().mode) -> CSFConfig:
    """The CSF (and CSF-G) config of problem ``name`` in the tables: ``steps`` reverse steps, the
    ``guidance`` mode, ``CSF_OVERRIDES[name]``, defaults otherwise."""
    fields = dict(CSF_OVERRIDES.get(name, {}))
    sub = fields.pop("guidance", {})
    return CSFConfig(reverse_steps=steps, guidance=GuidanceConfig(mode=guidance, **sub), **fields)


def sf_sampler_config(name: str, steps: int = CSFConfig().reverse_steps,
                      guidance: str = GuidanceConfig().mode) -> CSFConfig:
    """SF's sampler in the tables: ``SF_SAMPLER_BASE`` with ``SF_SAMPLER_OVERRIDES[name]``."""
    return CSFConfig(reverse_steps=steps, guidance=GuidanceConfig(mode=guidance),
                     **(SF_SAMPLER_BASE | SF_SAMPLER_OVERRIDES.get(name, {})))


def sf_shards(runs: int, sf: SFConfig) -> int:
    """Devices one SF run's training batch is split over: on a CPU with several XLA host devices
    and a single SF run, as many as divide ``sf.batch`` (more runs are spread over the devices
    instead, ``default_batch``); else 1."""
    n = jax.local_device_count()
    if runs != 1 or jax.default_backend() != "cpu" or n < 2:
        return 1
    return max(k for k in range(1, n + 1) if sf.batch % k == 0)


def run(name: str, methods=METHODS, runs: int = RUNS, particles: int = PARTICLES,
        steps: int = CSFConfig().reverse_steps, seed: int = 0, num_steps: int | None = None, prior: str = "pretrained",
        out: str | None = None, batch: int | None = None, sf: SFConfig = SFConfig(),
        method_runs: dict | None = None, progress: bool = True, figures: bool = True,
        guidance: str = GuidanceConfig().mode, reference: ReferenceConfig = REFERENCE) -> dict:
    """Simulate ``runs`` trajectories, run ``methods`` on them; returns the results dict (and writes
    ``results.json`` and figures under ``out``).

    method_runs: optional ``{method: R_m}`` to run a method on the first ``R_m <= runs`` runs only
    (SF on a CPU budget); its figures then use those runs.
    reference: the reference filter's settings. With the reference among the methods,
    ``rmse_ratio[m]`` is method m's RMSE over the reference's on the same runs.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    overrides = {} if num_steps is None else {"num_steps": num_steps}
    model = problems.get(name, **overrides)
    pretrained = load_pretrained(name) if prior == "pretrained" and "csf" in methods else None
    config = csf_config(name, steps, guidance)
    sf_sampler = sf_sampler_config(name, steps, guidance)
    truth, obs, shocks, ens, keys = simulate_runs(model, runs, particles, seed)
    truth, shocks_np = np.asarray(truth), np.asarray(shocks)
    K = obs.shape[1]
    cfg = {"runs": runs, "particles": particles, "reverse_steps": steps, "seed": seed,
           "num_steps": K, "problem": dataclasses.asdict(problems.config(name)) | overrides,
           "csf": dataclasses.asdict(config), "sf_sampler": dataclasses.asdict(sf_sampler),
           "csf_prior": prior,
           "csf_model": None if pretrained is None else pretrained.meta.get("problem"),
           "csf_model_id": None if pretrained is None else _fingerprint(pretrained.meta),
           "sf": dataclasses.asdict(sf), "method_runs": dict(method_runs or {})}
    out_dict = {"problem": name, "config": cfg, "rmse": {}, "rmse_per_dim": {},
                "seconds_per_step": {}, "compile_seconds": {}, "runs_used": {},
                "runs_at_once": {},
                "rmse_per_run": {}, "rmse_over_time": {}, "rmse_before_shock": {},
                "rmse_after_shock": {},
                "shock_steps": [np.nonzero(s)[0].tolist() for s in shocks_np]}
    cache = None if out is None else os.path.join(out, "cache")
    if cache is not None:
        os.makedirs(cache, exist_ok=True)
    means = {}
    for method in methods:
        r_m = min(runs, (method_runs or {}).get(method, runs))
        ident = method_ident(method, name, cfg, reference)
        bar = Progress(LABELS[method], r_m * K,
                       enabled=progress and method in ("csf", "csf_gaussian", "sf"))
        fn = method_fn(method, model, config, sf, pretrained, bar,
                       sf_shards=sf_shards(r_m, sf) if method == "sf" else 1, reference=reference,
                       prior=gaussian_prior(config.sigma_max) if prior == "gaussian" else None,
                       sf_sampler=sf_sampler)
        b = batch or default_batch(method, r_m)
        mean, seconds, compile_s, at_once = _filter_runs(method, fn, obs[:r_m], ens[:r_m],
                                                         keys[:r_m], b, cache, ident, bar)
        means[method] = mean
        summary = summarize(_errors(mean, truth[:r_m]), shocks_np[:r_m], model.dim)
        for field, value in summary.items():
            out_dict[field][method] = value
        out_dict["seconds_per_step"][method] = seconds / (r_m * K)
        out_dict["compile_seconds"][method] = compile_s
        out_dict["runs_used"][method] = r_m
        out_dict["runs_at_once"][method] = at_once
        print(f"  {LABELS[method]:5s} RMSE {summary['rmse']:.3f}  ({seconds:.1f} s for {r_m} runs, "
              f"compile {compile_s:.1f} s)", file=sys.stderr, flush=True)
    if "reference" in means:
        out_dict["config"]["reference"] = reference._asdict()
        out_dict["rmse_ratio"] = reference_ratios(means, truth)
    out_dict["machine"] = machine()
    out_dict["versions"] = versions()
    if out is not None:
        with open(os.path.join(out, "results.json"), "w") as f:
            json.dump(out_dict, f, indent=1)
        if figures:
            _figures(out, name, model, truth, shocks_np, means, pretrained, config, ens,
                     run_keys(seed, 1)[0, 0], "csf" in methods,
                     prior=gaussian_prior(config.sigma_max) if prior == "gaussian" else None)
    return out_dict


def _figures(out, name, model, truth, shocks, means, pretrained, config, ens, sim_key, with_csf,
             prior=None):
    """Write the PNG figures, or say how to get matplotlib."""
    try:
        from experiments import figures
    except ImportError as e:  # matplotlib missing
        print(f"  figures skipped ({e}); pip install matplotlib to get them", file=sys.stderr)
        return
    paths = [figures.estimates(out, name, truth, shocks, means),
             figures.rmse_over_time(out, name, truth, shocks, means)]
    if model.dim == 1 and with_csf:
        paths.append(figures.prior_vs_model(out, name, model, pretrained, config, ens[0], sim_key,
                                            shocks[0], prior=prior))
    print("  figures: " + ", ".join(paths), file=sys.stderr)


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((l.split(":", 1)[1].strip() for l in f if l.startswith("model name")), cpu)
    except OSError:
        pass
    return {"platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count(),
            "jax_backend": jax.default_backend(), "jax_devices": [str(d) for d in jax.devices()]}


def versions() -> dict:
    import flax
    import optax
    return {"python": platform.python_version(), "jax": jax.__version__, "flax": flax.__version__,
            "optax": optax.__version__, "numpy": np.__version__, "csf_jax": csf_jax.__version__}


def table(results: dict) -> str:
    """Markdown table of a results dict."""
    ratio = results.get("rmse_ratio", {})
    rows = ["| method | runs | RMSE | RMSE / reference | RMSE per dim | RMSE before / after 1st shock | "
            "s / filter step per run (runs at once) | compile s |", "|---|---|---|---|---|---|---|---|"]
    fmt = lambda v: "-" if v is None else f"{v:.3f}"
    for m in results["rmse"]:
        rows.append(f"| {LABELS[m]} | {results['runs_used'][m]} | {results['rmse'][m]:.3f} | "
                    f"{fmt(ratio.get(m))} | "
                    f"{results['rmse_per_dim'][m]:.3f} | {fmt(results['rmse_before_shock'][m])} / "
                    f"{fmt(results['rmse_after_shock'][m])} | "
                    f"{results['seconds_per_step'][m]:.4f} ({results['runs_at_once'].get(m, 1)}) | "
                    f"{results['compile_seconds'][m]:.1f} |")
    return "\n".join(rows)


DESCRIPTION = ("Run CSF, CSF-G, SF, EnKF, PF and the reference filter on one of the paper's "
               "problems and print the RMSE table; with --out, also write results.json, the PNG "
               "figures and a resumable cache of finished runs there.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.run``."""
    p = parser("run", DESCRIPTION)
    p.add_argument("problem", choices=problems.NAMES, metavar="PROBLEM",
                   help="the problem: %(choices)s")
    p.add_argument("--methods", type=name_list(METHODS, "method"), default=list(METHODS),
                   metavar="M,M,...",
                   help="comma-separated methods from: " + "; ".join(
                       f"{m} ({METHOD_HELP[m]})" for m in METHODS) + " (default: all)")
    p.add_argument("--runs", type=positive_int, default=None,
                   help=f"independent runs (default {RUNS}; {QUICK['runs']} with --quick)")
    p.add_argument("--particles", type=particle_count, default=None,
                   help=f"ensemble size N, at least 2 (default {PARTICLES}; "
                        f"{QUICK['particles']} with --quick)")
    p.add_argument("--steps", type=particle_count, default=None,
                   help=f"CSF's and SF's reverse steps L, at least 2 (default "
                        f"{CSFConfig().reverse_steps}; {QUICK['steps']} with --quick)")
    p.add_argument("--guidance", choices=MODES, default=GuidanceConfig().mode,
                   help="CSF's and SF's sampler: 'kalman' (ancestral with Kalman guidance) or a "
                        "DPS mode with Euler-Maruyama (the paper's: --guidance clipped --steps "
                        "500); choices %(choices)s (default %(default)s)")
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of the runs' keys (default %(default)s)")
    p.add_argument("--out", default=None,
                   help="directory for results.json, the figures and the run cache (default: "
                        "none, only the table is printed)")
    p.add_argument("--batch", type=positive_int, default=None,
                   help="runs per batch (default: all runs for EnKF, PF and the reference and on "
                        "an accelerator; on a CPU one run per core)")
    p.add_argument("--sf-runs", type=positive_int, default=None,
                   help=f"run SF on the first R runs only, R <= --runs (default: all runs; on a "
                        f"CPU {CPU_SF_RUNS}, its online training being the slow column)")
    p.add_argument("--prior", choices=PRIORS, default="pretrained",
                   help="CSF's prior: 'pretrained' (the shipped model), 'exact' (the exact "
                        "Gaussian mixture) or 'gaussian' (the ensemble's own Gaussian, no "
                        "training) (default %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--quick", action="store_true",
                   help=f"a first look and CI: {QUICK['runs']} runs, N={QUICK['particles']}, "
                        f"L={QUICK['steps']}, {QUICK['num_steps']} filter steps, SF budget "
                        f"{QUICK_SF.train_steps} steps (warm-up {QUICK_SF.warmup_steps}), a "
                        f"smaller reference filter")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    """The checked arguments, with ``runs``, ``particles`` and ``steps`` resolved (``--quick``)."""
    p = build_parser()
    args = p.parse_args(argv)
    if args.out is not None and os.path.exists(args.out) and not os.path.isdir(args.out):
        p.error(f"argument --out: {args.out!r} exists and is not a directory")
    q = QUICK if args.quick else {}
    args.runs = q.get("runs", RUNS) if args.runs is None else args.runs
    args.particles = q.get("particles", PARTICLES) if args.particles is None else args.particles
    args.steps = q.get("steps", CSFConfig().reverse_steps) if args.steps is None else args.steps
    if args.sf_runs is not None and args.sf_runs > args.runs:
        p.error(f"argument --sf-runs: {args.sf_runs} exceeds the {args.runs} runs (--runs)")
    return args


def main(argv=None):
    args = parse_args(argv)
    q = QUICK if args.quick else {}
    runs, particles, steps = args.runs, args.particles, args.steps
    methods = args.methods
    sf = QUICK_SF if args.quick else SFConfig()
    sf_runs = args.sf_runs
    if sf_runs is None and "sf" in methods and jax.default_backend() == "cpu":
        sf_runs = min(runs, CPU_SF_RUNS)
    print(f"{args.problem}: {runs} runs, N={particles}, L={steps} ({args.guidance}), methods {', '.join(methods)}; "
          f"SF budget {sf.train_steps} Adam steps x {sf.batch} per filter step "
          f"(+{sf.warmup_steps} warm-up)"
          + "".join(f"; {k}={v} (CSF_OVERRIDES)"
                    for k, v in CSF_OVERRIDES.get(args.problem, {}).items()),
          file=sys.stderr)
    results = run(args.problem, methods, runs, particles, steps, args.seed,
                  num_steps=q.get("num_steps"), prior=args.prior, out=args.out, batch=args.batch,
                  sf=sf, method_runs=None if sf_runs is None else {"sf": sf_runs},
                  progress=not args.no_progress, guidance=args.guidance,
                  reference=QUICK_REFERENCE if args.quick else REFERENCE)
    print(table(results))
    if args.out:
        print(f"wrote {os.path.join(args.out, 'results.json')}", file=sys.stderr)
    if args.quick or runs < RUNS or particles != PARTICLES:
        print(f"This is not the table's setting ({RUNS} runs, N={PARTICLES}).", file=sys.stderr)
    if sf_runs is not None and sf_runs < runs and args.sf_runs is None:
        print(f"SF ran on {sf_runs} of {runs} runs (CPU budget); --sf-runs {runs} for all.",
              file=sys.stderr)
    print("The full seven-problem table against the paper: python -m experiments.table "
          "(see docs/results.md).", file=sys.stderr)


if __name__ == "__main__":
    main()
