"""The experiments' harness: every maintained benchmark is a declaration on it.

    cases   = [Case("double_well"), Case("cauchy", particles=50), ...]      # the data
    entries = [Entry("CSF", "csf", csf_settings), Entry("EnKF", "enkf")]   # filters by name
    results = run(cases, entries, cache=Cache("results/cache"))            # cached, resumable
    write_results("results/x/results.json", results_record("x", command, rows))  # one schema

* **Data.** A ``Case`` is a problem of ``csf_jax.problems`` with its settings, R runs, N
  particles, a seed and optional missing data. Run r uses ``fold_in(key(seed), r)`` split into
  four streams: truth and observations, initial ensemble, filter, missing entries
  (``run_keys``). A run does not
  depend on how many others there are, and every filter sees the same data.
* **Filters.** An ``Entry`` names a builder of ``csf_jax.methods.REGISTRY`` (the registry the tests
  use) and its settings, possibly a function of the case (a pretrained prior, say).
* **Cache.** One ``.npz`` per (case, run, entry): the filtered means ``(K, d)``, ``finite`` and the
  run's seconds. Its key covers everything that changes the numbers: the case (the problem's full
  config), the run, a digest of the method's params, and the program the run executes
  (``program_digest``: the compiled computation's StableHLO, the model's and the filter's
  settings in it, and the jax version). A changed default, filter or model recomputes its cells
  and only those; an edit of the source that computes the same program (documentation, a
  refactoring, an option left off) recomputes none; a file written by other code is never read
  (its key differs). Writes are atomic, so a kill loses at most the batch in flight; an
  unreadable file is named, moved aside and recomputed.
* **Metrics** come from ``csf_jax.metrics``; **results** files share one schema (``SCHEMA``: the
  command, machine, versions and date, then one row per case and entry); **progress** is one line
  per batch on stderr.
* **Pages.** ``publish`` and ``replace_section`` rewrite a page's generated block; its first line
  is a hidden comment naming the command and a digest of the job's code (``made_by``,
  ``job_digest``), which ``python -m experiments.regenerate --stale`` compares with the code now.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import hashlib
import json
import os
import pathlib
import platform
import re
import sys
import time
import types
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax import metrics, problems

SCHEMA = "csf_jax.results/1"
ROOT = pathlib.Path(__file__).resolve().parents[1]
LIBRARY = pathlib.Path(csf_jax.__file__).resolve().parent
EXPERIMENTS = pathlib.Path(__file__).resolve().parent


# ------------------------------------------------------------------------------------------------
# Data
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Case:
    """The data of one benchmark column: R runs of a problem, each with its N-member ensemble.

    problem: a name of ``csf_jax.problems`` (the paper's, the zoo's, Lorenz-96's).
    settings: the problem's config overrides as ``(("num_steps", 10), ...)``.
    runs, particles, seed: R, N, and the seed of ``run_keys``.
    missing: the fraction of observation entries dropped at random (NaN: missing).
    whole_steps: the probability that a whole step has no observation.
    outage: ``(a, b)``: no observation at steps a .. b-1 (0-based), or None.
    start: the initial ensemble: "model" (``model.initial_ensemble``), "truth" (the true ``x_0``
      plus ``N(0, spread^2 I)``) or "standard" (``N(0, spread^2 I)``, far from the truth).
    spread: the std of the "truth" and "standard" starts.
    first_run: the index of the first run (tuning runs live at other indices than test runs).
    """

    problem: str
    settings: tuple = ()
    runs: int = 10
    particles: int = 1000
    seed: int = 0
    missing: float = 0.0
    whole_steps: float = 0.0
    outage: tuple | None = None
    start: str = "model"
    spread: float = 1.0
    first_run: int = 0

    @property
    def model(self):
        return problems.get(self.problem, **dict(self.settings))

    def identity(self) -> dict:
        """What the data depend on, for cache keys: every field and the problem's full config."""
        fields = dataclasses.asdict(self)
        fields["config"] = stable(problems.config(self.problem, **dict(self.settings)))
        return fields


class Data(NamedTuple):
    """A case's data: truth (R, K+1, d), obs (R, K, m), shocks (R, K) bool, ensembles (R, N, d),
    filter keys (R,)."""

    truth: np.ndarray
    obs: jax.Array
    shocks: np.ndarray
    ensembles: jax.Array
    keys: jax.Array


def run_keys(seed: int, runs, streams: int = 4):
    """``(R, streams)`` keys: run r is ``split(fold_in(key(seed), r), streams)``: truth and
    observations, initial ensemble, filter, missing entries."""
    return jax.vmap(lambda r: jax.random.split(jax.random.fold_in(jax.random.key(seed), r),
                                               streams))(jnp.asarray(runs))


@functools.partial(jax.jit, static_argnames=("case",))
def _simulate(case: Case, keys):
    model = case.model

    def one(k):
        truth, obs = csf_jax.simulate(model, k[0])
        shocks = csf_jax.shock_steps(model, k[0])
        if case.missing or case.whole_steps:
            obs = csf_jax.drop_observations(k[3], obs, case.missing, whole_steps=case.whole_steps)
        if case.outage is not None:
            steps = jnp.arange(obs.shape[0])[:, None]
            obs = jnp.where((steps >= case.outage[0]) & (steps < case.outage[1]), jnp.nan, obs)
        shape = (case.particles, model.dim)
        if case.start == "model":
            ens = model.initial_ensemble(k[1], case.particles)
        else:
            centre = truth[0] if case.start == "truth" else jnp.zeros(model.dim, truth.dtype)
            ens = centre + case.spread * jax.random.normal(k[1], shape, truth.dtype)
        return truth, obs, shocks, ens

    truth, obs, shocks, ens = jax.vmap(one)(keys)
    return truth, obs, shocks, ens, keys[:, 2]


def simulate(case: Case) -> Data:
    """The case's ``Data`` (one compiled computation for all runs)."""
    if case.start not in ("model", "truth", "standard"):
        raise ValueError(f"Case.start must be 'model', 'truth' or 'standard', got {case.start!r}")
    keys = run_keys(case.seed, np.arange(case.first_run, case.first_run + case.runs))
    truth, obs, shocks, ens, filter_keys = _simulate(case, keys)
    return Data(np.asarray(truth), obs, np.asarray(shocks), ens, filter_keys)


# ------------------------------------------------------------------------------------------------
# Filters
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Entry:
    """A filter of a benchmark: a row of its tables.

    label: the row's name ("CSF", "EnKF").
    method: a name of ``csf_jax.methods.REGISTRY``.
    settings: the builder's keyword arguments, or ``(case, model) -> dict`` for settings that depend
      on the case (a pretrained prior, a localisation).
    runs: at most this many runs of each case (None: all).
    batch: runs per vmapped call (None: all at once).
    """

    label: str
    method: str
    settings: dict | Callable[[Case, Any], dict] = dataclasses.field(default_factory=dict)
    runs: int | None = None
    batch: int | None = None

    def build(self, case: Case, model) -> csf_jax.Method:
        settings = self.settings(case, model) if callable(self.settings) else self.settings
        return csf_jax.methods.build(self.method, **settings)


LOCAL = ("letkf", "sharded_letkf", "local_csf", "local_transform", "sharded_transform")


def default_settings(name: str):
    """The settings of a registered filter joined to a benchmark by name (``--with``): its
    builder's defaults, with what depends on the model derived from it (a local filter's ring
    from the model's point sensor; the reference's own start)."""
    def settings(case: Case, model) -> dict:
        if name in LOCAL:
            from csf_jax.filters.letkf import sensor_sites

            sites = sensor_sites(model, model.initial_ensemble(jax.random.key(0), 1)[0])
            if sites is None:
                raise ValueError(f"--with {name}: model {model.name!r} is not a point sensor, "
                                 f"which a local filter needs")
            return {"localization": csf_jax.ring_localization(model.dim, sites)}
        return {"own_start": True} if name == "reference" else {}

    return settings


def extra_entries(args) -> list:
    """The entries of ``--with``: each named registered filter at its defaults (one run at a
    time for the ones that filter one run best so)."""
    return [Entry(name, name, default_settings(name), batch=1 if name in LOCAL else None)
            for name in getattr(args, "with_", None) or ()]


def stable(obj, _depth: int = 0):
    """A JSON-ready description of ``obj`` that is the same in every process: configs field by
    field, arrays by a digest of their bytes, functions by name and closure."""
    if _depth > 12:
        return "..."
    nxt = functools.partial(stable, _depth=_depth + 1)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        return repr(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {type(obj).__name__: {f.name: nxt(getattr(obj, f.name))
                                     for f in dataclasses.fields(obj)}}
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return {type(obj).__name__: {f: nxt(getattr(obj, f)) for f in obj._fields}}
    if isinstance(obj, (list, tuple)):
        return [nxt(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): nxt(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (np.ndarray, jax.Array, np.generic)):
        a = np.asarray(obj)
        return f"array{a.shape}{a.dtype}:{hashlib.sha256(a.tobytes()).hexdigest()[:16]}"
    if isinstance(obj, functools.partial):
        return {"partial": nxt(obj.func), "args": nxt(obj.args), "kw": nxt(obj.keywords)}
    if isinstance(obj, types.FunctionType):
        cells = [c.cell_contents for c in obj.__closure__ or () if _has_contents(c)]
        return {"fn": f"{obj.__module__}.{obj.__qualname__}", "closure": nxt(cells)}
    if isinstance(obj, jax.sharding.Mesh):
        return f"mesh{dict(obj.shape)}"
    return f"{type(obj).__module__}.{type(obj).__qualname__}:{obj!r}"


def _has_contents(cell) -> bool:
    try:
        cell.cell_contents  # noqa: B018
        return True
    except ValueError:  # an empty cell
        return False


def params_digest(params) -> str:
    """A digest of a method's params: every leaf's path and bytes (and a trained prior's network
    config, which its pytree holds as static data)."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(params)
    digest = hashlib.sha256()
    for path, leaf in leaves:
        digest.update(jax.tree_util.keystr(path).encode() + np.asarray(leaf).tobytes())
    if isinstance(params, csf_jax.TrainedPrior):
        digest.update(json.dumps(stable(params.network)).encode())
    return digest.hexdigest()[:16]


def _package_file(name: str) -> pathlib.Path | None:
    """The file of a dotted ``csf_jax`` or ``experiments`` module (the packages themselves
    included), or None for any other name."""
    top, *parts = name.split(".")
    base = {"csf_jax": LIBRARY, "experiments": EXPERIMENTS}.get(top)
    if base is None:
        return None
    base = base.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _package_imports(path: pathlib.Path) -> set:
    """The ``csf_jax`` and ``experiments`` modules a source file imports, anywhere in it (inside
    functions too), as files."""
    return _imports_in(source(path), LIBRARY, EXPERIMENTS)


@functools.lru_cache(maxsize=1024)
def _imports_in(text: bytes, library: pathlib.Path, experiments: pathlib.Path) -> frozenset:
    """``_package_imports`` of a source text, with the packages at ``library`` and
    ``experiments`` (cached by all three: a file is parsed once)."""
    import ast

    found = set()
    for node in ast.walk(ast.parse(text)):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        found |= {f for f in map(_package_file, names) if f is not None}
    return frozenset(found)


@functools.cache
def job_digest(*modules: str) -> str:
    """A digest of the code of a job's ``modules`` (dotted names, ``experiments.zoo``) and of
    every ``csf_jax`` and ``experiments`` module they import, transitively (``import csf_jax``
    counts the package's ``__init__`` and so what it imports): the code that made a page's
    generated block (``made_by``). Each file counts by ``code_tokens``, so an edit of its
    comments, docstrings or layout leaves the digest, and the blocks, as they were. 16 hex
    digits."""
    todo = [_package_file(m) for m in modules]
    missing = [m for m, f in zip(modules, todo) if f is None]
    if missing:
        raise ValueError(f"job_digest: no module {missing[0]!r} in csf_jax or experiments; "
                         f"name a module as experiments.<job>")
    seen: set = set()
    while todo:
        file = todo.pop()
        if file not in seen:
            seen.add(file)
            todo.extend(_package_imports(file) - seen)
    digest = hashlib.sha256()
    for file in sorted(seen):
        root = LIBRARY if file.is_relative_to(LIBRARY) else EXPERIMENTS
        label = f"{root.name}/{file.relative_to(root).as_posix()}"
        digest.update(label.encode() + b"\0" + code_tokens(source(file)))
    return digest.hexdigest()[:16]


MADE_BY = re.compile(r"<!-- made by: (?P<command>.*); code (?P<code>[0-9a-f]{16}) -->")
"""The first line of a generated block: the command that made it and its ``job_digest``."""


def made_by(command: str | None = None) -> str | None:
    """The line ``<!-- made by: COMMAND; code DIGEST -->`` for a block made by ``command``
    (``python -m experiments.<job> ...``; DIGEST: ``job_digest`` of that module). Without a
    command, the running job's, when Python runs one as ``python -m experiments.<job>``; None
    when there is none (a test calling a job's ``main``)."""
    if command is None:
        spec = getattr(sys.modules.get("__main__"), "__spec__", None)
        name = getattr(spec, "name", "") or ""
        if not name.startswith("experiments."):
            return None
        command = " ".join([f"python -m {name}", *sys.argv[1:]])
    found = re.match(r"python -m (experiments\.[\w.]+)", command)
    if found is None:
        return None
    return f"<!-- made by: {command}; code {job_digest(found.group(1))} -->"


def source(file: pathlib.Path) -> bytes:
    """The bytes of a source file."""
    return file.read_bytes()


@functools.lru_cache(maxsize=1024)
def code_tokens(text: bytes) -> bytes:
    """What ``job_digest`` reads of a Python source ``text``: its tokens, one per line as
    ``TYPE string``, without what cannot change what it computes: comments, line breaks inside
    brackets, the spaces between tokens, and statements that are only a string literal (the
    docstrings of modules, classes and functions, and those under an assignment). Indentation
    counts, as INDENT and DEDENT, and so do the ends of statements. The tokens are Python's
    (``tokenize``), so the digest of a file can differ between Python versions (an f-string is
    one token before 3.12, several after)."""
    import ast
    import io
    import tokenize

    strings = {(node.lineno, node.col_offset): (node.end_lineno, node.end_col_offset)
               for node in ast.walk(ast.parse(text))
               if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
               and isinstance(node.value.value, str)}
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.ENCODING}
    layout = {tokenize.INDENT, tokenize.DEDENT, tokenize.NEWLINE, tokenize.ENDMARKER}
    out, until, after = [], None, False
    for tok in tokenize.tokenize(io.BytesIO(text).readline):
        if tok.type in skip or (until is not None and tok.start < until):
            continue
        if after and tok.type == tokenize.NEWLINE:  # the line break that ends such a statement
            after = False
            continue
        until = strings.get(tok.start)
        after = until is not None
        if after:
            continue
        name = tokenize.tok_name[tok.type]
        out.append(name if tok.type in layout else f"{name} {tok.string}")
    return "\n".join(out).encode()


def cell_key(case: Case, run: int, method: csf_jax.Method, model,
             program: str | None = None) -> str:
    """The cache key of one run of ``method`` on ``case``: module docstring. ``program``: its
    ``program_digest``, when already computed (one per case and method)."""
    program = program_digest(case, method, model) if program is None else program
    what = {"case": case.identity(), "run": run, "params": params_digest(method.params),
            "program": program}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:20]


def program_digest(case: Case, method: csf_jax.Method, model) -> str:
    """A digest of the computation one run of ``method`` on ``case`` executes: the StableHLO
    text of ``Compiled``'s program at batch width 1 (without source locations, its constants in
    full: the model's numbers, the filter's static settings), with the jax and jaxlib versions
    that compile it. Source edits that leave the program as it was (documentation, a
    refactoring, a new option left off) keep the cells; any change of what is computed, in
    ``csf_jax`` or in the harness's runner, changes it. The method's params are arguments, not
    part of the program: ``cell_key`` digests them apart."""
    data = jax.eval_shape(lambda k: _simulate(case, k), run_keys(case.seed, np.arange(1)))
    _, obs, _, ensembles, keys = data
    text = Compiled(model).fn.lower(method, obs, ensembles, keys).as_text(debug_info=False)
    digest = hashlib.sha256(text.encode())
    digest.update(f"jax {jax.__version__} jaxlib {jax.lib.__version__}".encode())
    return digest.hexdigest()[:16]


# ------------------------------------------------------------------------------------------------
# Cache and execution
# ------------------------------------------------------------------------------------------------

class Cell(NamedTuple):
    """One run of one filter: mean (K, d), finite (K,), seconds of the run, compile seconds of
    its batch, runs in its batch, and the machine that computed it (``machine_key``; "" for a
    cell written before cells recorded it)."""

    mean: np.ndarray
    finite: np.ndarray
    seconds: float
    compile_seconds: float
    batch: int
    machine: str = ""


class Cache:
    """Cells on disk under ``root``, one ``<problem>/<key>.npz`` each (module docstring)."""

    def __init__(self, root: str | os.PathLike, log=print):
        self.root, self.log = pathlib.Path(root), log
        self.computed: list = []  # (problem, label, run) of every cell computed by this object
        self.machines: list = []  # Cell.machine of every cell ``run`` took, computed or read

    def path(self, case: Case, key: str) -> pathlib.Path:
        return self.root / case.problem / f"{key}.npz"

    def load(self, case: Case, key: str) -> Cell | None:
        path = self.path(case, key)
        if not path.exists():
            return None
        try:
            with np.load(path) as f:
                return Cell(f["mean"], f["finite"], float(f["seconds"]),
                            float(f["compile_seconds"]), int(f["batch"]), stored_machine(f))
        except Exception as e:  # noqa: BLE001  (truncated or foreign: zip, key, value errors)
            aside = path.with_suffix(".damaged")
            os.replace(path, aside)
            self.log(f"cache file {path} cannot be read ({type(e).__name__}: {e}); moved it to "
                     f"{aside.name} and recomputing the cell", file=sys.stderr)
            return None

    def save(self, case: Case, key: str, cell: Cell) -> None:
        path = self.path(case, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **cell._asdict())
        os.replace(tmp, path)


class Progress:
    """One line per batch on stderr: cells done of all, the batch, its time, an ETA."""

    def __init__(self, total: int, enabled: bool = True):
        self.total, self.done, self.enabled, self.t0 = total, 0, enabled, time.perf_counter()

    def __call__(self, text: str, cells: int) -> None:
        self.done += cells
        if self.enabled:
            spent = time.perf_counter() - self.t0
            eta = spent * (self.total - self.done) / max(self.done, 1)
            print(f"[{self.done}/{self.total}] {text} ({spent:.0f} s, ETA {eta:.0f} s)",
                  file=sys.stderr, flush=True)


class Compiled:
    """One filter on one model, vmapped over runs and compiled once per batch width:
    ``(method, data, runs)`` -> ``(means (B, K, d), finite (B, K), run seconds)``;
    ``seconds[B]`` is the compile time of width B."""

    def __init__(self, model):
        def one(m, obs, ens, key):
            result = csf_jax.run(m, obs, ens, model=model, key=key, check_finite=False)
            return result.mean, result.finite

        self.fn = jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0)))
        self.programs, self.seconds = {}, {}

    def __call__(self, method, data: Data, runs: np.ndarray):
        args = (method, data.obs[runs], data.ensembles[runs], data.keys[runs])
        if len(runs) not in self.programs:
            t0 = time.perf_counter()
            self.programs[len(runs)] = self.fn.lower(*args).compile()
            self.seconds[len(runs)] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mean, finite = jax.block_until_ready(self.programs[len(runs)](*args))
        return np.asarray(mean), np.asarray(finite), time.perf_counter() - t0


