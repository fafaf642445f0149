"""The README and the documentation: short, current, built, linted, and about the product only.

* the runnable snippets (the README's example, the home page's, the filter-choice page's) run as a
  user runs them: in a fresh process, with the user's XLA flags (not the suite's), and with a
  DeprecationWarning from their own code an error; the README's printed figures are checked;
* every Python snippet of the pages parses and uses the current API (``model=``, the grouped
  ``CSFConfig``, ``TrainedPrior``);
* the README's results table equals ``results/table/results.json``;
* every public name of `csf_jax` is in the API reference;
* the pages of finished studies say so, with the commit their code is at;
* `mkdocs build --strict` succeeds (broken links and anchors, pages outside the nav, missing API
  objects fail it), the site holds no ``__pycache__``, and `ruff check` is clean (both skipped
  only where the `docs`/`test` extras are not installed);
* no file of the tree speaks of how the project was built (its work log belongs in git).
"""

import importlib.util
import json
import os
import re
import subprocess
import sys

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
ROWS = ("CSF", "EnKF", "PF", "Ref.")  # the README table's rows: the entries of experiments.run
TABLE = os.path.join(ROOT, "results", "table", "results.json")

# The pages whose Python snippets a user runs as they stand, and where on the page they start.
RUNNABLE = {"README.md": "## Example", "docs/index.md": "## Example",
            "docs/choosing.md": "## Check the choice",
            "docs/fitting.md": "## Comparing two models on the same data"}
# The commit at which the finished studies' code is kept, and the nav section that lists them.
STUDIES_COMMIT = "cace770"
STUDIES_SECTION = "Finished studies"
# Spellings of the API that its next version drops: the docs' snippets must not use them.
DEPRECATED = [re.compile(p) for p in (
    r"\bproblem=", r"\blg=", r"(?<!Trained)\bPretrained\b",
    r"CSFConfig\((?:[^()]|\([^()]*\))*?\b(reverse_steps|t_min|sigma_max|guidance|assimilate_first|denoise_last|"
    r"prior_inflation|adaptive_inflation|inflation_threshold|inflation_max|inflation_statistic|"
    r"encode_particles|mixture|covariance)=",
    r"\b(prior_inflation|adaptive_inflation|inflation_threshold|inflation_max|"
    r"inflation_statistic)\b",
)]


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


def _python_blocks(text: str) -> list:
    """The bodies of the ```python blocks of a page's text, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def _runnable(page: str) -> str:
    """The Python blocks of ``page`` from its ``RUNNABLE`` heading on, joined as one script."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        text = f.read().split(RUNNABLE[page], 1)[1]
    blocks = _python_blocks(text)
    assert blocks, f"{page} has no ```python block after {RUNNABLE[page]!r}"
    return "\n".join(blocks)


def _user_env() -> dict:
    """The environment of a user's process (the suite sets no XLA flags of its own)."""
    return {**os.environ, "MPLBACKEND": "Agg"}


