"""The ``experiments`` command lines: every job's ``--help`` is true and complete, and every bad
value ends in argparse's one-line error naming the flag (exit status 2) before any work starts.

The parsers run in-process (``build_parser()`` / ``parse_args(argv)`` of each job), so nothing here
simulates, trains or filters."""

import argparse
import importlib
import os
import re
import sys

import pytest

JOBS = ("ablate", "bench", "compile_time", "ensf_l96", "gaussian_loss", "guidance_study", "lorenz96",
        "lorenz96_ablation", "lorenz96_csf", "lorenz96_transform", "make_pretrained", "own_prior", "posterior_quality",
        "prior_quality", "reference", "robust_table", "run", "scale_out", "small_ensembles",
        "step_parts", "table",
        "train", "tutorial", "zoo")

# measurement prose: timings, sizes, speed-ups and quoted errors
MEASUREMENT = re.compile(
    r"\b\d+(?:\.\d+)?\s*(?:ms|s|sec|seconds?|min|minutes?|hours?|GiB|MiB|GB|MB)\b"
    r"|\b\d+(?:\.\d+)?x\b"
    r"|\d+(?:\.\d+)?\s*%\s*(?:faster|slower|better|worse|gain|less|more)"
    r"|\bRMSE\s*(?:of\s*)?\d", re.I)


def _module(job: str):
    return importlib.import_module(f"experiments.{job}")


def _parse(job: str, argv):
    """The job's full argument check: ``parse_args`` where it has one, else its parser."""
    mod = _module(job)
    parse = getattr(mod, "parse_args", None) or mod.build_parser().parse_args
    return parse(argv)