class Outcome(NamedTuple):
    """One (case, entry): ``means (R, K, d)`` and ``finite (R, K)`` of its runs, seconds per
    filter step per run, compile seconds, runs per batch, and the built ``Method``."""

    means: np.ndarray
    finite: np.ndarray
    seconds_per_step: float
    compile_seconds: float
    batch: int
    method: csf_jax.Method


def run(cases, entries, cache: Cache, progress: bool = True) -> dict:
    """Every (case, entry) computed or read from ``cache``: ``{(case, label): Outcome}``."""
    cases, entries = list(cases), list(entries)
    todo = [(c, e) for c in cases for e in entries]
    bar = Progress(sum(min(c.runs, e.runs or c.runs) for c, e in todo), progress)
    out = {}
    for case in cases:
        data, model = None, case.model
        for entry in entries:
            method = entry.build(case, model)
            runs = min(case.runs, entry.runs or case.runs)
            program = program_digest(case, method, model)
            keys = [cell_key(case, case.first_run + r, method, model, program)
                    for r in range(runs)]
            cells = [cache.load(case, k) for k in keys]
            missing = [r for r, c in enumerate(cells) if c is None]
            if len(missing) < runs:
                bar(f"{case.problem} {entry.label}: {runs - len(missing)} runs cached",
                    runs - len(missing))
            width, compute = entry.batch or len(missing) or 1, Compiled(model)
            for lo in range(0, len(missing), width):
                batch = np.asarray(missing[lo:lo + width])
                data = simulate(case) if data is None else data
                mean, finite, seconds = compute(method, data, batch)
                compile_s = compute.seconds[len(batch)]
                for j, r in enumerate(batch):
                    cells[r] = Cell(mean[j], finite[j], seconds / len(batch), compile_s,
                                    len(batch), machine_key())
                    cache.save(case, keys[r], cells[r])
                    cache.computed.append((case.problem, entry.label, case.first_run + int(r)))
                done = [int(r) + case.first_run for r in batch]
                bar(f"{case.problem} {entry.label} runs {done}: {seconds:.1f} s"
                    + (f" + compile {compile_s:.1f} s" if lo == 0 else ""), len(batch))
            cache.machines += [c.machine for c in cells]
            steps = cells[0].mean.shape[0]
            out[(case, entry.label)] = Outcome(
                np.stack([c.mean for c in cells]), np.stack([c.finite for c in cells]),
                sum(c.seconds for c in cells) / (runs * steps),
                max(c.compile_seconds for c in cells), max(c.batch for c in cells), method)
    return out


