"""Seconds per LETKF step when the sites are split over devices: ``csf_jax.letkf`` on one device
against ``csf_jax.filters.sharded.sharded_letkf`` on 1, 2, ... host devices.

    python -m experiments.scale_out [--dims D,D] [--devices P,P] [--members N]
        [--sensor identity|arctan] [--steps K] [--repeats R] [--out out/scale_out]

For every d of ``--dims`` and device count P of ``--devices`` a fresh worker process starts with
P XLA host devices (``--xla_force_host_platform_device_count=P``: the device count is fixed when
jax starts) and filters ``--steps`` steps of Lorenz-96 (d sites, ``--sensor``, N = ``--members``,
``LETKFConfig()``'s radius and inflation) with ``sharded_letkf`` over a mesh of its P devices;
the P = 1 worker also runs ``csf_jax.letkf``. One untimed call compiles; then ``--repeats`` timed
calls (each ends with ``block_until_ready``) give the median seconds per filter step (forecast +
analysis), compilation excluded. The worker also reports the largest difference of the filtered
means from ``csf_jax.letkf``'s on the same inputs (that run happens in every worker; it is timed
only where P = 1); beyond ``LETKF_MAX_DIM`` sites, where ``csf_jax.letkf`` does not fit in
memory, from ``sharded_letkf`` on one device of the same worker.

On a CPU the P host devices share the machine's cores: the speed-up a real multi-GPU or multi-host
mesh gives is not what this measures; it measures the cost of the halo exchange and of the
per-device programs. Writes ``scale_out.json`` (machine, arguments, rows) to ``--out`` and prints
the table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from experiments._cli import int_list, parser, particle_count, positive_int

DESCRIPTION = ("Seconds per step of the site-sharded LETKF on 1, 2, ... XLA host devices against "
               "csf_jax.letkf on one, per state dimension; write scale_out.json to --out.")
SENSORS = ("identity", "arctan")
#: the arctan sensor's observation noise (that of the Lorenz-96 pages); identity: R = I
OBS_STD = {"identity": 1.0, "arctan": 0.05}
#: the largest d ``csf_jax.letkf`` runs at here: its ``local_obs`` takes the distances of every
#: site to every observation on the host (d x m float64: 3 GiB at d = m = 20000)
LETKF_MAX_DIM = 20000


def build_parser():
    """The command line of ``python -m experiments.scale_out``."""
    p = parser("scale_out", DESCRIPTION)
    p.add_argument("--dims", type=int_list(40), default="10000,100000", metavar="D,D,...",
                   help="comma-separated state dimensions d, each a multiple of every device "
                        "count (default %(default)s)")
    p.add_argument("--devices", type=int_list(1), default="1,2", metavar="P,P,...",
                   help="comma-separated XLA host device counts (default %(default)s)")
    p.add_argument("--members", type=particle_count, default=20,
                   help="ensemble size N (default %(default)s)")
    p.add_argument("--sensor", choices=SENSORS, default="identity",
                   help="Lorenz-96 sensor, %(choices)s (default %(default)s)")
    p.add_argument("--steps", type=positive_int, default=3,
                   help="filter steps per timed call, K (default %(default)s)")
    p.add_argument("--repeats", type=positive_int, default=3,
                   help="timed calls per filter (default %(default)s)")
    p.add_argument("--out", default=os.path.join("out", "scale_out"),
                   help="folder for scale_out.json (default %(default)s)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    return p


def _machine() -> dict:
    """What the numbers were measured on."""
    import platform

    import jax

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                       cpu)
    except OSError:
        pass
    return {"platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "jax": jax.__version__,
            "loadavg": [round(v, 2) for v in os.getloadavg()]}


def parse_args(argv=None):
    p = build_parser()
    args = p.parse_args(argv)
    if args.worker:
        return args
    from csf_jax.filters.letkf import LETKFConfig
    from csf_jax.filters.sharded import halo_width

    halo = halo_width(LETKFConfig().radius)
    for d in args.dims:
        for n in args.devices:
            if d % n:
                p.error(f"argument --dims: d={d} is not a multiple of {n} devices")
            if d // n < halo:
                p.error(f"argument --dims: d={d} over {n} devices leaves blocks of {d // n} "
                        f"sites, fewer than the halo of {halo} (LETKFConfig().radius)")
    return args


def _timed(call, repeats: int, steps: int):
    """``(compile + first call seconds, median seconds per filter step, the last result)`` of
    ``call()``."""
    t0 = time.perf_counter()
    result = call()
    result.mean.block_until_ready()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = call()
        result.mean.block_until_ready()
        times.append((time.perf_counter() - t0) / steps)
    return first, statistics.median(times), result


def worker(spec: dict) -> list:
    """One cell: ``sharded_letkf`` on this process's devices (and ``letkf`` timed where P = 1)."""
    import jax
    import numpy as np

    import csf_jax
    from csf_jax.filters.sharded import sharded_letkf, site_mesh
    from csf_jax.problems.lorenz96 import Lorenz96Config, lorenz96_problem, obs_sites

    d, steps, repeats = spec["d"], spec["steps"], spec["repeats"]
    config = Lorenz96Config(dim=d, sensor=spec["sensor"], obs_std=OBS_STD[spec["sensor"]],
                            num_steps=steps, burn_in=0)
    model = lorenz96_problem(config)
    _, obs = csf_jax.simulate(model, jax.random.key(0))
    ens = model.initial_ensemble(jax.random.key(1), spec["members"])
    kwargs = dict(problem=model, key=jax.random.key(2),
                  localization=csf_jax.ring_localization(d, obs_sites(config)))
    devices = len(jax.devices())
    rows = []
    with_letkf = d <= LETKF_MAX_DIM
    if with_letkf and devices == 1:
        first, per_step, reference = _timed(lambda: csf_jax.letkf(obs, ens, **kwargs), repeats,
                                            steps)
        rows.append({"filter": "letkf", "devices": 1, "first_call_s": first,
                     "s_per_step": per_step, "max_abs_diff": None, "reference": None})
    elif with_letkf:
        reference = csf_jax.letkf(obs, ens, **kwargs)
    elif devices > 1:
        reference = sharded_letkf(obs, ens, mesh=site_mesh(jax.devices()[:1]), **kwargs)
    mesh = site_mesh()
    first, per_step, got = _timed(lambda: sharded_letkf(obs, ens, mesh=mesh, **kwargs), repeats,
                                  steps)
    diff = None
    if with_letkf or devices > 1:
        diff = float(np.max(np.abs(np.asarray(got.mean) - np.asarray(reference.mean))))
    rows.append({"filter": "sharded_letkf", "devices": devices, "first_call_s": first,
                 "s_per_step": per_step, "max_abs_diff": diff,
                 "reference": None if diff is None else
                 "letkf" if with_letkf else "sharded_letkf, 1 device"})
    return [dict(row, d=d, N=spec["members"], sensor=spec["sensor"], steps=steps) for row in rows]


