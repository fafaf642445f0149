"""Benchmark the CSF online step: csf_jax against its PyTorch port, eager and ``torch.compile``.

    python -m experiments.bench [--dims 1,10,20] [--particles 1000] [--guidance kalman|clipped]
        [--steps L] [--device cpu|cuda] [--compile-mode default|reduce-overhead] [--repeats 3]
        [--filter-steps 2] [--impls jax,torch_eager,torch_compile] [--torch-threads T]
        [--out DIR] [--page PAGE] [--quick]

It needs PyTorch (``pip install -e '.[bench]'``) unless only ``--impls jax`` runs. For every state
dimension d and ensemble size N it times one filter step (propagate, encode, L reverse steps with
the learned prior: random-init weights of the shipped models' network, the Gaussian base; d = 1 is
the double well, d > 1 the cubic sensor ``cubic10_indep`` resized), with the sampler of
``--guidance`` on both sides: ``kalman`` (``CSFConfig()``'s: ancestral with Kalman guidance,
L = 20) or a DPS mode with Euler-Maruyama (the paper's sampler: ``--guidance clipped --steps
500``).

* ``jax``: ``jax.jit(csf_jax.filter)`` on jax's default backend; compile_s is trace + lower +
  XLA compile.
* ``torch_eager``: ``experiments.torch_port.csf`` on ``--device``, a Python loop over the levels.
* ``torch_compile``: the same with the reverse step under ``torch.compile(fullgraph=True,
  mode=--compile-mode)`` (``reduce-overhead``: CUDA graphs on a GPU); compile_s is its first call
  with an empty Inductor cache.

Each implementation runs in a worker process of its own (clean peak memory); the workers of one
(d, N) are asked in turn for ``--repeats`` timed runs of ``--filter-steps`` filter steps after an
untimed warm-up, so load changes on the machine hit all of them alike; the figure is the median
seconds per filter step. Every row names its device. Prints the table; ``--out`` writes
``results.json`` (``experiments.harness``'s schema) and ``--page`` the page's generated block for
this sampler.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from experiments import cli, harness, interrupt

IMPLS = ("jax", "torch_eager", "torch_compile")
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
TAG = "@@bench "
TORCH_MISSING = "PyTorch is not installed: pip install -e '.[bench]'"
DEFAULTS = {"dims": [1, 10, 20], "particles": [1000], "repeats": 3, "filter_steps": 2}
QUICK = {"dims": [10], "particles": [256], "repeats": 1, "filter_steps": 1}


def config(spec: dict):
    """The benchmarked ``CSFConfig``: ``csf_jax.PAPER`` (the learned prior's step, which the
    PyTorch port implements; the default's mixture components are not ported) with ``spec``'s
    sampler."""
    from csf_jax import PAPER, CSFConfig, GuidanceConfig, SamplerConfig

    return CSFConfig(sampler=SamplerConfig(reverse_steps=spec["steps"],
                                           guidance=GuidanceConfig(mode=spec["guidance"])),
                     inflation=PAPER.inflation, prior=PAPER.prior)


def network():
    """The shipped models' ``NetworkConfig`` (``csf_jax.pretrained.NETWORK``)."""
    from csf_jax.networks import NetworkConfig

    return NetworkConfig(base="gaussian")


def problem(d: int) -> tuple:
    """``(name, overrides)`` of the benchmarked problem of dimension ``d``."""
    return ("double_well", {}) if d == 1 else ("cubic10_indep", {"dim": d})


def data(d: int, n: int, k: int):
    """Observations ``(k, d)`` of a random walk seen through ``x^3``, and an ensemble ``(n, d)``."""
    rng = np.random.default_rng(0)
    truth = 0.3 + 0.5 * rng.standard_normal(d) + np.cumsum(0.1 * rng.standard_normal((k, d)), 0)
    obs = truth ** 3 + 0.1 * rng.standard_normal((k, d))
    return obs.astype(np.float32), (0.3 + 0.5 * rng.standard_normal((n, d))).astype(np.float32)


def memory_mb(field: str = "VmHWM") -> float:
    """This process's peak (``VmHWM``) or current (``VmRSS``) resident memory, MB."""
    with open("/proc/self/status") as f:
        return int(re.search(rf"^{field}:\s+(\d+) kB", f.read(), re.M).group(1)) / 1024.0


def _jax(spec: dict, params, obs, ens):
    import functools

    import jax

    import csf_jax
    from csf_jax import problems

    name, overrides = problem(spec["d"])
    one = functools.partial(csf_jax.filter, model=problems.get(name, **overrides),
                            network=network(), config=config(spec), check_finite=False)
    fn = jax.jit(lambda p, o, e, k: one(p, o, e, key=k).mean)
    t0 = time.perf_counter()
    compiled = fn.lower(params, obs, ens, jax.random.key(0)).compile()
    device = jax.devices()[0]
    kind = harness.machine()["cpu"] if device.platform == "cpu" else device.device_kind
    info = {"compile_s": time.perf_counter() - t0, "device": f"{device.platform} ({kind})"}

    def run(r):
        key = jax.block_until_ready(jax.random.key(r))
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, obs, ens, key))
        return time.perf_counter() - t0

    return info, run


