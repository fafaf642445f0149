"""The ``experiments`` command lines: every job's ``--help`` works, every bad value ends in
argparse's one-line error naming the flag (exit status 2) before any work starts, and the main
job runs end to end on the shipped prior."""

import importlib
import json
import re

import pytest

from experiments import harness

JOBS = ("run", "table", "zoo", "defaults", "small_ensembles", "lorenz96", "lorenz96_scaling",
        "lorenz96_robustness", "train", "bench", "tutorial", "exact_jumps")

# measurement prose: timings, sizes, speed-ups and quoted errors
MEASUREMENT = re.compile(
    r"\b\d+(?:\.\d+)?\s*(?:ms|sec|seconds?|min|minutes?|hours?|GiB|MiB|GB|MB)\b"
    r"|\b\d+(?:\.\d+)?x\b|\bRMSE\s*(?:of\s*)?\d", re.I)


def _main(job):
    return importlib.import_module(f"experiments.{job}").main


@pytest.mark.parametrize("job", JOBS)
def test_help_exits_0_without_measurements(job, capsys):
    with pytest.raises(SystemExit) as exit_:
        _main(job)(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert f"python -m experiments.{job}" in text
    assert not MEASUREMENT.search(text), MEASUREMENT.search(text)


CASES = [
    ("run", ["nowhere"], "PROBLEM", "double_well"),
    ("run", ["double_well", "--runs", "0"], "--runs", ">= 1"),
    ("run", ["double_well", "--runs", "x"], "--runs", "expected an integer"),
    ("run", ["double_well", "--particles", "1"], "--particles", ">= 2"),
    ("run", ["double_well", "--methods", "CSF,Kalman"], "--methods", "CSF-G"),
    ("run", ["double_well", "--sf-runs", "5", "--runs", "2"], "--sf-runs", "exceeds the 2 runs"),
    ("table", ["--problems", "double_well,nowhere"], "--problems", "cubic20_corr"),
    ("table", ["--sf-runs", "0"], "--sf-runs", ">= 1"),
    ("zoo", ["--models", "bogus"], "--models", "pendulum"),
    ("zoo", ["--particles", "1"], "--particles", ">= 2"),
    ("defaults", ["--candidates", "CSF,bogus"], "--candidates", "PAPER"),
    ("run", ["double_well", "--preset", "robust"], "--preset", "paper"),
    ("defaults", ["--groups", "all"], "--groups", "moderate"),
    ("small_ensembles", ["--problems", "bogus"], "--problems", "cauchy"),
    ("small_ensembles", ["--runs", "0"], "--runs", ">= 1"),
    ("lorenz96", ["--setups", "bogus"], "--setups", "identity"),
    ("lorenz96", ["--runs", "-1"], "--runs", ">= 1"),
    ("train", ["bogus"], "NAME", "double_well"),
    ("tutorial", ["a", "b"], "b", "unrecognized"),
    ("bench", ["--worker", "not json"], "--worker", "not a worker spec"),
    ("bench", ["--dims", "0"], "--dims", ">= 1"),
    ("lorenz96_scaling", ["--dims", "3"], "--dims", ">= 40"),
    ("lorenz96_robustness", ["--setups", "identity"], "--setups", "ensf_calm"),
]


@pytest.mark.parametrize("job,argv,flag,fragment", CASES,
                         ids=[f"{c[0]} {' '.join(c[1])}" for c in CASES])
def test_bad_values_are_one_line_errors_naming_the_flag(job, argv, flag, fragment, capsys):
    with pytest.raises(SystemExit) as exit_:
        _main(job)(argv)
    assert exit_.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(f"python -m experiments.{job}: error: "), line
    assert flag in line and fragment in line, line


def test_quick_main_job_writes_its_table_results_and_figures(tmp_path, capsys):
    out = tmp_path / "out"
    _main("run")(["double_well", "--quick", "--out", str(out), "--cache", str(tmp_path / "c"),
                  "--no-progress"])
    text = capsys.readouterr().out
    for label in ("CSF", "CSF-G", "SF", "EnKF", "PF", "Ref."):
        assert re.search(rf"^\| {re.escape(label)} \| \d+ \| \d", text, re.M), label
    record = harness.read_results(out / "results.json")
    assert record["benchmark"] == "run" and record["command"].startswith(
        "python -m experiments.run double_well --quick")
    rows = {r["entry"]: r for r in record["rows"]}
    assert rows["SF"]["runs"] == 1 and rows["CSF"]["runs"] == 2
    assert rows["Ref."]["rmse_ratio"] == pytest.approx(1.0)
    assert 0.8 < rows["CSF"]["rmse_ratio"] < 1.5 < rows["PF"]["rmse_ratio"]
    assert {p.name for p in out.glob("*.png")} == {"estimates.png", "rmse_over_time.png",
                                                   "prior.png"}
    json.dumps(record)
    assert record["preset"] == "default"
    prior = rows["CSF"]["config"]["CSFSpec"]["config"]["CSFConfig"]["prior"]["PriorConfig"]
    assert prior["mixture"] is not None


@pytest.mark.slow
def test_the_paper_preset_runs_the_paper_config_and_is_recorded(tmp_path, capsys):
    out = tmp_path / "out"
    _main("run")(["double_well", "--quick", "--preset", "paper", "--methods", "CSF,EnKF",
                  "--out", str(out), "--cache", str(tmp_path / "c"), "--no-progress"])
    record = harness.read_results(out / "results.json")
    assert record["preset"] == "paper"
    row = {r["entry"]: r for r in record["rows"]}["CSF"]
    config = row["config"]["CSFSpec"]["config"]["CSFConfig"]
    assert config["prior"]["PriorConfig"]["mixture"] is None
    assert config["inflation"]["InflationConfig"]["adaptive"] is True


def test_table_renders_its_blocks_from_a_results_record(tmp_path):
    from experiments import table

    rows = [{"case": {"problem": "cauchy"}, "entry": e, "runs": 10 if e != "SF" else 5,
             "rmse": v, "rmse_ratio": v / 0.25, "rmse_before_shock": None,
             "rmse_after_shock": 0.2, "seconds_per_step": 0.01}
            for e, v in (("CSF", 0.28), ("SF", 0.35), ("EnKF", 24.9), ("PF", 1.16),
                         ("Ref.", 0.25))]
    record = harness.results_record("table", "python -m experiments.table", rows)
    text = table.render(record)
    assert "| CSF | 0.28 (0.217) |" in text and "| SF | 0.35 (0.285, 5 runs) |" in text
    assert "| EnKF | 99.6 |" in text and "(1.55)" in text
    page = tmp_path / "page.md"
    page.write_text("# head\n<!-- results:start -->\nold\n<!-- results:end -->\ntail\n")
    harness.replace_section(page, table.readme_block(record))
    assert page.read_text().startswith("# head\n<!-- results:start -->\n| filter | Cauchy |")
    assert page.read_text().endswith("<!-- results:end -->\ntail\n")
