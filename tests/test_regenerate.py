"""``python -m experiments.regenerate``: the stale blocks, the listing, the dry run, the resume
after a finished or failed job, one Ctrl-C, and the code record the jobs write in their blocks.

The jobs here are fakes (one-line ``python -c`` commands that rewrite a block of a page in a
temporary tree, with modules of their own there): the real jobs take hours."""

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from experiments import harness, regenerate

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGE = "docs/page.md"


def fake_job(name: str, module: str, tag: str) -> regenerate.Job:
    """A job that writes the line of ``line_<name>.txt`` and "new" into the block ``tag`` of the
    page, its results file, and one line to ``runs.log``; it fails while ``fail_<name>`` exists."""
    start, end = f"<!-- results:{tag}:start -->", f"<!-- results:{tag}:end -->"
    script = (
        "import pathlib, sys; "
        f"log = open('runs.log', 'a'); log.write('{name}\\n'); log.close(); "
        f"sys.exit(1) if pathlib.Path('fail_{name}').exists() else None; "
        f"p = pathlib.Path('{PAGE}'); head, rest = p.read_text().split('{start}', 1); "
        f"line = pathlib.Path('line_{name}.txt').read_text(); "
        f"p.write_text(head + '{start}\\n' + line + '\\nnew\\n{end}' + rest.split('{end}', 1)[1]); "
        f"pathlib.Path('results').mkdir(exist_ok=True); "
        f"pathlib.Path('results/{name}.json').write_text('{{}}')")
    return regenerate.Job(name, ("-c", script), ((PAGE, tag),), (f"results/{name}.json",),
                          (f"experiments.{module}",))


@pytest.fixture
def tree(tmp_path, monkeypatch):
    """A temporary tree: a page with the blocks ``a`` and ``b``, the jobs ``a`` and ``b`` whose
    modules ``experiments.job_a`` and ``experiments.job_b`` both import ``experiments.shared``."""
    code = tmp_path / "experiments"
    code.mkdir()
    (code / "__init__.py").write_text("")
    (code / "shared.py").write_text("VALUE = 1\n")
    for name in ("a", "b"):
        (code / f"job_{name}.py").write_text(f"from experiments import shared\nNAME = '{name}'\n")
    (tmp_path / "docs").mkdir()
    (tmp_path / PAGE).write_text("# page\n\n<!-- results:a:start -->\nold\n<!-- results:a:end -->"
                                 "\n\ntext\n\n<!-- results:b:start -->\n<!-- results:b:end -->\n")
    monkeypatch.setattr(harness, "EXPERIMENTS", code)
    monkeypatch.setattr(regenerate, "ROOT", tmp_path)
    jobs = (fake_job("a", "job_a", "a"), fake_job("b", "job_b", "b"))
    monkeypatch.setattr(regenerate, "JOBS", jobs)
    monkeypatch.chdir(tmp_path)
    lines()
    return tmp_path


def lines() -> None:
    """Write each fake job's block line, with its code now, where it reads it."""
    for j in regenerate.JOBS:
        pathlib.Path(f"line_{j.name}.txt").write_text(
            f"<!-- made by: {j.recorded}; code {j.digest()} -->")


def runs() -> list:
    log = pathlib.Path("runs.log")
    return log.read_text().split() if log.exists() else []


def stale() -> dict:
    return {tag: why for _, tag, _, why in regenerate.stale_blocks()[0]}