def _torch(spec: dict, params, obs, ens):
    import torch

    from experiments.torch_port import csf as port

    if spec.get("torch_threads"):
        torch.set_num_threads(spec["torch_threads"])
    device = torch.device(spec["device"])
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    name, overrides = problem(spec["d"])
    cfg = config(spec)
    nets = port.flax_to_torch(params, network(), spec["d"], device=device)
    model = port.torch_problem(name, device=device, **overrides)
    step = port.make_reverse_step(nets, model, cfg, compile=spec["impl"] == "torch_compile",
                                  mode=spec["compile_mode"])
    obs, ens = torch.from_numpy(obs).to(device), torch.from_numpy(ens).to(device)
    kind = (torch.cuda.get_device_name(device) if device.type == "cuda"
            else harness.machine()["cpu"])
    info = {"device": f"{device.type} ({kind})"}
    if spec["impl"] == "torch_compile":
        t0 = time.perf_counter()
        port.first_reverse_step(nets, step, port.schedule(cfg, device=device), ens.clone(),
                                obs[0])
        sync()
        info["compile_s"] = time.perf_counter() - t0

    def run(r):
        sync()
        t0 = time.perf_counter()
        port.csf_filter(nets, model, obs, ens, cfg, seed=r, step=step)
        sync()
        return time.perf_counter() - t0

    return info, run


def worker(spec: dict) -> None:
    """Set one implementation up, report, then answer ``run <r>`` lines on stdin until EOF."""
    def send(payload):
        print(TAG + json.dumps(payload), flush=True)

    try:
        with np.load(spec["params"]) as f:
            params = {}
            for key in f.files:
                node = params
                *parents, leaf = key.split("/")
                for p in parents:
                    node = node.setdefault(p, {})
                node[leaf] = f[key]
        obs, ens = data(spec["d"], spec["N"], spec["filter_steps"])
        info, run = (_jax if spec["impl"] == "jax" else _torch)(spec, params, obs, ens)
        run(0)
    except Exception as e:  # noqa: BLE001  (reported to the parent, which records it)
        send({"error": f"{type(e).__name__}: {e}"})
        return
    send(info)
    for line in sys.stdin:
        if line.startswith("run"):
            send({"seconds": run(int(line.split()[1]))})
    send({"peak_mb": memory_mb()})