def _run_as_user(script: str, tmp_path) -> str:
    """Run ``script`` in a fresh Python process as a user would, with a DeprecationWarning raised
    by the script's own code (``__main__``) an error; returns its stdout."""
    path = tmp_path / "snippet.py"
    path.write_text(script)
    done = subprocess.run([sys.executable, "-W", "error::DeprecationWarning:__main__", str(path)],
                          cwd=tmp_path, env=_user_env(), capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    return done.stdout


# After the README's example, the figures the test compares with what it printed: the example's
# two RMSEs and the defaults' RMSE that the text below it quotes.
README_CHECK = """
import json as _json
_paper = csf_jax.filter(None, obs, ensemble, model=pendulum, key=jax.random.key(2),
                        config=csf_jax.PAPER)
print("CHECK", _json.dumps({"shape": list(result.mean.shape) + list(result.std.shape),
                            "csf": float(csf_jax.rmse(result.mean, truth[1:])),
                            "pf": float(csf_jax.rmse(pf.mean, truth[1:])),
                            "enkf": float(csf_jax.rmse(enkf.mean, truth[1:])),
                            "paper": float(csf_jax.rmse(_paper.mean, truth[1:]))}))
"""


def test_readme_example_runs(tmp_path):
    block = _runnable("README.md")
    out = _run_as_user(block + README_CHECK, tmp_path)
    figures = json.loads(out.split("CHECK ", 1)[1])
    assert figures["shape"] == [50, 2, 50, 2]
    printed = re.search(r"# ([0-9.]+) ([0-9.]+) ([0-9.]+)\n", block).groups()
    # CSF's figure: the mixture's resampling takes other branches under another CPU's rounding
    # (the mixture prior without kernels gave 0.270 on an Intel Xeon, 0.255 on an AMD EPYC, same
    # key), so it is checked to 10%
    assert abs(float(printed[0]) - figures["csf"]) <= 0.1 * float(printed[0]), (printed, figures)
    assert _agrees(printed[1], figures["pf"]), (printed, figures)
    assert _agrees(printed[2], figures["enkf"]), (printed, figures)
    quoted = re.search(r"gives ([0-9.]+) here", _readme()).group(1)
    assert _agrees(quoted, figures["paper"]), (quoted, figures)


@pytest.mark.parametrize("page", ["docs/index.md", "docs/choosing.md", "docs/fitting.md"])
def test_page_snippets_run(page, tmp_path):
    out = _run_as_user(_runnable(page), tmp_path)
    assert "RMSE" in out or re.search(r"\d\.\d", out), out


def _pages():
    """The documentation's Markdown pages and the README, as paths relative to the root."""
    pages = ["README.md"]
    for folder, _, files in os.walk(os.path.join(ROOT, "docs")):
        pages += [os.path.relpath(os.path.join(folder, f), ROOT) for f in files if f.endswith(".md")]
    return sorted(pages)


def test_every_snippet_parses_and_uses_the_current_api():
    """Every ```python block of every page compiles, and none spells the API in a way its next
    version drops (``problem=``, ``lg=``, ``Pretrained``, flat ``CSFConfig`` fields)."""
    bad = []
    for page in _pages():
        with open(os.path.join(ROOT, page), encoding="utf-8") as f:
            blocks = _python_blocks(f.read())
        for number, block in enumerate(blocks):
            compile(block, f"{page}#{number}", "exec")
            bad += [f"{page} block {number}: {p.pattern}" for p in DEPRECATED if p.search(block)]
    assert not bad, "deprecated API in the docs' snippets:\n" + "\n".join(bad)


def test_the_guide_pages_name_the_current_api():
    """The pages that teach the API (not the finished studies, which record what was run) name no
    deprecated spelling in their inline code either; the API reference lists the old name of
    ``TrainedPrior`` as such."""
    bad = []
    for page in ("README.md", "docs/index.md", "docs/getting_started.md", "docs/choosing.md",
                 "docs/guide.md", "docs/tutorial.md", "docs/design.md"):
        with open(os.path.join(ROOT, page), encoding="utf-8") as f:
            spans = re.findall(r"`([^`\n]+)`", f.read())
        bad += [f"{page}: `{span}`" for span in spans for p in DEPRECATED if p.search(span)]
    assert not bad, "deprecated API named in the guide pages:\n" + "\n".join(bad)


def test_deprecated_patterns_can_fail():
    for old in ("csf_jax.filter(None, obs, e, problem=m, key=k)", "kalman_filter(obs, lg=lg)",
                "csf_jax.Pretrained", "CSFConfig(reverse_steps=5)",
                "CSFConfig(sampler=s, adaptive_inflation=False)"):
        assert any(p.search(old) for p in DEPRECATED), old
    for new in ("csf_jax.filter(None, obs, e, model=m, key=k)", "csf_jax.TrainedPrior",
                "CSFConfig(sampler=SamplerConfig(reverse_steps=5))",
                "CSFConfig(inflation=InflationConfig(adaptive=False))"):
        assert not any(p.search(new) for p in DEPRECATED), new


def _readme_table() -> dict:
    """``{row: [cell, ...]}`` of the README's results table: (value, ratio or None) per column,
    value None where the cell says "-" or "diverged"."""
    text = _readme().split("## Results", 1)[1]
    table = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] in ROWS:
            parsed = []
            for cell in cells[1:]:
                m = re.fullmatch(r"(?:([0-9.]+)|-|diverged)(?: \(([0-9.]+)\))?", cell)
                assert m, f"README table cell {cell!r}"
                parsed.append((m.group(1), m.group(2)))
            table[cells[0]] = parsed
    return table


