"""Writes ``tests/slow_tests.txt``: the tests the default run leaves to ``-m slow`` so that it stays
under 10 minutes on the CI machine (2 cores). A test goes there when its setup, call and teardown
took ``THRESHOLD`` seconds or more in a full default run, except ``KEPT``: the closed-form checks
of CSF (its filter and its log evidence) and of the reference against the Kalman filter, the
API's bad-input errors, the README's example, ``jax.jit`` of ``csf_jax.filter`` as a user writes
it and the transform CSF's default radius switch against the LETKF, which the default run keeps
whatever they cost.

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
        "tests/test_docs.py::test_readme_example_runs",
        "tests/test_local_transform.py::test_far_steps_are_analysed_at_the_far_radius",
        "tests/test_evidence.py::test_csf_evidence_near_the_exact_likelihood",
        "tests/test_user_calls.py::test_jit_of_csf_filter_equals_the_plain_call")
LIST = pathlib.Path(__file__).with_name("slow_tests.txt")
LINE = re.compile(r"^\s*([0-9.]+)s (?:setup|call|teardown)\s+(\S.*?)\s*$")


HEADER = f"""# Tests the default run leaves to `python -m pytest -q -m slow` (tests/conftest.py marks them):
# each took {THRESHOLD:g} s or more in a full default run on the CI machine (2 cores). Written by
# tests/slow_list.py from a `--durations=0` log; see its docstring.
"""


def main(log: str) -> None:
    seconds = collections.Counter()
    for line in pathlib.Path(log).read_text().splitlines():
        match = LINE.match(line)
        if match:
            seconds[match.group(2)] += float(match.group(1))
    listed = LIST.read_text().splitlines() if LIST.exists() else []
    slow = {t for t, s in seconds.items() if s >= THRESHOLD and t not in KEPT}
    slow |= {line for line in listed if line and not line.startswith("#")}
    LIST.write_text(HEADER + "".join(f"{t}\n" for t in sorted(slow)))
    print(f"{len(slow)} tests in {LIST.name}")


if __name__ == "__main__":
    main(sys.argv[1])
