"""Remake every committed table, figure and example output, resuming where a run stopped.

    python -m experiments.regenerate [--only NAME,...] [--gpu] [--force] [--jobs N]
    python -m experiments.regenerate --list | --dry-run | --stale

``JOBS`` declares each maintained job: its name, its command line, the generated blocks of the
pages it rewrites (``(page, tag)``: between ``<!-- results:<tag>:start -->`` and ``:end``, or
``results:start`` / ``:end`` for tag None), the results files and figures it writes, and the
modules whose code makes them. A run runs each selected job that is not up to date, in order,
as a subprocess (``experiments.interrupt``: one Ctrl-C stops it and its child, exit status 130),
and prints ``[3/17] zoo_N50: started`` and ``... done in 4 min 12 s``, then a table of what it
remade and how long each job took.

* **Side by side.** With ``--jobs 2`` (the default on a machine with two cores or more) two
  jobs run at once where both may: neither is ``timed`` (its outputs quote seconds, which a
  neighbour would inflate: the table, the zoo, the costs, the profile, the benchmarks, the
  tutorial, the fits, Lorenz-96's main table and scaling: they run alone), and they write no
  file in common (a page is read, changed and written whole). A job that may start runs before
  an earlier one that must wait; each line a job prints is prefixed with its name.
* **Code of a block.** Each job writes, as the first line inside each block it makes, the
  comment ``<!-- made by: COMMAND; code DIGEST -->`` (``harness.made_by``): DIGEST is
  ``harness.job_digest`` of the job's module, the code of it and of every ``csf_jax`` and
  ``experiments`` module it imports, transitively (their tokens: comments, docstrings and
  layout do not count). A block is *stale* when it records no code,
  other code than the job's now, another command than the job's, or when the page lacks it;
  ``--stale`` lists them (and blocks that no job makes) and runs nothing.
* **Resume.** ``results/regenerate.json`` (``STATE``) records, after each job finishes, the
  digest it ran with and its seconds. A job is up to date when none of its blocks is stale, its
  results files exist, and the state records its digest (or, for a job with blocks, its blocks
  record it: a job run by hand counts). An interrupted job resumes from its own cache of cells.
* **Devices.** A job runs with ``JAX_PLATFORMS=cpu``, so that its rows are the CPU blocks on any
  machine; the jobs of the GPU blocks run with ``JAX_PLATFORMS=cuda`` and only with ``--gpu``.

The whole set takes hours on a 2-core CPU; the jobs' own docstrings say what each one measures.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import json
import os
import re
import shlex
import subprocess
import sys
import threading
import time

from experiments import harness, interrupt

ROOT = harness.ROOT
STATE = "results/regenerate.json"
SCHEMA = "csf_jax.regenerate/1"
BLOCK = re.compile(r"^<!-- (results(?::[\w.-]+)?):start -->\n(.*?)^<!-- \1:end -->$", re.S | re.M)
"""A generated block: its markers on lines of their own."""


@dataclasses.dataclass(frozen=True)
class Job:
    """One command that remakes committed outputs.

    name: what ``--only`` takes (``zoo_N50``).
    argv: the command's arguments after ``python`` (``("-m", "experiments.zoo", ...)``).
    blocks: the ``(page, tag)`` generated blocks it rewrites (tag None: ``results:start``).
    results: the results files and figures it writes (paths from the repository root).
    modules: the modules whose code (with what they import: ``harness.job_digest``) makes them.
    inputs: other files whose contents make them (the tutorial's page), in its digest too.
    gpu: its blocks are a GPU's: run only with ``--gpu``, with ``JAX_PLATFORMS=cuda``.
    timed: its outputs quote seconds measured while it runs: it runs with no other job beside it
      (``--jobs``).
    """

    name: str
    argv: tuple
    blocks: tuple = ()
    results: tuple = ()
    modules: tuple = ()
    inputs: tuple = ()
    gpu: bool = False
    timed: bool = False

    @property
    def outputs(self) -> set:
        """The files it writes: its blocks' pages and its results (two jobs that share one do
        not run side by side: a page is read, changed and written whole)."""
        return {page for page, _ in self.blocks} | set(self.results)

    @property
    def env(self) -> dict:
        """The environment the job runs with, over this process's."""
        return {"JAX_PLATFORMS": "cuda" if self.gpu else "cpu"}

    @property
    def command(self) -> str:
        """The shell command, as ``--dry-run`` prints it."""
        prefix = " ".join(f"{k}={v}" for k, v in self.env.items())
        return f"{prefix} {shlex.join(['python', *self.argv])}"

    @property
    def recorded(self) -> str:
        """The command as its blocks record it (``harness.command``: arguments joined by spaces,
        ``--no-progress`` left out)."""
        return _plain(" ".join(["python", *self.argv]))

    def digest(self) -> str:
        """The digest of its code now (uncached: the files may have changed since the last)."""
        code = harness.job_digest.__wrapped__(*self.modules)
        if not self.inputs:
            return code
        digest = hashlib.sha256(code.encode())
        for path in self.inputs:
            digest.update(path.encode() + b"\0" + (ROOT / path).read_bytes())
        return digest.hexdigest()[:16]


