"""The jobs' command lines under misuse: an edited or misshapen cached cell is named and
recomputed; flags given explicitly win over ``--quick``; one Ctrl-C stops a job with status 130
and one line; a bad path or number ends in argparse's one-line error naming the flag before any
work."""

import importlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from experiments import bench, cells, cli, harness, interrupt, train, tutorial
from experiments import run as main_job

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CASE = harness.Case("double_well", settings=(("num_steps", 5),), runs=2, particles=20)
ENKF = [harness.Entry("EnKF", "enkf")]


# ------------------------------------------------------------------------------------------------
# The cache's checksum
# ------------------------------------------------------------------------------------------------

def _cached(tmp_path):
    """A cache of the EnKF's two runs on ``CASE``: its means and its cell files."""
    found = harness.run([CASE], ENKF, cells.Cache(tmp_path), progress=False)
    return found[(CASE, "EnKF")].means, sorted((tmp_path / "double_well").glob("*.npz"))


def _rerun(tmp_path):
    cache = cells.Cache(tmp_path)
    found = harness.run([CASE], ENKF, cache, progress=False)
    return found[(CASE, "EnKF")].means, cache


def _rewrite(path, **changes):
    """Write the cell ``path`` again as a valid npz with ``changes`` to its arrays."""
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    np.savez(path, **(arrays | changes))


@pytest.mark.parametrize("edit", ["times 10", "nan"])
def test_an_edited_cell_fails_its_checksum_and_is_recomputed(tmp_path, capsys, edit):
    means, paths = _cached(tmp_path)
    with np.load(paths[0]) as f:
        mean = f["mean"] * 10 if edit == "times 10" else np.full_like(f["mean"], np.nan)
    _rewrite(paths[0], mean=mean)
    again, cache = _rerun(tmp_path)
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"warning: cache file {paths[0]} fails its checksum (edited or damaged); "
                     f"moved it to {paths[0].stem}.damaged and recomputing the cell"]
    assert len(cache.computed) == 1
    np.testing.assert_array_equal(again, means)


def test_a_cell_copied_under_another_key_fails_its_checksum(tmp_path, capsys):
    means, paths = _cached(tmp_path)
    paths[0].write_bytes(paths[1].read_bytes())
    again, cache = _rerun(tmp_path)
    assert "fails its checksum" in capsys.readouterr().err
    np.testing.assert_array_equal(again, means)


def test_cells_without_a_checksum_are_read_as_they_are(tmp_path, capsys):
    """A cache written before the checksum (``harness.Cache``) keeps working, unchanged."""
    harness.run([CASE], ENKF, harness.Cache(tmp_path), progress=False)
    files = {p: p.stat().st_mtime_ns for p in (tmp_path / "double_well").iterdir()}
    _, cache = _rerun(tmp_path)
    assert cache.computed == [] and capsys.readouterr().err == ""
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "double_well").iterdir()} == files


@pytest.mark.parametrize("edit", ["shape", "nan"])
def test_a_cell_without_a_checksum_is_still_checked(tmp_path, capsys, edit):
    harness.run([CASE], ENKF, harness.Cache(tmp_path), progress=False)
    means, _ = _rerun(tmp_path)
    path = sorted((tmp_path / "double_well").glob("*.npz"))[0]
    with np.load(path) as f:
        mean, finite = f["mean"], f["finite"]
    if edit == "shape":
        _rewrite(path, mean=mean[:3], finite=finite[:3])
        why = "holds a mean of shape (3, 1) and finite of shape (3,), not the case's (5, 1) and (5,)"
    else:
        _rewrite(path, mean=np.full_like(mean, np.nan))
        why = "has finite flags that disagree with its mean"
    again, cache = _rerun(tmp_path)
    err = capsys.readouterr().err
    assert f"warning: cache file {path} {why}; moved it to" in err and len(cache.computed) == 1
    np.testing.assert_array_equal(again, means)


# ------------------------------------------------------------------------------------------------
# The machine a cell was computed on
# ------------------------------------------------------------------------------------------------

OTHER = json.dumps({"cpu": "Other CPU", "cpu_count": 64, "jax_backend": "cpu"}, sort_keys=True)


