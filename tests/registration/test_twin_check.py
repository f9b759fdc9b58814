"""The SfM mode's twin check on the generated room (exact depth): the half-turn twin that a free SfM links is refused,
the true link passes, and the room without its door is reported as symmetric."""

from __future__ import annotations

import numpy as np
import pytest
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.cameras import Intrinsics, intrinsics_from_fov
from nerfuser_ns.registration.render_cache import render_views_cached
from nerfuser_ns.registration.twin_check import relative_link, twin_check

W, H, VIEWS = 240, 180, 16
QUIET = Console(quiet=True)
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])  # about the room's vertical axis, which its walls repeat under


def room(work, symmetric: bool):
    """The room's two captures rendered with depth at their training poses, their true link and its twin."""
    layout = scenes.make_layout("room", seed=0, num_views=VIEWS, num_test_views=1, width=W, height=H,
                                symmetric=symmetric)  # fmt: skip
    renderers = [SceneFrameRenderer.from_layout(layout, c) for c in ("capture_a", "capture_b")]
    config = reg.RegistrationConfig(sampling=reg.PoseSamplingConfig(source="training", width=W, height=H, fov_deg=60.0,
                                                                    max_training_poses=VIEWS))  # fmt: skip
    views = [render_views_cached(r, config.sampling, work / "renders", QUIET, depth=True) for r in renderers]
    a, b = (c.capture_to_world for c in layout.captures[:2])
    true, twin = sim3.invert_sim3(a) @ b, sim3.invert_sim3(a) @ HALF_TURN @ b
    return renderers, views, config, true, twin


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("twin_check")


def check(renderers, views, config, T_b_to_a):
    intr = Intrinsics(*intrinsics_from_fov(W, H, 60.0), W, H)
    return twin_check(renderers, views, np.stack([np.eye(4), T_b_to_a]), [(0, 1)], intr, config, QUIET)


def test_the_half_turn_twin_is_refused_and_the_true_link_passes(work):
    renderers, views, config, true, twin = room(work, symmetric=False)
    passed = check(renderers, views, config, true)
    assert passed.refusal is None and passed.warning is None
    (pair,) = passed.summary["pairs"]
    assert pair["verdict"] == "passed" and pair["rivals"] >= 1  # the twin is among the hypotheses, and loses
    assert pair["sfm_ncc"] > pair["rival_ncc"] + config.known_geometry.ambiguity_margin
    refused = check(renderers, views, config, twin)
    assert refused.refusal is not None and refused.refusal.startswith("twin check: capture_a / capture_b: another "
                                                                      "transform (180 deg")  # fmt: skip
    (pair,) = refused.summary["pairs"]
    assert pair["verdict"] == "twin"
    # the rival that beat the twin is the true link
    err = sim3.sim3_errors(np.asarray(pair["rival_T_j_to_i"]), true)
    assert err.r_err_deg < 0.1 and err.t_err < 0.005 and err.s_err < 0.005


def test_the_symmetric_room_is_a_warning_not_a_refusal(work):
    renderers, views, config, true, _ = room(work / "symmetric", symmetric=True)
    verdict = check(renderers, views, config, true)
    assert verdict.refusal is None
    assert verdict.warning is not None and "the overlap looks symmetric" in verdict.warning
    assert verdict.summary["pairs"][0]["verdict"] == "ambiguous"


def test_the_relative_link_is_b_to_a():
    rng = np.random.default_rng(0)
    T = sim3.random_sim3(rng, size=(3,))
    T[0] = np.eye(4)
    p_b = rng.normal(size=3)
    # a point of b mapped into the reference frame equals the linked point of a mapped there
    assert np.allclose(sim3.transform_points(T[2], p_b),
                       sim3.transform_points(T[1], sim3.transform_points(relative_link(T, 1, 2), p_b)))
