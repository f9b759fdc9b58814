"""The ``auto`` blend method (ours): the paper's IDW-Sample around objects, ``coverage`` for captures along a path.

NeRFuser's IDW-Sample weighs each NeRF by a sample's distance to the NeRF's origin, which tells which NeRF renders
the sample better when each capture circles an object (the paper's object-centric scenes). For captures laid side by
side along a street, a drive or through rooms, the origin says little and the training cameras' coverage
(:mod:`nerfuser_ns.coverage`) says more. ``auto`` tells the two apart from the training cameras alone, once, when
the fused model is built:

* per NeRF, the focus of attention ``f`` of its training cameras (the point nearest every optical axis, among the
  cameras that have it in front: nerfstudio's :func:`~nerfstudio.cameras.camera_utils.focus_of_attention`, started
  at the centroid of the camera centres);
* each camera's miss angle: between its optical axis and the direction from its centre to ``f``;
* the spread of the cameras around ``f``: the length ``R`` of the mean of the unit vectors from ``f`` to the camera
  centres (0 for cameras all around ``f``, 1 for cameras all on one line of sight from it);
* the NeRF *looks at a centre* when the median miss angle is at most :data:`CENTRE_MISS_DEG` and ``R`` at most
  :data:`CENTRE_SPREAD` (cameras a little turned along a street converge far away, all on one side of that point).

``auto`` is ``idw-sample`` when every NeRF looks at a centre and ``coverage`` otherwise; ``idw-sample`` too when a
NeRF's training cameras are unknown (``coverage`` would fall back to it anyway). Angles and the focus move with the
cameras under a similarity, so the choice does not depend on the frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, get_args

import torch
from jaxtyping import Float
from nerfstudio.cameras.camera_utils import focus_of_attention
from torch import Tensor

from nerfuser_ns.coverage import CameraIndex

BlendChoice = Literal["auto", "nerf", "nearest", "idw-2d", "idw-3d", "idw-sample", "coverage", "coverage-3d"]
"""What a user may set: ``auto`` (ours, the default) or one of the blend methods
(:data:`nerfuser_ns.blending.BlendMethod`)."""
BLEND_CHOICES: tuple[str, ...] = get_args(BlendChoice)
AUTO = "auto"

CENTRE_MISS_DEG = 20.0
"""Largest median miss angle (degrees) of cameras that look at one centre. Fixed on validation seeds (900-902) of the
generated layouts before any reported case was scored with ``auto``: rings around an object miss their focus by a
median 2.3-3.1 deg, cameras of streets, drives, rooms and row houses by 68-98 deg."""

CENTRE_SPREAD = 0.9
"""Largest ``R`` (the mean unit vector from the focus to the cameras) of cameras around a centre: a quarter turn of a
ring has 0.91, half a turn 0.71, the generated rings 0.37; a 20 m walk past facades, each view turned by up to 4-15
deg, converges on a point it sees from one side, R 0.96-1.00 (with miss angles of 4-14 deg)."""

AROUND_OBJECTS = "idw-sample"
ALONG_A_PATH = "coverage"


def miss_angles(c2w: Float[Tensor, "num_cams 3|4 4"]) -> tuple[Float[Tensor, " num_cams"], float] | None:
    """Each camera's angle (degrees) between its optical axis (OpenGL: ``-z``) and the direction to the cameras'
    focus of attention, and the cameras' spread ``R`` around it; None when the cameras have no focus (fewer than
    two, or parallel axes)."""
    if c2w.shape[0] < 2:
        return None
    # Setup-time and a few hundred cameras: nerfstudio's solver builds its identity on the CPU, so it runs there.
    poses = c2w[:, :3, :4].detach().to("cpu", torch.float64)
    R = poses[:, :, :3] / torch.linalg.det(poses[:, :, :3]).abs().pow(1.0 / 3.0)[:, None, None]
    poses = torch.cat([R, poses[:, :, 3:]], dim=-1)
    centres, forward = poses[:, :, 3], -poses[:, :, 2]
    # Axes within a couple of degrees of parallel have no focus to speak of (and the solve below would be singular).
    spread = torch.eye(3, dtype=forward.dtype) - (forward[:, :, None] * forward[:, None, :]).mean(dim=0)
    if float(torch.linalg.eigvalsh(spread)[0]) < 1e-3:
        return None
    try:
        focus = focus_of_attention(poses, centres.mean(dim=0))
    except RuntimeError:  # singular: the axes are parallel
        return None
    to_focus = focus - centres
    norm = to_focus.norm(dim=-1)
    if not bool(torch.isfinite(focus).all()) or not bool((norm > 0).all()):
        return None
    unit = to_focus / norm[:, None]
    cos = (unit * forward).sum(dim=-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos)), float(unit.mean(dim=0).norm())


def looks_at_centre(cameras: CameraIndex) -> tuple[bool, float | None, float | None]:
    """Whether one NeRF's training cameras look at a centre, their median miss angle (degrees) and their spread ``R``
    around their focus (both None: no focus)."""
    w2c = cameras.w2c.detach().to("cpu", torch.float64)
    Rt = w2c[:, :, :3]
    c2w = torch.cat([Rt.transpose(-1, -2), cameras.centres.detach().to("cpu", torch.float64)[:, :, None]], dim=-1)
    found = miss_angles(c2w)
    if found is None:
        return False, None, None
    median, spread = float(found[0].median()), found[1]
    return median <= CENTRE_MISS_DEG and spread <= CENTRE_SPREAD, median, spread


def choose_blend_method(cameras: Sequence[CameraIndex | None], names: Sequence[str] | None = None) -> tuple[str, str]:
    """``(method, why)``: the method ``auto`` renders with for NeRFs with these training cameras (None: unknown),
    and one line saying why."""
    names = list(names) if names is not None else [f"NeRF {i}" for i in range(len(cameras))]
    missing = [n for n, c in zip(names, cameras, strict=True) if c is None]
    if missing:
        return AROUND_OBJECTS, (f"{AROUND_OBJECTS}: the training cameras of {', '.join(missing)} are not in the "
                                "registration file")  # fmt: skip
    verdicts = [looks_at_centre(c) for c in cameras]  # type: ignore[arg-type]
    found = ", ".join(f"{n} " + ("no focus" if m is None else f"{m:.0f} deg / {r:.2f}")
                      for n, (_, m, r) in zip(names, verdicts, strict=True))  # fmt: skip
    measured = (f"(median miss angle from the cameras' focus / spread R around it: {found}; a centre: <= "
                f"{CENTRE_MISS_DEG:g} deg / {CENTRE_SPREAD:g})")  # fmt: skip
    if all(inward for inward, _, _ in verdicts):
        return AROUND_OBJECTS, f"{AROUND_OBJECTS} (the paper's): every NeRF's cameras look at a centre {measured}"
    return ALONG_A_PATH, f"{ALONG_A_PATH} (ours): not every NeRF's cameras look at a centre {measured}"