def test_stale_lists_blocks_without_a_record_or_with_other_code(tree, capsys):
    assert stale() == {"a": "records no code", "b": "records no code"}
    assert regenerate.main([]) == 0
    assert stale() == {}
    assert regenerate.main(["--stale"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "no stale block (2 blocks)"
    # a module that only job a imports, and one that both import (through an import)
    (tree / "experiments" / "job_a.py").write_text("from experiments import shared\nNAME = 'A'\n")
    assert list(stale()) == ["a"] and stale()["a"].startswith("code changed (block ")
    (tree / "experiments" / "shared.py").write_text("VALUE = 2\n")
    assert sorted(stale()) == ["a", "b"]
    regenerate.main(["--stale"])
    out = capsys.readouterr().out
    assert f"{PAGE} a (a): code changed" in out and "2 of 2 blocks stale" in out


def test_stale_names_blocks_no_job_makes_and_blocks_a_page_lacks(tree, monkeypatch):
    page = tree / PAGE
    page.write_text(page.read_text() + "<!-- results:c:start -->\nx\n<!-- results:c:end -->\n")
    monkeypatch.setattr(regenerate, "JOBS", (*regenerate.JOBS, fake_job("d", "job_a", "d")))
    found = {tag: (name, why) for _, tag, name, why in regenerate.stale_blocks()[0]}
    assert found["c"] == (None, "no job makes it")
    assert found["d"] == ("d", "the page lacks the block")
    # markers quoted inside a line are not a block
    page.write_text(page.read_text() + "see `<!-- results:e:start -->` and "
                                       "`<!-- results:e:end -->`\n")
    assert "e" not in {tag for _, tag, _, _ in regenerate.stale_blocks()[0]}


def test_a_block_made_by_another_command_is_stale(tree):
    regenerate.main([])
    line = pathlib.Path("line_a.txt").read_text().replace("python -c", "python -c  ")
    page = tree / PAGE
    page.write_text(page.read_text().replace(pathlib.Path("line_a.txt").read_text(), line))
    assert stale()["a"].startswith("made by another command")


def test_list_and_dry_run_run_nothing(tree, capsys):
    assert regenerate.main(["--list"]) == 0
    out = capsys.readouterr().out
    assert "a: JAX_PLATFORMS=cpu python -c " in out and f"blocks: {PAGE} a" in out
    assert regenerate.main(["--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("[1/2] a: JAX_PLATFORMS=cpu python -c ")
    assert out[1].startswith("[2/2] b: JAX_PLATFORMS=cpu python -c ")
    assert runs() == [] and "old" in (tree / PAGE).read_text()
    assert not (tree / regenerate.STATE).exists()


def test_a_rerun_skips_finished_jobs_and_resumes_after_a_failed_one(tree, capsys):
    pathlib.Path("fail_b").write_text("")
    assert regenerate.main([]) == 1
    out = capsys.readouterr().out
    assert "[1/2] a: started" in out and "[1/2] a: done in 0 s" in out
    assert "[2/2] b: failed with exit status 1" in out
    state = json.loads((tree / regenerate.STATE).read_text())["jobs"]
    assert list(state) == ["a"] and state["a"]["code"] == regenerate.JOBS[0].digest()
    assert state["a"]["seconds"] >= 0
    assert runs() == ["a", "b"]

    os.remove("fail_b")
    assert regenerate.main([]) == 0
    out = capsys.readouterr().out
    assert runs() == ["a", "b", "b"]
    assert "[1/2] a: up to date" in out and "[2/2] b: done in" in out
    summary = out.split("\n\n", 1)[1].splitlines()
    assert summary[0].split() == ["job", "blocks", "result", "time"]
    assert summary[1].split()[:4] == ["a", PAGE, "a", "up"]
    assert summary[2].split()[:4] == ["b", PAGE, "b", "remade"]

    assert regenerate.main([]) == 0
    assert runs() == ["a", "b", "b"]
    (tree / "experiments" / "job_b.py").write_text("from experiments import shared\nNAME = 2\n")
    lines()
    assert regenerate.main([]) == 0
    assert runs() == ["a", "b", "b", "b"]
    assert regenerate.main(["--only", "a", "--force"]) == 0
    assert runs() == ["a", "b", "b", "b", "a"]


def test_a_job_without_blocks_is_up_to_date_by_its_recorded_code(tree, monkeypatch, capsys):
    j = fake_job("a", "job_a", "a")
    quiet = regenerate.Job("quiet", ("-c", "open('runs.log', 'a').write('quiet\\n')"),
                           modules=j.modules, inputs=("docs/input.txt",))
    (tree / "docs" / "input.txt").write_text("1")
    monkeypatch.setattr(regenerate, "JOBS", (quiet,))
    regenerate.main([])
    regenerate.main([])
    assert runs() == ["quiet"]
    (tree / "docs" / "input.txt").write_text("2")
    regenerate.main([])
    assert runs() == ["quiet", "quiet"]


def test_a_job_writes_the_code_record_that_stale_reads(tmp_path):
    """Every real job's block line (``harness.made_by`` from its command) records the digest that
    ``--stale`` compares with, and ``replace_section`` writes it first inside the block."""
    for j in regenerate.JOBS:
        if j.blocks:
            line = harness.made_by(j.recorded)
            assert regenerate.recorded(line + "\nbody") == (j.recorded, j.digest()), j.name
            assert regenerate._why(j, line + "\nbody", j.digest()) is None, j.name
    j = next(j for j in regenerate.JOBS if j.name == "zoo_N50")
    page = tmp_path / "zoo.md"
    page.write_text("# zoo\n<!-- results:N50:start -->\nold\n<!-- results:N50:end -->\ntail\n")
    harness.replace_section(page, "| a |", "<!-- results:N50:start -->",
                            "<!-- results:N50:end -->", j.recorded)
    assert page.read_text() == (f"# zoo\n<!-- results:N50:start -->\n{harness.made_by(j.recorded)}"
                                f"\n| a |\n<!-- results:N50:end -->\ntail\n")
    assert regenerate.page_blocks(page.read_text())["N50"].startswith("<!-- made by: python -m "
                                                                      "experiments.zoo --part")
    # outside a job (a test calling replace_section), no record
    harness.replace_section(page, "| b |", "<!-- results:N50:start -->",
                            "<!-- results:N50:end -->")
    assert "made by" not in page.read_text()


def test_the_digest_follows_the_jobs_imports():
    assert harness.job_digest("experiments.zoo") != harness.job_digest("experiments.costs")
    with pytest.raises(ValueError, match="job_digest: no module 'experiments.nope'"):
        harness.job_digest("experiments.nope")


CODE = b'''"""A module."""
import math  # the library


def area(r,
         scale=1.0):
    """The disc's area."""
    label = "not a docstring"
    return scale * math.pi * r ** 2
'''


@pytest.mark.parametrize("edit, same", [
    (lambda s: s.replace(b'"""The disc\'s area."""', b'"""Pi r squared,\n    scaled."""'), True),
    (lambda s: s.replace(b"  # the library", b"") + b"# the end\n", True),
    (lambda s: s.replace(b"r,\n         scale", b"r, scale").replace(b"* math", b"*  math"), True),
    (lambda s: s.replace(b'"""A module."""\n', b""), True),
    (lambda s: s.replace(b"r ** 2", b"r ** 3"), False),
    (lambda s: s.replace(b"not a docstring", b"not a docstring!"), False),
    (lambda s: s.replace(b"    return", b"    if r:\n        return"), False),
])
def test_the_digest_reads_code_not_comments_docstrings_or_layout(edit, same):
    """``code_tokens``: an edit of documentation or layout keeps a file's digest (its blocks stay
    fresh); any edit of what runs changes it."""
    assert (harness.code_tokens(edit(CODE)) == harness.code_tokens(CODE)) is same


def test_every_block_of_the_pages_has_a_job():
    stale, count = regenerate.stale_blocks()
    assert count >= 18
    assert not [s for s in stale if s[2] is None], "blocks no job makes"
    names = [j.name for j in regenerate.JOBS]
    assert len(names) == len(set(names))


def test_one_ctrl_c_stops_the_job_and_its_child(tmp_path):
    """SIGINT: exit status 130 at once, one line, and the running job is stopped."""
    pid = tmp_path / "pid"
    child = f"import os, time; open({str(pid)!r}, 'w').write(str(os.getpid())); time.sleep(60)"
    driver = ("from experiments import interrupt, regenerate as r; "
              f"r.ROOT = __import__('pathlib').Path({str(tmp_path)!r}); "
              f"r.JOBS = (r.Job('sleep', ('-c', {child!r}), modules=('experiments.costs',)),); "
              "interrupt.main(r.main, 'regenerate', 'rerun to resume')")
    proc = subprocess.Popen([sys.executable, "-c", driver], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 25
    while not (pid.exists() and pid.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert pid.exists(), proc.communicate(timeout=30)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "python -m experiments.regenerate: interrupted; " \
                                           "rerun to resume"
    assert "[1/1] sleep: started" in out
    assert not running(int(pid.read_text()))


def running(pid: int) -> bool:
    """Whether process ``pid`` still runs (a killed one whose parent is gone may stay a zombie
    until the system reaps it)."""
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        try:
            state = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return False
        if state in ("Z", "X"):
            return False
        time.sleep(0.05)
    return True


def timing_job(name: str, timed: bool, output: str) -> regenerate.Job:
    """A job without blocks that prints a line, logs its start and end and sleeps 1 s between,
    and writes ``output``."""
    script = (f"import pathlib, time; print('hello from {name}', flush=True); "
              f"log = lambda w: open('times.log', 'a').write('{name} ' + w + ' ' "
              f"+ str(time.time()) + '\\n'); "
              f"log('start'); time.sleep(1.0); pathlib.Path({output!r}).write_text('x'); "
              f"log('end')")
    return regenerate.Job(name, ("-c", script), (), (output,), ("experiments.job_a",),
                          timed=timed)


def spans() -> dict:
    found = {}
    for line in pathlib.Path("times.log").read_text().split("\n"):
        if line:
            name, what, t = line.split()
            found.setdefault(name, {})[what] = float(t)
    return found


def test_jobs_that_time_nothing_run_side_by_side_and_timed_ones_alone(tree, monkeypatch,
                                                                      capsys):
    jobs = (timing_job("first", False, "one.txt"), timing_job("second", False, "two.txt"),
            timing_job("timed", True, "three.txt"), timing_job("same", False, "one.txt"))
    monkeypatch.setattr(regenerate, "JOBS", jobs)
    assert regenerate.main(["--force", "--jobs", "2"]) == 0
    out = capsys.readouterr().out
    assert "[first] hello from first" in out and "[timed] hello from timed" in out
    s = spans()

    def overlap(a, b):
        return s[a]["start"] < s[b]["end"] and s[b]["start"] < s[a]["end"]

    assert overlap("first", "second")  # neither is timed, different files
    assert not overlap("first", "same")  # both write one.txt
    assert not any(overlap("timed", other) for other in ("first", "second", "same"))
    summary = [line.split()[:3] for line in out.split("\n\n", 1)[1].splitlines()[1:]]
    assert summary == [[name, "-", "remade"] for name in ("first", "second", "timed", "same")]
    state = json.loads((tree / regenerate.STATE).read_text())["jobs"]
    assert sorted(state) == ["first", "same", "second", "timed"]


def test_one_job_at_a_time_with_jobs_1(tree, monkeypatch):
    jobs = (timing_job("first", False, "one.txt"), timing_job("second", False, "two.txt"))
    monkeypatch.setattr(regenerate, "JOBS", jobs)
    assert regenerate.main(["--force", "--jobs", "1"]) == 0
    s = spans()
    assert s["first"]["end"] <= s["second"]["start"]


def test_the_timed_jobs_are_those_whose_outputs_quote_seconds():
    timed = {j.name for j in regenerate.JOBS if j.timed}
    assert {"table", "zoo_N1000", "zoo_N50", "costs", "profile", "bench_kalman", "lorenz96",
            "tutorial"} <= timed
    assert not {"defaults_N1000", "defaults_N50", "small_ensembles_N50",
                "lorenz96_robustness"} & timed
    assert all(j.timed for j in regenerate.JOBS if j.gpu)


def test_every_jobs_digest_covers_the_library(monkeypatch):
    """A change of ``csf_jax`` restales every job, the tutorial too (whose code runs in a
    subprocess, not imported by its module)."""
    before = {j.name: j.digest() for j in regenerate.JOBS}
    read = harness.source
    init = harness.LIBRARY / "__init__.py"
    monkeypatch.setattr(harness, "source", lambda f: read(f) + (b"\nX = 1\n" if f == init else b""))
    after = {j.name: j.digest() for j in regenerate.JOBS}
    assert [name for name in before if before[name] == after[name]] == []
