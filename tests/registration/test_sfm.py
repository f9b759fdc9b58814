"""The SfM over the renders (:mod:`nerfuser_ns.registration.sfm`): the pose-guided pair list, linear in the
image count, and three street segments whose 48 images take it instead of exhaustive matching."""

from __future__ import annotations

import numpy as np
import pytest
from registration_helpers import H, W, gt_of, small_config

from nerfuser_ns import registration as reg
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.registration import sfm as reg_sfm
from nerfuser_ns.sampling import sample_hemisphere_poses


@pytest.mark.slow
def test_street_three_nerfs(work):
    """Three street segments from their training poses (12 per capture leaves one segment unconnected)."""
    layout = scenes.make_layout("street", seed=1, num_views=16, num_test_views=1, num_captures=3, width=W, height=H)
    renderers = [SceneFrameRenderer.from_layout(layout, c.name) for c in layout.captures]
    # 48 images over the exhaustive limit: exercises the pose-guided pair list
    config = small_config(sampling={"source": "training"}, sfm=reg.SfMConfig(exhaustive_max_images=40))
    rec = score_registration(reg.register(renderers, config, work), gt_of(layout))
    assert rec["sfm"]["matching"] == "pose-guided pairs"
    assert len(rec["pairs"]) == 3
    checked = [p for p in rec["pairs"] if p["self_check"] is not None]
    assert len(checked) == 2 and all(p["self_check"]["passed"] for p in checked)  # spanning tree of 3 NeRFs
    for n in rec["nerfs"][1:]:
        g = n["ground_truth"]
        # measured: capture_2 (14 m from the reference capture) r 0.096 deg, t 0.011, s 0.0076 -- t is in the
        # reference's units (~2.5 m), so the lever arm turns a 0.1 deg rotation error into ~0.01 of translation
        assert g["r_err_deg"] < 0.4 and g["t_err"] < 0.04 and g["s_err"] < 0.03, (n["name"], g)


def test_pose_guided_pairs_are_linear_in_the_image_count(tmp_path):
    def viewset(name, n):
        c2w = sample_hemisphere_poses(n)
        return reg.ViewSet(name, tmp_path / name, c2w, ["hemisphere"] * n, np.ones(n), np.ones(n, bool))

    cfg = reg.SfMConfig(own_neighbors=4, cross_views=6)
    views = [viewset("a", 40), viewset("b", 40), viewset("c", 40)]
    pairs = reg_sfm._cheap_pairs(views, [v.image_names for v in views], cfg)
    assert len(pairs) == len(set(pairs)) and all(a < b for a, b in pairs)
    assert len(pairs) <= 120 * (4 + 2 * 6)
    n_ab = sum(a.startswith("a/") and b.startswith("b/") for a, b in pairs)
    assert n_ab >= 40 * 6  # every image of a meets 6 views of b (and vice versa)


@pytest.mark.parametrize("source", ["hemisphere", "training", "both"])
def test_separate_models_advise_what_fits_the_pose_source(source):
    # after the training poses, advice to render "the run's training poses" would send the user in a circle
    from types import SimpleNamespace

    views = [SimpleNamespace(name=n, kept=np.ones(8, bool)) for n in ("a", "b")]
    sfm = SimpleNamespace(model_counts=[[8, 0], [0, 8]])
    with pytest.raises(reg.RegistrationError, match="b: its views form a separate SfM model from a") as e:
        reg_sfm.check_registered_views(sfm, views, 2, source)
    assert ("--sampling.source training|both" in str(e.value)) == (source == "hemisphere")
    assert ("--mode known-geometry" in str(e.value)) == (source != "hemisphere")
