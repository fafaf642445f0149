"""The site-sharded LETKF (``csf_jax.filters.sharded``) equals ``csf_jax.letkf``, and the sharded
transform CSF (``csf_jax.filters.sharded_transform``) equals ``csf_jax.local_transform_filter``: on 1
(here), 2 and 4 CPU devices of one process, and on two processes joined by ``jax.distributed``; and
they refuse what they cannot filter exactly with one-line errors.

The runs on several devices happen in subprocesses (``tests/_distributed_worker.py``): jax fixes
its device count when it starts, and this process has one device. Every subprocess has a timeout,
so a hang fails the test instead of blocking the suite.
"""

import dataclasses
import importlib.util
import os
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import MATMUL_ATOL

import csf_jax
from csf_jax.filters.letkf import _probe, local_obs, sensor_sites
from csf_jax.filters.sharded import (
    CHUNK,
    gather_result,
    halo_width,
    sharded_letkf,
    site_mesh,
    site_plan,
    site_slots,
)
from csf_jax.filters.sharded_transform import sharded_transform_filter

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
WORKER = os.path.join(HERE, "_distributed_worker.py")
TIMEOUT = 150
# float32 round-off: the window sums run in another order than csf_jax.letkf's (atol 1e-5 on
# values of order 10 leaves the relative part to rtol)
TOL = dict(rtol=max(1e-5, MATMUL_ATOL), atol=max(1e-5, MATMUL_ATOL))
# the transform CSF in float64: 1e-14 step by step, but a Levenberg-Marquardt step that a
# converged site accepts or refuses on a round-off difference of its cost moves it by up to 1e-9
TOL64 = dict(rtol=0, atol=1e-7)


