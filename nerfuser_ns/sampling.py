"""Camera pose sampling in a NeRF's own frame, for registration from re-rendering (NeRFuser, Sec. 3.2 / 4.1).

The paper renders each NeRF from poses "roughly uniformly placed on the upper hemisphere of radius 1, with elevation
from 0 to 30 deg", looking at the origin. Poses here are camera-to-world 4x4 matrices in nerfstudio's OpenGL camera
convention: the camera looks along its -z axis, +y is up in the image, +x to the right. The world is +z up.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

Vec3 = Sequence[float] | np.ndarray


def look_at(
    eye: Float[np.ndarray, "*bs 3"],
    target: Float[np.ndarray, "*bs 3"],
    up: Float[np.ndarray, "*bs 3"] = (0.0, 0.0, 1.0),
) -> Float[np.ndarray, "*bs 4 4"]:
    """Camera-to-world poses (OpenGL convention) at ``eye`` looking at ``target``, image-up towards ``up``.

    The camera's -z axis points from ``eye`` to ``target`` and its x axis is perpendicular to ``up`` (horizontal for
    ``up = +z``). When the viewing direction is (anti)parallel to ``up`` the image-up direction is undefined; then the
    world axis least aligned with the viewing direction is used instead of ``up``, which gives a deterministic,
    valid frame. Inputs broadcast against each other. Raises ``ValueError`` if ``eye == target`` or ``up == 0``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    eye, target, up = np.broadcast_arrays(eye, target, up)

    back = eye - target  # camera +z points away from what it looks at
    dist = np.linalg.norm(back, axis=-1, keepdims=True)
    if np.any(dist <= 1e-12 * np.maximum(1.0, np.linalg.norm(eye, axis=-1, keepdims=True))):
        raise ValueError("look_at: eye and target coincide, the viewing direction is undefined")
    up_norm = np.linalg.norm(up, axis=-1, keepdims=True)
    if np.any(up_norm == 0):
        raise ValueError("look_at: up vector must be non-zero")
    z = back / dist

    x = np.cross(up / up_norm, z)
    x_norm = np.linalg.norm(x, axis=-1, keepdims=True)
    degenerate = x_norm[..., 0] < 1e-9
    if np.any(degenerate):
        # Fallback "up": the world axis least aligned with the viewing direction.
        zd = z[degenerate]
        alt = np.eye(3)[np.argmin(np.abs(zd), axis=-1)]
        x_alt = np.cross(alt, zd)
        x[degenerate] = x_alt
        x_norm[degenerate] = np.linalg.norm(x_alt, axis=-1, keepdims=True)
    x = x / x_norm
    y = np.cross(z, x)

    c2w = np.zeros(eye.shape[:-1] + (4, 4))
    c2w[..., :3, 0] = x
    c2w[..., :3, 1] = y
    c2w[..., :3, 2] = z
    c2w[..., :3, 3] = eye
    c2w[..., 3, 3] = 1.0
    return c2w


def _auto_num_rings(num_poses: int, el_min: float, el_max: float) -> int:
    """Rings so that spacing along elevation ~ spacing along azimuth (roughly uniform density on the band)."""
    band = el_max - el_min
    if band <= 0 or num_poses == 1:
        return 1
    mid_circumference = 2 * math.pi * max(math.cos((el_min + el_max) / 2), 1e-3)
    # Equal spacing: band / (n - 1) = circumference * n / N  ->  n (n - 1) = N band / circumference =: x.
    x = num_poses * band / mid_circumference
    return int(min(num_poses, max(1, round((1 + math.sqrt(1 + 4 * x)) / 2))))


def _split_counts(num_poses: int, weights: np.ndarray) -> np.ndarray:
    """Integer counts summing to ``num_poses``, proportional to ``weights``, at least 1 each (largest remainder)."""
    k = len(weights)
    counts = np.ones(k, dtype=int)
    rest = num_poses - k
    if rest > 0:
        share = rest * weights / weights.sum()
        counts += np.floor(share).astype(int)
        left = num_poses - counts.sum()
        order = np.argsort(-(share - np.floor(share)), kind="stable")
        counts[order[:left]] += 1
    return counts