def job(name: str, module: str, *args: str, blocks=(), results=(), inputs=(), uses=(),
        gpu: bool = False, timed: bool = False) -> Job:
    """The ``Job`` running ``python -m experiments.<module> *args``; ``uses``: modules its
    code runs without importing them (in a subprocess), in its digest too."""
    return Job(name, ("-m", f"experiments.{module}", *args), tuple(blocks), tuple(results),
               (f"experiments.{module}", *uses), tuple(inputs), gpu, timed or gpu)


def _outputs(folder: str, page: str) -> tuple:
    return ("--out", folder, "--page", page)


ZOO, DEFAULTS, SMALL = "docs/zoo.md", "docs/defaults.md", "docs/small_ensembles.md"
L96, BENCH = "docs/lorenz96.md", "docs/benchmark.md"
CPU_BENCH = ("--torch-threads", "1", "--omp-wait-policy", "passive", *_outputs("results/bench",
                                                                              BENCH))
GPU_BENCH = ("--torch-threads", "1", *_outputs("results/bench", BENCH))

JOBS = (
    job("costs", "costs", *_outputs("results/costs", "docs/choosing.md"),
        blocks=[("docs/choosing.md", "costs")], results=["results/costs/results.json"], timed=True),
    job("costs_paper", "costs", "--paper", *_outputs("results/costs", BENCH),
        blocks=[(BENCH, "costs_paper")], results=["results/costs/results_paper.json"], timed=True),
    # the tutorial's code runs in a subprocess: the library is named, not imported
    job("tutorial", "tutorial", "docs/tutorial", inputs=["docs/tutorial.md"], uses=["csf_jax"],
        results=["docs/tutorial/output.txt", "docs/tutorial/lorenz63_tutorial.png"], timed=True),
    job("table", "table", *_outputs("results/table", "docs/results.md"), "--readme", "README.md",
        blocks=[("docs/results.md", None), ("README.md", None)],
        results=["results/table/results.json", "results/table/double_well/estimates.png"],
        timed=True),
    job("zoo_N1000", "zoo", *_outputs("results/zoo", ZOO), blocks=[(ZOO, "N1000")],
        results=["results/zoo/results_N1000.json"], timed=True),
    job("zoo_N50", "zoo", "--particles", "50", *_outputs("results/zoo", ZOO),
        blocks=[(ZOO, "N50")], results=["results/zoo/results_N50.json"], timed=True),
    job("defaults_N1000", "defaults", *_outputs("results/defaults", DEFAULTS),
        blocks=[(DEFAULTS, "N1000")], results=["results/defaults/results_N1000.json"]),
    job("defaults_N50", "defaults", "--particles", "50", *_outputs("results/defaults", DEFAULTS),
        blocks=[(DEFAULTS, "N50")], results=["results/defaults/results_N50.json"]),
    job("exact_jumps", "exact_jumps", *_outputs("results/exact_jumps", DEFAULTS),
        blocks=[(DEFAULTS, "jumps")], results=["results/exact_jumps/results.json"]),
    job("flows_N1000", "defaults", "--candidates", "CSF,mode_flow,member_flow", "--tag",
        "flows_N1000", *_outputs("results/defaults", DEFAULTS), blocks=[(DEFAULTS, "flows_N1000")],
        results=["results/defaults/results_flows_N1000.json"]),
    job("flows_N50", "defaults", "--candidates", "CSF,mode_flow,member_flow", "--particles", "50",
        "--tag", "flows_N50", *_outputs("results/defaults", DEFAULTS),
        blocks=[(DEFAULTS, "flows_N50")], results=["results/defaults/results_flows_N50.json"]),
    job("small_ensembles_N50", "small_ensembles", "--particles", "50",
        *_outputs("results/small_ensembles", SMALL), blocks=[(SMALL, "N50")],
        results=["results/small_ensembles/results_N50.json"]),
    job("small_ensembles_N1000", "small_ensembles", "--particles", "1000", "--filters",
        "CSF-G sample,Ref.", *_outputs("results/small_ensembles", SMALL),
        blocks=[(SMALL, "N1000")], results=["results/small_ensembles/results_N1000.json"]),
    job("fitting", "fitting", *_outputs("results/fitting", "docs/fitting.md"),
        blocks=[("docs/fitting.md", "evidence"), ("docs/fitting.md", "comparison"),
                ("docs/fitting.md", "fits")],
        results=["results/fitting/results.json", "docs/fitting.png"], timed=True),
    job("lorenz96", "lorenz96", *_outputs("results/lorenz96", L96), blocks=[(L96, None)],
        results=["results/lorenz96/results.json"], timed=True),
    job("lorenz96_adaptive", "lorenz96", "--study", "adaptive",
        *_outputs("results/lorenz96", L96), blocks=[(L96, "adaptive")],
        results=["results/lorenz96/results_adaptive.json"]),
    job("lorenz96_robustness", "lorenz96_robustness", *_outputs("results/lorenz96", L96),
        blocks=[(L96, "robustness")], results=["results/lorenz96/results_robustness.json",
                                               "docs/lorenz96_robustness.png"]),
    job("lorenz96_scaling", "lorenz96_scaling", *_outputs("results/lorenz96", L96),
        blocks=[(L96, "scaling")], results=["results/lorenz96/scaling.json"], timed=True),
    job("bench_kalman", "bench", *CPU_BENCH, blocks=[(BENCH, "kalman_L20")],
        results=["results/bench/results_kalman_L20.json"], timed=True),
    job("bench_clipped", "bench", "--guidance", "clipped", "--steps", "500", *CPU_BENCH,
        blocks=[(BENCH, "clipped_L500")], results=["results/bench/results_clipped_L500.json"],
        timed=True),
    job("profile", "profile", *_outputs("results/profile", BENCH), blocks=[(BENCH, "profile")],
        results=["results/profile/results.json"], timed=True),
    job("lorenz96_scaling_gpu", "lorenz96_scaling", *_outputs("results/lorenz96", L96),
        blocks=[(L96, "scaling_gpu")], results=["results/lorenz96/scaling_gpu.json"], gpu=True),
    job("bench_kalman_gpu", "bench", "--dims", "1,10", "--device", "cuda", "--compile-mode",
        "default", *GPU_BENCH, blocks=[(BENCH, "kalman_L20_gpu")],
        results=["results/bench/results_kalman_L20_gpu.json"], gpu=True),
    job("bench_clipped_gpu", "bench", "--dims", "1,10", "--guidance", "clipped", "--steps", "500",
        "--device", "cuda", "--compile-mode", "reduce-overhead", *GPU_BENCH,
        blocks=[(BENCH, "clipped_L500_gpu")],
        results=["results/bench/results_clipped_L500_gpu.json"], gpu=True),
)
GPU_JOBS = {j.name for j in JOBS if j.gpu}
DEFAULT_WIDTH = min(2, os.cpu_count() or 1)
"""``--jobs``' default: two jobs side by side on a machine with two cores or more. A job's
compilation runs on one core, so two jobs that time nothing keep both busy where one leaves one
idle for much of its time."""


