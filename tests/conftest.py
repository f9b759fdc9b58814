"""Fixtures shared across the suite (the tiny generated scene that the NeRF-training tests start from), the order
in which the test files are handed to the two test processes, and each process's share of the cores."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch
from threadpoolctl import threadpool_limits

from nerfuser_ns.bench import scenes

TESTS = Path(__file__).resolve().parent

LONGEST_FIRST = (
    "registration/test_pose_graph.py",
    "bench/test_evaluation.py",
    "bench/test_evaluate_script.py",
    "registration/test_known_geometry.py",
    "test_viewer.py",
    "test_model.py",
    "bench/test_practitioner_cases.py",
    "bench/test_scenes.py",
    "test_plugin.py",
    "registration/test_pipeline.py",
)
"""The ten longest test files (35-155 s each in `scripts/test.sh --durations=0` on two cores), longest first.
scripts/test.sh hands whole files to two processes in collection order (``--dist loadfile --no-loadscope-reorder``);
started last, one of these would keep one process busy after the other ran out of work. Replayed from those
durations, this order ends 23 s sooner than the earlier list of eight (574 s against 597 s for the slower process)."""


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def pytest_configure(config: pytest.Config) -> None:
    """Each of the test processes gets its share of the cores for its thread pools (torch's OpenMP, numpy's OpenBLAS,
    and those of the programs it starts). With a pool of every core in each process, their spinning threads fight over
    the cores: the registration tests took 3.7 times as long on two cores (573 s against 156 s for two test files)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if "PYTEST_XDIST_WORKER" not in os.environ or workers < 2 or any(name in os.environ for name in THREAD_VARIABLES):
        return  # one process, or the caller chose
    threads = max(1, torch.get_num_threads() // workers)  # the pool each process would have made, shared out
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)  # for the programs the tests start
    torch.set_num_threads(threads)
    threadpool_limits(threads)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        path = item.path.relative_to(TESTS).as_posix() if item.path.is_relative_to(TESTS) else ""
        return LONGEST_FIRST.index(path) if path in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: every file's tests keep their order, the other files theirs


@pytest.fixture(scope="session")
def load_script() -> Callable[[str], ModuleType]:
    """``load_script(name)``: ``scripts/<name>.py`` imported as the module ``<name>_script``, once per session (kept in
    ``sys.modules``, through which its dataclasses resolve their annotations)."""

    def load(name: str) -> ModuleType:
        module_name = f"{name}_script"
        if module_name not in sys.modules:
            spec = importlib.util.spec_from_file_location(module_name, TESTS.parent / "scripts" / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            sys.modules[module_name] = module
            spec.loader.exec_module(module)
        return sys.modules[module_name]

    return load


@pytest.fixture(scope="session")
def tiny_layout() -> scenes.SceneLayout:
    """An object-centric room at 40x30 px, 12 views per capture, 2 test views (seconds to train on)."""
    return scenes.make_layout("object-centric", seed=3, num_views=12, num_test_views=2, width=40, height=30)


@pytest.fixture(scope="session")
def tiny_scene(tiny_layout, tmp_path_factory) -> Path:
    """``tiny_layout`` written once as datasets (``capture_a``, ``capture_b``, ``test``, ground_truth.json);
    tests read it and never write into it."""
    out = tmp_path_factory.mktemp("tiny_scene") / "scene"
    scenes.write_scene(tiny_layout, out, supersample=1)
    return out