def _agrees(shown: str, value: float) -> bool:
    digits = len(shown.split(".")[1]) if "." in shown else 0
    return abs(float(shown) - value) <= 0.51 * 10.0 ** (-digits)


def test_readme_table_is_current():
    assert os.path.exists(TABLE), (f"{os.path.relpath(TABLE, ROOT)} is missing: python -m "
                                   f"experiments.table --out results/table --page docs/results.md "
                                   f"--readme README.md")
    with open(TABLE) as f:
        rows = {(r["case"]["problem"], r["entry"]): r for r in json.load(f)["rows"]}
    table = _readme_table()
    assert set(table) == set(ROWS), sorted(table)
    for column, problem in enumerate(PROBLEMS):
        for row in ROWS:
            value, ratio = table[row][column]
            stored = rows.get((problem, row))
            if value is None:
                continue
            assert stored is not None, (row, problem)
            assert _agrees(value, stored["rmse"]), (row, problem, value, stored["rmse"])
            if ratio is not None:
                assert _agrees(ratio, stored["rmse_ratio"]), (row, problem, ratio)


def test_api_reference_lists_every_public_name():
    with open(os.path.join(ROOT, "docs", "api.md"), encoding="utf-8") as f:
        api = f.read()
    documented = set(re.findall(r"csf_jax\.(?:[a-z_]+\.)*([A-Za-z_]+)", api))
    missing = [name for name in csf_jax.__all__ if name not in documented]
    assert not missing, f"not in docs/api.md: {missing}"


def _nav_section(nav, title):
    """The pages under the nav section ``title`` of mkdocs.yml's nav."""
    for item in nav:
        if isinstance(item, dict) and title in item:
            return [p for entry in item[title] for p in (entry.values() if isinstance(entry, dict)
                                                         else [entry])]
    return []


def test_finished_studies_say_so():
    """Every page of the nav's finished studies opens (right after its title) with the note that
    names the commit its study's code is at, and only such pages are in that section."""
    yaml = pytest.importorskip("yaml")
    with open(os.path.join(ROOT, "mkdocs.yml"), encoding="utf-8") as f:
        nav = yaml.safe_load(f)["nav"]
    pages = _nav_section(nav, STUDIES_SECTION)
    assert len(pages) >= 7, pages
    for page in pages:
        with open(os.path.join(ROOT, "docs", page), encoding="utf-8") as f:
            head = f.read().split("\n\n", 2)
        note = head[1] if head[0].startswith("# ") else head[0]
        assert note.startswith("> **A finished study.**"), page
        assert f"git show {STUDIES_COMMIT}:experiments/" in note.replace("\n> ", " "), page


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="the docs extra is not installed")
def test_docs_build_strict(tmp_path):
    # as a user builds it: Python free to write bytecode, which must not reach the site
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                           str(site)], cwd=ROOT, capture_output=True, text=True,
                          env={**env, "NO_MKDOCS_2_WARNING": "1"}, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    leaked = [str(p.relative_to(site)) for p in site.rglob("*")
              if p.name == "__pycache__" or p.suffix == ".py"]
    assert not leaked, leaked
    api = (site / "api" / "index.html").read_text(encoding="utf-8")
    for anchor in ("csf_jax.filters.driver.run", "csf_jax.filters.driver.Method", "csf_jax.methods",
                   "csf_jax.filters.csf.SamplerConfig", "csf_jax.inflation.InflationConfig",
                   "csf_jax.prior.PriorConfig"):
        assert f'id="{anchor}"' in api, anchor
    # Args/Attributes sections render as tables, not as admonitions made of the field lines
    assert api.count("doc-section-title") > 20 and "<details" not in api


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed")
def test_ruff_is_clean():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout[-3000:]