# ------------------------------------------------------------------------------------------------
# Metrics and results
# ------------------------------------------------------------------------------------------------

def summary(outcome: Outcome, data: Data, window: tuple | None = None) -> dict:
    """The row of one (case, entry): RMSE (the paper's: ``csf_jax.rmse`` over runs and steps),
    per run, per coordinate, before and after the first shock, the RMSE over ``window = (a, b)``
    of steps (per run, the time average of the RMSE over coordinates: Lorenz-96's convention),
    diverged runs, seconds per filter step and compile seconds."""
    runs = outcome.means.shape[0]
    truth = data.truth[:runs, 1:]
    ok = outcome.finite.all(-1)
    per_run = [float(metrics.rmse(m, t)) if f else float("inf")
               for m, t, f in zip(outcome.means, truth, ok)]
    row = {"runs": runs, "diverged": int((~ok).sum()),
           "rmse": float(metrics.rmse(outcome.means, truth)) if ok.all() else float("inf"),
           "rmse_per_run": per_run,
           "rmse_per_dim": float(metrics.rmse_per_dim(outcome.means, truth)) if ok.all()
           else float("inf"),
           "seconds_per_step": outcome.seconds_per_step,
           "compile_seconds": outcome.compile_seconds, "runs_at_once": outcome.batch}
    shocks = data.shocks[:runs]
    if shocks.any():
        first = np.where(shocks.any(-1), shocks.argmax(-1), shocks.shape[-1])
        before = np.arange(shocks.shape[-1])[None] < first[:, None]
        err = np.sum((outcome.means - truth) ** 2, -1)
        row["rmse_before_shock"] = float(np.sqrt(err[before].mean())) if before.any() else None
        row["rmse_after_shock"] = float(np.sqrt(err[~before].mean())) if (~before).any() else None
    if window is not None:
        a, b = window
        site = np.sqrt(np.mean((outcome.means[:, a:b] - truth[:, a:b]) ** 2, -1)).mean(-1)
        row["window"] = [a, b]
        row["window_rmse_per_run"] = [float(v) if f else float("inf") for v, f in zip(site, ok)]
    return row


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f
                        if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {"platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count(),
            "jax_backend": jax.default_backend(),
            "devices": sorted({d.device_kind for d in jax.devices()})}


