"""The subprocesses of ``tests/test_sharded.py``: jax fixes its device count when it starts, so runs
on several devices need a process of their own.

    python tests/_distributed_worker.py local OUT.npz
        (started with XLA_FLAGS=--xla_force_host_platform_device_count=4) for every case of
        ``CASES``: ``csf_jax.letkf`` on one device and ``sharded_letkf`` on meshes of the case's
        device counts (for "identity" also on 2 devices analysing 4 sites at a time); writes
        their means, stds, ensembles and finite flags to OUT.npz.
    python tests/_distributed_worker.py transform OUT.npz
        (4 devices, as ``local``) in float64, for every case of ``TRANSFORM_CASES``:
        ``csf_jax.local_transform_filter`` on one device and ``sharded_transform_filter`` on 4
        devices and on 2 devices analysing their blocks in classes (``chunk=4``); writes them as
        ``local`` does.
    python tests/_distributed_worker.py distributed PROCESS_ID PORT INPUTS.npz OUT.npz [FILTER]
        one of two processes joined by ``jax.distributed.initialize`` on localhost:PORT (CPU
        collectives by gloo): ``sharded_letkf`` (FILTER "letkf", the default) or
        ``sharded_transform_filter`` in float64 (FILTER "transform", with ``transform_config``)
        over every device of both on the Lorenz-96 problem and inputs of INPUTS.npz (the ensemble
        as a global array, the observations from the host); the gathered result goes to OUT.npz.
"""

from __future__ import annotations

import sys

import jax
import numpy as np

#: name -> (sensor, obs_every, obs_std, rate of missing entries, device counts of the meshes)
CASES = {
    "identity": ("identity", 1, 1.0, 0.0, (4,)),
    "identity_missing": ("identity", 1, 1.0, 0.3, (4,)),
    "arctan": ("arctan", 1, 0.05, 0.0, (4,)),
    "every2_missing": ("every", 2, 1.0, 0.2, (4,)),
}
DIM, MEMBERS, STEPS, RADIUS, INFLATION = 40, 20, 6, 4.0, 1.05
#: name -> (sensor, obs_every, obs_std, rate of missing entries, radius, inflation)
TRANSFORM_CASES = {
    "identity_missing": ("identity", 1, 1.0, 0.3, 4.0, 1.05),
    "arctan": ("arctan", 1, 0.05, 0.0, 1.0, 1.2),
    "every2_missing": ("every", 2, 1.0, 0.2, 3.0, 1.05),
}


def transform_config(radius: float = RADIUS, inflation: float = INFLATION):
    """The ``LocalTransformConfig`` of a transform case (few levels: the runs are for equality)."""
    import csf_jax

    return csf_jax.LocalTransformConfig(radius=radius, inflation=inflation, reverse_steps=4)


def problem(sensor: str, obs_every: int = 1, obs_std: float = 1.0):
    """The Lorenz-96 model of a case, its ``ring_localization`` and ``LETKFConfig``."""
    import csf_jax
    from csf_jax.problems.lorenz96 import Lorenz96Config, lorenz96_problem, obs_sites

    config = Lorenz96Config(dim=DIM, sensor=sensor, obs_every=obs_every, obs_std=obs_std,
                            num_steps=STEPS, burn_in=0, spinup_steps=200)
    return (lorenz96_problem(config), csf_jax.ring_localization(DIM, obs_sites(config)),
            csf_jax.LETKFConfig(radius=RADIUS, inflation=INFLATION))


def inputs(model, missing: float):
    """Truth ``(K + 1, d)``, observations ``(K, m)`` (a fraction ``missing`` NaN, and whole steps
    now and then) and the initial ensemble ``(N, d)`` of a case, from fixed seeds."""
    import csf_jax

    truth, obs = csf_jax.simulate(model, jax.random.key(0))
    if missing:
        obs = csf_jax.drop_observations(jax.random.key(3), obs, missing, whole_steps=0.2)
    ensemble = model.initial_ensemble(jax.random.key(1), MEMBERS)
    return np.asarray(truth), np.asarray(obs), np.asarray(ensemble)


