"""Seconds per filter step and peak memory of the transform CSF and the sharded LETKF at large d.

    python -m experiments.lorenz96_scaling [--dims 10000,100000] [--members 20]
        [--filter-steps 3] [--repeats 2] [--radius 1.0] [--inflation 1.4] [--out DIR] [--page PAGE]

EnSF's Lorenz-96 setup (``lorenz96_ensf``: arctan sensor of every site, std 0.05) at each d,
N members, float32, on the default device. Each (d, filter) runs in a fresh subprocess: the data
and the filter's compilation first (a first call), then ``--repeats`` calls of ``--steps`` steps
each; the time is the fastest call's, per step (forecast and analysis), and the memory is the
process's peak resident set during the timed calls (``VmHWM``, reset by ``/proc/self/clear_refs``
before them) minus its resident set just before them, so it counts what the filter allocates, not
the interpreter, the libraries, the inputs or the compiler. The subprocess runs with
``MALLOC_MMAP_THRESHOLD_=131072``: glibc then maps every buffer above 128 KiB on its own and
unmaps it when freed, so buffers freed by the first call do not stay resident and hide the timed
calls' peak. On a GPU the memory is the device's peak bytes in use (``memory_stats``, the same
shapes in the first and the timed calls) minus its bytes in use before the timed calls; the rows
then go to ``scaling_gpu.json`` and the page's ``scaling_gpu`` block. ``ratio`` is that peak over
the ensemble's ``N d 4`` bytes.
"""

from __future__ import annotations

import json
import os
import sys
import time

from experiments import cli, harness, interrupt
from experiments.bench import where


def _status(field: str) -> float:
    """A ``/proc/self/status`` entry in MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def measure(dim: int, filter_name: str, members: int, steps: int, repeats: int, radius: float,
            inflation: float) -> dict:
    """One (d, filter) cell in this process (``main`` runs each in a fresh one)."""
    import jax
    import numpy as np

    import csf_jax
    from csf_jax import problems

    model = problems.get("lorenz96_ensf", dim=dim, num_steps=steps, burn_in=0)
    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1000), members)
    loc = csf_jax.ring_localization(dim, range(dim))
    if filter_name == "transform":
        # the fixed inflation of the LETKF's row (no EnKF-N factor), so the two time one analysis
        config = csf_jax.LocalTransformConfig(radius=radius, inflation=inflation, adaptive=0.0)
        method = csf_jax.methods.local_transform(loc, config)
    else:
        config = csf_jax.LETKFConfig(radius=radius, inflation=inflation)
        method = csf_jax.methods.sharded_letkf(loc, config)

    def call():
        result = csf_jax.run(method, obs, ens, model=model, key=jax.random.key(2),
                             check_finite=False)
        return jax.block_until_ready(result)

    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    device = jax.devices()[0]
    gpu = device.platform != "cpu"
    before = (device.memory_stats()["bytes_in_use"] / 2 ** 20 if gpu else _status("VmRSS"))
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    seconds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = call()
        seconds.append(time.perf_counter() - t0)
    peak = device.memory_stats()["peak_bytes_in_use"] / 2 ** 20 if gpu else _status("VmHWM")
    extra = peak - before
    err = np.sqrt(np.mean((np.asarray(result.mean) - np.asarray(truth)[1:]) ** 2, -1))
    ensemble_mib = members * dim * 4 / 2 ** 20
    return {"dim": dim, "filter": filter_name, "N": members, "steps": steps,
            "seconds_per_step": min(seconds) / steps, "first_call_s": first,
            "peak_mib": extra, "ensemble_mib": ensemble_mib, "ratio": extra / ensemble_mib,
            "rmse_last": float(err[-1]), "device": str(jax.devices()[0])}


def main(argv=None) -> None:
    p = harness.parser("lorenz96_scaling", __doc__.splitlines()[0], cache=False)
    p.add_argument("--dims", type=harness.int_list(40), default=[10000, 100000],
                   help="comma-separated state dimensions d, each >= 40 (default 10000,100000)")
    p.add_argument("--members", type=harness.int_at_least(2), default=20,
                   help="ensemble size N (default %(default)s)")
    harness.add_timing(p, repeats=2, steps=3)
    p.add_argument("--radius", type=cli.positive_float, default=1.0,
                   help="localisation radius, > 0 (default 1)")
    p.add_argument("--inflation", type=cli.positive_float, default=1.4,
                   help="inflation, > 0 (default 1.4)")
    harness.add_outputs(p, "results/lorenz96", "docs/lorenz96.md")
    args = p.parse_args(argv)
    import jax

    gpu = jax.default_backend() != "cpu"
    cli.check_outputs(p, args, "scaling_gpu" if gpu else "scaling")
    rows = []
    for dim in args.dims:
        for name in ("sharded_letkf", "transform"):
            code = (f"import json; from experiments.lorenz96_scaling import measure; print(json."
                    f"dumps(measure({dim}, {name!r}, {args.members}, {args.filter_steps}, "
                    f"{args.repeats}, {args.radius!r}, {args.inflation!r})))")
            out = interrupt.run([sys.executable, "-c", code], capture_output=True, text=True,
                                env={**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"})
            if out.returncode != 0:
                last = (out.stderr.strip().splitlines() or ["no output"])[-1]
                raise SystemExit(f"lorenz96_scaling: the worker of d={dim} ({name}) failed: {last}")
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"d={dim} {name}: {rows[-1]['seconds_per_step']:.3f} s / step", file=sys.stderr)
    record = harness.results_record("lorenz96_scaling", harness.command("lorenz96_scaling", argv),
                                    rows, radius=args.radius, inflation=args.inflation)
    m = record["machine"]
    lines = ([f"Made by `{record['command']}` on {record['date']}, {where(m)}, N = {args.members}, radius {args.radius:g}, "
              f"inflation {args.inflation:g}. Seconds per filter step (the fastest of "
              f"{args.repeats} calls of {args.filter_steps} steps) and the peak memory the filter "
              f"allocates, in MiB and over the ensemble's size:", ""]
             + harness.table(["d", "filter", "s / step", "first call s", "peak MiB",
                              "peak / ensemble"],
                             [[r["dim"], r["filter"], f"{r['seconds_per_step']:.3g}",
                               f"{r['first_call_s']:.1f}", f"{r['peak_mib']:.0f}",
                               f"{r['ratio']:.1f}"] for r in rows]))
    with interrupt.WRITING:
        harness.publish(args, record, lines, "scaling_gpu.json" if gpu else "scaling.json",
                        "scaling_gpu" if gpu else "scaling")


if __name__ == "__main__":
    interrupt.main(main, "lorenz96_scaling")