def _record(cache, previous=None):
    return harness.results_record("demo", "python -m experiments.demo", [], cache, previous)


def test_a_cell_records_its_machine_and_a_record_of_cached_cells_names_it(tmp_path):
    _, paths = _cached(tmp_path)
    here = json.loads(harness.machine_key())
    assert _record(_rerun(tmp_path)[1])["machine"]["cpu"] == here["cpu"]
    for path in paths:  # cells computed on another machine, checksums and all
        with np.load(path) as f:
            cell = harness.Cell(f["mean"], f["finite"], float(f["seconds"]),
                                float(f["compile_seconds"]), int(f["batch"]), OTHER)
        key = path.stem
        path.with_suffix(".sha256").write_text(cells.checksum(key, cell) + "\n")
        _rewrite(path, machine=np.asarray(OTHER))
    again, cache = _rerun(tmp_path)
    machine = _record(cache)["machine"]
    assert cache.computed == [] and machine["cpu"] == "Other CPU"
    assert machine["cells"] == {OTHER: 2}
    paths[0].unlink()  # one cell recomputed here: the header names both machines
    _, cache = _rerun(tmp_path)
    machine = _record(cache)["machine"]
    assert sorted(machine["cpu"].split(" and ")) == sorted(["Other CPU", here["cpu"]])
    assert sorted(machine["cells"].values()) == [1, 1]


def test_a_relabelled_machine_fails_the_checksum(tmp_path, capsys):
    _, paths = _cached(tmp_path)
    _rewrite(paths[0], machine=np.asarray(OTHER))
    _, cache = _rerun(tmp_path)
    assert "fails its checksum" in capsys.readouterr().err and len(cache.computed) == 1


def test_cells_without_a_machine_are_the_replaced_record_s(tmp_path):
    """Cells written before cells recorded their machine: the machine the block they made
    names (the results file the new record replaces), else "unrecorded"."""
    harness.run([CASE], ENKF, harness.Cache(tmp_path), progress=False)
    for path in (tmp_path / "double_well").glob("*.npz"):
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files if k != "machine"}
        np.savez(path, **arrays)
    _, cache = _rerun(tmp_path)
    assert _record(cache)["machine"]["cpu"] == "unrecorded"
    old = _record(None)
    old["machine"] |= json.loads(OTHER)
    harness.write_results(tmp_path / "results.json", old)
    assert _record(cache, tmp_path / "results.json")["machine"]["cpu"] == "Other CPU"


# ------------------------------------------------------------------------------------------------
# --quick and explicit flags
# ------------------------------------------------------------------------------------------------

class _Stop(Exception):
    pass


def _stop_at(monkeypatch, module, name, seen: list):
    """Replace ``module.name`` by a function that records its arguments and stops the job."""
    def record(*args, **kwargs):
        seen.append(args)
        raise _Stop

    monkeypatch.setattr(module, name, record)


@pytest.mark.parametrize("argv,runs,particles", [
    ([], 2, 100), (["--runs", "10"], 10, 100), (["--particles", "1000"], 2, 1000),
    (["--runs", "3", "--particles", "50"], 3, 50)])
def test_explicit_flags_win_over_quick_in_the_main_job(tmp_path, monkeypatch, argv, runs,
                                                       particles):
    seen = []
    _stop_at(monkeypatch, harness, "run", seen)
    with pytest.raises(_Stop):
        main_job.main(["double_well", "--quick", "--methods", "EnKF", "--sf-runs", "1",
                       "--cache", str(tmp_path), *argv])
    (case,), _, _ = seen[0]
    assert (case.runs, case.particles, dict(case.settings)) == (runs, particles,
                                                                {"num_steps": 10})


CACHED_JOBS = [("run", ["double_well", "--methods", "EnKF"]), ("table", []), ("zoo", []),
               ("small_ensembles", []), ("defaults", []), ("lorenz96", []),
               ("lorenz96_robustness", []), ("exact_jumps", [])]