# ------------------------------------------------------------------------------------------------
# Blocks
# ------------------------------------------------------------------------------------------------

def _plain(command: str) -> str:
    """A recorded command without ``--no-progress`` (which changes no output)."""
    return " ".join(w for w in command.split(" ") if w != "--no-progress")


def label(page: str, tag: str | None) -> str:
    """``docs/zoo.md N50``, or the page alone for its untagged block."""
    return page if tag is None else f"{page} {tag}"


def page_blocks(text: str) -> dict:
    """``{tag: body}`` of a page's generated blocks (tag None: ``results:start``)."""
    return {(None if name == "results" else name.split(":", 1)[1]): body
            for name, body in BLOCK.findall(text)}


def recorded(body: str) -> tuple | None:
    """``(command, digest)`` of a block's first line (``harness.MADE_BY``), or None."""
    found = harness.MADE_BY.match(body.split("\n", 1)[0].strip())
    return None if found is None else (found["command"], found["code"])


def pages() -> list:
    """The pages that may hold generated blocks: README.md and docs/ (paths from the root)."""
    found = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [p.relative_to(ROOT).as_posix() for p in found if p.is_file()]


def stale_blocks(jobs=None) -> tuple:
    """``(stale, count)``: ``[(page, tag, job name or None, why)]`` for every block of a page
    that is stale (module docstring) or that no job makes, and the number of blocks looked at."""
    jobs = JOBS if jobs is None else jobs
    owner = {block: j for j in jobs for block in j.blocks}
    digests = {j.name: j.digest() for j in jobs}
    found, stale = {}, []
    for page in sorted(set(pages()) | {p for p, _ in owner}):
        path = ROOT / page
        found |= {(page, t): b for t, b in
                  (page_blocks(path.read_text()) if path.is_file() else {}).items()}
    for (page, tag), body in found.items():
        j = owner.get((page, tag))
        why = "no job makes it" if j is None else _why(j, body, digests[j.name])
        if why:
            stale.append((page, tag, None if j is None else j.name, why))
    missing = [(p, t, j.name, "the page lacks the block")
               for (p, t), j in owner.items() if (p, t) not in found]
    return stale + missing, len(found) + len(missing)


