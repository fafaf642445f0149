"""Checkpoints with orbax-checkpoint: the training state plus a JSON record of what made it.

A checkpoint stores ``state = {"params", "opt_state", "step"}`` and ``meta`` (problem, dimension,
network and training configs, dataset id, seed, validation history). Saves are synchronous and
atomic (orbax writes a temporary directory and renames it when complete), so a ``kill -9`` at any
moment leaves the last complete checkpoint intact; the next run resumes from it.

Checkpoints do not depend on a device: the state is saved as host arrays (no sharding recorded)
and restored onto this process's default device whatever a checkpoint records, so a run started
on a GPU, or on several devices, resumes on a CPU and the other way round.

A checkpoint damaged afterwards (a truncated array file or meta record, a missing folder) is not
fatal: ``restore_intact`` resumes from the newest checkpoint that restores, moves each newer,
damaged one aside to ``<dir>.damaged-<step>`` (never deleting it) and says so in one line.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import orbax.checkpoint as ocp

from csf_jax import _store

# The fields of ``meta`` that must agree for a checkpoint to be resumed or used.
IDENTITY = ("problem", "dim", "network", "dataset_id", "seed")

# The training-config fields (``meta["train"]``) that may differ on resume: the run's length (a
# longer run continues the shorter one), the checkpoint and validation intervals, and the seed
# (compared in IDENTITY). Every other one changes the parameters a run makes.
RESUMABLE = ("steps", "save_every", "eval_every", "seed")


def manager(directory: str, save_every: int, keep: int = 2) -> ocp.CheckpointManager:
    """A CheckpointManager that keeps the last ``keep`` checkpoints, synchronous saves."""
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=save_every,
                                           enable_async_checkpointing=False,
                                           cleanup_tmp_directories=True)
    return ocp.CheckpointManager(os.path.abspath(directory), options=options,
                                 item_names=("state", "meta"))


def save(mngr: ocp.CheckpointManager, step: int, state, meta: dict, force: bool = False) -> bool:
    """Save ``state`` and ``meta`` at ``step`` (if due, or ``force``); True if saved. The state's
    arrays are saved as numpy arrays, so the checkpoint records no device."""
    state = _store.host_arrays(state)
    return mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   meta=ocp.args.JsonSave(meta)), force=force)


def read_meta(mngr: ocp.CheckpointManager, step: int | None = None) -> dict | None:
    """The ``meta`` record of ``step`` (default: latest), or None if there is no checkpoint."""
    step = mngr.latest_step() if step is None else step
    if step is None:
        return None
    return mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]


class CheckpointMismatch(ValueError):
    """An intact checkpoint made for another problem, network, dataset, seed or training
    config."""


def identity_diffs(found: dict, expected: dict) -> list[str]:
    """``field: checkpoint has X, requested Y`` for every ``IDENTITY`` field and every training
    setting outside ``RESUMABLE`` that both meta records hold and on which they differ (a record
    without ``train`` is compared on IDENTITY alone)."""
    diffs = [f"{k}: checkpoint has {found.get(k)!r}, requested {expected.get(k)!r}"
             for k in IDENTITY if found.get(k) != expected.get(k)]
    old, new = found.get("train"), expected.get("train")
    if isinstance(old, dict) and isinstance(new, dict):
        diffs += [f"train.{k}: checkpoint has {old.get(k)!r}, requested {new.get(k)!r}"
                  for k in sorted(set(old) & set(new))
                  if k not in RESUMABLE and old.get(k) != new.get(k)]
    return diffs


def check_identity(found: dict, expected: dict, where: str) -> None:
    """Raise CheckpointMismatch (a ValueError) naming both sides if ``found`` was made for
    something else (``identity_diffs``)."""
    diffs = identity_diffs(found, expected)
    if diffs:
        folder = os.path.dirname(os.path.abspath(where))
        raise CheckpointMismatch(f"checkpoint {where} does not match the requested run "
                                 f"({'; '.join(diffs)}). Use another directory (or delete "
                                 f"{folder} to train afresh), or the matching configuration.")


def restore(mngr: ocp.CheckpointManager, abstract_state, step: int | None = None):
    """Restore ``(state, meta)`` of ``step`` (default latest) into the structure of
    ``abstract_state`` (a fresh state, or its ``jax.eval_shape``). The arrays go to this process's
    default device, whatever devices the checkpoint records (``_store.restore_target``)."""
    step = mngr.latest_step() if step is None else step
    target = _store.restore_target(abstract_state)
    out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target),
                                                     meta=ocp.args.JsonRestore()))
    return out["state"], out["meta"]


def _reason(part: str, error: Exception) -> str:
    """One line saying which part of a checkpoint failed and how (the error's first line, cut)."""
    first = (str(error).strip().splitlines() or [""])[0]
    first = first if len(first) <= 100 else first[:97] + "..."
    return f"its {part} cannot be read: {type(error).__name__}: {first}"


def _try_restore(mngr: ocp.CheckpointManager, abstract_state, step: int, expected: dict):
    """``(state, meta, None)`` if ``step`` restores, else ``(None, None, reason)``. A readable
    checkpoint made for another run raises CheckpointMismatch (that is no damage)."""
    where = os.path.join(str(mngr.directory), str(step))
    try:
        found = read_meta(mngr, step)
    except Exception as e:  # noqa: BLE001  (orbax, tensorstore, JSON and OS errors alike)
        return None, None, _reason("meta record", e)
    if not isinstance(found, dict):
        return None, None, f"its meta record is not a JSON object: {found!r:.60}"
    check_identity(found, expected, where)
    damage = _store.damaged_array(os.path.join(where, "state"))
    if damage is not None:
        return None, None, f"its state cannot be read: {damage}"
    try:
        state, meta = restore(mngr, abstract_state, step)
    except Exception as e:  # noqa: BLE001
        return None, None, _reason("state", e)
    return state, meta, None


def move_aside(directory: str, step: int) -> str:
    """Rename ``directory/step`` to a free ``directory.damaged-<step>[.i]``; returns the new path."""
    base = f"{os.path.abspath(directory)}.damaged-{step}"
    target, i = base, 1
    while os.path.exists(target):
        target, i = f"{base}.{i}", i + 1
    os.rename(os.path.join(directory, str(step)), target)
    return target


def restore_intact(mngr: ocp.CheckpointManager, abstract_state, expected: dict,
                   log: Callable[[str], None]):
    """Restore the newest intact checkpoint of ``mngr``: ``(state, meta)``, or None if there is none.

    Newer checkpoints that fail to restore are moved aside (``move_aside``) with one ``log`` line
    each, naming the folder, the reason and where it went; ``mngr`` is reloaded so that later saves
    of those steps do not collide. If every checkpoint is damaged, nothing is moved and a
    RuntimeError names the directory and each reason. An intact checkpoint of another run raises
    CheckpointMismatch.
    """
    directory = str(mngr.directory)
    damaged = []
    for step in sorted(mngr.all_steps(), reverse=True):
        state, meta, reason = _try_restore(mngr, abstract_state, step, expected)
        if reason is None:
            for bad, why in damaged:
                aside = move_aside(directory, bad)
                log(f"checkpoint {os.path.join(directory, str(bad))} is damaged ({why}); moved it "
                    f"to {aside} and resuming from step {step}")
            if damaged:
                mngr.reload()
            return state, meta
        damaged.append((step, reason))
    if damaged:
        reasons = "; ".join(f"step {s}: {why}" for s, why in damaged)
        raise RuntimeError(f"no intact checkpoint in {directory} ({reasons}); move that directory "
                           f"away to start afresh")
    return None
