"""Which test files to start first: per-file times from a test log with every duration, and the hand-out replayed.

``scripts/test.sh`` runs two pytest-xdist processes with ``--dist loadfile --no-loadscope-reorder``: each process gets
the next file in collection order when it has at most two tests of its own left. ``tests/conftest.py`` moves the
files of ``LONGEST_FIRST`` to the front. To re-measure::

    bash scripts/test.sh --durations=0 > test.log
    python scripts/test_order.py --log test.log

prints the longest files and, replayed with those times, when the slower process finishes under the current order,
under the ``--top`` longest files first, and under every file longest first.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]
"""The repository: its ``tests`` folder is read wherever the script is run from."""
DURATION = re.compile(r"^([\d.]+)s (?:setup|call|teardown)\s+(tests/\S+?\.py)::(\S+)", re.M)
TRUNCATED = re.compile(r"slowest \d+ durations")
"""pytest's header when it lists only the slowest tests (``--durations=N``, as ``make test`` runs it)."""


@dataclass
class OrderTests:
    """Per-file test times and the replayed hand-out of files to the test processes."""

    log: Path
    """Output of ``bash scripts/test.sh --durations=0`` (pytest's per-test setup / call / teardown times)."""
    workers: int = 2
    """Test processes (``NERFUSER_TEST_WORKERS``)."""
    top: int = 10
    """How many of the longest files to put first in the proposed order."""


def file_times(log: str) -> dict[str, list[float]]:
    """Per test file (``tests/...py``, first-seen order), the seconds of each of its tests (setup + call + teardown)."""
    per_test: dict[tuple[str, str], float] = defaultdict(float)
    for seconds, path, name in DURATION.findall(log):
        per_test[(path, name)] += float(seconds)
    files: dict[str, list[float]] = {}
    for (path, _), seconds in per_test.items():
        files.setdefault(path, []).append(seconds)
    return files


def replay(order: list[str], files: dict[str, list[float]], workers: int) -> list[float]:
    """When each process finishes: xdist's loadfile hand-out (one file each, then the next whenever a process has at
    most two tests pending), each process running its tests one after another. Files without times (new since the
    log) are left out."""
    queue = [path for path in order if files.get(path)]
    pending: list[list[float]] = [[] for _ in range(workers)]
    clock = [0.0] * workers

    def hand_out(k: int) -> None:
        if queue and len(pending[k]) <= 2:
            pending[k] += files[queue.pop(0)]

    for k in range(workers):
        hand_out(k)
    for k in range(workers):
        hand_out(k)
    while any(pending):
        k = min((k for k in range(workers) if pending[k]), key=lambda k: clock[k])
        clock[k] += pending[k].pop(0)
        hand_out(k)
    return clock


def collection_order(root: Path) -> list[str]:
    """Test files as pytest collects them: each folder's entries sorted by name, folders and files alike; paths
    relative to ``root``'s parent (``tests/...py``, as pytest's log names them)."""
    found: list[str] = []
    for entry in sorted(root.iterdir(), key=lambda p: p.name):
        if entry.is_dir() and not entry.name.startswith((".", "_")):
            found += [f"{root.name}/{p}" for p in collection_order(entry)]
        elif entry.name.startswith("test_") and entry.suffix == ".py":
            found.append(f"{root.name}/{entry.name}")
    return found


def longest_first(conftest: Path) -> list[str]:
    """``LONGEST_FIRST`` of ``tests/conftest.py``, read from its source (importing it would load torch)."""
    for node in ast.parse(conftest.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "LONGEST_FIRST" for t in node.targets):
            return list(ast.literal_eval(node.value))
    raise SystemExit(f"test_order: no LONGEST_FIRST in {conftest}")


def main(cmd: OrderTests) -> None:
    log = cmd.log.read_text()
    if TRUNCATED.search(log) or not (files := file_times(log)):
        raise SystemExit(f"test_order: {cmd.log} lacks every test's duration; run scripts/test.sh with --durations=0")
    total = {path: sum(times) for path, times in files.items()}
    collected = collection_order(ROOT / "tests")
    longest = sorted(collected, key=lambda p: -total.get(p, 0.0))
    print(f"{len(files)} files, {sum(total.values()):.0f} s of tests in all")
    for path in longest[: cmd.top]:
        print(f"{total.get(path, 0.0):8.1f} s  {len(files.get(path, [])):3d} tests  {path}")

    def first(paths: list[str]) -> list[str]:
        return paths + [p for p in collected if p not in paths]

    orders = {
        "current (tests/conftest.py)": first([f"tests/{p}" for p in longest_first(ROOT / "tests" / "conftest.py")]),
        f"the {cmd.top} longest first": first(longest[: cmd.top]),
        "every file longest first": longest,
    }
    for label, order in orders.items():
        clock = replay(order, files, cmd.workers)
        print(f"{label}: slower process {max(clock):.0f} s ({', '.join(f'{c:.0f}' for c in clock)})")


if __name__ == "__main__":
    main(tyro.cli(OrderTests))
