"""Benchmark the CSF online step: csf_jax against the PyTorch port (eager and torch.compile).

    python -m experiments.bench [--out DIR] [--quick] [--dims D,D] [--particles N,N]
        [--guidance kalman|clipped|raw|normalized|none] [--steps L] [--repeats R]
        [--filter-steps K] [--impls jax,torch_eager,torch_compile]
        [--traj-runs R] [--traj-steps K] [--traj-dim D] [--traj-particles N]
        [--torch-threads T] [--omp-wait-policy passive|active|unset] [--shards auto|S]

It needs PyTorch (``pip install -e '.[bench]'``) unless only ``--impls jax`` runs with
``--traj-runs 0``.

For every state dimension d and ensemble size N it measures one filter step (propagate + encode +
L reverse steps with the learned prior; random-init weights of the shipped models' network
(:func:`network`: the default sizes with the Gaussian base, ``csf_jax.pretrained.NETWORK``); d = 1
is the double well, d > 1 the cubic sensor ``cubic<d>_indep``), with the sampler of
``--guidance``, the same on both sides:

* ``kalman`` (default, ``CSFConfig()``'s sampler, its adaptive inflation included): the ancestral
  sampler with Kalman guidance, L = ``CSFConfig().reverse_steps`` = 20 levels (``--steps``
  defaults to it);
* ``clipped`` (``raw``, ``normalized``, ``none`` likewise): Euler-Maruyama with DPS guidance, the
  paper's sampler; pass ``--steps 500`` for the paper's L.

Implementations:

* ``jax``: ``jax.jit(csf_jax.filter)``; compile_s is trace + lower + XLA compile. On a CPU the
  worker gets one XLA host device per core (``--xla_force_host_platform_device_count``) and the
  filter splits the particles over them (``shards``; ``--shards 1`` turns this off).
* ``torch_eager``: ``experiments.torch_csf`` with a Python loop over the reverse steps.
* ``torch_compile``: the same with the reverse step (one level) under
  ``torch.compile(dynamic=False)``;
  compile_s is the first call of the step (Dynamo + Inductor, with an empty Inductor cache).

Each implementation runs in its own worker process (clean peak RSS: ``VmHWM`` of /proc/self/status,
which includes the interpreter and libraries; ``base_mb`` is the RSS after set-up, before the first
filter step). The workers of one (d, N) are started together and asked in turn for one timed run
of ``--filter-steps`` filter steps, ``--repeats`` times (alternating, so load changes on the machine
hit all of them alike), after one untimed warm-up run; median_s is the median seconds per filter
step.
Then the whole-trajectory case: ``--traj-runs`` independent runs of ``--traj-steps`` filter steps,
JAX vmapped over the runs (``jax_vmap``) and JAX with ``lax.map`` over the runs (``jax_map``, one
run at a time inside one compiled program), both compiled ahead with no warm-up run, against a loop
over the runs in eager PyTorch.

Writes ``bench.json`` (machine info and one row per measurement) and ``bench.md`` (the tables) to
``--out`` (default ``out/bench``, git-ignored), and prints the tables.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from experiments._cli import (
    int_list,
    name_list,
    nonnegative_int,
    parser,
    particle_count,
    positive_int,
)

IMPLS = ("jax", "torch_eager", "torch_compile")
TRAJ_IMPLS = ("jax_vmap", "jax_map", "torch_eager_loop")
_TAG = "@@bench "


# --------------------------------------------------------------------------------------------
# Shared set-up (parent and workers)
# --------------------------------------------------------------------------------------------

def csf_config(spec: dict):
    """The ``CSFConfig`` of a worker spec: ``steps`` reverse steps, the sampler of ``guidance``
    (a ``GuidanceConfig.mode``), every other setting at its default."""
    from csf_jax import CSFConfig
    from csf_jax.guidance import GuidanceConfig

    return CSFConfig(reverse_steps=spec["steps"], guidance=GuidanceConfig(mode=spec["guidance"]))


def problem_name(d: int) -> tuple[str, dict]:
    """``(name, overrides)`` for ``csf_jax.problems.get``: the double well for d = 1, else the
    independent cubic sensor of dimension d."""
    return ("double_well", {}) if d == 1 else ("cubic10_indep", {"dim": d})


def make_data(d: int, n: int, k: int, runs: int, seed: int = 0):
    """Observations ``(runs, k, d)`` and initial ensembles ``(runs, n, d)``, float32 numpy.

    The truth is a random walk ``x_k ~ N(x_{k-1}, 0.1^2)`` from ``N(0.3, 0.5^2)``, observed as
    ``x^3 + N(0, 0.1^2)``; the ensemble is drawn from the truth's initial law.
    """
    rng = np.random.default_rng(seed)
    truth = 0.3 + 0.5 * rng.standard_normal((runs, 1, d)) + np.cumsum(
        0.1 * rng.standard_normal((runs, k, d)), axis=1)
    obs = truth**3 + 0.1 * rng.standard_normal((runs, k, d))
    ens = 0.3 + 0.5 * rng.standard_normal((runs, n, d))
    return obs.astype(np.float32), ens.astype(np.float32)


def save_params(params: dict, path: str) -> None:
    """Flatten a nested params dict to ``"encoder/params/embed/kernel"`` keys in an npz."""
    flat = {}

    def walk(node, prefix):
        if isinstance(node, dict) or hasattr(node, "items"):
            for key, value in node.items():
                walk(value, f"{prefix}/{key}" if prefix else key)
        else:
            flat[prefix] = np.asarray(node)

    walk(params, "")
    np.savez(path, **flat)


def network():
    """The benchmarked ``NetworkConfig``: the shipped models' (``csf_jax.pretrained.NETWORK``, the
    default sizes with the Gaussian base). Imported here, not at the top: a torch worker loads jax
    only through this and ``csf_jax.filters.csf``'s configs."""
    from csf_jax.networks import NetworkConfig

    return NetworkConfig(base="gaussian")


