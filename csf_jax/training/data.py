"""Prior-ensemble datasets from particle-filter rollouts (paper Sec. 2.1, the offline stage).

A SIR filter with N particles runs over M independent simulated trajectories; at every step the
propagated (prior) ensemble is a training example. Raw, the 20-D set is M x K x N x d = 2000 x 200 x
1000 x 20 floats (32 GB), so we keep, per recorded ensemble, ``keep`` particles drawn uniformly
without replacement, every ``stride``-th step, in float16, in a memory-mapped ``.npy`` on disk:

    double_well  1000 traj x 100 steps x 256 x 1  -> 51 MB
    cauchy       1000 traj x 100 steps x 256 x 5  -> 256 MB   (stride 2)
    cubic10      2000 traj x 100 steps x 128 x 10 -> 512 MB   (stride 2)
    cubic20      2000 traj x 100 steps x 128 x 20 -> 1.0 GB   (stride 2)

Generation is jitted and vmapped over a chunk of trajectories; RAM holds one chunk. Each finished
chunk is flushed and recorded in ``meta.json``, so an interrupted generation resumes at the next
chunk. Training reads random ensembles through the memory map (RAM stays small).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from csf_jax import _checks, problems
from csf_jax.filters.pf import sir_step
from csf_jax.ssm import at_step, simulate, steps
from csf_jax.trained import model_fingerprint
from csf_jax.training.progress import Progress


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    """What to record. Defaults follow the paper for the wells (M = 1000, N = 1000).

    Attributes:
      trajectories: M.
      particles: N of the recording PF.
      keep: particles stored per ensemble.
      stride: record every stride-th step.
      seed: data seed.
      chunk: trajectories per jitted batch.
      dtype: "float16" (the shipped models' datasets: half the disk) or "float32" (for states whose
        magnitude or resolution float16 would not hold: it keeps 3 significant digits up to 65504).
    """

    trajectories: int = 1000
    particles: int = 1000
    keep: int = 256
    stride: int = 1
    seed: int = 0
    chunk: int = 50
    dtype: str = "float16"

    def __post_init__(self):
        _checks.check_fields(self)
        for f in ("trajectories", "particles", "keep", "stride", "chunk"):
            if getattr(self, f) < 1:
                raise ValueError(f"DatasetConfig.{f} must be >= 1, got {getattr(self, f)}")
        if self.trajectories < 2:
            raise ValueError(f"DatasetConfig.trajectories must be >= 2 (training holds out at "
                             f"least one for validation), got {self.trajectories}")
        if self.keep > self.particles:
            raise ValueError(f"DatasetConfig.keep ({self.keep}) cannot exceed particles "
                             f"({self.particles})")
        if self.dtype not in ("float16", "float32"):
            raise ValueError(f"DatasetConfig.dtype must be 'float16' or 'float32', got "
                             f"{self.dtype!r}")


def _config_record(config: DatasetConfig) -> dict:
    """The dataset config as hashed: the default dtype is left out, so the ids of datasets made
    before the field existed stay the same."""
    record = dataclasses.asdict(config)
    if record["dtype"] == "float16":
        del record["dtype"]
    return record


def dataset_id(problem, config: DatasetConfig) -> str:
    """A short hash naming the data: the problem (a registry name: its config; a model: its
    ``model_fingerprint``) and the dataset config."""
    if isinstance(problem, str):
        head = {"problem": problem, "problem_config": repr(problems.config(problem))}
    else:
        head = {"problem": problem.name, "model": model_fingerprint(problem)}
    text = json.dumps({**head, "dataset": _config_record(config)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def rollout_priors(model, key, num_particles: int, keep: int, stride: int):
    """One PF rollout on a fresh simulated trajectory; returns ``(S, keep, d)`` prior subsets."""
    k_sim, k_init, k_pf, k_sub = jax.random.split(key, 4)
    _, obs = simulate(model, k_sim)
    ensemble = model.initial_ensemble(k_init, num_particles)

    def step(ens, inputs):
        y, k_step, k_keep, time = inputs
        out = sir_step(at_step(model, time), k_step, ens, y)
        idx = jax.random.choice(k_keep, num_particles, (keep,), replace=False)
        return out.posterior, out.prior[idx]

    K = obs.shape[0]
    inputs = (obs, jax.random.split(k_pf, K), jax.random.split(k_sub, K), steps(K))
    _, priors = jax.lax.scan(step, ensemble, inputs)
    return priors[stride - 1::stride]


def generate(problem, config: DatasetConfig, directory: str, *, verbose: bool = True) -> str:
    """Write (or finish) the dataset of ``problem`` under ``directory``; returns the .npy path.

    problem: a ``StateSpaceModel``, or the name of a built-in problem.
    Resumable: chunks recorded as done in ``meta.json`` are skipped. A directory holding another
    problem's or config's dataset is refused.
    """
    model = problems.get(problem) if isinstance(problem, str) else problem
    name = problem if isinstance(problem, str) else model.name
    _checks.check_folder(directory, f"dataset {directory}", writable=True)
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, "ensembles.npy")
    meta_path = os.path.join(directory, "meta.json")
    ident = dataset_id(problem, config)
    steps = len(range(config.stride - 1, model.num_steps, config.stride))
    shape = (config.trajectories, steps, config.keep, model.dim)
    meta = {"problem": name, "dataset": dataclasses.asdict(config), "id": ident,
            "shape": list(shape), "chunks_done": 0}
    if os.path.exists(meta_path) and os.path.exists(path):
        old = read_meta(directory)
        if old.get("id") != ident:
            raise ValueError(f"{directory} holds dataset {old.get('id')} ({old.get('problem')}, "
                             f"{old.get('dataset')}), not {ident} ({name}, "
                             f"{dataclasses.asdict(config)}); use another directory")
        check_array_file(path, shape, np.dtype(config.dtype), directory)
        meta = old
        data = np.lib.format.open_memmap(path, mode="r+")
    else:
        data = np.lib.format.open_memmap(path, mode="w+", dtype=np.dtype(config.dtype),
                                         shape=shape)
    n_chunks = -(-config.trajectories // config.chunk)
    batch = jax.jit(jax.vmap(lambda k: rollout_priors(model, k, config.particles, config.keep,
                                                      config.stride)))
    keys = jax.random.split(jax.random.key(config.seed), config.trajectories)
    progress = Progress(f"[data {name}]", config.trajectories,
                        min(meta["chunks_done"] * config.chunk, config.trajectories),
                        unit="trajectories", verbose=verbose)
    for c in range(meta["chunks_done"], n_chunks):
        lo, hi = c * config.chunk, min((c + 1) * config.chunk, config.trajectories)
        ks = keys[lo:hi]
        if hi - lo < config.chunk:  # pad the last chunk to keep one compiled shape
            ks = jnp.concatenate([ks, keys[: config.chunk - (hi - lo)]])
        data[lo:hi] = finite_chunk(np.asarray(batch(ks)[: hi - lo]), data.dtype, name, lo, hi)
        data.flush()
        meta["chunks_done"] = c + 1
        _atomic_json(meta_path, meta)
        progress.report(hi)
    progress.close()
    return path


def finite_chunk(chunk: np.ndarray, dtype, name: str, lo: int, hi: int) -> np.ndarray:
    """``chunk`` (the priors of trajectories ``lo .. hi``) cast to the dataset's ``dtype``;
    ValueError if the rollouts hold NaN/inf, or values beyond ``dtype``'s range."""
    if not np.isfinite(chunk).all():
        raise ValueError(f"dataset of {name}: the particle-filter rollouts of trajectories "
                         f"{lo}..{hi - 1} contain NaN/inf ({int((~np.isfinite(chunk)).sum())} "
                         f"values): check the model's drift (and its noise and initial ensemble) "
                         f"for blow-up")
    out = chunk.astype(dtype)
    if not np.isfinite(out).all():
        raise ValueError(f"dataset of {name}: the rollouts of trajectories {lo}..{hi - 1} exceed "
                         f"the range of {np.dtype(dtype).name} (largest |x| "
                         f"{float(np.abs(chunk).max()):.3g}); use DatasetConfig(dtype='float32')")
    return out


