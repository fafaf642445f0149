"""``slow_tests.txt`` names tests that exist: a renamed or deleted test in it would silently go
back to the default run (or vanish from both)."""

import pathlib
import re

from conftest import SLOW_TESTS

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_listed_slow_test_exists():
    assert len(SLOW_TESTS) > 0
    for node in sorted(SLOW_TESTS):
        path, name = node.split("::", 1)
        function = re.sub(r"\[.*\]$", "", name)
        source = (ROOT / path).read_text()
        assert re.search(rf"^def {re.escape(function)}\(", source, re.M), node


def test_listed_tests_run_only_under_the_slow_marker(request):
    """The default run's selection (``-m 'not slow'`` in pyproject) leaves the listed ones out."""
    collected = {item.nodeid for item in request.session.items}
    if request.config.getoption("markexpr") == "not slow":
        assert not collected & SLOW_TESTS