def _why(j: Job, body: str, digest: str) -> str | None:
    """Why a block of job ``j`` is stale, or None when it records the job's code and command."""
    made = recorded(body)
    if made is None:
        return "records no code"
    if made[1] != digest:
        return f"code changed (block {made[1]}, now {digest})"
    if _plain(made[0]) != j.recorded:
        return f"made by another command: {made[0]}"
    return None


# ------------------------------------------------------------------------------------------------
# State and running
# ------------------------------------------------------------------------------------------------

def read_state() -> dict:
    """``{job name: {"code", "seconds", "date", "command"}}`` of ``STATE`` ({} if none)."""
    path = ROOT / STATE
    if not path.exists():
        return {}
    try:
        record = json.loads(path.read_text())
        if record.get("schema") != SCHEMA:
            raise ValueError(record.get("schema"))
        return dict(record["jobs"])
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        print(f"python -m experiments.regenerate: {STATE} is unreadable ({e}); every job counts "
              f"as not run", file=sys.stderr)
        return {}


def write_state(state: dict) -> None:
    """Write ``STATE`` atomically (an interrupt waits for it)."""
    path = ROOT / STATE
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with interrupt.WRITING:
        tmp.write_text(json.dumps({"schema": SCHEMA, "jobs": state}, indent=1, sort_keys=True)
                       + "\n")
        os.replace(tmp, path)


def up_to_date(j: Job, state: dict, stale_names: set, digest: str) -> bool:
    """No stale block, every results file there, and its code recorded (module docstring)."""
    if j.name in stale_names or not all((ROOT / r).exists() for r in j.results):
        return False
    return state.get(j.name, {}).get("code") == digest or bool(j.blocks)