def fields(prefix: str, result) -> dict:
    """``{prefix/mean, prefix/std, prefix/ensembles, prefix/finite}`` as numpy arrays."""
    return {f"{prefix}/{k}": np.asarray(getattr(result, k))
            for k in ("mean", "std", "ensembles", "finite")}


def run_local(out: str) -> None:
    import csf_jax
    from csf_jax.filters.sharded import sharded_letkf, site_mesh

    saved = {}
    for name, (sensor, every, std, missing, counts) in CASES.items():
        model, loc, config = problem(sensor, every, std)
        truth, obs, ens = inputs(model, missing)
        saved[f"{name}/truth"] = truth[1:]
        kwargs = dict(problem=model, key=jax.random.key(2), localization=loc, config=config,
                      return_ensembles=True)
        saved.update(fields(f"{name}/letkf", csf_jax.letkf(obs, ens, **kwargs)))
        for count in counts:
            mesh = site_mesh(jax.devices()[:count])
            saved.update(fields(f"{name}/sharded{count}", sharded_letkf(obs, ens, mesh=mesh,
                                                                         **kwargs)))
        if name == "identity":        # blocks of 20 sites analysed 4 at a time
            saved.update(fields(f"{name}/sharded2_chunk4", sharded_letkf(
                obs, ens, mesh=site_mesh(jax.devices()[:2]), chunk=4, **kwargs)))
    np.savez(out, **saved)


def run_transform(out: str) -> None:
    jax.config.update("jax_enable_x64", True)
    import csf_jax
    from csf_jax.filters.sharded import site_mesh
    from csf_jax.filters.sharded_transform import sharded_transform_filter

    saved = {}
    for name, (sensor, every, std, missing, radius, inflation) in TRANSFORM_CASES.items():
        model, loc, _ = problem(sensor, every, std)
        truth, obs, ens = inputs(model, missing)
        saved[f"{name}/truth"] = truth[1:]
        kwargs = dict(model=model, key=jax.random.key(2), localization=loc,
                      config=transform_config(radius, inflation), return_ensembles=True)
        obs, ens = obs.astype(np.float64), ens.astype(np.float64)
        saved.update(fields(f"{name}/one", csf_jax.local_transform_filter(obs, ens, **kwargs)))
        saved.update(fields(f"{name}/sharded4", sharded_transform_filter(
            obs, ens, mesh=site_mesh(jax.devices()[:4]), **kwargs)))
        saved.update(fields(f"{name}/sharded2_chunk4", sharded_transform_filter(
            obs, ens, mesh=site_mesh(jax.devices()[:2]), chunk=4, **kwargs)))
    np.savez(out, **saved)


def run_distributed(process_id: int, port: int, given: str, out: str,
                    filter_name: str = "letkf") -> None:
    if filter_name == "transform":
        jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=2,
                               process_id=process_id, initialization_timeout=60)
    from jax.sharding import NamedSharding, PartitionSpec

    from csf_jax.filters.sharded import gather_result, sharded_letkf, site_mesh
    from csf_jax.filters.sharded_transform import sharded_transform_filter

    data = np.load(given)
    model, loc, config = problem(str(data["sensor"]))
    run, dtype = sharded_letkf, np.float32
    if filter_name == "transform":
        run, dtype, config = sharded_transform_filter, np.float64, transform_config()
    # the ensemble as a global array, each process making its own blocks; the obs from the host
    host = data["ensemble"].astype(dtype)
    ensemble = jax.make_array_from_callback(
        host.shape, NamedSharding(site_mesh(), PartitionSpec(None, "sites")), lambda i: host[i])
    assert not ensemble.is_fully_addressable
    result = run(data["obs"].astype(dtype), ensemble, model=model, key=jax.random.key(2),
                 localization=loc, config=config, return_ensembles=True)
    gathered = gather_result(result)
    np.savez(out, devices=len(jax.devices()), local=len(jax.local_devices()),
             **fields("sharded", gathered))
    jax.distributed.shutdown()


if __name__ == "__main__":
    if sys.argv[1] == "local":
        run_local(sys.argv[2])
    elif sys.argv[1] == "transform":
        run_transform(sys.argv[2])
    else:
        run_distributed(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5],
                        *sys.argv[6:])
