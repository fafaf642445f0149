"""Checkpoints with orbax-checkpoint: the training state plus a JSON record of what made it.

A checkpoint stores ``state = {"params", "opt_state", "step"}`` and ``meta`` (problem, dimension,
network and training configs, dataset id, seed, validation history). Saves are synchronous and
atomic (orbax writes a temporary directory and renames it when complete), so a ``kill -9`` at any
moment leaves the last complete checkpoint intact; the next run resumes from it.
"""

from __future__ import annotations

import os

import jax
import orbax.checkpoint as ocp

# The fields of ``meta`` that must agree for a checkpoint to be resumed or used.
IDENTITY = ("problem", "dim", "network", "dataset_id", "seed")


def manager(directory: str, save_every: int, keep: int = 2) -> ocp.CheckpointManager:
    """A CheckpointManager that keeps the last ``keep`` checkpoints, synchronous saves."""
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=save_every,
                                           enable_async_checkpointing=False,
                                           cleanup_tmp_directories=True)
    return ocp.CheckpointManager(os.path.abspath(directory), options=options,
                                 item_names=("state", "meta"))


def save(mngr: ocp.CheckpointManager, step: int, state, meta: dict, force: bool = False) -> bool:
    """Save ``state`` and ``meta`` at ``step`` (if due, or ``force``); True if saved."""
    return mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   meta=ocp.args.JsonSave(meta)), force=force)


def read_meta(mngr: ocp.CheckpointManager, step: int | None = None) -> dict | None:
    """The ``meta`` record of ``step`` (default: latest), or None if there is no checkpoint."""
    step = mngr.latest_step() if step is None else step
    if step is None:
        return None
    return mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]


def check_identity(found: dict, expected: dict, where: str) -> None:
    """Raise ValueError naming both sides if ``found`` was made for something else."""
    diffs = [k for k in IDENTITY if found.get(k) != expected.get(k)]
    if diffs:
        lines = "; ".join(f"{k}: checkpoint has {found.get(k)!r}, requested {expected.get(k)!r}"
                          for k in diffs)
        raise ValueError(f"checkpoint {where} does not match the requested run ({lines}). Use "
                         f"another --out directory, or the matching configuration.")


def restore(mngr: ocp.CheckpointManager, abstract_state, step: int | None = None):
    """Restore ``(state, meta)`` of ``step`` (default latest) into the structure of
    ``abstract_state`` (e.g. ``jax.eval_shape`` of a fresh state)."""
    step = mngr.latest_step() if step is None else step
    target = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, abstract_state)
    out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target),
                                                     meta=ocp.args.JsonRestore()))
    return out["state"], out["meta"]
