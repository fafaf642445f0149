"""Timers that leave compilation out: every time an experiment prints or records is the run of an
already compiled program, with the compile time reported on its own."""

from __future__ import annotations

import time
import weakref

import jax

_COMPILED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # fn -> {shapes: executable}


def compiled(fn, *args):
    """``(executable, compile_s)`` of the ``jax.jit`` function ``fn`` for ``args``' shapes and
    dtypes, compiled once per (fn, shapes) and kept while ``fn`` lives (``compile_s`` is 0.0 when
    reused)."""
    leaves = jax.tree_util.tree_leaves(args)
    key = (jax.tree_util.tree_structure(args),
           tuple((getattr(a, "shape", ()), str(getattr(a, "dtype", type(a)))) for a in leaves))
    known = _COMPILED.setdefault(fn, {})
    if key in known:
        return known[key], 0.0
    t0 = time.perf_counter()
    known[key] = fn.lower(*args).compile()
    return known[key], time.perf_counter() - t0


def timed(fn, *args):
    """``(out, run_s, compile_s)``: ``fn`` (``jax.jit``) compiled for ``args``, then run once and
    waited for; ``run_s`` excludes compilation."""
    exe, compile_s = compiled(fn, *args)
    t0 = time.perf_counter()
    out = jax.block_until_ready(exe(*args))
    return out, time.perf_counter() - t0, compile_s
