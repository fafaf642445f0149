"""Orbax array folders that do not depend on a device: written without shardings, restored onto
this process's default device, and checked one array at a time before orbax reads them.

Orbax records the sharding of every ``jax.Array`` it saves (``_sharding``: ``cpu:0``, ``cuda:0``,
or the device ids of a mesh), and a restore without an explicit sharding rebuilds that sharding,
failing ("Topology mismatch") wherever those devices do not exist: a model saved on a CPU would
not load on a GPU machine, a run started on a GPU would not resume on a CPU. ``host_arrays``
turns a tree's arrays into numpy before a save, so nothing device-specific is recorded, and
``restore_target`` gives every restore an explicit target on ``default_device()``, so whatever
a folder records (checkpoints already on disk record ``cpu:0``) is never consulted.

Orbax reads the arrays of a checkpoint concurrently on an asyncio loop that it closes when the
first read fails (their data on a restore, their zarr headers when it reads a checkpoint's
metadata); the reads still in flight then report into the closed loop, and Python prints a
traceback for each ("Event loop is closed", "coroutine ... ignored GeneratorExit"), long after the
one-line error. ``damaged_array`` reads every array of such a folder with TensorStore directly,
sequentially and synchronously; called before any orbax read of the folder, metadata included, it
finds a damaged folder before orbax touches it and the error path stays quiet.

The layout read is orbax's default: an OCDBT key-value store in the folder holding one zarr array
(``<name>/.zarray``, or ``<name>/zarr.json`` for zarr 3) per leaf. A folder in any other layout is
left to orbax.
"""

from __future__ import annotations

import os

import jax
import numpy as np
import tensorstore as ts

_DRIVERS = {b"/.zarray": "zarr", b"/zarr.json": "zarr3"}


def _first_line(error: Exception, limit: int = 160) -> str:
    first = (str(error).strip().splitlines() or [""])[0]
    return first if len(first) <= limit else first[:limit - 3] + "..."


def default_device() -> jax.Device:
    """The device new arrays go to in this process: ``jax.default_device`` where one is set (a
    device or a platform name), else the first local device."""
    chosen = jax.config.jax_default_device
    if isinstance(chosen, jax.Device):
        return chosen
    return jax.local_devices(backend=chosen or None)[0]


def host_arrays(tree):
    """``tree`` with its arrays as numpy arrays, for saving: orbax records a device for every
    ``jax.Array`` it saves and none for numpy ones."""
    return jax.device_get(tree)


def restore_target(tree):
    """An orbax restore target for a tree shaped like ``tree`` (arrays or ``ShapeDtypeStruct``s):
    each array leaf becomes a ``ShapeDtypeStruct`` on ``default_device()``. With a sharding on
    every leaf orbax never rebuilds the ones a folder records, so the restore works whatever
    platform and device count wrote it."""
    sharding = jax.sharding.SingleDeviceSharding(default_device())

    def leaf(x):
        if not (hasattr(x, "shape") and hasattr(x, "dtype")):
            return x
        return jax.ShapeDtypeStruct(np.shape(x), x.dtype, sharding=sharding)

    return jax.tree_util.tree_map(leaf, tree)


def stored_arrays(directory: str) -> list[tuple[str, str]] | None:
    """``(name, zarr driver)`` of every array in the OCDBT store of ``directory``, or None if the
    folder is not one (then nothing can be said about it here)."""
    if not os.path.isfile(os.path.join(directory, "manifest.ocdbt")):
        return None
    base = {"driver": "ocdbt", "base": f"file://{os.path.abspath(directory)}/"}
    keys = ts.KvStore.open(base).result().list().result()
    found = []
    for key in keys:
        for suffix, driver in _DRIVERS.items():
            if key.endswith(suffix):
                found.append((key[: -len(suffix)].decode(), driver))
    return sorted(found)


def damaged_array(directory: str) -> str | None:
    """None if every array stored in the orbax folder ``directory`` reads back in full (or the
    folder is not in the OCDBT layout); else one line naming the first array that does not, and
    why."""
    try:
        arrays = stored_arrays(directory)
    except Exception as e:  # noqa: BLE001  (tensorstore reports damage as several error types)
        return f"its array index cannot be read ({type(e).__name__}: {_first_line(e)})"
    base = f"file://{os.path.abspath(directory)}/"
    for name, driver in arrays or ():
        spec = {"driver": driver, "kvstore": {"driver": "ocdbt", "base": base, "path": name + "/"}}
        try:
            ts.open(spec, open=True).result().read().result()
        except Exception as e:  # noqa: BLE001
            return f"array {name!r} cannot be read ({type(e).__name__}: {_first_line(e)})"
    return None
