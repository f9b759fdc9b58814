"""Tests for nerfuser_ns.cameras: intrinsics from a field of view, pixel rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfuser_ns.cameras import (
    Intrinsics,
    camera_rays,
    fov_from_intrinsics,
    intrinsics_from_fov,
    intrinsics_matrix,
    supersample_offsets,
)


def test_intrinsics_from_fov():
    fx, fy, cx, cy = intrinsics_from_fov(640, 480, 90.0)
    assert (fx, fy, cx, cy) == pytest.approx((320.0, 320.0, 320.0, 240.0), abs=1e-9)
    fx, fy, _, _ = intrinsics_from_fov(640, 480, 60.0, fov_axis="y")
    assert fx == fy == pytest.approx(240.0 / math.tan(math.radians(30.0)), rel=1e-12)
    assert fov_from_intrinsics(fx, 480) == pytest.approx(60.0, abs=1e-12)
    K = intrinsics_matrix(100.0, 110.0, 50.0, 40.0)
    np.testing.assert_array_equal(K, [[100, 0, 50], [0, 110, 40], [0, 0, 1]])


@pytest.mark.parametrize("args", [(0, 10, 60), (10, -1, 60), (10, 10, 0), (10, 10, 180)])
def test_intrinsics_bad_inputs(args):
    with pytest.raises(ValueError):
        intrinsics_from_fov(*args)


def test_intrinsics_from_fov_matches_the_tuple_form():
    k = Intrinsics.from_fov(64, 48, 70.0)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx(intrinsics_from_fov(64, 48, 70.0), rel=1e-12)
    with pytest.raises(ValueError, match="width"):
        Intrinsics.from_fov(0, 48, 70.0)


def test_camera_rays_hit_the_pixel_they_belong_to():
    """Projecting a point along each pixel-centre ray back through K lands on that pixel's centre (OpenGL axes)."""
    k = Intrinsics(50.0, 55.0, 16.5, 11.0, 32, 24)
    c2w = np.eye(4)
    o, d = camera_rays(c2w, k)
    assert o.shape == d.shape == (24, 32, 1, 3)
    torch.testing.assert_close(torch.linalg.norm(d, dim=-1), torch.ones(24, 32, 1, dtype=torch.float64))
    p = (o + 2.0 * d)[..., 0, :]  # camera frame = world frame
    col = k.fx * p[..., 0] / -p[..., 2] + k.cx
    row = -k.fy * p[..., 1] / -p[..., 2] + k.cy
    rows, cols = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    torch.testing.assert_close(col, cols.double() + 0.5)
    torch.testing.assert_close(row, rows.double() + 0.5)


def test_supersample_offsets_are_a_centred_grid():
    assert supersample_offsets(1) == [(0.5, 0.5)]
    offs = np.array(supersample_offsets(3))
    assert offs.shape == (9, 2) and np.allclose(offs.mean(axis=0), 0.5)
    with pytest.raises(ValueError):
        supersample_offsets(0)