MACHINE_FIELDS = ("cpu", "cpu_count", "jax_backend")
"""What a cell records of the machine that computed it: what a page's header names."""


@functools.cache
def machine_key() -> str:
    """This machine as a cell records it: ``MACHINE_FIELDS`` of ``machine()``, as JSON."""
    here = machine()
    return json.dumps({k: here[k] for k in MACHINE_FIELDS}, sort_keys=True)


def stored_machine(npz) -> str:
    """The machine a cell file (an open ``.npz``) records, or "" where it records none."""
    return str(npz["machine"]) if "machine" in npz.files else ""


def cells_machine(cache: Cache, previous=None) -> dict:
    """``machine()`` with the header's fields (``MACHINE_FIELDS``) those of the machines that
    computed the cells ``cache`` gave out, not this one's: a page re-rendered from cached cells
    names the machine that measured their seconds. A cell without a record is taken to be the
    machine the results file ``previous`` (the one the new record replaces) names, the machine
    its block was made on. Cells of several machines: their fields joined by " and "; the count
    of cells per machine is kept under "cells"."""
    fallback = None
    if previous is not None and pathlib.Path(previous).exists():
        old = read_results(previous)["machine"]
        fallback = json.dumps({k: old[k] for k in MACHINE_FIELDS}, sort_keys=True)
    counts: dict = {}
    for m in cache.machines:
        m = m or fallback or json.dumps({k: "unrecorded" for k in MACHINE_FIELDS})
        counts[m] = counts.get(m, 0) + 1
    here = machine()
    if not counts:
        return here
    found = [json.loads(m) for m in counts]
    fields = {k: " and ".join(dict.fromkeys(str(f[k]) for f in found)) for k in MACHINE_FIELDS}
    if len(set(f["cpu_count"] for f in found)) == 1:
        fields["cpu_count"] = found[0]["cpu_count"]
    return here | fields | {"cells": counts}