def run_cell(spec: dict, devices: int) -> list:
    """``worker(spec)`` in a fresh process with ``devices`` XLA host devices."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": " ".join(flags + [f"--xla_force_host_platform_device_count={devices}"])}
    done = subprocess.run([sys.executable, "-m", "experiments.scale_out", "--worker",
                           json.dumps(spec)], env=env, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"worker d={spec['d']} P={devices} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


HEADER = ["| d | N | sensor | filter | devices | s/step | first call s | max abs diff of the mean "
          "| against |", "|---|---|---|---|---|---|---|---|---|"]


def row_line(r: dict) -> str:
    """One row of the table."""
    diff = "-" if r["max_abs_diff"] is None else f"{r['max_abs_diff']:.1e}"
    return (f"| {r['d']} | {r['N']} | {r['sensor']} | {r['filter']} | {r['devices']} | "
            f"{r['s_per_step']:.3f} | {r['first_call_s']:.1f} | {diff} | "
            f"{r['reference'] or '-'} |")


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    rows = []
    start = _machine()
    print("\n".join(HEADER), flush=True)
    for d in args.dims:
        for devices in args.devices:
            spec = {"d": d, "members": args.members, "sensor": args.sensor, "steps": args.steps,
                    "repeats": args.repeats}
            new = run_cell(spec, devices)
            rows += new
            print("\n".join(map(row_line, new)), flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "scale_out.json"), "w") as f:
        arguments = {k: v for k, v in vars(args).items() if k != "worker"}
        json.dump({"machine": start, "loadavg_end": _machine()["loadavg"], "args": arguments,
                   "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
