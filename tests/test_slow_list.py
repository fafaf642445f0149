"""``slow_tests.txt`` names tests that exist: a renamed or deleted test in it would silently go
back to the default run (or vanish from both)."""

import pathlib
import re

from conftest import SLOW_TESTS, pytest_collection_modifyitems

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_listed_slow_test_exists():
    assert len(SLOW_TESTS) > 0
    for node in sorted(SLOW_TESTS):
        path, name = node.split("::", 1)
        function = re.sub(r"\[.*\]$", "", name)
        source = (ROOT / path).read_text()
        assert re.search(rf"^def {re.escape(function)}\(", source, re.M), node


def test_the_hook_marks_listed_tests_slow_and_no_other():
    """``conftest.pytest_collection_modifyitems`` adds the slow marker to a listed test only."""

    class Item:
        def __init__(self, nodeid):
            self.nodeid, self.markers = nodeid, []

        def add_marker(self, marker):
            self.markers.append(marker.name)

    listed, other = Item(sorted(SLOW_TESTS)[0]), Item("tests/test_kalman.py::not_listed")
    pytest_collection_modifyitems(None, [listed, other])
    assert listed.markers == ["slow"] and other.markers == []