def versions() -> dict:
    import flax
    import optax

    return {"python": platform.python_version(), "jax": jax.__version__, "flax": flax.__version__,
            "optax": optax.__version__, "numpy": np.__version__, "csf_jax": csf_jax.__version__}


def results_record(benchmark: str, command: str, rows: list, cache: Cache | None = None,
                   previous=None, **extra) -> dict:
    """A results record of ``benchmark`` (``SCHEMA``): command, date, machine, versions, ``extra``
    fields, then ``rows`` (one dict per case and filter). Rows from the cells of ``cache``: the
    machine is the cells' (``cells_machine``, ``previous`` the results file it replaces)."""
    here = machine() if cache is None else cells_machine(cache, previous)
    return json.loads(json.dumps(
        {"schema": SCHEMA, "benchmark": benchmark, "command": command,
         "date": datetime.date.today().isoformat(), "machine": here, "versions": versions(),
         **extra, "rows": rows}, default=float))


def output(args, filename: str = "results.json"):
    """The results file a benchmark's ``publish`` writes (``--out``), or None."""
    return pathlib.Path(args.out) / filename if getattr(args, "out", None) else None


def write_results(path, record: dict) -> dict:
    """Write a results record (``results_record``) to ``path`` atomically; returns it."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(tmp, path)
    return record


def read_results(path) -> dict:
    """A results file, checked to be of ``SCHEMA``."""
    record = json.loads(pathlib.Path(path).read_text())
    if record.get("schema") != SCHEMA:
        raise ValueError(f"{path} is not a results file of schema {SCHEMA}")
    return record


def describe(case: Case, entry: Entry, outcome: Outcome) -> dict:
    """The identity part of a results row: the case, the entry and the method's full config."""
    return {"case": {k: v for k, v in dataclasses.asdict(case).items()},
            "entry": entry.label, "method": entry.method,
            "config": stable(outcome.method.config)}


