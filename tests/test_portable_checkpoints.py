"""Checkpoints restore onto this process's default device whatever devices their orbax metadata
records: a model or a training run saved on a GPU, or on two devices, loads and resumes on one CPU.

Orbax records each saved ``jax.Array``'s sharding in the folder's ``_sharding`` file (the device
string, ``cpu:0``, or for a ``NamedSharding`` the ids of its mesh's devices). A restore that lets
orbax rebuild those shardings fails where the devices do not exist ("Topology mismatch"). These
tests rewrite the records of real checkpoints to devices this machine lacks (``cuda:0``, a
two-device mesh) and check that loading and resuming give the same arrays, bit for bit. They also
check that a damaged parameter folder fails in one line, with no asyncio noise after it.
"""

import gc
import glob
import json
import os
import re
import shutil
import time

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import csf_jax
from csf_jax import problems
from csf_jax.pretrained import MODEL_DIR, load_dir
from csf_jax.training import checkpoint
from csf_jax.training.train import TrainConfig, init_state

NET = csf_jax.NetworkConfig(base="gaussian", hidden=8, heads=2, blocks=1, code_dim=4,
                            score_hidden=8, score_layers=2, fourier_features=2)
TRAIN = TrainConfig(steps=20, save_every=10)
META = {"problem": "tiny", "dim": 2, "network": {"hidden": 8}, "dataset_id": "data-0", "seed": 0,
        "valid_loss": [[10, 1.5]]}

# Orbax's own serialisations of a sharding on a device this machine lacks, and of a sharding
# over a two-device mesh (a NamedSharding with its device ids, as orbax writes one).
ON_GPU = json.dumps({"sharding_type": "SingleDeviceSharding", "device_str": "cuda:0"})
ON_TWO = json.dumps({"sharding_type": "NamedSharding", "shape": [2], "axis_names": ["devices"],
                     "partition_spec": [None], "device_mesh": {"mesh": [{"id": 0}, {"id": 1}]}})
RECORDS = {"cuda:0": ON_GPU, "two devices": ON_TWO}

# What marks a device in orbax's metadata files.
DEVICE_MARKS = (b"device_str", b"device_mesh", b"cpu:0", b"TFRT_CPU")


def _files(folder) -> list[str]:
    return sorted(p for p in glob.glob(os.path.join(folder, "**"), recursive=True)
                  if os.path.isfile(p))


def _device_files(folder) -> list[str]:
    """The files under ``folder`` that record a device."""
    found = []
    for path in _files(folder):
        with open(path, "rb") as f:
            data = f.read()
        if any(mark in data for mark in DEVICE_MARKS):
            found.append(path)
    return found


def _rewrite_devices(folder, record: str) -> int:
    """Replace every device record under ``folder`` by ``record`` (an orbax sharding string);
    returns how many arrays' records were rewritten. Orbax keeps them in ``_sharding`` files (a
    JSON object: array name -> sharding string); any other file recording a device fails the test,
    so a new place orbax writes devices to is noticed."""
    files = _device_files(folder)
    others = [p for p in files if os.path.basename(p) != "_sharding"]
    assert not others, f"device records outside _sharding files: {others}"
    rewritten = 0
    for path in files:
        with open(path) as f:
            shardings = json.load(f)
        with open(path, "w") as f:
            json.dump({name: record for name in shardings}, f)
        rewritten += len(shardings)
    assert not any(mark in open(p, "rb").read() for p in files for mark in (b"cpu:0", b"TFRT"))
    return rewritten