def load_params(path: str) -> dict:
    """The nested dict of numpy arrays saved by :func:`save_params`."""
    out: dict = {}
    with np.load(path) as data:
        for key in data.files:
            node = out
            *parents, leaf = key.split("/")
            for p in parents:
                node = node.setdefault(p, {})
            node[leaf] = data[key]
    return out


def rss_mb(field: str = "VmHWM") -> float:
    """``VmHWM`` (peak) or ``VmRSS`` (current) resident memory of this process, in MB."""
    with open("/proc/self/status") as f:
        match = re.search(rf"^{field}:\s+(\d+) kB", f.read(), re.M)
    return int(match.group(1)) / 1024.0


# --------------------------------------------------------------------------------------------
# Workers: one implementation in its own process; JSON lines on stdout, commands on stdin
# --------------------------------------------------------------------------------------------

def _jax_runner(spec: dict, params: dict, obs: np.ndarray, ens: np.ndarray):
    """``(setup_info, run(repeat) -> seconds)`` for csf_jax, single run or vmapped over runs."""
    import functools

    import jax

    import csf_jax
    from csf_jax import problems

    name, overrides = problem_name(spec["d"])
    model = problems.get(name, **overrides)
    shards = spec.get("shards", 1)
    shards = shards if shards <= len(jax.local_devices()) and spec["N"] % shards == 0 else 1
    one = functools.partial(csf_jax.filter, problem=model, network=network(),
                            config=csf_config(spec), check_finite=False, shards=shards)
    params = jax.tree_util.tree_map(jax.numpy.asarray, params)
    if spec["vmap"]:
        fn = jax.jit(jax.vmap(lambda p, o, e, k: one(p, o, e, key=k), in_axes=(None, 0, 0, 0)))
        keys = lambda r: jax.random.split(jax.random.key(r), obs.shape[0])
        args = (obs, ens)
    elif spec["impl"] == "jax_map":
        fn = jax.jit(lambda p, o, e, k: jax.lax.map(lambda a: one(p, a[0], a[1], key=a[2]),
                                                    (o, e, k)))
        keys = lambda r: jax.random.split(jax.random.key(r), obs.shape[0])
        args = (obs, ens)
    else:
        fn = jax.jit(lambda p, o, e, k: one(p, o, e, key=k))
        keys = jax.random.key
        args = (obs[0], ens[0])
    args = tuple(jax.device_put(a) for a in args)
    t0 = time.perf_counter()
    compiled = fn.lower(params, *args, keys(0)).compile()
    compile_s = time.perf_counter() - t0

    def run(r):
        key = keys(r)
        jax.block_until_ready(key)
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, *args, key).mean)
        return time.perf_counter() - t0

    return {"compile_s": compile_s, "shards": shards}, run


