"""Reading an orbax array folder back, one array at a time, before orbax restores it.

Orbax restores the arrays of a checkpoint concurrently on an asyncio loop that it closes when the
first read fails; the reads still in flight then report into the closed loop, and Python prints a
traceback for each ("Event loop is closed", "coroutine ... ignored GeneratorExit"), long after the
one-line error. ``damaged_array`` reads every array of such a folder with TensorStore directly,
sequentially and synchronously, so a damaged folder is found before orbax touches it and the
error path stays quiet.

The layout read is orbax's default: an OCDBT key-value store in the folder holding one zarr array
(``<name>/.zarray``, or ``<name>/zarr.json`` for zarr 3) per leaf. A folder in any other layout is
left to orbax.
"""

from __future__ import annotations

import os

import tensorstore as ts

_DRIVERS = {b"/.zarray": "zarr", b"/zarr.json": "zarr3"}


def _first_line(error: Exception, limit: int = 160) -> str:
    first = (str(error).strip().splitlines() or [""])[0]
    return first if len(first) <= limit else first[:limit - 3] + "..."


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
