"""Writes ``tests/slow_tests.txt``: the tests the default run leaves to ``-m slow`` so that it stays
under 10 minutes on the CI machine (2 cores). A test goes there when its setup, call and teardown
took ``THRESHOLD`` seconds or more in a full default run, except ``KEPT``: the closed-form checks
of CSF and of the reference against the Kalman filter, the API's bad-input errors and the README's
example, which the default run keeps whatever they cost.

    python -m pytest -q --durations=0 -p no:cacheprovider > durations.log
    python tests/slow_list.py durations.log

Tests already in the list stay in it (a slow test is not in the durations of a default run).
"""

import collections
import pathlib
import re
import sys

THRESHOLD = 8.0
KEPT = ("tests/test_csf.py::test_gaussian_prior_csf_tracks_kalman",
        "tests/test_csf.py::test_bad_inputs_raise_clear_errors",
        "tests/test_reference.py::test_matches_kalman_on_a_separable_linear_gaussian_model",
        "tests/test_docs.py::test_readme_example_runs")
LIST = pathlib.Path(__file__).with_name("slow_tests.txt")
LINE = re.compile(r"^\s*([0-9.]+)s (?:setup|call|teardown)\s+(\S.*?)\s*$")


def read(path) -> set:
    """The node ids listed in ``path`` (comments and blank lines skipped)."""
    text = pathlib.Path(path).read_text() if pathlib.Path(path).exists() else ""
    return {s.strip() for s in text.splitlines() if s.strip() and not s.startswith("#")}


def main(log: str) -> None:
    seconds = collections.Counter()
    for line in pathlib.Path(log).read_text().splitlines():
        match = LINE.match(line)
        if match:
            seconds[match.group(2)] += float(match.group(1))
    slow = {t for t, s in seconds.items() if s >= THRESHOLD and t not in KEPT} | read(LIST)
    header = [line for line in LIST.read_text().splitlines() if line.startswith("#")] if \
        LIST.exists() else []
    LIST.write_text("\n".join(header + sorted(slow)) + "\n")
    print(f"{len(slow)} tests in {LIST.name}")


if __name__ == "__main__":
    main(sys.argv[1])