def _torch_runner(spec: dict, params: dict, obs: np.ndarray, ens: np.ndarray):
    """``(setup_info, run(repeat) -> seconds)`` for the PyTorch port, eager or compiled; several
    runs are filtered one after the other."""
    import torch

    from experiments import torch_csf as tc

    if spec.get("torch_threads"):
        torch.set_num_threads(spec["torch_threads"])
    name, overrides = problem_name(spec["d"])
    config = csf_config(spec)
    nets = tc.flax_to_torch(params, network(), spec["d"])
    problem = tc.torch_problem(name, **overrides)
    step = tc.make_reverse_step(nets, problem, config, compile=spec["compile"])
    obs_t, ens_t = torch.from_numpy(obs), torch.from_numpy(ens)
    info = {"torch_threads": torch.get_num_threads()}
    if spec["compile"]:
        sched = tc.schedule(config)
        t0 = time.perf_counter()
        tc.first_reverse_step(nets, step, sched, ens_t[0].clone(), obs_t[0, 0])
        info["compile_s"] = time.perf_counter() - t0

    def run(r):
        t0 = time.perf_counter()
        for i in range(obs_t.shape[0]):
            tc.csf_filter(nets, problem, obs_t[i], ens_t[i], config, seed=1000 * r + i, step=step)
        return time.perf_counter() - t0

    return info, run


def _send(payload: dict) -> None:
    sys.stdout.write(_TAG + json.dumps(payload) + "\n")
    sys.stdout.flush()


def worker(spec: dict) -> None:
    """Set up one implementation, report, then answer ``run <r>`` / ``quit`` commands on stdin."""
    try:
        params = load_params(spec["params"])
        with np.load(spec["data"]) as data:
            obs, ens = data["obs"], data["ens"]
        build = _jax_runner if spec["impl"].startswith("jax") else _torch_runner
        t0 = time.perf_counter()
        info, run = build(spec, params, obs, ens)
        info["setup_s"] = time.perf_counter() - t0
        if spec["kind"] == "step":
            info["warmup_s"] = run(0)
        info["base_mb"] = rss_mb("VmRSS")
    except Exception as e:  # reported to the parent, which records the failure and goes on
        _send({"error": f"{type(e).__name__}: {e}"})
        return
    _send(info)
    for line in sys.stdin:
        cmd = line.split()
        if cmd and cmd[0] == "run":
            _send({"seconds": run(int(cmd[1]))})
        else:
            break
    _send({"peak_mb": rss_mb("VmHWM")})


# --------------------------------------------------------------------------------------------
# Parent: start workers, alternate them, collect rows
# --------------------------------------------------------------------------------------------

