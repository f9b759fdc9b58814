"""The test-order tool (scripts/test_order.py): per-file times from pytest's durations, xdist's hand-out replayed, and
the order tests/conftest.py keeps."""

from __future__ import annotations

from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]

LOG = """============================= slowest durations =============================
12.50s call     tests/registration/test_a.py::test_one[cpu]
0.50s setup    tests/registration/test_a.py::test_one[cpu]
3.00s call     tests/registration/test_a.py::test_two
2.00s call     tests/test_b.py::test_three
0.25s teardown tests/test_b.py::test_three
(20 durations < 0.005s hidden.  Use -vv to show these durations.)
"""


@pytest.fixture(scope="module")
def order(load_script):
    return load_script("test_order")


def test_file_times_sum_each_tests_phases_per_file(order):
    assert order.file_times(LOG) == {"tests/registration/test_a.py": [13.0, 3.0], "tests/test_b.py": [2.25]}
    assert order.file_times("no durations here") == {}
    assert order.TRUNCATED.search("=== slowest 15 durations ===") and not order.TRUNCATED.search(LOG)


def test_replay_follows_xdists_hand_out_of_whole_files(order):
    files = {"a": [10.0], "b": [6.0], "c": [4.0], "d": [1.0, 1.0, 1.0, 1.0]}
    # each process takes one file, then another while it has at most two tests pending: a one-test file pairs up
    assert order.replay(["a", "b", "c"], files, 2) == [14.0, 6.0]
    clock = order.replay(["d", "a", "b", "c"], files, 2)
    assert sum(clock) == pytest.approx(sum(map(sum, files.values())))  # every test runs once
    assert max(clock) >= 10.0
    assert order.replay(["a"], files, 2) == [10.0, 0.0]
    # a file the log does not know (new since) is left out, and never stalls the process that drew it
    assert order.replay(["a", "new", "b", "c"], files, 2) == order.replay(["a", "b", "c"], files, 2)


def test_every_file_conftest_starts_first_exists(order):
    listed = order.longest_first(TESTS / "conftest.py")
    assert len(listed) == len(set(listed)) >= 1
    missing = [p for p in listed if not (TESTS / p).is_file()]
    assert not missing, f"tests/conftest.py LONGEST_FIRST names files that do not exist: {missing}"


def test_collection_order_names_files_as_pytests_log_does(order, tmp_path, monkeypatch):
    (tmp_path / "tests" / "sub").mkdir(parents=True)
    for name in ("tests/test_b.py", "tests/sub/test_a.py", "tests/sub/helper.py", "tests/test_a.py"):
        (tmp_path / name).write_text("")
    monkeypatch.chdir(tmp_path / "tests" / "sub")  # the result does not depend on where the tool runs
    assert order.collection_order(tmp_path / "tests") == ["tests/sub/test_a.py", "tests/test_a.py", "tests/test_b.py"]
    assert order.ROOT == TESTS.parent and "tests/bench/test_test_order.py" in order.collection_order(TESTS)