# The pages a new user reads first: no commit hash (a page says which command makes its figures),
# and code blocks whose lines fit a laptop-width page (1280 px, both sidebars shown: about 76
# characters) without wrapping.
USER_PAGES = ("README.md", "docs/index.md", "docs/getting_started.md", "docs/choosing.md",
              "docs/results.md", "docs/zoo.md", "docs/defaults.md", "docs/small_ensembles.md",
              "docs/lorenz96.md", "docs/benchmark.md", "docs/tutorial.md", "docs/api.md",
              "docs/guide.md", "CHANGELOG.md")
FIRST_PAGES = ("README.md", "docs/index.md", "docs/getting_started.md", "docs/choosing.md",
               "docs/guide.md")
CODE_WIDTH = 76
# The README's two set-up commands, kept as they are (a user copies them whole).
SETUP = ("python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[plots]' && "
         "python -m experiments.run double_well --out out/double_well",
         ". .venv/bin/activate && pip install -e '.[test]' && python -m pytest -q")
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def _text(page: str) -> str:
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        return f.read()


def test_user_pages_name_no_commit():
    hits = [f"{page}:{n}: {line.strip()[:100]}" for page in USER_PAGES
            for n, line in enumerate(_text(page).splitlines(), 1) if COMMIT.search(line)
            and not line.startswith("<!-- made by:")]  # a hidden code digest, not a commit
    assert not hits, "commit hashes on the user pages:\n" + "\n".join(hits)


def test_commit_pattern_can_fail():
    assert COMMIT.search("made at commit 738fda7") and COMMIT.search("cace770:experiments/")
    assert not COMMIT.search("seed 1000000, 0.0297, lorenz96_abs, deadbeef")


def test_first_pages_code_fits_the_page():
    """The code blocks of the README, the home page, Getting started, the filter-choice page and
    "Your own model" have lines of at most CODE_WIDTH characters, but for the README's set-up
    commands."""
    long = []
    for page in FIRST_PAGES:
        for block in re.findall(r"^```[a-z]*\n(.*?)^```", _text(page), flags=re.S | re.M):
            long += [f"{page}: {line}" for line in block.splitlines()
                     if len(line) > CODE_WIDTH and line not in SETUP]
    assert not long, f"code lines over {CODE_WIDTH} characters:\n" + "\n".join(long)


def test_readme_speaks_to_a_user_first():
    """The README keeps its two set-up commands as they are, says how long the tests take, comes
    to its example before its results, and says what "Ref." is before its table uses it."""
    text = _readme()
    for command in SETUP:
        assert f"```bash\n{command}\n```" in text, command
    assert re.search(r"about \d+ minutes on a 2-core machine, install included", text)
    assert text.index("## Example") < text.index("## Results")
    assert '"Ref." is' in text.split("<!-- results:start -->", 1)[0]


def test_site_css_keeps_code_whole():
    """Code blocks wrap instead of hiding their ends behind a scrollbar, and code in a table cell
    is not broken in the middle of a word."""
    css = re.sub(r"/\*.*?\*/", "", _text("docs/stylesheets/extra.css"), flags=re.S)
    rules = {k.strip(): v for k, v in re.findall(r"([^{}]+)\{([^}]*)\}", css)}
    pre = rules[".md-typeset pre > code"]
    assert "white-space: pre-wrap" in pre and "overflow-x" not in pre
    cell = rules[".md-typeset table:not([class]) code"]
    assert "word-break: keep-all" in cell and "overflow-wrap: normal" in cell


def test_raw_outputs_are_linked_not_in_the_nav():
    """The benchmark history's raw outputs are reached from it, not listed in the navigation (and
    mkdocs.yml says so, so that the strict build does not warn)."""
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load(_text("mkdocs.yml"))
    listed = json.dumps(config["nav"])
    history = _text("docs/bench/history.md")
    raw = sorted(f for f in os.listdir(os.path.join(ROOT, "docs", "bench"))
                 if f.startswith("bench_") and f.endswith(".md"))
    assert raw
    for name in raw:
        assert name not in listed, name
        assert f"]({name})" in history, name
    assert "/bench/bench_d10_*.md" in config["not_in_nav"]