# ------------------------------------------------------------------------------------------------
# Pages and command lines
# ------------------------------------------------------------------------------------------------

def table(header: list, rows: list) -> list:
    """Markdown lines of a table."""
    return (["| " + " | ".join(map(str, header)) + " |", "|" + "---|" * len(header)]
            + ["| " + " | ".join(map(str, r)) + " |" for r in rows])


def number(v, digits: int = 3) -> str:
    """``v`` with ``digits`` significant figures; "diverged" for inf, "-" for None."""
    if v is None:
        return "-"
    return "diverged" if not np.isfinite(v) else f"{v:.{digits}g}"


def replace_section(path, body: str, start: str = "<!-- results:start -->",
                    end: str = "<!-- results:end -->", command: str | None = None) -> None:
    """Replace the text between the markers of the page ``path`` with ``body``, after the line
    ``made_by(command)`` (the command that made the block and the digest of its code; none when
    no job is known). The page is rewritten atomically."""
    path = pathlib.Path(path)
    text = path.read_text()
    if start not in text or end not in text:
        raise SystemExit(f"{path} lacks the {start} / {end} markers")
    head, rest = text.split(start, 1)
    record = made_by(command)
    inside = body if record is None else f"{record}\n{body}"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{head}{start}\n{inside}\n{end}{rest.split(end, 1)[1]}")
    os.replace(tmp, path)