def _assert_same(a, b) -> None:
    """Same tree, dtypes and values, bit for bit; ``b``'s arrays on the default device."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    assert tree_a == tree_b
    device = jax.local_devices()[0]
    for x, y in zip(leaves_a, leaves_b):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), strict=True)
        assert isinstance(y, jax.Array) and y.devices() == {device}


# --- a model folder (the shipped ones record cpu:0) ----------------------------------------------


@pytest.fixture(scope="module")
def shipped():
    """The shipped double-well model, loaded from its own folder."""
    return load_dir(os.path.join(MODEL_DIR, "double_well"))


@pytest.mark.parametrize("where", RECORDS)
def test_a_shipped_model_saved_elsewhere_loads_bit_identical(shipped, tmp_path, where):
    folder = str(tmp_path / "double_well")
    shutil.copytree(os.path.join(MODEL_DIR, "double_well"), folder)
    assert _rewrite_devices(folder, RECORDS[where]) == len(jax.tree_util.tree_leaves(
        shipped.params))
    loaded = load_dir(folder)
    _assert_same(shipped.params, loaded.params)
    assert loaded.network == shipped.network and loaded.meta == shipped.meta
    prior = csf_jax.load_prior(folder, problems.get("double_well"))
    _assert_same(shipped.params, prior.params)


def test_a_saved_prior_records_no_device_and_loads_bit_identical(shipped, tmp_path):
    path = shipped.save(str(tmp_path / "prior"))
    assert _device_files(path) == []
    _assert_same(shipped.params, csf_jax.load_prior(path, problems.get("double_well")).params)


# --- a training checkpoint -----------------------------------------------------------------------


def _abstract():
    """The shapes of a fresh state, with no device (how a resume may describe its target)."""
    return jax.eval_shape(lambda: init_state(jax.random.key(0), NET, 2, TRAIN))


def _state(seed: int):
    """A training state of ``init_state``'s tree and shapes with distinct values in every leaf."""
    leaves, tree = jax.tree_util.tree_flatten(_abstract())
    rng = np.random.default_rng(seed)
    leaves = [jax.numpy.asarray(rng.standard_normal(x.shape).astype(x.dtype)
                                if np.issubdtype(x.dtype, np.floating)
                                else rng.integers(1, 100, x.shape).astype(x.dtype))
              for x in leaves]
    return jax.tree_util.tree_unflatten(tree, leaves)


def _save_as_jax_arrays(mngr, step: int, state, meta: dict) -> None:
    """A checkpoint in the layout where orbax records each array's sharding (a state saved as
    ``jax.Array`` leaves), as runs already on disk hold them."""
    mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                            meta=ocp.args.JsonSave(meta)), force=True)


@pytest.mark.parametrize("where", RECORDS)
@pytest.mark.parametrize("layout", ["written by checkpoint.save", "with recorded shardings"])
def test_a_training_checkpoint_saved_elsewhere_resumes_bit_identical(tmp_path, where, layout):
    directory = str(tmp_path / "ckpt")
    states = {10: _state(1), 20: _state(2)}
    with checkpoint.manager(directory, TRAIN.save_every) as mngr:
        for step, state in states.items():
            if layout == "written by checkpoint.save":
                assert checkpoint.save(mngr, step, state, {**META, "step": step}, force=True)
            else:
                _save_as_jax_arrays(mngr, step, state, {**META, "step": step})
        mngr.wait_until_finished()
    rewritten = _rewrite_devices(directory, RECORDS[where])
    if layout == "with recorded shardings":
        assert rewritten == 2 * len(jax.tree_util.tree_leaves(states[10]))
    else:
        assert rewritten == 0  # checkpoint.save records no device
    logged = []
    with checkpoint.manager(directory, TRAIN.save_every) as mngr:
        for target in (_abstract(), _state(5)):
            for step, state in states.items():
                restored, meta = checkpoint.restore(mngr, target, step)
                _assert_same(state, restored)
                assert meta == {**META, "step": step}
            restored, meta = checkpoint.restore_intact(mngr, target, META, logged.append)
            _assert_same(states[20], restored)
            assert meta["step"] == 20
    assert logged == []
    assert sorted(os.listdir(directory)) == ["10", "20"]
    assert not glob.glob(f"{directory}.damaged-*")


# --- a damaged parameter folder ends in one line -------------------------------------------------


def _truncate(path) -> None:
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
@pytest.mark.parametrize("damage", ["array index", "arrays"])
def test_truncated_parameter_arrays_fail_in_one_line_and_nothing_after(tmp_path, capfd, damage):
    folder = str(tmp_path / "model")
    shutil.copytree(os.path.join(MODEL_DIR, "double_well"), folder)
    params = os.path.join(folder, "params")
    data = [p for p in _files(params) if os.sep + "d" + os.sep in p]
    top = [p for p in data if os.path.dirname(p) == os.path.join(params, "d")]
    assert top and len(data) > len(top)
    for path in top if damage == "array index" else sorted(set(data) - set(top)):
        _truncate(path)
    capfd.readouterr()
    with pytest.raises(ValueError, match=f"^model {re.escape(folder)}: the parameters in "
                                         f"{re.escape(params)} cannot be restored \\(") as caught:
        csf_jax.load_prior(folder, problems.get("double_well"))
    assert "\n" not in str(caught.value)
    gc.collect()
    time.sleep(0.3)
    gc.collect()
    err = capfd.readouterr().err
    for noise in ("Event loop is closed", "Traceback", "GeneratorExit", "WARNING", "ERROR"):
        assert noise not in err, err