def _error(job: str, argv, capsys) -> str:
    """The one-line error of ``argv``; asserts exit status 2."""
    with pytest.raises(SystemExit) as exit_:
        _parse(job, argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err, f"{job} {argv}: no message"
    assert err[-1].startswith(f"python -m experiments.{job}: error: "), err[-1]
    return err[-1]


def _documented(action) -> bool:
    return action.help is not argparse.SUPPRESS and not isinstance(action, argparse._HelpAction)


# --- --help ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("job", JOBS)
def test_help_exits_0_and_lists_every_flag(job, capsys):
    mod = _module(job)
    with pytest.raises(SystemExit) as exit_:
        mod.main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: python -m experiments.{job}")
    for action in mod.build_parser()._actions:
        if _documented(action):
            for flag in action.option_strings:
                assert flag in text, f"{job}: {flag} missing from --help"


@pytest.mark.parametrize("job", JOBS)
def test_every_flag_has_a_help_string_and_a_true_default(job):
    p = _module(job).build_parser()
    assert p.description and "\n" not in p.description.strip()
    for action in p._actions:
        if not _documented(action):
            continue
        name = action.option_strings or [action.dest]
        assert action.help and action.help.strip(), f"{job} {name}: no help"
        if isinstance(action.default, (int, str)) and not isinstance(action.default, bool):
            assert "%(default)s" in action.help, f"{job} {name}: default not from %(default)s"


@pytest.mark.parametrize("job", JOBS)
def test_help_has_no_measurement_prose(job):
    text = _module(job).build_parser().format_help()
    found = MEASUREMENT.findall(text)
    assert not found, f"{job}: {found}"


def test_named_methods_and_models_are_listed():
    run_help = _module("run").build_parser().format_help()
    for method in _module("run").METHODS:
        assert method in run_help
    bench_help = _module("bench").build_parser().format_help()
    for impl in _module("bench").IMPLS:
        assert impl in bench_help


# --- bad values: one line naming the flag ---------------------------------------------------------


CASES = [
    # the main job and the table: --sf-runs within --runs, the same message
    ("run", ["double_well", "--sf-runs", "5", "--runs", "2"], "--sf-runs", "exceeds the 2 runs"),
    ("run", ["double_well", "--runs", "0"], "--runs", ">= 1"),
    ("run", ["double_well", "--methods", "csf,kalman"], "--methods", "csf_gaussian"),
    ("run", ["nowhere"], "PROBLEM", "double_well"),
    ("table", ["--sf-runs", "0"], "--sf-runs", ">= 1"),
    ("table", ["--sf-runs", "5", "--runs", "2"], "--sf-runs", "exceeds the 2 runs"),
    ("table", ["--sf-runs", "cauchy=11"], "--sf-runs", "exceeds the 10 runs"),
    ("table", ["--sf-runs", "nowhere=3"], "--sf-runs", "unknown problem"),
    ("table", ["--sf-runs", "five"], "--sf-runs", "expected R"),
    # Lorenz-96 jobs: counts, the burn-in, memory, the local CSF's dimensions
    ("lorenz96", ["--steps", "10000000"], "--steps", "GiB"),
    ("lorenz96", ["--steps", "100"], "--steps", "burn-in"),
    ("lorenz96", ["--runs", "0"], "--runs", ">= 1"),
    ("lorenz96", ["--runs", "-1"], "--runs", ">= 1"),
    ("lorenz96_csf", ["--dims", "0"], "--dims", "multiple of 40"),
    ("lorenz96_csf", ["--dims", "-5"], "--dims", "multiple of 40"),
    ("lorenz96_csf", ["--dims", "40", "50"], "--dims", "multiple of 40"),
    ("lorenz96_csf", ["--scaling-steps", "0"], "--scaling-steps", ">= 1"),
    ("lorenz96_csf", ["--runs", "0"], "--runs", ">= 1"),
    ("lorenz96_csf", ["--steps", "10000000"], "--steps", "GiB"),
    ("lorenz96_ablation", ["--runs", "0"], "--runs", ">= 1"),
    ("small_ensembles", ["--particles", "1"], "--particles", ">= 2"),
    ("small_ensembles", ["--methods", "csf,bogus"], "--methods", "bogus"),
    ("lorenz96_ablation", ["--steps", "50"], "--steps", "burn-in"),
    ("own_prior", ["--runs", "0"], "--runs", ">= 1"),
    ("own_prior", ["--runs", "-1"], "--runs", ">= 1"),
    ("own_prior", ["nowhere"], "PROBLEM", "double_well"),
    # the tutorial has a real parser
    ("tutorial", ["--out", "x"], "--out", "unrecognized"),
    ("tutorial", ["a", "b"], "b", "unrecognized"),
    # training: what the data allow
    ("train", ["double_well", "--stride", "1000"], "--stride", "must be <= 100"),
    ("train", ["cauchy", "--stride", "201"], "--stride", "must be <= 200"),
    ("train", ["double_well", "--keep", "2000"], "--keep", "cannot exceed --particles"),
    ("train", ["double_well", "--particles", "100"], "--particles", "cannot exceed --particles"),
    ("train", ["double_well", "--steps", "0"], "--steps", ">= 1"),
    # the benchmark
    ("bench", ["--impls", "bogus"], "--impls", "torch_compile"),
    ("bench", ["--shards", "0"], "--shards", ">= 1"),
    # the model makers read names, not flags
    ("make_pretrained", ["bogus"], "NAME", "double_well"),
    ("make_pretrained", ["--bogus"], "--bogus", "unrecognized"),
    ("gaussian_loss", ["bogus"], "NAME", "double_well"),
    ("gaussian_loss", ["--bogus"], "--bogus", "unrecognized"),
    # every other job
    ("ablate", ["double_well", "--runs", "0"], "--runs", ">= 1"),
    ("ablate", [], "problem", "required"),
    ("ablate", ["double_well", "--setting", "nowhere=1"], "--setting", "CSFConfig"),
    ("guidance_study", ["--runs", "0"], "--runs", ">= 1"),
    ("guidance_study", ["--problems", "bogus"], "--problems", "double_well"),
    ("guidance_study", ["--steps", "1"], "--steps", ">= 2"),
    ("posterior_quality", ["--trials", "0"], "--trials", ">= 1"),
    ("posterior_quality", ["--particles", "1"], "--particles", ">= 2"),
    ("prior_quality", ["double_well", "--ensembles", "0"], "--ensembles", ">= 1"),
    ("prior_quality", ["triple_well"], "PROBLEM", "double_well"),
    ("reference", ["--runs", "0"], "--runs", ">= 1"),
    ("reference", ["--particles", "1000,1"], "--particles", ">= 2"),
    ("reference", ["--problems", "bogus"], "--problems", "double_well"),
    ("robust_table", ["cauchy=0"], "PROBLEM=R", "R >= 1"),
    ("robust_table", ["nowhere=3"], "PROBLEM=R", "table problem"),
    ("robust_table", ["cauchy=11"], "PROBLEM=R", "<= 10"),
    ("zoo", ["--runs", "0"], "--runs", ">= 1"),
    ("zoo", ["--particles", "1"], "--particles", ">= 2"),
    ("zoo", ["--models", "bogus"], "--models", "unknown model"),
    ("zoo", ["--methods", "bogus"], "--methods", "csf_robust"),
]


@pytest.mark.parametrize("job,argv,flag,fragment", CASES,
                         ids=[f"{c[0]} {' '.join(c[1])}" for c in CASES])
def test_bad_values_are_one_line_errors_naming_the_flag(job, argv, flag, fragment, capsys):
    line = _error(job, argv, capsys)
    assert flag in line, line
    assert fragment in line, line


def test_run_and_table_refuse_more_sf_runs_than_runs_alike(capsys):
    run_line = _error("run", ["double_well", "--runs", "3", "--sf-runs", "4"], capsys)
    table_line = _error("table", ["--runs", "3", "--sf-runs", "4"], capsys)
    assert run_line.split("error: ")[1] == table_line.split("error: ")[1]


def test_good_values_parse():
    assert _parse("table", ["--sf-runs", "5"]).sf_runs["double_well"] == 5
    assert _parse("table", ["--sf-runs", "cauchy=3"]).sf_runs == {"cauchy": 3}
    args = _parse("run", ["double_well", "--quick"])
    assert (args.runs, args.particles) == (_module("run").QUICK["runs"],
                                           _module("run").QUICK["particles"])
    assert _parse("lorenz96_csf", ["--dims", "40", "80"]).dims == [40, 80]
    assert _parse("own_prior", []).problems == list(_module("own_prior").DEFAULT)
    assert _parse("train", ["double_well", "--stride", "100"]).dataset.stride == 100
    assert _parse("robust_table", ["cauchy=3"]).cases == [("cauchy", 3)]


def test_tutorial_help_and_out_create_no_folders(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    tutorial = _module("tutorial")
    with pytest.raises(SystemExit) as exit_:
        tutorial.main(["--help"])
    assert exit_.value.code == 0
    _error("tutorial", ["--out", "x"], capsys)
    assert os.listdir(tmp_path) == []
    args = tutorial.parse_args(["elsewhere"])
    assert args.out == "elsewhere" and not args.no_extras
    assert tutorial.parse_args([]).out == str(tutorial.PAGE.parent / "tutorial")


def test_bench_without_torch_says_how_to_get_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "torch", None)  # as if PyTorch were not installed
    line = _error("bench", [], capsys)
    assert line.endswith("PyTorch is not installed: pip install -e '.[bench]'"), line
    _error("bench", ["--impls", "jax"], capsys)  # the trajectory rows need torch too
    args = _parse("bench", ["--impls", "jax", "--traj-runs", "0"])  # jax alone does not
    assert args.impls == ["jax"]


def test_help_of_model_makers_is_not_a_model_name(capsys):
    for job in ("make_pretrained", "gaussian_loss"):
        with pytest.raises(SystemExit) as exit_:
            _module(job).main(["--help"])
        assert exit_.value.code == 0
        assert "double_well" in capsys.readouterr().out


def test_matplotlib_hint_works_for_any_install():
    import inspect
    source = inspect.getsource(_module("run")._figures)
    assert "pip install matplotlib" in source and "pip install -e" not in source