class Worker:
    """A worker subprocess speaking the ``_TAG`` JSON-line protocol."""

    def __init__(self, spec: dict, env: dict):
        self.spec = spec
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "experiments.bench", "--worker", json.dumps(spec)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        self.info: dict | None = None

    def read(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith(_TAG):
                return json.loads(line[len(_TAG):])
        return {"error": f"worker exited with code {self.proc.wait()}"}

    def ask(self, cmd: str) -> dict:
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        return self.read()

    def close(self) -> dict:
        out = self.ask("quit") if self.proc.poll() is None else {}
        self.proc.wait()
        return out


def _worker_env(impl: str, args, cache_root: str) -> dict:
    """The worker's environment: this checkout first on PYTHONPATH; for torch, the OpenMP wait
    policy and a fresh (empty) Inductor cache, so that compile_s is a cold compile; for JAX with
    ``--jax-cache warm``, a fresh persistent compilation cache (filled by a first worker)."""
    env = dict(os.environ)
    env.setdefault("PYTHONPATH", "")
    env["PYTHONPATH"] = os.pathsep.join([os.getcwd(), env["PYTHONPATH"]]).rstrip(os.pathsep)
    if impl.startswith("jax") and args.shards > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count="
                            f"{args.shards}").strip()
    if impl.startswith("jax") and args.jax_cache == "warm":
        env["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(dir=cache_root)
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    if impl.startswith("torch"):
        if args.omp_wait_policy != "unset":
            env["OMP_WAIT_POLICY"] = args.omp_wait_policy.upper()
        env["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(dir=cache_root)
    return env


def measure(impls, base_spec: dict, args, cache_root: str, repeats: int) -> list[dict]:
    """Start one worker per implementation, alternate ``repeats`` timed runs, return rows."""
    workers, cold = {}, {}
    for impl in impls:
        spec = dict(base_spec, impl=impl, compile=impl == "torch_compile",
                    vmap=impl == "jax_vmap", torch_threads=args.torch_threads,
                    shards=args.shards)
        env = _worker_env(impl, args, cache_root)
        if "JAX_COMPILATION_CACHE_DIR" in env:
            # a first worker compiles into the empty cache (the cold compile and its memory),
            # the measured one loads the program from it
            first = Worker(spec, env)
            cold[impl] = dict(first.read(), **first.close())
        workers[impl] = Worker(spec, env)
        workers[impl].info = workers[impl].read()
    times = {impl: [] for impl in impls}
    for r in range(1, repeats + 1):
        for impl, w in workers.items():
            if "error" not in w.info:
                reply = w.ask(f"run {r}")
                if "seconds" in reply:
                    times[impl].append(reply["seconds"])
                else:
                    w.info = reply
    rows = []
    for impl, w in workers.items():
        end = w.close()
        per = base_spec["filter_steps"] * base_spec["runs"]
        med = statistics.median(times[impl]) if times[impl] else None
        rows.append({
            "impl": impl, "d": base_spec["d"], "N": base_spec["N"], "steps": base_spec["steps"],
            "guidance": base_spec["guidance"],
            "kind": base_spec["kind"], "runs": base_spec["runs"],
            "filter_steps": base_spec["filter_steps"],
            "median_s": None if med is None else med / per,
            "total_median_s": med,
            "compile_s": cold.get(impl, w.info).get("compile_s"), "peak_mb": end.get("peak_mb"),
            "cache_load_s": w.info.get("compile_s") if impl in cold else None,
            "cold_peak_mb": cold[impl].get("peak_mb") if impl in cold else None,
            "base_mb": w.info.get("base_mb"), "warmup_s": w.info.get("warmup_s"),
            "times_s": times[impl], "torch_threads": w.info.get("torch_threads"),
            "shards": w.info.get("shards"),
            "error": w.info.get("error"),
        })
    return rows


def machine_info(args) -> dict:
    """CPU model and flags, core count, library versions, load average, torch's OpenMP policy."""
    import jax

    torch = importlib.import_module("torch") if needs_torch(args) else None
    with open("/proc/cpuinfo") as f:
        cpuinfo = f.read()
    match = re.search(r"^model name\s*:\s*(.+)$", cpuinfo, re.M)
    flags = re.search(r"^flags\s*:\s*(.+)$", cpuinfo, re.M)
    return {
        "cpu": match.group(1).strip() if match else "unknown", "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(), "jax": jax.__version__,
        "jaxlib": __import__("jaxlib").__version__, "flax": __import__("flax").__version__,
        "torch": None if torch is None else torch.__version__, "numpy": np.__version__,
        "avx512": sorted(f for f in (flags.group(1).split() if flags else []) if "avx512" in f),
        "loadavg_start": [round(v, 2) for v in os.getloadavg()],
        "omp_wait_policy_torch": args.omp_wait_policy,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def _jax_peak(row: dict) -> str:
    """The JAX worker's peak MB; with a warm cache, the compiling worker's in parentheses."""
    cold = row.get("cold_peak_mb")
    return _fmt(row.get("peak_mb"), ".0f") + ("" if cold is None else f" ({cold:.0f})")


def _fmt(x, spec=".3f"):
    return "-" if x is None else format(x, spec)


def tables(rows: list[dict]) -> str:
    """Markdown: the per-filter-step table with the ratios, and the trajectory table."""
    by = {(r["kind"], r["d"], r["N"], r["impl"]): r for r in rows}
    out = ["### One filter step (seconds per filter step, median)", "",
           "| d | N | L | JAX s | eager s | compile s | JAX/eager | JAX/compile | JAX compile s "
           "| torch.compile s | peak MB JAX (compiling) / eager / compile |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["d"], r["N"], r["steps"]) for r in rows if r["kind"] == "step"})
    for d, n, steps in keys:
        j, e, c = (by.get(("step", d, n, impl), {}) for impl in IMPLS)
        js, es, cs = j.get("median_s"), e.get("median_s"), c.get("median_s")
        ratio = lambda a, b: None if a is None or b is None else a / b
        out.append(
            f"| {d} | {n} | {steps} | {_fmt(js)} | {_fmt(es)} | "
            f"{_fmt(cs) if not c.get('error') else 'failed'} | {_fmt(ratio(js, es), '.2f')} | "
            f"{_fmt(ratio(js, cs), '.2f')} | {_fmt(j.get('compile_s'), '.1f')} | "
            f"{_fmt(c.get('compile_s'), '.1f')} | {_jax_peak(j)} / "
            f"{_fmt(e.get('peak_mb'), '.0f')} / {_fmt(c.get('peak_mb'), '.0f')} |")
    traj = [r for r in rows if r["kind"] == "trajectory"]
    if traj:
        out += ["", "### Whole trajectories (seconds for all runs, median)", "",
                "| JAX form | d | N | L | runs x filter steps | JAX s | eager loop s | eager / JAX "
                "| JAX compile s | peak MB JAX / eager |", "|---|---|---|---|---|---|---|---|---|---|"]
        e = next((r for r in traj if r["impl"] == "torch_eager_loop"), {})
        et = e.get("total_median_s")
        for impl in TRAJ_IMPLS[:-1]:
            j = next((r for r in traj if r["impl"] == impl), None)
            if j is None:
                continue
            jt = j.get("total_median_s")
            out.append(
                f"| {impl} | {j.get('d')} | {j.get('N')} | {j.get('steps')} | {j.get('runs')} x "
                f"{j.get('filter_steps')} | {_fmt(jt, '.1f')} | {_fmt(et, '.1f')} | "
                f"{_fmt(None if jt is None or et is None else et / jt, '.2f')} | "
                f"{_fmt(j.get('compile_s'), '.1f')} | {_fmt(j.get('peak_mb'), '.0f')} / "
                f"{_fmt(e.get('peak_mb'), '.0f')} |")
    errors = [f"- {r['impl']} d={r['d']} N={r['N']}: {r['error']}" for r in rows if r["error"]]
    if errors:
        out += ["", "Failures:", ""] + errors
    return "\n".join(out) + "\n"


def sampler_line(args) -> str:
    """One line naming the benchmarked sampler and its L."""
    if args.guidance == "kalman":
        return f"ancestral with Kalman guidance (guidance 'kalman'), L = {args.steps} levels"
    return f"Euler-Maruyama with DPS guidance '{args.guidance}', L = {args.steps} steps"


def _ints(s: str) -> list[int]:
    return [int(v) for v in s.split(",") if v]


def _checked(parse):
    """An argparse ``type`` that validates a comma-separated list and keeps it as text (``_ints``
    reads it later, and ``--quick`` overrides it as text)."""

    def check(text: str) -> str:
        parse(text)
        return text

    check.__name__ = parse.__name__
    return check


def _shards(text: str):
    """``--shards``: ``"auto"`` or a positive int (an argparse ``type``)."""
    return "auto" if text == "auto" else positive_int(text)


def needs_torch(args) -> bool:
    """Whether the run has PyTorch workers: a torch implementation, or the trajectory rows (their
    eager PyTorch loop)."""
    return any(i.startswith("torch") for i in args.impls) or args.traj_runs > 0


TORCH_MISSING = "PyTorch is not installed: pip install -e '.[bench]'"
DESCRIPTION = ("Benchmark the CSF online step, csf_jax against its PyTorch port (eager and "
               "torch.compile), per state dimension and ensemble size, and whole trajectories; "
               "write bench.json and bench.md to --out.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.bench``."""
    from csf_jax.filters.csf import CSFConfig
    from csf_jax.guidance import MODES, GuidanceConfig

    p = parser("bench", DESCRIPTION)
    p.add_argument("--out", default="out/bench",
                   help="folder for bench.json and bench.md (default %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="smoke test: d=10, N=256, 1 repeat of 1 filter step; trajectories: "
                        "--traj-runs runs x 2 filter steps at d=10, N=256 (L from --steps)")
    p.add_argument("--dims", type=_checked(int_list(1)), default="1,10,20", metavar="D,D,...",
                   help="comma-separated state dimensions d (default %(default)s)")
    p.add_argument("--particles", type=_checked(int_list(2)), default="256,1000,4000",
                   metavar="N,N,...",
                   help="comma-separated ensemble sizes N, each at least 2 (default %(default)s)")
    p.add_argument("--guidance", choices=MODES, default=GuidanceConfig().mode,
                   help="the sampler: 'kalman' (ancestral with Kalman guidance) or a DPS mode "
                        "with Euler-Maruyama (the paper's: --guidance clipped --steps 500); "
                        "choices %(choices)s (default %(default)s)")
    p.add_argument("--steps", type=particle_count, default=CSFConfig().reverse_steps,
                   help="reverse steps L, at least 2 (default %(default)s, "
                        "CSFConfig().reverse_steps)")
    p.add_argument("--repeats", type=positive_int, default=3,
                   help="timed runs per implementation (default %(default)s)")
    p.add_argument("--filter-steps", type=positive_int, default=2,
                   help="filter steps per timed run (default %(default)s)")
    p.add_argument("--impls", type=name_list(IMPLS, "implementation"), default=list(IMPLS),
                   metavar="I,I,...",
                   help="comma-separated implementations from: " + ", ".join(IMPLS)
                   + " (default: all)")
    p.add_argument("--traj-runs", type=nonnegative_int, default=10,
                   help="runs of the whole-trajectory rows; 0: no trajectory rows (default "
                        "%(default)s)")
    p.add_argument("--traj-steps", type=positive_int, default=10,
                   help="filter steps per trajectory run, K (default %(default)s)")
    p.add_argument("--traj-dim", type=positive_int, default=10,
                   help="state dimension of the trajectory rows (default %(default)s)")
    p.add_argument("--traj-particles", type=particle_count, default=1000,
                   help="ensemble size of the trajectory rows (default %(default)s)")
    p.add_argument("--traj-repeats", type=positive_int, default=None,
                   help="timed runs of the trajectory rows (default: --repeats)")
    p.add_argument("--torch-threads", type=positive_int, default=None,
                   help="torch's intra-op threads (default: torch's own)")
    p.add_argument("--omp-wait-policy", choices=("passive", "active", "unset"), default="unset",
                   help="OMP_WAIT_POLICY of the torch workers ('unset': leave the environment "
                        "alone); with other processes on the cores, OpenMP's spin-waiting can "
                        "stall torch's threads (default %(default)s)")
    p.add_argument("--shards", type=_shards, default="auto",
                   help="XLA host devices (one per core) the JAX workers split the particles over "
                        "on a CPU: 'auto' = the number of cores, 1 = off (default %(default)s)")
    p.add_argument("--jax-cache", choices=("cold", "warm"), default="cold",
                   help="'warm': each JAX worker loads its program from a persistent compilation "
                        "cache that a first worker filled (compile_s and cold_peak_mb are that "
                        "first worker's; peak_mb is the measured worker's: the memory of a run "
                        "whose program is already compiled); 'cold': one worker compiles "
                        "(default %(default)s)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    return p


def parse_args(argv=None):
    p = build_parser()
    args = p.parse_args(argv)
    if not args.worker:
        if args.shards == "auto":
            args.shards = os.cpu_count() or 1
        if needs_torch(args) and importlib.util.find_spec("torch") is None:
            p.error(TORCH_MISSING)
    if args.quick:
        args.dims, args.particles, args.repeats = "10", "256", 1
        args.filter_steps, args.traj_steps, args.traj_particles, args.traj_dim = 1, 2, 256, 10
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        worker(json.loads(args.worker))
        return
    import jax

    import csf_jax

    os.makedirs(args.out, exist_ok=True)
    impls = args.impls
    info = machine_info(args)
    print(json.dumps(info, indent=1), flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        def prepare(d, n, k, runs, tag):
            params_path, data_path = f"{tmp}/params_{d}.npz", f"{tmp}/data_{tag}_{d}_{n}.npz"
            if not os.path.exists(params_path):
                save_params(csf_jax.init_params(jax.random.key(0), network(), d), params_path)
            obs, ens = make_data(d, n, k, runs)
            np.savez(data_path, obs=obs, ens=ens)
            return {"params": params_path, "data": data_path, "d": d, "N": n, "steps": args.steps,
                    "guidance": args.guidance, "filter_steps": k, "runs": runs}

        for d in _ints(args.dims):
            for n in _ints(args.particles):
                spec = dict(prepare(d, n, args.filter_steps, 1, "step"), kind="step")
                t0 = time.perf_counter()
                new = measure(impls, spec, args, tmp, args.repeats)
                rows += new
                summary = ", ".join(f"{r['impl']} {_fmt(r['median_s'])} s"
                                    + (f" ({r['error']})" if r["error"] else "") for r in new)
                print(f"d={d} N={n}: {summary}  [{time.perf_counter() - t0:.0f} s]", flush=True)
        if args.traj_runs > 0:
            spec = dict(prepare(args.traj_dim, args.traj_particles, args.traj_steps, args.traj_runs,
                                "traj"), kind="trajectory")
            rows += measure(TRAJ_IMPLS, spec, args, tmp,
                            args.repeats if args.traj_repeats is None else args.traj_repeats)
    info["loadavg_end"] = [round(v, 2) for v in os.getloadavg()]
    with open(os.path.join(args.out, "bench.json"), "w") as f:
        json.dump({"machine": info, "args": vars(args), "rows": rows}, f, indent=1)
    md = tables(rows)
    print(f"Sampler: {sampler_line(args)}")
    with open(os.path.join(args.out, "bench.md"), "w") as f:
        f.write(f"Machine: {info['cpu']}, {info['cores']} cores; jax {info['jax']}, torch "
                f"{info['torch']}; load average {info['loadavg_start']} -> "
                f"{info['loadavg_end']}\n\nSampler: {sampler_line(args)}\n\n" + md)
    print(md)


if __name__ == "__main__":
    main()
