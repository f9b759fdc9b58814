"""Pinhole cameras shared by every part of the project: intrinsics, pixel rays and field-of-view conversions.

Cameras follow nerfstudio: camera-to-world 4x4 matrices with OpenGL camera axes (the camera looks along -z, +y is up
in the image, +x right); pinhole intrinsics ``fx, fy, cx, cy, width, height`` in pixels; the ray of pixel
``(row, col)`` goes through ``(col + 0.5, row + 0.5)``. Camera poses and SIM(3) maths live in :mod:`nerfuser_ns.sim3`,
pose sampling in :mod:`nerfuser_ns.sampling`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

ArrayOrTensor = np.ndarray | Tensor


def check_positive_int(name: str, value, minimum: int = 1) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is an integer >= ``minimum`` (bools refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (nerfstudio convention: principal point in pixel units, pixel centres at +0.5)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, centred principal point, horizontal field of view ``hfov_deg``."""
        check_positive_int("width", width)
        check_positive_int("height", height)
        if not 1.0 <= hfov_deg <= 170.0:
            raise ValueError(f"horizontal field of view must be in [1, 170] degrees, got {hfov_deg}")
        f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        return cls(fx=f, fy=f, cx=width / 2, cy=height / 2, width=width, height=height)


def intrinsics_from_fov(
    width: int, height: int, fov_deg: float, fov_axis: Literal["x", "y"] = "x"
) -> tuple[float, float, float, float]:
    """Pinhole intrinsics ``(fx, fy, cx, cy)`` with square pixels and the principal point at the image centre.

    ``fov_deg`` is the full field of view along the image width (``fov_axis="x"``) or height (``"y"``).
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not 0 < fov_deg < 180:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    if fov_axis not in ("x", "y"):
        raise ValueError(f"fov_axis must be 'x' or 'y', got {fov_axis!r}")
    extent = width if fov_axis == "x" else height
    f = (extent / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return f, f, width / 2.0, height / 2.0


def fov_from_intrinsics(focal: float, extent: int) -> float:
    """Full field of view in degrees for focal length ``focal`` (pixels) over ``extent`` pixels."""
    return math.degrees(2.0 * math.atan2(extent / 2.0, focal))


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> Float[np.ndarray, "3 3"]:
    """3x3 pinhole calibration matrix ``K``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def camera_rays(
    c2w: ArrayOrTensor, intrinsics: Intrinsics, offsets: Sequence[tuple[float, float]] = ((0.5, 0.5),)
) -> tuple[Float[Tensor, "h w k 3"], Float[Tensor, "h w k 3"]]:
    """Unit-direction rays (float64) of one camera; ``offsets`` are (x, y) sub-pixel positions within each pixel.

    Directions follow nerfstudio: camera-space ``((col + ox - cx) / fx, -(row + oy - cy) / fy, -1)``, normalised.
    """
    fx, fy, cx, cy, width, height = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width,
                                     intrinsics.height)  # fmt: skip
    c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float64) if not isinstance(c2w, Tensor) else c2w)
    c2w_t = c2w_t.to(torch.float64)
    if c2w_t.shape not in ((3, 4), (4, 4)):
        raise ValueError(f"c2w must be [3, 4] or [4, 4], got {tuple(c2w_t.shape)}")
    device = c2w_t.device
    rows = torch.arange(height, dtype=torch.float64, device=device)[:, None, None]
    cols = torch.arange(width, dtype=torch.float64, device=device)[None, :, None]
    off = torch.as_tensor(offsets, dtype=torch.float64, device=device)  # [k, 2]
    x = (cols + off[:, 0] - cx) / fx
    y = -(rows + off[:, 1] - cy) / fy
    x, y = torch.broadcast_tensors(x, y)
    d_cam = torch.stack([x, y, -torch.ones_like(x)], dim=-1)  # [h, w, k, 3]
    d_cam = d_cam / torch.linalg.norm(d_cam, dim=-1, keepdim=True)
    directions = d_cam @ c2w_t[:3, :3].T
    directions = directions / torch.linalg.norm(directions, dim=-1, keepdim=True)
    origins = c2w_t[:3, 3].expand_as(directions)
    return origins, directions


def supersample_offsets(n: int) -> list[tuple[float, float]]:
    """Regular n x n sub-pixel grid (stratified centres) used for anti-aliasing."""
    check_positive_int("supersample", n)
    grid = [(i + 0.5) / n for i in range(n)]
    return [(ox, oy) for oy in grid for ox in grid]