def test_changelog_is_a_users_changelog():
    """CHANGELOG.md: under 15 KB; an Unreleased section first, then versions; under each, only
    Keep a Changelog's sections, each entry one to three lines."""
    text = _text("CHANGELOG.md")
    assert len(text.encode()) < 15_000
    versions = re.findall(r"^## (.+)$", text, flags=re.M)
    assert versions[0] == "Unreleased" and all(
        re.fullmatch(r"\d+\.\d+\.\d+ \(\d{4}-\d\d-\d\d\)", v) for v in versions[1:]), versions
    kinds = set(re.findall(r"^### (.+)$", text, flags=re.M))
    assert kinds <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}, kinds
    entries = re.findall(r"^- .*(?:\n  .*)*", text, flags=re.M)
    assert entries and max(e.count("\n") for e in entries) <= 2


def test_costs_block_and_command():
    """The filter-choice page's table has its cost columns, made by `python -m experiments.costs`
    (whose help runs), with a row for every builder of the command's table."""
    from experiments import costs

    page = _text("docs/choosing.md")
    block = page.split("<!-- results:costs:start -->", 1)[1].split("<!-- results:costs:end -->")[0]
    assert "| first call | per step |" in block
    assert "Made by `python -m experiments.costs --out results/costs --page docs/choosing.md`" \
        in block
    for row in costs.ROWS:
        line = next(l for l in block.splitlines() if f"`{row.builder}`" in l)
        cells = [c.strip() for c in line.strip("|").split("|")]
        timed = [re.fullmatch(r"[0-9.]+&nbsp;m?s", c) for c in cells[-2:]]
        assert all(timed) if row.build is not None else cells[-2:] == ["-", "-"], line
    record = json.loads(_text("results/costs/results.json"))
    assert record["benchmark"] == "costs" and len(record["rows"]) == sum(
        r.build is not None for r in costs.ROWS)
    done = subprocess.run([sys.executable, "-m", "experiments.costs", "--help"], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0 and "--page" in done.stdout, done.stderr[-2000:]


def test_costs_paper_rows_and_block():
    """``--paper`` times the EnKF, the README's call and the trained prior on both of the paper's
    cubic columns, and its block gives each as a multiple of the EnKF's on the same column; the
    benchmark page holds the block's markers, and the command checks them."""
    from experiments import costs

    rows = costs.paper_rows()
    assert [(r.problem, r.label) for r in rows] == [
        (p, label) for p in costs.PAPER_COLUMNS
        for label in ("EnKF", "CSF params=None", "CSF trained")]

    def timed(label, builder, first, step):
        return {"filter": label, "builder": builder, "problem": "cubic20_indep", "dim": 20,
                "particles": 1000, "steps": 40, "first_call_seconds": first,
                "seconds_per_step": step}

    record = {"rows": [timed("EnKF", "methods.enkf()", 4.0, 0.001),
                       timed("CSF params=None", "csf_jax.filter(None, ...)", 10.0, 0.025)],
              "machine": {"cpu": "a CPU", "cpu_count": 2, "jax_backend": "cpu"},
              "command": "python -m experiments.costs --paper", "date": "today"}
    line = next(l for l in costs.paper_page(record) if "filter(None" in l)
    assert "| 25x | 2.5x |" in line, line
    page = _text("docs/benchmark.md")
    assert "<!-- results:costs_paper:start -->" in page and "<!-- results:costs_paper:end -->" in page
    done = subprocess.run([sys.executable, "-m", "experiments.costs", "--paper", "--page",
                           "docs/choosing.md", "--steps", "1"], cwd=ROOT, capture_output=True,
                          text=True, check=False)
    assert done.returncode == 2 and "costs_paper" in done.stderr, done.stderr[-2000:]


def _png_size(path) -> tuple:
    """(width, height) of a PNG, read from its header."""
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n", path
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def test_screenshots_are_small_and_laptop_wide():
    folder = os.path.join(ROOT, "docs", "screenshots")
    shots = sorted(f for f in os.listdir(folder) if f.endswith(".png"))
    assert {"index.png", "choosing.png", "guide.png"} <= set(shots), shots
    for name in shots:
        path = os.path.join(folder, name)
        assert os.path.getsize(path) < 400_000, name
        assert _png_size(path)[0] == 1280, name
