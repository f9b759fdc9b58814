"""Fixtures shared by the registration tests: a work folder and the object-centric pair (its layout, its two
ground-truth renderers and their registration, scored).

All ``scope="package"`` (this folder has no ``__init__.py``, so pytest keeps them for the session): computed once for
every file here, as they were once for the single module these tests came from. Renders and SfM results are cached
in the shared work folder, so tests that reuse a NeRF's views do not render them again."""

from __future__ import annotations

from pathlib import Path

import pytest
from registration_helpers import H, W, gt_of, small_config

from nerfuser_ns import registration as reg
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer


@pytest.fixture(scope="package")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("register_work")


@pytest.fixture(scope="package")
def oc_layout():
    return scenes.make_layout("object-centric", seed=0, num_views=16, num_test_views=1, width=W, height=H)


@pytest.fixture(scope="package")
def oc_renderers(oc_layout) -> list[SceneFrameRenderer]:
    return [SceneFrameRenderer.from_layout(oc_layout, c) for c in ("capture_a", "capture_b")]


@pytest.fixture(scope="package")
def oc_record(oc_layout, oc_renderers, work) -> dict:
    return score_registration(reg.register(oc_renderers, small_config(), work), gt_of(oc_layout))
