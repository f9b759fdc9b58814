"""The self-check calibration script's geometry (scripts/calibrate_ncc.py): perturbations of the exact size asked,
and the views nearest the other NeRF's cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nerfuser_ns import sim3
from nerfuser_ns.registration import ViewSet


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("calibrate_ncc")


def _sim3(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return sim3.make_sim3(sim3.so3_exp(rng.normal(size=3)), rng.normal(size=3), float(np.exp(rng.normal(0, 0.3))))


@pytest.mark.parametrize("kind,size", [("rotation_deg", 5.0), ("translation", 0.2), ("log_scale", 0.1)])
def test_each_perturbation_is_the_error_it_names(script, kind, size):
    T = _sim3(1)
    moved = script.perturb(T, kind, size, np.random.default_rng(0))
    e = sim3.sim3_errors(moved, T)
    if kind == "rotation_deg":  # about the NeRF's own origin, which stays (t_err is the common frame origin's move)
        assert (e.r_err_deg, e.s_err) == pytest.approx((size, 0.0), abs=1e-9)
        assert np.allclose(sim3.transform_points(moved, np.zeros((1, 3))), T[:3, 3])
    elif kind == "translation":
        assert (e.r_err_deg, e.t_err, e.s_err) == pytest.approx((0.0, size, 0.0), abs=1e-9)
    else:  # about the NeRF's origin: its origin stays where it was
        assert (e.r_err_deg, e.s_err) == pytest.approx((0.0, size), abs=1e-9)
        assert np.allclose(sim3.transform_points(moved, np.zeros((1, 3))), T[:3, 3])
    assert np.array_equal(script.perturb(T, "none", 0.0, np.random.default_rng(0)), T)


def test_nearest_views_puts_the_views_by_the_other_nerf_first_and_drops_unkept_ones(script):
    def views(xs: list[float], kept: list[bool]) -> ViewSet:
        c2w = np.tile(np.eye(4), (len(xs), 1, 1))
        c2w[:, 0, 3] = xs
        return ViewSet("v", Path("."), c2w, ["training"] * len(xs), np.ones(len(xs)), np.array(kept))

    a = views([0.0, 1.0, 2.0, 3.0], [True, True, False, True])
    b = views([0.0, 0.5], [True, True])
    # a's frame is b's shifted by -3 along x: a's view at x=3 sits at b's x=0
    T_a_to_b = sim3.make_sim3(np.eye(3), np.array([-3.0, 0.0, 0.0]), 1.0)
    assert script.nearest_views(a, T_a_to_b, b) == [3, 1, 0]  # view 2 (nearer than 1) is not kept