def read_meta(directory: str) -> dict:
    """The ``meta.json`` of a dataset folder; one-line errors naming the file."""
    path = os.path.join(directory, "meta.json")
    meta = _checks.read_json_record(
        directory, "dataset", "not a dataset folder, or its generation never finished a chunk",
        f"delete {directory} to generate the data afresh")
    fields = ("id", "shape", "dataset", "chunks_done")
    if any(k not in meta for k in fields):
        raise ValueError(f"dataset {directory}: {path} must be a JSON object with the fields "
                         f"{', '.join(fields)}; delete {directory} to generate the data afresh")
    return meta


def check_array_file(path: str, shape: tuple, dtype, directory: str) -> None:
    """Refuse an ``.npy`` file whose header or size is not that of an array of ``shape`` and
    ``dtype`` (a truncated or foreign file), naming it; the memory map would read zeros past a
    truncation."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            found_shape, _, found_dtype = read_header(f)
            offset = f.tell()
    except (OSError, ValueError) as e:
        raise ValueError(f"dataset {directory}: {path} is not a readable .npy file "
                         f"({type(e).__name__}: {e}); delete {directory} to generate the data "
                         f"afresh") from None
    expected = offset + int(np.prod(shape)) * np.dtype(dtype).itemsize
    size = os.path.getsize(path)
    if tuple(found_shape) != tuple(shape) or np.dtype(found_dtype) != np.dtype(dtype) \
            or size != expected:
        raise ValueError(f"dataset {directory}: {path} is damaged or foreign (shape "
                         f"{tuple(found_shape)} {np.dtype(found_dtype).name}, {size} bytes; "
                         f"expected {tuple(shape)} {np.dtype(dtype).name}, {expected} bytes); "
                         f"delete {directory} to generate the data afresh")


def _atomic_json(path: str, obj) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class Dataset(NamedTuple):
    """A memory-mapped dataset: ``ensembles (M, S, keep, d)`` float16, its id and split."""

    ensembles: np.ndarray
    id: str
    train: np.ndarray  # trajectory indices used for training
    valid: np.ndarray  # held-out trajectory indices


def load(directory: str, valid_fraction: float = 0.05) -> Dataset:
    """Open a finished dataset read-only; hold out the last ``valid_fraction`` of trajectories.
    A damaged folder (meta.json, the array's size) fails with one line naming the file."""
    meta = read_meta(directory)
    M = meta["shape"][0]
    n_chunks = -(-M // meta["dataset"]["chunk"])
    if meta["chunks_done"] < n_chunks:
        raise ValueError(f"dataset {directory} is incomplete ({meta['chunks_done']}/{n_chunks} "
                         f"chunks); run the generation again to finish it")
    path = os.path.join(directory, "ensembles.npy")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"dataset {directory}: {path} is missing; delete {directory} to "
                                f"generate the data afresh")
    check_array_file(path, tuple(meta["shape"]),
                     np.dtype(meta["dataset"].get("dtype", "float16")), directory)
    arr = np.load(path, mmap_mode="r")
    n_valid = max(1, int(round(valid_fraction * M)))
    if M - n_valid < 1:
        raise ValueError(f"dataset {directory} has {M} trajectories: too few to hold out "
                         f"{n_valid} for validation and train on the rest (DatasetConfig."
                         f"trajectories >= 2)")
    idx = np.arange(M)
    return Dataset(arr, meta["id"], idx[:-n_valid], idx[-n_valid:])


def sample_batch(data: Dataset, rng: np.random.Generator, batch: int, split: str = "train"):
    """``(batch, keep, d)`` float32 ensembles at random (trajectory, step) of a split."""
    trajs = data.train if split == "train" else data.valid
    t = rng.choice(trajs, batch)
    s = rng.integers(0, data.ensembles.shape[1], batch)
    order = np.argsort(t * data.ensembles.shape[1] + s)  # sorted reads from the memory map
    out = np.empty((batch,) + data.ensembles.shape[2:], np.float32)
    out[order] = data.ensembles[t[order], s[order]]
    return out