def sample_hemisphere_poses(
    num_poses: int = 32,
    radius: float = 1.0,
    elevation_range_deg: tuple[float, float] = (0.0, 30.0),
    center: Vec3 = (0.0, 0.0, 0.0),
    target: Vec3 | None = None,
    num_rings: int | None = None,
    jitter_deg: float = 0.0,
    seed: int | None = None,
) -> Float[np.ndarray, "n 4 4"]:
    """Camera-to-world poses on rings of a sphere around ``center``, all looking at ``target`` (+z up, OpenGL).

    Rings are spread evenly over the elevation band (both ends included when there are several), poses are shared
    among the rings in proportion to their circumference, azimuths are even on each ring and successive rings are
    rotated by a fraction of the azimuth step so that cameras interleave. ``jitter_deg`` adds a seeded uniform
    perturbation in ``[-jitter, jitter]`` to azimuth and elevation (elevation clipped to the band, radius kept).

    Args:
        num_poses: number of cameras (>= 1).
        radius: distance from ``center`` (> 0), in the NeRF's units.
        elevation_range_deg: ``(min, max)`` elevation above the ``center``'s xy plane, in [-90, 90].
        center: centre of the sphere.
        target: point every camera looks at; defaults to ``center``.
        num_rings: number of elevation rings; chosen from ``num_poses`` and the band if None.
        jitter_deg: amplitude of the random perturbation (0: fully deterministic layout).
        seed: seed of the jitter.

    Returns:
        ``[num_poses, 4, 4]`` camera-to-world matrices.
    """
    if int(num_poses) != num_poses or num_poses < 1:
        raise ValueError(f"num_poses must be a positive integer, got {num_poses}")
    num_poses = int(num_poses)
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive and finite, got {radius}")
    el_min_deg, el_max_deg = (float(e) for e in elevation_range_deg)
    if not (-90.0 <= el_min_deg <= 90.0 and -90.0 <= el_max_deg <= 90.0):
        raise ValueError(f"elevations must lie in [-90, 90] degrees, got {elevation_range_deg}")
    if el_min_deg > el_max_deg:
        raise ValueError(f"elevation range must satisfy min <= max, got {elevation_range_deg}")
    if num_rings is not None and (int(num_rings) != num_rings or not 1 <= num_rings <= num_poses):
        raise ValueError(f"num_rings must be an integer in [1, num_poses={num_poses}], got {num_rings}")
    if not (np.isfinite(jitter_deg) and jitter_deg >= 0):
        raise ValueError(f"jitter_deg must be >= 0, got {jitter_deg}")
    center = np.asarray(center, dtype=np.float64)
    target = center if target is None else np.asarray(target, dtype=np.float64)
    if center.shape != (3,) or target.shape != (3,):
        raise ValueError("center and target must be 3-vectors")

    el_min, el_max = math.radians(el_min_deg), math.radians(el_max_deg)
    n_rings = _auto_num_rings(num_poses, el_min, el_max) if num_rings is None else int(num_rings)
    ring_el = np.linspace(el_min, el_max, n_rings) if n_rings > 1 else np.array([(el_min + el_max) / 2])
    # Circumference weights; a small floor keeps a ring at the pole from getting zero cameras.
    counts = _split_counts(num_poses, np.maximum(np.cos(ring_el), 1e-3))

    ring = np.repeat(np.arange(n_rings), counts)
    idx = np.arange(num_poses) - np.repeat(np.cumsum(counts) - counts, counts)  # index within ring
    n_on_ring = counts[ring]
    azimuth = 2 * math.pi * (idx + ring / n_rings) / n_on_ring
    elevation = ring_el[ring]

    if jitter_deg > 0:
        rng = np.random.default_rng(seed)
        j = math.radians(jitter_deg)
        azimuth = azimuth + rng.uniform(-j, j, num_poses)
        elevation = np.clip(elevation + rng.uniform(-j, j, num_poses), el_min, el_max)

    direction = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    )
    eye = center + radius * direction
    return look_at(eye, target, np.array([0.0, 0.0, 1.0]))