class Worker:
    """A worker subprocess speaking the ``TAG`` JSON-line protocol."""

    def __init__(self, spec: dict, env: dict):
        self.proc = interrupt.spawn([sys.executable, "-m", "experiments.bench", "--worker",
                                     json.dumps(spec)], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, text=True, env=env)
        self.info = self.read()

    def read(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith(TAG):
                return json.loads(line[len(TAG):])
        return {"error": f"the worker exited with code {self.proc.wait()}"}

    def ask(self, r: int) -> dict:
        self.proc.stdin.write(f"run {r}\n")
        self.proc.stdin.flush()
        return self.read()

    def close(self) -> dict:
        self.proc.stdin.close()
        out = self.read() if self.proc.poll() is None else {}
        self.proc.wait()
        interrupt.CHILDREN.discard(self.proc)
        return out


def measure(spec: dict, args, tmp: str) -> list:
    """The rows of one (d, N): one worker per implementation, timed in turn."""
    workers = {}
    for impl in args.impls:
        env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=tempfile.mkdtemp(dir=tmp))
        if args.omp_wait_policy != "unset":
            env["OMP_WAIT_POLICY"] = args.omp_wait_policy.upper()
        workers[impl] = Worker(dict(spec, impl=impl), env)
    times = {impl: [] for impl in workers}
    for r in range(1, args.repeats + 1):
        for impl, w in workers.items():
            if "error" not in w.info:
                reply = w.ask(r)
                times[impl].append(reply["seconds"]) if "seconds" in reply else w.info.update(reply)
    rows = []
    for impl, w in workers.items():
        end = w.close()
        rows.append({"case": {k: spec[k] for k in ("d", "N", "steps", "guidance")},
                     "entry": impl, "device": w.info.get("device"),
                     "compile_mode": spec["compile_mode"] if impl == "torch_compile" else None,
                     "seconds_per_step": statistics.median(times[impl]) / spec["filter_steps"]
                     if times[impl] else None, "times_s": times[impl],
                     "compile_seconds": w.info.get("compile_s"), "peak_mb": end.get("peak_mb"),
                     "error": w.info.get("error")})
    return rows


def table(rows: list) -> list:
    """Markdown lines: seconds per filter step of each implementation and JAX's ratios."""
    by = {(r["case"]["d"], r["case"]["N"], r["entry"]): r for r in rows}
    fmt = lambda v, spec=".3g": "-" if v is None else format(v, spec)
    body = []
    for d, n in dict.fromkeys((r["case"]["d"], r["case"]["N"]) for r in rows):
        j, e, c = (by.get((d, n, impl), {}) for impl in IMPLS)
        s = [x.get("seconds_per_step") for x in (j, e, c)]
        ratio = lambda a, b: None if a is None or b is None else a / b
        body.append([d, n, *(fmt(v) if not x.get("error") else "failed"
                             for v, x in zip(s, (j, e, c))),
                     fmt(ratio(s[0], s[1]), ".2f"), fmt(ratio(s[0], s[2]), ".2f"),
                     fmt(j.get("compile_seconds"), ".1f"), fmt(c.get("compile_seconds"), ".1f"),
                     " / ".join(fmt(x.get("peak_mb"), ".0f") for x in (j, e, c))])
    devices = sorted({f"{r['entry']}: {r['device']}" for r in rows if r["device"]})
    errors = [f"- {r['entry']} d={r['case']['d']} N={r['case']['N']}: {r['error']}"
              for r in rows if r["error"]]
    return (harness.table(["d", "N", "JAX s", "eager s", "compiled s", "JAX / eager",
                           "JAX / compiled", "JAX compile s", "torch.compile s",
                           "peak MB JAX / eager / compiled"], body)
            + ["", "Devices: " + "; ".join(devices) + "."] + (["", "Failures:"] + errors
                                                                if errors else []))


def where(machine_record: dict) -> str:
    """A results line's machine (also lorenz96_scaling's): the CPU and its cores, and the
    accelerator JAX ran on, if any."""
    m = machine_record
    cpu = f"{m['cpu']} ({m['cpu_count']} cores)"
    if m["jax_backend"] == "cpu":
        return cpu
    return f"{', '.join(m['devices'])} (jax {m['jax_backend']}) with {cpu}"