def int_at_least(low: int):
    """An argparse ``type``: an int ``>= low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = f"int >= {low}"
    return parse


def int_list(low: int):
    """An argparse ``type``: a comma-separated, non-empty list of ints ``>= low``."""
    item = int_at_least(low)

    def parse(text: str) -> list:
        values = [item(v.strip()) for v in text.split(",") if v.strip()]
        if not values:
            raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}")
        return values

    parse.__name__ = f"list of int >= {low}"
    return parse


def name_list(known, what: str):
    """An argparse ``type``: a comma-separated, non-empty list of names from ``known``."""

    def parse(text: str) -> list:
        names = [n.strip() for n in text.split(",") if n.strip()]
        unknown = [n for n in names if n not in known]
        if unknown or not names or len(set(names)) != len(names):
            raise argparse.ArgumentTypeError(
                f"expected distinct names from {', '.join(known)}, got {text!r}")
        return names

    parse.__name__ = f"{what} list"
    return parse


def parser(module: str, description: str,
           cache: str | None | bool = str(ROOT / "results" / "cache")) -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.<module>`` with the flags every benchmark
    has: ``--cache`` (default ``cache``; False: no cache flag) and ``--no-progress``."""
    p = argparse.ArgumentParser(prog=f"python -m experiments.{module}", description=description,
                                epilog=f"Details: the docstring of experiments/{module}.py.")
    if cache is not False:
        p.add_argument("--cache", default=cache,
                       help="folder of the cached cells (default %(default)s)")
        p.add_argument("--with", dest="with_", type=name_list(list(csf_jax.methods.REGISTRY),
                                                             "filter"), default=[],
                       help="add registered filters by name, at their defaults (csf_jax.methods."
                            "REGISTRY: a new filter joins every benchmark this way)")
    p.add_argument("--no-progress", action="store_true", help="no progress lines")
    return p