def _worker_module():
    spec = importlib.util.spec_from_file_location("_distributed_worker", WORKER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


W = _worker_module()


def _env(devices: int) -> dict:
    """This process's environment with ``devices`` XLA host devices (other XLA flags kept)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    flags.append(f"--xla_force_host_platform_device_count={devices}")
    return {**os.environ, "XLA_FLAGS": " ".join(flags), "JAX_PLATFORMS": "cpu",
            "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _assert_same(got: dict, want: dict, label: str, tol: dict = TOL) -> None:
    for key in ("mean", "std", "ensembles"):
        np.testing.assert_allclose(got[key], want[key], **tol, err_msg=f"{label}: {key}")
    np.testing.assert_array_equal(got["finite"], want["finite"], err_msg=f"{label}: finite")


def _split(data, prefix: str) -> dict:
    return {k: data[f"{prefix}/{k}"] for k in ("mean", "std", "ensembles", "finite")}


def _worker_results(tmp_path_factory, mode: str):
    """The results of ``_distributed_worker.py <mode>`` in a process with 4 CPU devices."""
    out = str(tmp_path_factory.mktemp("sharded") / f"{mode}.npz")
    done = subprocess.run([sys.executable, WORKER, mode, out], env=_env(4), cwd=ROOT,
                          capture_output=True, text=True, timeout=TIMEOUT, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return np.load(out)


@pytest.fixture(scope="module")
def several_devices(tmp_path_factory):
    """Every case of ``CASES``, ``letkf`` and ``sharded_letkf`` on meshes of the case's device
    counts (``_worker_results`` of "local")."""
    return _worker_results(tmp_path_factory, "local")


@pytest.mark.parametrize("case", list(W.CASES))
def test_sharded_equals_letkf_on_several_devices(several_devices, case):
    want = _split(several_devices, f"{case}/letkf")
    assert want["finite"].all()
    truth = several_devices[f"{case}/truth"]
    runs = [f"sharded{count}" for count in W.CASES[case][-1]]
    runs += ["sharded2_chunk4"] if case == "identity" else []
    for run in runs:
        got = _split(several_devices, f"{case}/{run}")
        _assert_same(got, want, f"{case}, {run}")
        rmse = float(csf_jax.rmse(got["mean"], truth))
        assert rmse == pytest.approx(float(csf_jax.rmse(want["mean"], truth)), rel=1e-5)


@pytest.fixture(scope="module")
def transform_devices(tmp_path_factory):
    """The transform CSF on one device and sharded (``_worker_results`` of "transform")."""
    return _worker_results(tmp_path_factory, "transform")


@pytest.mark.slow
@pytest.mark.parametrize("case", list(W.TRANSFORM_CASES))
def test_sharded_transform_equals_one_device_on_several_devices(transform_devices, case):
    want = _split(transform_devices, f"{case}/one")
    assert want["finite"].all() and want["mean"].dtype == np.float64
    for run in ("sharded4", "sharded2_chunk4"):
        _assert_same(_split(transform_devices, f"{case}/{run}"), want, f"{case}, {run}", TOL64)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _two_processes(tmp_path, local_devices: int, filter_name: str) -> tuple:
    """Run ``_distributed_worker.py distributed`` as two processes on the identity case (30 %
    of the observations and some whole steps missing); their gathered results and the inputs."""
    model, loc, _ = W.problem("identity")
    _, obs, ens = W.inputs(model, 0.3)
    assert np.isnan(obs).any() and np.isnan(obs).all(axis=1).any()
    given = str(tmp_path / "inputs.npz")
    np.savez(given, sensor="identity", obs=obs, ensemble=ens)
    port = _free_port()
    outs = [str(tmp_path / f"out{i}.npz") for i in range(2)]
    logs = [tmp_path / f"log{i}.txt" for i in range(2)]
    procs = []
    try:
        for i in range(2):
            with open(logs[i], "w") as log:       # files, not pipes: nothing blocks on output
                procs.append(subprocess.Popen(
                    [sys.executable, WORKER, "distributed", str(i), str(port), given, outs[i],
                     filter_name], env=_env(local_devices), cwd=ROOT, stdout=log,
                    stderr=subprocess.STDOUT))
        for proc in procs:
            proc.wait(timeout=TIMEOUT)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    for proc, log in zip(procs, logs):
        assert proc.returncode == 0, log.read_text()[-3000:]
    datas = [np.load(out) for out in outs]
    for data in datas:
        assert int(data["devices"]) == 2 * local_devices
        assert int(data["local"]) == local_devices
    return model, loc, obs, ens, datas


# both slow: two processes each compile the filter (kept out of the default run's time budget)
@pytest.mark.parametrize("local_devices", [pytest.param(1, marks=pytest.mark.slow),
                                           pytest.param(2, marks=pytest.mark.slow)])
def test_sharded_over_two_processes_equals_letkf(tmp_path, local_devices):
    model, loc, obs, ens, datas = _two_processes(tmp_path, local_devices, "letkf")
    ref = csf_jax.letkf(obs, ens, model=model, key=jax.random.key(2), localization=loc,
                        config=W.problem("identity")[2], return_ensembles=True)
    want = {k: np.asarray(getattr(ref, k)) for k in ("mean", "std", "ensembles", "finite")}
    for i, data in enumerate(datas):
        _assert_same(_split(data, "sharded"), want, f"process {i}")


@pytest.mark.slow
def test_sharded_transform_over_two_processes_equals_one_device(tmp_path, x64):
    model, loc, obs, ens, datas = _two_processes(tmp_path, 1, "transform")
    ref = csf_jax.local_transform_filter(obs.astype(np.float64), ens.astype(np.float64),
                                         model=model, key=jax.random.key(2), localization=loc,
                                         config=W.transform_config(), return_ensembles=True)
    want = {k: np.asarray(getattr(ref, k)) for k in ("mean", "std", "ensembles", "finite")}
    for i, data in enumerate(datas):
        _assert_same(_split(data, "sharded"), want, f"process {i}", TOL64)


# --- one device here: the plan, the refusals, the single-device run ---------------------------------


def test_halo_is_the_sites_in_reach():
    # Gaspari-Cohn reaches distance 2 radius (exclusive): radius 4 -> offsets 1 .. 7
    assert halo_width(4.0) == 7
    assert halo_width(0.4) == 0
    index, weight = local_obs(csf_jax.ring_localization(40, range(40)), 4.0)
    assert 2 * halo_width(4.0) + 1 == index.shape[1]
    plan = site_plan(40, 4.0, 4)
    assert (plan.block, plan.halo, len(plan.offsets), plan.chunk) == (10, 7, 15, 10)
    assert site_plan(40, 4.0, 2, chunk=8).chunk == 5        # the largest divisor of 20 up to 8
    assert plan.offsets[:3] == (0, -1, 1)
    np.testing.assert_allclose(sorted(plan.taper, reverse=True), weight[0])


@pytest.mark.parametrize("dim, radius, devices, fragment", [
    (40, 4.0, 8, "wider than a device's block"),
    (42, 4.0, 4, "not a multiple of the 4 devices"),
    (12, 4.0, 1, "wider than the ring"),
])
def test_plan_refusals(dim, radius, devices, fragment):
    with pytest.raises(ValueError, match=fragment):
        site_plan(dim, radius, devices)


def test_two_observations_of_one_site_are_refused():
    with pytest.raises(ValueError, match="at most one observation per site, but site 3 has 2"):
        site_slots(np.array([0, 3, 3, 5]), 8)
    slots = site_slots(np.array([0, 2, 4, 6]), 8)
    assert not slots.identity and slots.has.tolist() == [True, False] * 4
    assert slots.index[[0, 2, 4, 6]].tolist() == [0, 1, 2, 3]
    assert site_slots(np.arange(8), 8).identity


@pytest.fixture(scope="module")
def small():
    model, loc, config = W.problem("identity")
    _, obs, ens = W.inputs(model, 0.0)
    return model, loc, config, obs, ens


def _call(small, obs=None, ensemble=None, **overrides):
    """``sharded_letkf`` on the ``small`` case, with arguments replaced by ``overrides``."""
    model, loc, config, obs_, ens_ = small
    kwargs = dict(model=model, key=jax.random.key(2), localization=loc, config=config)
    return sharded_letkf(obs_ if obs is None else obs, ens_ if ensemble is None else ensemble,
                         **{**kwargs, **overrides})


def test_non_ring_localization_is_refused(small):
    model, loc, _, _, _ = small
    line = csf_jax.Localization(loc.state, loc.obs, None)
    with pytest.raises(ValueError, match="needs the ring"):
        _call(small, localization=line)


def test_sensor_mixing_sites_is_refused(small):
    model = small[0]
    mixing = model._replace(observe=lambda x: x + 0.5 * jnp.roll(x, 1), name="mixing")
    with pytest.raises(ValueError, match="not a point sensor"):
        _call(small, model=mixing)


def test_misplaced_observations_are_refused(small):
    reversed_sites = csf_jax.ring_localization(40, range(39, -1, -1))
    with pytest.raises(ValueError, match="observation 0 reads site 0, but the localization "
                                         "places it at 39"):
        _call(small, localization=reversed_sites)


def test_point_sensor_sites_beyond_float32_ramps():
    # one ramp 1 + i / d cannot tell sites apart in float32 beyond d = 2^23; the digits can
    d = 2 ** 23 + 2 ** 20
    model = csf_jax.StateSpaceModel(
        name="points", dim=d, obs_dim=d // 2, num_steps=1, dt=1.0, drift=lambda x: x,
        observe=lambda x: jnp.arctan(x[1::2]), process_std=0.0,
        obs_noise=csf_jax.gaussian_noise(1.0), initial_truth=lambda key: jnp.zeros(d),
        initial_ensemble=lambda key, n: jnp.zeros((n, d)))
    sites = sensor_sites(model, _probe(model))
    assert sites is not None and np.array_equal(sites, np.arange(1, d, 2))


@pytest.mark.parametrize("field", [dict(adaptive=4.0), dict(radii=(2.0, 4.0))])
def test_adaptive_settings_are_refused(small, field):
    # the sharded LETKF refuses both; the sharded transform CSF shards the EnKF-N's inflation
    # (its default; test_one_device_transform_equals_local_transform)
    with pytest.raises(ValueError, match="config.adaptive and config.radii .* are not sharded"):
        _call(small, config=dataclasses.replace(small[2], **field))


def test_mesh_without_a_sites_axis_is_refused(small):
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("data",))
    with pytest.raises(ValueError, match="axis named 'sites'"):
        _call(small, mesh=mesh)


def test_bad_inputs_are_refused_like_letkf(small):
    ens = np.array(small[4])
    ens[3, 7] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        _call(small, ensemble=ens)
    with pytest.raises(ValueError, match="ensemble has dimension d=39"):
        _call(small, ensemble=small[4][:, :39])


@pytest.mark.parametrize("chunk, double", [(CHUNK, False), (8, True)])
def test_one_device_run_equals_letkf(small, chunk, double, request):
    """Whole block in float32; chunks of 8 sites in float64, where the two agree to 1e-10."""
    model, loc, config, obs, ens = small
    tol = TOL
    if double:
        request.getfixturevalue("x64")
        obs, ens, tol = obs.astype(np.float64), ens.astype(np.float64), dict(rtol=0, atol=1e-10)
    got = gather_result(_call(small, obs, ens, return_ensembles=True, mesh=site_mesh(),
                              chunk=chunk))
    ref = csf_jax.letkf(obs, ens, model=model, key=jax.random.key(2), localization=loc,
                        config=config, return_ensembles=True)
    assert got.mean.dtype == ref.mean.dtype == (np.float64 if double else np.float32)
    _assert_same(got._asdict(), ref._asdict(), f"one device, chunk {chunk}", tol)
    assert isinstance(got.mean, np.ndarray) and got.ess is None and got.info is None


def test_probe_errors_are_one_line(small):
    model, loc, config, obs, ens = small
    with pytest.raises(ValueError, match="site_mesh: devices is empty"):
        site_mesh([])
    with pytest.raises(TypeError, match="site_mesh: devices must be a sequence of jax devices"):
        site_mesh("cpu")
    with pytest.raises(TypeError, match="site_mesh: devices must be jax devices"):
        site_mesh([0, 1])
    with pytest.raises(TypeError, match="gather_result: takes the FilterResult of a sharded "
                                        "filter, got NoneType"):
        gather_result(None)
    for run, conf in ((sharded_letkf, config), (sharded_transform_filter,
                                                csf_jax.LocalTransformConfig())):
        name = run.__name__
        with pytest.raises(TypeError, match=f"{name}: takes concrete arrays .* not tracers of "
                                            f"an outer jax.jit"):
            jax.jit(lambda o: run(o, ens, model=model, key=jax.random.key(2), localization=loc,
                                  config=conf).mean)(obs)


def test_one_device_transform_switches_radius_as_local_transform(small):
    """With a far radius (``LocalTransformConfig.far_radius``) the sharded transform CSF takes
    the same radius in each step as ``local_transform_filter``: a narrow ensemble 3 off the
    truth gives steps at both radii."""
    model, loc, _, obs, ens = small
    ens = 0.1 * (ens - ens.mean(0)) + ens.mean(0) + 3.0
    config = csf_jax.LocalTransformConfig(radius=4.0, far_radius=2.0, reverse_steps=4)
    kw = dict(model=model, key=jax.random.key(2), localization=loc, config=config,
              return_ensembles=True)
    got = gather_result(sharded_transform_filter(obs, ens, mesh=site_mesh(), **kw))
    ref = csf_jax.local_transform_filter(obs, ens, **kw)
    assert set(np.asarray(ref.info["radius"]).tolist()) == {2.0, 4.0}
    _assert_same(got._asdict(), ref._asdict(), "one device, two radii")


def test_one_device_transform_equals_local_transform(small):
    model, loc, _, obs, ens = small
    kw = dict(model=model, key=jax.random.key(2), localization=loc,
              config=W.transform_config(), return_ensembles=True)
    got = gather_result(sharded_transform_filter(obs, ens, mesh=site_mesh(), **kw))
    ref = csf_jax.local_transform_filter(obs, ens, **kw)
    _assert_same(got._asdict(), ref._asdict(), "one device, transform")
    with pytest.raises(TypeError, match="sharded_transform_filter: config must be a "
                                        "LocalTransformConfig, got LETKFConfig"):
        sharded_transform_filter(obs, ens, **dict(kw, config=csf_jax.LETKFConfig()))
    with pytest.raises(ValueError, match="sharded_transform_filter: needs the ring"):
        sharded_transform_filter(obs, ens, **dict(kw, localization=csf_jax.Localization(
            loc.state, loc.obs, None)))