def main(argv=None):
    from csf_jax.guidance import MODES

    p = harness.parser("bench", "Time the CSF online step: csf_jax against its PyTorch port, "
                       "eager and compiled, per state dimension and ensemble size.", cache=False)
    p.add_argument("--dims", type=harness.int_list(1), default=None,
                   help="comma-separated state dimensions d (default 1,10,20; 10 with --quick)")
    p.add_argument("--particles", type=harness.int_list(2), default=None,
                   help="comma-separated ensemble sizes N (default 1000; 256 with --quick)")
    p.add_argument("--guidance", choices=MODES, default="kalman",
                   help="the sampler: kalman (the default's) or a DPS mode (the paper's: clipped "
                        "with --steps 500); default %(default)s")
    p.add_argument("--steps", type=harness.int_at_least(2), default=20,
                   help="reverse steps L (default %(default)s)")
    p.add_argument("--repeats", type=harness.int_at_least(1), default=None,
                   help="timed calls per implementation (default 3; 1 with --quick)")
    p.add_argument("--filter-steps", type=harness.int_at_least(1), default=None,
                   help="filter steps per timed call (default 2; 1 with --quick)")
    p.add_argument("--impls", type=harness.name_list(IMPLS, "implementation"),
                   default=list(IMPLS), help=f"comma-separated from {','.join(IMPLS)}")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="where the PyTorch side runs (default: cuda if torch sees a GPU)")
    p.add_argument("--compile-mode", choices=COMPILE_MODES, default="default",
                   help="torch.compile's mode (reduce-overhead: CUDA graphs on a GPU)")
    p.add_argument("--torch-threads", type=harness.int_at_least(1), default=None,
                   help="torch's intra-op threads (default: torch's own)")
    p.add_argument("--omp-wait-policy", choices=("passive", "active", "unset"), default="unset",
                   help="OMP_WAIT_POLICY of the torch workers (default %(default)s)")
    harness.add_outputs(p, "results/bench", "docs/benchmark.md")
    p.add_argument("--quick", action="store_true",
                   help="a smoke test: d = 10, N = 256, 1 repeat of 1 filter step (the flags "
                        "given win)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    cli.fill(args, DEFAULTS, QUICK if args.quick else None)
    if args.worker:
        try:
            spec = json.loads(args.worker)
        except json.JSONDecodeError as e:
            p.error(f"argument --worker: not a worker spec (JSON): {e}")
        return worker(spec)
    torch_needed = any(i.startswith("torch") for i in args.impls)
    if torch_needed and importlib.util.find_spec("torch") is None:
        p.error(TORCH_MISSING)
    if torch_needed:
        import torch

        found = "cuda" if torch.cuda.is_available() else "cpu"
        if args.device == "cuda" and found != "cuda":
            p.error("argument --device: torch sees no CUDA GPU; use --device cpu")
        args.device = args.device or found
    # JAX allocates GPU memory as it goes, so that PyTorch workers on the same GPU get theirs
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    import jax

    import csf_jax

    # a GPU's rows go to blocks of their own, so that a page keeps its CPU rows beside them
    tag = f"{args.guidance}_L{args.steps}" + ("" if jax.default_backend() == "cpu" else "_gpu")
    cli.check_outputs(p, args, tag)

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for d in args.dims:
            params = f"{tmp}/params_{d}.npz"
            flat = {jax.tree_util.keystr(k, simple=True, separator="/"): np.asarray(v)
                    for k, v in jax.tree_util.tree_flatten_with_path(
                        csf_jax.init_params(jax.random.key(0), network(), d))[0]}
            np.savez(params, **flat)
            for n in args.particles:
                spec = {"params": params, "d": d, "N": n, "steps": args.steps,
                        "guidance": args.guidance, "filter_steps": args.filter_steps,
                        "device": args.device, "compile_mode": args.compile_mode,
                        "torch_threads": args.torch_threads}
                t0 = time.perf_counter()
                rows += measure(spec, args, tmp)
                print(f"d={d} N={n}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    sampler = (f"ancestral with Kalman guidance, L = {args.steps}" if args.guidance == "kalman"
               else f"Euler-Maruyama with DPS guidance '{args.guidance}', L = {args.steps}")
    record = harness.results_record("bench", harness.command("bench", argv), rows,
                                    sampler=sampler, loadavg=list(os.getloadavg()))
    m = record["machine"]
    lines = [f"Made by `{record['command']}` on {record['date']}, {where(m)}. Sampler: "
             f"{sampler}; seconds per filter step, the median of "
             f"{args.repeats} timed runs of {args.filter_steps} filter steps; compilation "
             f"apart.", ""] + table(rows)
    with interrupt.WRITING:
        harness.publish(args, record, lines, f"results_{tag}.json", tag)


if __name__ == "__main__":
    interrupt.main(main, "bench")
