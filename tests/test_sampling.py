"""Tests for nerfuser_ns.sampling: hemisphere poses and look_at."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfuser_ns.sampling import look_at, sample_hemisphere_poses


def _assert_valid_c2w(c2w: np.ndarray) -> None:
    R = c2w[..., :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(c2w[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], c2w.shape[:-2] + (4,)))


def _assert_looks_at(c2w: np.ndarray, target: np.ndarray) -> None:
    """The camera's -z axis must be the unit vector from its centre to the target."""
    to_target = target - c2w[..., :3, 3]
    to_target /= np.linalg.norm(to_target, axis=-1, keepdims=True)
    np.testing.assert_allclose(-c2w[..., :3, 2], to_target, atol=1e-12)


# --------------------------------------------------------------------------------------------------------------------
# look_at


def test_look_at_axes_opengl():
    c2w = look_at(np.array([2.0, 0.0, 0.0]), np.zeros(3))
    # Camera on +x looking at the origin: -z_cam = -x_world, x_cam = +y_world (right), y_cam = +z_world (up).
    np.testing.assert_allclose(c2w[:3, 2], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(c2w[:3, 0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(c2w[:3, 1], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(c2w[:3, 3], [2.0, 0.0, 0.0])
    _assert_valid_c2w(c2w)


def test_look_at_vectorised_and_broadcast():
    rng = np.random.default_rng(0)
    eye = rng.normal(size=(5, 7, 3))
    target = rng.normal(size=(3,))
    c2w = look_at(eye, target)
    assert c2w.shape == (5, 7, 4, 4)
    _assert_valid_c2w(c2w)
    _assert_looks_at(c2w, target)
    np.testing.assert_allclose(c2w[..., 2, 0], 0.0, atol=1e-12)  # x axis horizontal for +z up
    assert np.all(c2w[..., 2, 1] > 0)  # image up points to world up (camera not upside down)


@pytest.mark.parametrize("eye", [[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]])
def test_look_at_degenerate_up_parallel(eye):
    c2w = look_at(np.array(eye), np.zeros(3))
    assert np.all(np.isfinite(c2w))
    _assert_valid_c2w(c2w)
    _assert_looks_at(c2w, np.zeros(3))


def test_look_at_bad_inputs():
    with pytest.raises(ValueError, match="coincide"):
        look_at(np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="up"):
        look_at(np.ones(3), np.zeros(3), np.zeros(3))


# --------------------------------------------------------------------------------------------------------------------
# hemisphere sampling


@pytest.mark.parametrize("n", [1, 2, 7, 32, 60, 101])
def test_hemisphere_defaults_geometry(n):
    c2w = sample_hemisphere_poses(n)
    assert c2w.shape == (n, 4, 4)
    assert c2w.dtype == np.float64
    _assert_valid_c2w(c2w)
    centres = c2w[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(centres, axis=-1), 1.0, atol=1e-12)
    elevation = np.degrees(np.arcsin(centres[:, 2]))
    assert elevation.min() >= -1e-9 and elevation.max() <= 30 + 1e-9
    _assert_looks_at(c2w, np.zeros(3))
    np.testing.assert_allclose(c2w[:, 2, 0], 0.0, atol=1e-12)  # +z up: camera x axis horizontal
    assert np.all(c2w[:, 2, 1] > 0)
    # No two cameras at the same place.
    if n > 1:
        d = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.eye(n) * 10
        assert d.min() > 1e-3


def test_hemisphere_paper_layout_covers_band_and_azimuth():
    c2w = sample_hemisphere_poses(32)
    centres = c2w[:, :3, 3]
    elevation = np.degrees(np.arcsin(centres[:, 2]))
    # Both ends of the band are used (rings at 0 and 30 deg).
    np.testing.assert_allclose([elevation.min(), elevation.max()], [0.0, 30.0], atol=1e-9)
    # Azimuths cover the full circle: the largest gap is small.
    az = np.sort(np.arctan2(centres[:, 1], centres[:, 0]))
    gaps = np.diff(np.concatenate([az, az[:1] + 2 * np.pi]))
    assert gaps.max() < np.radians(360 / 32 * 2.5)


def test_hemisphere_radius_center_target_band():
    center = np.array([0.5, -1.0, 2.0])
    target = np.array([0.6, -0.9, 1.5])
    c2w = sample_hemisphere_poses(40, radius=2.5, elevation_range_deg=(10, 60), center=center, target=target)
    rel = c2w[:, :3, 3] - center
    np.testing.assert_allclose(np.linalg.norm(rel, axis=-1), 2.5, atol=1e-12)
    elevation = np.degrees(np.arcsin(rel[:, 2] / 2.5))
    np.testing.assert_allclose([elevation.min(), elevation.max()], [10.0, 60.0], atol=1e-9)
    _assert_looks_at(c2w, target)
    np.testing.assert_allclose(c2w[:, 2, 0], 0.0, atol=1e-12)


def test_hemisphere_num_rings_and_single_elevation():
    c2w = sample_hemisphere_poses(12, elevation_range_deg=(20, 20))
    np.testing.assert_allclose(np.degrees(np.arcsin(c2w[:, 2, 3])), 20.0, atol=1e-9)
    c2w = sample_hemisphere_poses(12, elevation_range_deg=(0, 40), num_rings=3)
    elev = np.round(np.degrees(np.arcsin(c2w[:, 2, 3])), 9)
    np.testing.assert_allclose(np.unique(elev), [0.0, 20.0, 40.0], atol=1e-9)


def test_hemisphere_pole_is_valid():
    c2w = sample_hemisphere_poses(5, elevation_range_deg=(60, 90), num_rings=2)
    _assert_valid_c2w(c2w)
    _assert_looks_at(c2w, np.zeros(3))


def test_hemisphere_jitter_seeded_and_within_band():
    a = sample_hemisphere_poses(32, jitter_deg=5.0, seed=3)
    b = sample_hemisphere_poses(32, jitter_deg=5.0, seed=3)
    c = sample_hemisphere_poses(32, jitter_deg=5.0, seed=4)
    base = sample_hemisphere_poses(32)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert not np.allclose(a, base)
    # Without jitter the layout is deterministic regardless of the seed.
    np.testing.assert_array_equal(base, sample_hemisphere_poses(32, seed=123))
    elevation = np.degrees(np.arcsin(a[:, 2, 3]))
    assert elevation.min() >= -1e-9 and elevation.max() <= 30 + 1e-9
    _assert_looks_at(a, np.zeros(3))
    # The jitter is bounded: every centre stays within ~5 deg (both angles) of its unjittered place.
    ang = np.degrees(np.arccos(np.clip(np.sum(a[:, :3, 3] * base[:, :3, 3], -1), -1, 1)))
    assert ang.max() < 5.0 * math.sqrt(2) + 1e-6


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"num_poses": 0}, "num_poses"),
        ({"num_poses": 2.5}, "num_poses"),
        ({"radius": 0.0}, "radius"),
        ({"radius": -1.0}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"elevation_range_deg": (0, 91)}, r"\[-90, 90\]"),
        ({"elevation_range_deg": (-95, 10)}, r"\[-90, 90\]"),
        ({"elevation_range_deg": (30, 0)}, "min <= max"),
        ({"num_poses": 4, "num_rings": 5}, "num_rings"),
        ({"num_rings": 0}, "num_rings"),
        ({"jitter_deg": -1.0}, "jitter"),
        ({"center": (0.0, 0.0)}, "3-vectors"),
    ],
)
def test_hemisphere_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sample_hemisphere_poses(**kwargs)


def test_hemisphere_target_on_camera_raises():
    # A camera coinciding with the target cannot look at it.
    with pytest.raises(ValueError, match="coincide"):
        sample_hemisphere_poses(4, radius=1.0, target=(1.0, 0.0, 0.0), elevation_range_deg=(0, 0))


# --------------------------------------------------------------------------------------------------------------------
# intrinsics
