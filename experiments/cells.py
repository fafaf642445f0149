"""The jobs' cache of cells, checked on read: ``Cache`` is ``harness.Cache`` with a content checksum.

Each cell ``<problem>/<key>.npz`` gets a checksum file beside it, ``<key>.sha256``: the SHA-256 of
the cell's key and its arrays (``checksum``). On read, a cell whose checksum does not match (an
edited or damaged file, or a cell copied under another key), or whose mean is not the case's
``(K, d)``, or whose ``finite`` flags disagree with its mean (a NaN mean flagged finite), is
named in one warning line on stderr, moved aside to ``<key>.damaged`` and recomputed, as an
unreadable file already is. A cell without a checksum file (written before the cache kept them,
as the caches under ``results/cache`` were) is accepted after the shape and ``finite`` checks and
left as it is; rewriting such a cell is not detected, so delete a cache you do not trust.

The class lives here, not in ``experiments/harness.py``, which holds what makes a cell's key
(``harness.program_digest``).
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys

import jax
import numpy as np

import csf_jax
from experiments import harness, interrupt


def checksum(key: str, cell: harness.Cell) -> str:
    """The SHA-256 (hex) of a cell's key and contents: mean (K, d) and finite (K,) with their
    dtypes and shapes, the seconds, the compile seconds, the batch width and the machine."""
    digest = hashlib.sha256(key.encode())
    for array in (np.asarray(cell.mean), np.asarray(cell.finite)):
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    digest.update(repr((float(cell.seconds), float(cell.compile_seconds),
                        int(cell.batch))).encode())
    if cell.machine:  # a cell written before cells recorded their machine keeps its checksum
        digest.update(cell.machine.encode())
    return digest.hexdigest()


@functools.cache
def mean_shape(case: harness.Case) -> tuple:
    """``(K, d)``: the shape of a filtered mean of ``case`` (from the simulation's shapes, without
    running it)."""
    model = case.model
    truth, _ = jax.eval_shape(lambda k: csf_jax.simulate(model, k), jax.random.key(0))
    return truth.shape[0] - 1, truth.shape[1]


def problem(cell: harness.Cell, shape: tuple, stored: str | None, key: str) -> str | None:
    """What is wrong with a cell read from disk, in words, or None: a checksum ``stored`` that
    does not match, a mean not of ``shape``, ``finite`` not of ``(K,)`` or not true exactly where
    the mean is finite."""
    if stored is not None and stored != checksum(key, cell):
        return "fails its checksum (edited or damaged)"
    mean, finite = np.asarray(cell.mean), np.asarray(cell.finite)
    if mean.shape != tuple(shape) or finite.shape != tuple(shape[:1]):
        return (f"holds a mean of shape {mean.shape} and finite of shape {finite.shape}, not the "
                f"case's {tuple(shape)} and {tuple(shape[:1])}")
    if finite.dtype != bool or not np.array_equal(finite, np.isfinite(mean).all(-1)):
        return "has finite flags that disagree with its mean"
    return None


class Cache(harness.Cache):
    """``harness.Cache`` whose cells carry a checksum, checked on read (module docstring)."""

    def checksum_path(self, case: harness.Case, key: str):
        return self.path(case, key).with_suffix(".sha256")

    def load(self, case: harness.Case, key: str) -> harness.Cell | None:
        path = self.path(case, key)
        if not path.exists():
            return None
        try:
            with np.load(path) as f:
                cell = harness.Cell(f["mean"], f["finite"], float(f["seconds"]),
                                    float(f["compile_seconds"]), int(f["batch"]),
                                    harness.stored_machine(f))
        except Exception as e:  # noqa: BLE001  (truncated or foreign: zip, key, value errors)
            return self._aside(path, f"cannot be read ({type(e).__name__}: {e})")
        sums = self.checksum_path(case, key)
        stored = sums.read_text().strip() if sums.exists() else None
        wrong = problem(cell, mean_shape(case), stored, key)
        return cell if wrong is None else self._aside(path, wrong)

    def _aside(self, path, why: str) -> None:
        """Move a bad cell aside (``.damaged``) and say so in one line; None: recompute it."""
        aside = path.with_suffix(".damaged")
        os.replace(path, aside)
        self.log(f"warning: cache file {path} {why}; moved it to {aside.name} and recomputing "
                 f"the cell", file=sys.stderr)
        return None

    def save(self, case: harness.Case, key: str, cell: harness.Cell) -> None:
        cell = harness.Cell(np.asarray(cell.mean), np.asarray(cell.finite), float(cell.seconds),
                            float(cell.compile_seconds), int(cell.batch), str(cell.machine))
        path, sums = self.path(case, key), self.checksum_path(case, key)
        with interrupt.WRITING:  # an interrupt waits for the pair of files
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = sums.with_name(sums.name + ".tmp")
            tmp.write_text(checksum(key, cell) + "\n")
            os.replace(tmp, sums)
            super().save(case, key, cell)