@pytest.mark.parametrize("job,argv", CACHED_JOBS, ids=[j for j, _ in CACHED_JOBS])
def test_every_cached_job_checks_its_cells(job, argv, tmp_path, monkeypatch):
    seen = []
    _stop_at(monkeypatch, harness, "run", seen)
    with pytest.raises(_Stop):
        importlib.import_module(f"experiments.{job}").main([*argv, "--cache", str(tmp_path)])
    assert type(seen[0][2]) is cells.Cache


def test_without_quick_the_main_job_runs_the_tables_setting(tmp_path, monkeypatch):
    seen = []
    _stop_at(monkeypatch, harness, "run", seen)
    with pytest.raises(_Stop):
        main_job.main(["double_well", "--methods", "EnKF", "--cache", str(tmp_path)])
    (case,), _, _ = seen[0]
    assert (case.runs, case.particles, case.settings) == (main_job.RUNS, main_job.PARTICLES, ())


def test_explicit_flags_win_over_quick_in_the_benchmark(monkeypatch):
    seen = []
    _stop_at(monkeypatch, bench, "measure", seen)
    with pytest.raises(_Stop):
        bench.main(["--quick", "--impls", "jax", "--dims", "1", "--filter-steps", "3"])
    spec, args, _ = seen[0]
    assert (spec["d"], spec["N"], spec["filter_steps"], args.repeats) == (1, 256, 3, 1)


# ------------------------------------------------------------------------------------------------
# Bad paths and numbers: refused before any work
# ------------------------------------------------------------------------------------------------

@pytest.fixture
def no_work(monkeypatch):
    """Every job's work raises: a check that comes too late fails the test at once."""
    def work(*args, **kwargs):
        raise AssertionError("the job started its work before checking its arguments")

    for module, name in ((harness, "run"), (bench, "measure"), (train, "train_prior"),
                         (interrupt, "run"), (tutorial, "run")):
        monkeypatch.setattr(module, name, work)


PAGE = "# a page\n<!-- results:start -->\n<!-- results:end -->\n"
PATH_CASES = [  # job, argv ({file}: an existing file, {dir}: a folder, {page}: a page), flag, words
    ("run", ["double_well", "--quick", "--out", "{file}"], "--out", "is a file, not a folder"),
    ("run", ["double_well", "--cache", "{file}/c"], "--cache", "which is a file, not a folder"),
    ("train", ["double_well", "--out", "{file}"], "--out", "is a file, not a folder"),
    ("table", ["--out", "{file}"], "--out", "is a file"),
    ("table", ["--page", "{dir}/missing.md"], "--page", "does not exist"),
    ("table", ["--readme", "{dir}"], "--readme", "is a folder, not a page"),
    ("zoo", ["--page", "{dir}/missing.md"], "--page", "does not exist"),
    ("zoo", ["--page", "{page}"], "--page", "lacks the <!-- results:N1000:start -->"),
    ("zoo", ["--cache", "{file}"], "--cache", "is a file"),
    ("small_ensembles", ["--page", "{dir}/missing.md"], "--page", "does not exist"),
    ("small_ensembles", ["--out", "{file}"], "--out", "is a file"),
    ("small_ensembles", ["--cache", "{file}"], "--cache", "is a file"),
    ("defaults", ["--page", "{page}"], "--page", "lacks the <!-- results:N1000:start -->"),
    ("defaults", ["--tag", "flows_N50", "--page", "{page}"], "--page",
     "lacks the <!-- results:flows_N50:start -->"),
    ("lorenz96", ["--out", "{file}"], "--out", "is a file"),
    ("lorenz96", ["--study", "adaptive", "--page", "{page}"], "--page", "results:adaptive:start"),
    ("lorenz96_robustness", ["--cache", "{file}"], "--cache", "is a file"),
    ("lorenz96_scaling", ["--dims", "40", "--page", "{page}"], "--page",
     "lacks the <!-- results:scaling"),
    ("bench", ["--impls", "jax", "--out", "{file}"], "--out", "is a file"),
    ("bench", ["--impls", "jax", "--page", "{page}"], "--page", "lacks the <!-- results:kalman_L20"),
    ("tutorial", ["{file}"], "OUT", "is a file, not a folder"),
    ("lorenz96_scaling", ["--radius", "nan"], "--radius", "must be a finite number > 0, got 'nan'"),
    ("lorenz96_scaling", ["--radius", "-1"], "--radius", "got '-1'"),
    ("lorenz96_scaling", ["--inflation", "0"], "--inflation", "got '0'"),
    ("lorenz96_scaling", ["--inflation", "inf"], "--inflation", "got 'inf'"),
    ("lorenz96_scaling", ["--radius", "x"], "--radius", "expected a number, got 'x'"),
]


