"""The README and the documentation: short, current, built, linted, and about the product only.

* the README's example runs as written, and its results table equals `results/*/results.json`;
* every public name of `csf_jax` is in the API reference;
* `mkdocs build --strict` succeeds (broken links, missing API objects fail it) and `ruff check`
  is clean (both skipped only where the `docs`/`test` extras are not installed);
* no file of the tree speaks of how the project was built (its work log belongs in git).
"""

import importlib.util
import json
import os
import re
import subprocess
import sys

import jax
import pytest

import csf_jax

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
TEXT_SUFFIXES = (".py", ".md", ".json", ".toml", ".yml", ".yaml", ".txt", ".cfg")
SKIP_DIRS = {".git", ".venv", "site", "build", "runs", "out", "__pycache__", ".pytest_cache",
             "csf_jax.egg-info"}

# Built from pieces so that this file does not match itself.
HISTORY = [re.compile(p, re.IGNORECASE) for p in (
    r"\bsess" + r"ions?\b",
    r"\biss" + r"ue\s*#?\s*\d+",
    r"\bprevious " + r"default",
    r"\bearlier " + r"(runs of the project|versions)\b",
)]

PROBLEMS = ("double_well", "triple_well", "cauchy", "cubic10_indep", "cubic10_corr",
            "cubic20_indep", "cubic20_corr")
ROWS = {"CSF": "csf", "EnKF": "enkf", "PF": "pf", "reference": "reference"}


def _readme() -> str:
    with open(README, encoding="utf-8") as f:
        return f.read()


def _tree_files():
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS]
        for name in files:
            if name.endswith(TEXT_SUFFIXES):
                yield os.path.join(folder, name)


def test_no_development_history_in_the_tree():
    hits = []
    for path in _tree_files():
        with open(path, encoding="utf-8", errors="replace") as f:
            for number, line in enumerate(f, 1):
                if any(p.search(line) for p in HISTORY):
                    hits.append(f"{os.path.relpath(path, ROOT)}:{number}: {line.strip()[:100]}")
    assert not hits, "development history in the tree:\n" + "\n".join(hits[:40])


def test_history_patterns_can_fail():
    assert any(p.search("as in " + "sess" + "ion 23") for p in HISTORY)
    assert any(p.search("see iss" + "ue 11") for p in HISTORY)


def test_readme_is_short():
    assert len(_readme().splitlines()) <= 150


def test_readme_example_runs():
    text = _readme()
    block = text.split("## Example", 1)[1].split("```python", 1)[1].split("```", 1)[0]
    namespace = {}
    exec(compile(block, "README.md#example", "exec"), namespace)  # noqa: S102
    result, pf, truth = namespace["result"], namespace["pf"], namespace["truth"]
    assert result.mean.shape == result.std.shape == (50, 2)
    printed = re.search(r"# ([0-9.]+) ([0-9.]+)\n", block).groups()
    assert _agrees(printed[0], float(csf_jax.rmse(result.mean, truth[1:])))
    assert _agrees(printed[1], float(csf_jax.rmse(pf.mean, truth[1:])))
    defaults = csf_jax.filter(None, namespace["obs"], namespace["ensemble"],
                              problem=namespace["pendulum"], key=jax.random.key(2))
    quoted = re.search(r"give ([0-9.]+) here", text).group(1)
    assert _agrees(quoted, float(csf_jax.rmse(defaults.mean, truth[1:])))


def _readme_table() -> dict:
    """``{row: [cell, ...]}`` of the README's results table: (value, ratio or None) per column."""
    text = _readme().split("## Results", 1)[1]
    table = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] in ROWS:
            parsed = []
            for cell in cells[1:]:
                m = re.fullmatch(r"([0-9.]+)(?: \(([0-9.]+)\))?", cell)
                assert m, f"README table cell {cell!r}"
                parsed.append((m.group(1), m.group(2)))
            table[cells[0]] = parsed
    return table


def _agrees(shown: str, value: float) -> bool:
    digits = len(shown.split(".")[1]) if "." in shown else 0
    return abs(float(shown) - value) <= 0.51 * 10.0 ** (-digits)


def test_readme_table_is_current():
    table = _readme_table()
    assert set(table) == set(ROWS)
    for column, problem in enumerate(PROBLEMS):
        with open(os.path.join(ROOT, "results", problem, "results.json")) as f:
            stored = json.load(f)
        for row, key in ROWS.items():
            value, ratio = table[row][column]
            assert _agrees(value, stored["rmse"][key]), (row, problem, value, stored["rmse"][key])
            if ratio is not None:
                assert _agrees(ratio, stored["rmse_ratio"][key]), (row, problem, ratio)


def test_api_reference_lists_every_public_name():
    with open(os.path.join(ROOT, "docs", "api.md"), encoding="utf-8") as f:
        api = f.read()
    documented = set(re.findall(r"csf_jax\.(?:[a-z_]+\.)*([A-Za-z_]+)", api))
    missing = [name for name in csf_jax.__all__ if name not in documented]
    assert not missing, f"not in docs/api.md: {missing}"


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="the docs extra is not installed")
def test_docs_build_strict(tmp_path):
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                           str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"}, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed")
def test_ruff_is_clean():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout[-3000:]