def duration(seconds: float) -> str:
    """``42 s``, ``4 min 12 s``, ``3 h 5 min``."""
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {s % 3600 // 60} min"


def run_job(j: Job) -> int:
    """Run ``j`` in the repository root (its output on this terminal); its exit status."""
    env = {**os.environ, **j.env}
    return interrupt.run([sys.executable, *j.argv], cwd=ROOT, env=env).returncode


def _relay(child, name: str) -> None:
    """Print each line ``child`` writes, prefixed with its job's name (side by side)."""
    for line in child.stdout:
        print(f"[{name}] {line.rstrip()}", flush=True)


def may_start(j: Job, running: list) -> bool:
    """Whether ``j`` may start beside the ``running`` jobs: a timed job only alone, nothing
    beside a timed one, and no two jobs that write the same file (``Job.outputs``)."""
    if not running:
        return True
    return not j.timed and not any(r.timed or j.outputs & r.outputs for r in running)


def run_side_by_side(todo: list, width: int, finish) -> None:
    """Run ``todo`` (``(step, job)`` pairs, in order) up to ``width`` at a time (``may_start``:
    a later job starts before a waiting one where only it may), each job's output prefixed
    with its name; ``finish(step, job, status, seconds)`` as each ends."""
    pending, running = list(todo), {}
    while pending or running:
        for step, j in list(pending):
            if len(running) >= width:
                break
            if not may_start(j, [r[1] for r in running.values()]):
                continue
            pending.remove((step, j))
            print(f"{step}: started ({j.command})", flush=True)
            child = interrupt.spawn([sys.executable, *j.argv], cwd=ROOT,
                                    env={**os.environ, **j.env}, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True, bufsize=1)
            relay = threading.Thread(target=_relay, args=(child, j.name), daemon=True)
            relay.start()
            running[child] = (step, j, time.perf_counter(), relay)
        time.sleep(0.2)
        for child in [c for c in running if c.poll() is not None]:
            step, j, t0, relay = running.pop(child)
            relay.join()
            interrupt.CHILDREN.discard(child)
            with interrupt.WRITING:  # an interrupt in flight ends the process first
                pass
            finish(step, j, child.returncode, time.perf_counter() - t0)


def columns(rows: list) -> list:
    """Lines of ``rows`` (lists of strings) in left-aligned columns."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def blocks_text(j: Job) -> str:
    return ", ".join(label(p, t) for p, t in j.blocks) or "-"


def run_all(jobs, force: bool = False, gpu: bool = False, dry: bool = False,
            width: int = 1) -> int:
    """Run each of ``jobs`` that is not up to date (all with ``force``; GPU jobs only with
    ``gpu``), in order, up to ``width`` side by side (``run_side_by_side``); print the progress
    and the summary; 0 if none failed, else 1."""
    state = read_state()
    stale_names = {name for _, _, name, _ in stale_blocks()[0]}
    rows, failed, todo, digests = {}, [], [], {}
    for i, j in enumerate(jobs, 1):
        step = f"[{i}/{len(jobs)}] {j.name}"
        digest, last = j.digest(), state.get(j.name, {}).get("seconds")
        if j.gpu and not gpu:
            rows[step] = [j.name, blocks_text(j), "skipped: needs a GPU (--gpu)", "-"]
            print(f"{step}: skipped, its blocks are a GPU's (--gpu on a machine with one)")
        elif not force and up_to_date(j, state, stale_names, digest):
            took = "-" if last is None else f"{duration(last)} last time"
            rows[step] = [j.name, blocks_text(j), "up to date", took]
            print(f"{step}: up to date (code {digest})")
        elif dry:
            print(f"{step}: {j.command}")
        else:
            todo.append((step, j))
            digests[step] = digest
    if dry:
        return 0

    def finish(step: str, j: Job, code: int, seconds: float) -> None:
        if code != 0:
            failed.append(j.name)
            rows[step] = [j.name, blocks_text(j), f"failed (exit {code})", duration(seconds)]
            print(f"{step}: failed with exit status {code} after {duration(seconds)}",
                  flush=True)
            return
        state[j.name] = {"code": digests[step], "seconds": round(seconds, 1),
                         "command": j.recorded, "date": datetime.date.today().isoformat()}
        write_state(state)
        rows[step] = [j.name, blocks_text(j), "remade", duration(seconds)]
        print(f"{step}: done in {duration(seconds)}", flush=True)

    if width > 1:
        run_side_by_side(todo, width, finish)
    else:
        for step, j in todo:
            print(f"{step}: started ({j.command})", flush=True)
            t0 = time.perf_counter()
            finish(step, j, run_job(j), time.perf_counter() - t0)
    order = [f"[{i}/{len(jobs)}] {j.name}" for i, j in enumerate(jobs, 1)]
    print("\n" + "\n".join(columns([["job", "blocks", "result", "time"]]
                                    + [rows[s] for s in order if s in rows])))
    if failed:
        print(f"python -m experiments.regenerate: {len(failed)} job(s) failed "
              f"({', '.join(failed)}); their output is above; rerun to retry them",
              file=sys.stderr)
        return 1
    return 0


def list_jobs(jobs) -> None:
    """``--list``: each job's command, blocks, results and last time."""
    state = read_state()
    for j in jobs:
        last = state.get(j.name, {}).get("seconds")
        print(f"{j.name}{' (GPU)' if j.gpu else ''}: {j.command}")
        print(f"    blocks: {blocks_text(j)}")
        print(f"    writes: {', '.join(j.results) or '-'}")
        if last is not None:
            print(f"    last run: {duration(last)}, code {state[j.name].get('code')}")


def print_stale() -> None:
    """``--stale``: the stale blocks, one a line, or 'no stale block'."""
    stale, count = stale_blocks()
    if not stale:
        print(f"no stale block ({count} blocks)")
        return
    for page, tag, name, why in stale:
        print(f"{label(page, tag)}" + (f" ({name})" if name else "") + f": {why}")
    gpu = any(name in GPU_JOBS for _, _, name, _ in stale)
    print(f"{len(stale)} of {count} blocks stale; python -m experiments.regenerate remakes them"
          + (" (with --gpu, on a machine with one, those of a GPU)" if gpu else ""))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m experiments.regenerate",
        description="Remake every committed table, figure and example output: each job that "
                    "is not up to date, in order; a rerun resumes.",
        epilog="Details: the docstring of experiments/regenerate.py.")
    p.add_argument("--only", type=harness.name_list([j.name for j in JOBS], "job"),
                   metavar="NAME[,NAME...]",
                   help="only these jobs (comma-separated names, as --list shows them)")
    p.add_argument("--gpu", action="store_true", help="also run the jobs of the GPU blocks")
    p.add_argument("--force", action="store_true", help="run the jobs even when up to date")
    p.add_argument("--jobs", type=harness.int_at_least(1), default=DEFAULT_WIDTH, metavar="N",
                   help="run up to N jobs side by side: those that time nothing and write "
                        "different files (default: %(default)s, this machine's cores up to 2)")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--list", action="store_true", help="list the jobs and run nothing")
    what.add_argument("--dry-run", action="store_true",
                      help="print the commands that would run and run nothing")
    what.add_argument("--stale", action="store_true",
                      help="list the blocks whose code changed or is not recorded; run nothing")
    args = p.parse_args(argv)
    jobs = [j for j in JOBS if args.only is None or j.name in args.only]
    if args.list:
        list_jobs(jobs)
        return 0
    if args.stale:
        print_stale()
        return 0
    return run_all(jobs, force=args.force, gpu=args.gpu, dry=args.dry_run, width=args.jobs)


if __name__ == "__main__":
    sys.exit(interrupt.main(main, "regenerate", f"the finished jobs are recorded in {STATE}, "
                                                "rerun to resume"))
