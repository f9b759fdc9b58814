"""Fixtures shared across the suite: the tiny generated scene that the NeRF-training tests start from."""

from __future__ import annotations

from pathlib import Path

import pytest

from nerfuser_ns.bench import scenes


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
