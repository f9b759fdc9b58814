"""Direct photometric alignment (step 4b): the pure maths against exact answers, a perturbed transform pulled back to
the truth on ground-truth scene renderers (exact depth), the caps, and the SfM mode with it end to end."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from registration_helpers import gt_of, small_config
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration import direct
from nerfuser_ns.registration.known_geometry import pixel_rays
from nerfuser_ns.registration.render_cache import render_views_cached

QUIET = Console(quiet=True)


def test_correction_is_identity_at_zero_and_keeps_its_centre():
    centre = np.array([0.3, -0.2, 0.5])
    np.testing.assert_allclose(direct.correction(np.zeros(7), centre, 200.0, 3.0), np.eye(4), atol=1e-15)
    # 2 units about z at focal 200: 0.01 rad; the centre stays put; a scale unit is exp(1/200)
    D = direct.correction(np.array([0, 0, 2.0, 0, 0, 0, 1.0]), centre, 200.0, 3.0)
    R, t, s = sim3.decompose_sim3(D)
    assert sim3.rotation_angle_deg(R) == pytest.approx(np.degrees(0.01), rel=1e-9)
    assert s == pytest.approx(np.exp(1 / 200), rel=1e-12)
    np.testing.assert_allclose(sim3.transform_points(D, centre), centre, atol=1e-12)
    # a translation unit moves by distance / focal
    D = direct.correction(np.array([0, 0, 0, 1.0, 0, 0, 0]), centre, 200.0, 3.0)
    np.testing.assert_allclose(sim3.transform_points(D, centre) - centre, [3.0 / 200, 0, 0], atol=1e-12)


def test_subsampled_intrinsics_keep_every_other_pixel_ray_for_ray():
    full = Intrinsics(200.0, 210.0, 120.0, 90.0, 240, 180)
    small = direct.subsampled(full, 2)
    assert (small.width, small.height) == (120, 90)
    c2w = np.eye(4)
    xy_small = np.array([[0.5, 0.5], [7.5, 3.5], [119.5, 89.5]])
    xy_full = 2 * (xy_small - 0.5) + 0.5  # the centres of pixels (0, 0), (14, 6), (238, 178)
    np.testing.assert_allclose(pixel_rays(c2w, xy_small, small), pixel_rays(c2w, xy_full, full), atol=1e-12)


@pytest.fixture(scope="module")
def oc_pair(oc_layout, oc_renderers, work):
    cfg = small_config()
    views = [render_views_cached(r, cfg.sampling, work / "renders", QUIET) for r in oc_renderers]
    gt = gt_of(oc_layout)
    T_true = sim3.relative_sim3(gt[0], gt[1])  # capture_b -> capture_a
    return views, T_true, cfg.sampling.intrinsics()


def _samples(oc_renderers, oc_pair, T, cfg):
    views, _, intr = oc_pair
    accs = [v.load_accumulation() for v in views]
    order = {(a, b): np.flatnonzero(views[a].kept) for a, b in ((0, 1), (1, 0))}
    return direct._pair_samples(oc_renderers, views, T, 0, 1, order, intr, cfg, accs)


def test_residuals_vanish_at_the_true_transform(oc_renderers, oc_pair):
    _, T_true, intr = oc_pair
    samples = _samples(oc_renderers, oc_pair, T_true, direct.DirectConfig(views=3))
    assert {s.parent_side for s in samples} == {True, False}
    r = direct.residuals(np.eye(4), T_true, samples, intr)
    assert len(r) > 5000
    # exact renderers, the half-size render's rays on the full renders' pixel centres: agree up to PNG rounding
    assert np.median(np.abs(r)) < 0.002


def test_alignment_pulls_a_perturbed_transform_back_to_the_truth(oc_renderers, oc_pair):
    _, T_true, intr = oc_pair
    # 0.4 deg, 1% of the scene in translation, 0.5% in scale: the size of an SfM error on blurry renders, and more
    wrong = sim3.make_sim3(1.005 * sim3.so3_exp(np.radians(0.4) * np.array([0.6, -0.64, 0.48])),
                           np.array([0.01, -0.008, 0.006]))  # fmt: skip
    T0 = wrong @ T_true
    cfg = direct.DirectConfig(views=6)
    T, result = direct.align_pair(_samples(oc_renderers, oc_pair, T0, cfg), T0, intr, cfg, 0, 1)
    before, after = sim3.sim3_errors(T0, T_true), sim3.sim3_errors(T, T_true)
    assert result.used and result.cost_after < result.cost_before
    assert after.r_err_deg < 0.2 * before.r_err_deg and after.r_err_deg < 0.05
    assert after.t_err < 0.2 * before.t_err
    assert after.s_err < 0.2 * before.s_err
    # the caps: the same fit is refused when it must move further than allowed, and the transform is kept
    tight = dataclasses.replace(cfg, max_change_deg=0.1)
    T_kept, refused = direct.align_pair(_samples(oc_renderers, oc_pair, T0, tight), T0, intr, tight, 0, 1)
    assert not refused.used and "beyond the caps" in refused.reason
    np.testing.assert_array_equal(T_kept, T0)


def test_too_few_pixels_keep_the_transform(oc_pair):
    _, T_true, intr = oc_pair
    T, result = direct.align_pair([], T_true, intr, direct.DirectConfig(), 0, 1)
    assert not result.used and "pixels" in result.reason
    np.testing.assert_array_equal(T, T_true)


def test_sfm_mode_aligns_directly_by_default_and_records_it(oc_layout, oc_renderers, oc_record, work):
    section = oc_record["direct"]  # the package's registration, every default
    assert [(p["parent"], p["child"]) for p in section["pairs"]] == [(0, 1)]
    assert section["settings"] == dataclasses.asdict(direct.DirectConfig())
    assert "direct" in oc_record["compute_timings_s"]
    without = reg.register(oc_renderers, small_config(direct=direct.DirectConfig(enabled=False)), work, QUIET)
    record = score_registration(without, gt_of(oc_layout))
    assert "direct" not in record and reg.RegistrationResult.from_record(record).direct is None
    base, with_direct = record["nerfs"][1]["ground_truth"], oc_record["nerfs"][1]["ground_truth"]
    # exact renders: the bundle adjustment is already near-exact; the direct fit must not make it worse
    assert with_direct["r_err_deg"] <= max(base["r_err_deg"], 0.01) * 1.5
    assert with_direct["t_err"] <= max(base["t_err"], 0.001) * 1.5


def test_renderers_without_depth_keep_their_transform(oc_pair):
    views, T_true, intr = oc_pair

    class NoDepth:
        name = "no-depth"

        def render(self, c2w, intrinsics):
            raise AssertionError("must not render")

    T = np.stack([np.eye(4), sim3.invert_sim3(T_true)])
    out, section = direct.align_direct([NoDepth(), NoDepth()], views, T, [(0, 1)], 0, intr, direct.DirectConfig(),
                                       {}, QUIET)  # fmt: skip
    np.testing.assert_array_equal(out, T)
    assert section["pairs"][0]["used"] is False and "gives no depth" in section["pairs"][0]["reason"]