@pytest.mark.parametrize("job,argv,flag,words", PATH_CASES,
                         ids=[f"{c[0]} {' '.join(c[1])}" for c in PATH_CASES])
def test_bad_paths_and_numbers_are_refused_before_any_work(job, argv, flag, words, tmp_path,
                                                           capsys, no_work):
    (tmp_path / "file").write_text("x")
    (tmp_path / "page.md").write_text(PAGE)
    argv = [a.format(file=tmp_path / "file", dir=tmp_path, page=tmp_path / "page.md")
            for a in argv]
    if "--cache" not in argv and job not in ("train", "tutorial", "bench", "lorenz96_scaling"):
        argv += ["--cache", str(tmp_path / "cache")]
    with pytest.raises(SystemExit) as exit_:
        importlib.import_module(f"experiments.{job}").main(argv)
    assert exit_.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].startswith(f"python -m experiments.{job}: error: argument {flag}: "), lines
    assert words in lines[-1], lines[-1]
    assert not (tmp_path / "cache").exists()


def test_a_folder_to_create_and_a_page_with_its_markers_pass(tmp_path):
    assert cli.folder_problem(str(tmp_path / "new" / "deeper")) is None
    assert cli.folder_problem(str(tmp_path)) is None
    (tmp_path / "page.md").write_text(PAGE.replace("results:", "results:N50:"))
    assert cli.page_problem(str(tmp_path / "page.md"), "N50") is None
    assert "lacks" in cli.page_problem(str(tmp_path / "page.md"))


# ------------------------------------------------------------------------------------------------
# Ctrl-C
# ------------------------------------------------------------------------------------------------

def _interrupt(command: list, wait_for: str, timeout: float = 120.0):
    """Start ``command``, send it one SIGINT after ``wait_for`` appears on its stderr; its
    status, its stderr and the seconds it took to end after the signal."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if wait_for in line:
                break
        assert proc.poll() is None, "".join(seen)
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=timeout)
        return proc.returncode, "".join(seen) + err, time.perf_counter() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_one_ctrl_c_stops_the_main_job_and_keeps_its_cells(tmp_path):
    status, err, seconds = _interrupt(
        [sys.executable, "-m", "experiments.run", "double_well", "--quick", "--methods",
         "EnKF,PF,Ref.", "--out", str(tmp_path)], "double_well EnKF runs")
    assert status == 130 and seconds < 20, err
    assert err.strip().splitlines()[-1] == ("python -m experiments.run: interrupted; cached cells "
                                            "are kept, rerun to resume"), err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert len(list((tmp_path / "cache" / "double_well").glob("*.npz"))) >= 2


CHILD = """
import sys
from experiments import interrupt

def main(argv):
    child = interrupt.spawn([sys.executable, "-c", "import time; time.sleep(60)"])
    print(f"child {child.pid}", file=sys.stderr, flush=True)
    child.wait()
    print("not reached", flush=True)

interrupt.main(main, "demo")
"""


def test_one_ctrl_c_stops_a_job_blocked_on_a_child_and_the_child():
    status, err, seconds = _interrupt([sys.executable, "-c", CHILD], "child ", timeout=10)
    assert status == 130 and seconds < 5, err
    assert err.strip().splitlines()[-1] == "python -m experiments.demo: interrupted", err
    pid = int(err.split("child ")[1].split()[0])
    for _ in range(50):  # the killed child is reaped by init once it has gone
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        with open(f"/proc/{pid}/stat") as f:
            assert f.read().split()[2] == "Z", f"child {pid} still runs"


def test_outside_the_entry_point_a_job_keeps_python_s_interrupt():
    before = signal.getsignal(signal.SIGINT)
    with interrupt.stopping("python -m experiments.demo"):
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before