def add_sizes(p: argparse.ArgumentParser, runs: int | None = None,
              particles: int | None = None, seed: int | None = None) -> None:
    """``--runs``, ``--particles`` and ``--seed`` with these defaults (None: no such flag)."""
    for flag, default, low, what in (("--runs", runs, 1, "independent runs per case"),
                                     ("--particles", particles, 2, "ensemble size N"),
                                     ("--seed", seed, 0, "seed of the runs")):
        if default is not None:
            p.add_argument(flag, type=int_at_least(low), default=default,
                           help=f"{what} (default %(default)s)")


def add_timing(p: argparse.ArgumentParser, repeats: int, steps: int) -> None:
    """``--repeats`` timed calls of ``--filter-steps`` filter steps each, for timings."""
    p.add_argument("--repeats", type=int_at_least(1), default=repeats,
                   help="timed calls per implementation (default %(default)s)")
    p.add_argument("--filter-steps", type=int_at_least(1), default=steps,
                   help="filter steps per timed call (default %(default)s)")


def add_outputs(p: argparse.ArgumentParser, out: str, page: str | None = None) -> None:
    """``--out`` and ``--page``: opt-in, so that running a benchmark to look writes nothing; the
    help names the committed paths."""
    p.add_argument("--out", default=None, help=f"folder for the results file (the committed "
                                                f"one: {out}; default: none, only printed)")
    if page is not None:
        p.add_argument("--page", default=None, help=f"page whose generated block is rewritten "
                                                    f"(the committed one: {page})")


def add_names(p: argparse.ArgumentParser, flag: str, known, default=None,
              what: str = "name") -> None:
    """A flag taking a comma-separated list of names from ``known`` (default: ``default``, else
    all of them)."""
    p.add_argument(flag, type=name_list(list(known), what), default=list(default or known),
                   help=f"comma-separated, from {', '.join(known)} (default: "
                        f"{','.join(default or known)})")


def publish(args, record: dict, lines: list, filename: str = "results.json",
            tag: str | None = None) -> None:
    """Print a benchmark's generated block ``lines``; with ``--out``, write its results
    ``record`` there as ``filename``; with ``--page``, rewrite the page's block (markers
    ``results:<tag>:start`` / ``:end``, or ``results:start`` / ``:end`` without a tag), the
    record's command and the digest of its code on the block's first line (``made_by``)."""
    if args.out:
        write_results(pathlib.Path(args.out) / filename, record)
    if getattr(args, "page", None):
        name = "results" if tag is None else f"results:{tag}"
        replace_section(args.page, "\n".join(lines), f"<!-- {name}:start -->",
                        f"<!-- {name}:end -->", record.get("command"))
    print("\n".join(lines))


def command(module: str, argv) -> str:
    """The command line that made a results file."""
    return " ".join([f"python -m experiments.{module}", *(argv if argv is not None
                                                          else sys.argv[1:])])
