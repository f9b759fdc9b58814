"""Coverage-aware blend weights (ours, beyond the paper): how well each NeRF's training cameras saw a sample.

A NeRF renders well what its training cameras saw, from similar directions and at a similar or finer resolution:
the per-source-camera weighting of image-based rendering since Unstructured Lumigraph Rendering (Buehler et al.,
2001: angle, resolution and field-of-view penalties). The ``coverage`` blend method replaces IDW-Sample's distances
to the NeRF origins (the paper's) by a score of each NeRF's training cameras, per merged sample; everything else
(merging, background pseudo-sample, distance test, both normalisations) is IDW-Sample's.

Pure, vectorised torch math; every tensor is created on the input's device. No model, no dataset.

Formulas
--------
For a sample point ``x = o + t d`` on a query ray (origin ``o``, unit direction ``d``, angular pixel size
``a = sqrt(pixel_area)``, so the query pixel's footprint at ``x`` is ``r_q = a t``) and a training camera ``j``
(centre ``c_j``, camera-to-world rotation ``R_j`` with OpenGL axes, pinhole ``fx, fy, cx, cy``, image ``W x H``):

* camera coordinates ``p = R_j^T (x - c_j)``, depth ``z = -p_z``, pixel ``u = cx + fx p_x / z``,
  ``v = cy - fy p_y / z``;
* visibility ``vis_j = [z > 0] [0 <= u <= W] [0 <= v <= H]`` (in front, inside the frustum);
* angle ``theta_j = angle(d, x - c_j)``: between the query ray and the training ray through ``x``;
  angular term ``A_j = exp(-theta_j^2 / (2 sigma^2))``;
* resolution: the training pixel's footprint at ``x`` is ``r_j = z / sqrt(fx fy)``; resolution term
  ``P_j = min(1, r_q / r_j)`` (1 when the camera saw ``x`` at least as finely as the query needs it, the ratio when
  it saw it coarser);
* camera quality ``q_j = vis_j A_j P_j`` in ``[0, 1]``;
* NeRF score ``S(x, d) = (1 / k) sum of the k largest q_j`` (absent cameras count 0): a point that only one camera
  saw scores lower than one that ``k`` cameras saw alike, as a NeRF's geometry needs several views.

Every term is invariant under a similarity applied to cameras, points and rays together (angles, the frustum test
and the ratio ``r_q / r_j`` do not change), so the index may live in the NeRF's frame or in the common frame.

Look-ups: ``q`` against every camera would cost ``samples x cameras``. Instead, per ray, the ``m`` candidate
cameras (``CoverageParams.candidates``) with the best quality at one representative point of the ray (the blend's
expected termination point) are found with one ``[rays, cameras]`` evaluation and ``topk``; every sample of the ray
then scores against those ``m`` alone (``[rays, samples, m]``). With ``m >=`` the number of cameras this is exact.

Blend weights (normalisation (1) of IDW-Sample, :func:`nerfuser_ns.blending.coverage_weights`): ``w_i ∝ S_i^gamma``
over the NeRFs passing the distance test, i.e. IDW on the pseudo-distance ``1 / S_i``: ``gamma`` keeps its meaning
(0: the mean, inf: the best-covered NeRF alone). Samples that no NeRF taking part covers (every ``S_i = 0``) take
IDW-Sample's weights from the distances to the NeRF origins.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor


@dataclass(frozen=True)
class CoverageParams:
    """Constants of the coverage score (fix them on a validation scene, never on reported test views)."""

    sigma_deg: float = 20.0
    """Width of the angular term ``exp(-theta^2 / (2 sigma^2))``, degrees."""
    k: int = 4
    """Cameras averaged into a NeRF's score (the ``k`` best)."""
    candidates: int = 16
    """Candidate cameras per ray, chosen at the ray's representative point; each sample scores against these."""

    def checked(self) -> CoverageParams:
        """This value, or ValueError (one line) naming what is wrong."""
        if not (0 < self.sigma_deg <= 180):
            raise ValueError(f"nerfuser: coverage sigma_deg must be in (0, 180], got {self.sigma_deg}")
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ValueError(f"nerfuser: coverage k must be an integer >= 1, got {self.k!r}")
        if isinstance(self.candidates, bool) or not isinstance(self.candidates, int) or self.candidates < self.k:
            raise ValueError(f"nerfuser: coverage candidates must be an integer >= k ({self.k}), "
                             f"got {self.candidates!r}")
        return self


@dataclass
class CameraIndex:
    """One NeRF's training cameras, packed for look-ups: world-to-camera matrices and intrinsics."""

    w2c: Float[Tensor, "num_cams 3 4"]
    """``[R^T | -R^T c]`` with ``R`` the (orthonormal) camera-to-world rotation, OpenGL axes."""
    intrinsics: Float[Tensor, "num_cams 6"]
    """``fx, fy, cx, cy, width, height`` in pixels."""

    @classmethod
    def from_cameras(
        cls,
        c2w: Float[Tensor, "num_cams 3|4 4"] | Float[np.ndarray, "num_cams 3|4 4"],
        intrinsics: Float[Tensor, "num_cams 6"] | Float[np.ndarray, "num_cams 6"] | Sequence[float],
    ) -> CameraIndex:
        """From camera-to-world poses (a pose's scale, if any, is removed from its rotation) and intrinsics
        ``[fx, fy, cx, cy, width, height]`` per camera (or one row shared by all)."""
        c2w_t = torch.as_tensor(np.asarray(c2w) if not isinstance(c2w, Tensor) else c2w).to(torch.float32)
        if c2w_t.ndim != 3 or c2w_t.shape[-2:] not in ((3, 4), (4, 4)):
            raise ValueError(f"camera poses must be [n, 3|4, 4], got {tuple(c2w_t.shape)}")
        k = torch.as_tensor(np.asarray(intrinsics) if not isinstance(intrinsics, Tensor) else intrinsics)
        k = k.to(device=c2w_t.device, dtype=torch.float32).reshape(-1, 6).expand(len(c2w_t), 6).contiguous()
        if not bool(torch.isfinite(c2w_t).all() & torch.isfinite(k).all()) or not bool((k[:, [0, 1, 4, 5]] > 0).all()):
            raise ValueError("camera poses and intrinsics must be finite, focal lengths and sizes positive")
        A, c = c2w_t[:, :3, :3], c2w_t[:, :3, 3]
        scale = torch.linalg.det(A).abs().pow(1.0 / 3.0).clamp(min=torch.finfo(A.dtype).tiny)
        R = A / scale[:, None, None]
        Rt = R.transpose(-1, -2)
        w2c = torch.cat([Rt, -(Rt @ c[:, :, None])], dim=-1)
        return cls(w2c=w2c, intrinsics=k)

    def __len__(self) -> int:
        return int(self.w2c.shape[0])

    @property
    def centres(self) -> Float[Tensor, "num_cams 3"]:
        Rt, b = self.w2c[:, :, :3], self.w2c[:, :, 3]
        return -(Rt.transpose(-1, -2) @ b[:, :, None])[..., 0]

    def transformed(self, T: Float[Tensor, "4 4"] | Float[np.ndarray, "4 4"]) -> CameraIndex:
        """The same cameras in another frame: ``T`` (a SIM(3), ``p' = T [p, 1]``) maps this index's frame into it.
        Intrinsics do not change (angles do not)."""
        T64 = torch.as_tensor(np.asarray(T) if not isinstance(T, Tensor) else T, dtype=torch.float64)
        T64 = T64.to(self.w2c.device)
        A, t = T64[:3, :3], T64[:3, 3]
        s = torch.linalg.det(A).pow(1.0 / 3.0)
        Q = A / s
        Rt = self.w2c[:, :, :3].double()
        c = self.centres.double()
        c_new = c @ A.T + t
        Rt_new = Rt @ Q.T  # (Q R)^T
        w2c = torch.cat([Rt_new, -(Rt_new @ c_new[:, :, None])], dim=-1)
        return CameraIndex(w2c=w2c.to(self.w2c.dtype), intrinsics=self.intrinsics)

    def to(self, *args, **kwargs) -> CameraIndex:
        return CameraIndex(w2c=self.w2c.to(*args, **kwargs), intrinsics=self.intrinsics.to(*args, **kwargs))


def camera_quality(
    index: CameraIndex,
    ray_origins: Float[Tensor, "*bs 3"],
    ray_directions: Float[Tensor, "*bs 3"],
    ts: Float[Tensor, "*bs num_points"],
    pixel_widths: Float[Tensor, " *bs"],
    sigma_deg: float,
    cam_ids: Int[Tensor, "*bs m"] | None = None,
) -> Float[Tensor, "*bs num_points m"]:
    """``q_j`` (module docstring) of the points ``o + t d`` of each ray against the cameras ``cam_ids`` of that ray
    (all cameras when None: ``m = len(index)``).

    Args:
        index: the cameras, in the frame of the rays.
        ray_origins, ray_directions: the query rays (directions need not be unit).
        ts: distances along ``ray_directions`` (the points are ``o + t d``).
        pixel_widths: the query pixel's angular size ``sqrt(pixel_area)`` (its footprint at distance 1).
        sigma_deg: angular width.
        cam_ids: per ray, the cameras to score against.
    """
    dtype = ray_origins.dtype
    w2c, k = index.w2c.to(dtype), index.intrinsics.to(dtype)
    if cam_ids is None:
        P = w2c.expand(ray_origins.shape[:-1] + w2c.shape)  # [*bs, m, 3, 4]
        K = k.expand(ray_origins.shape[:-1] + k.shape)  # [*bs, m, 6]
    else:
        P, K = w2c[cam_ids], k[cam_ids]
    norm = torch.linalg.vector_norm(ray_directions, dim=-1, keepdim=True).clamp(min=torch.finfo(dtype).tiny)
    d = ray_directions / norm
    dist = ts * norm  # [*bs, S]: distances from the ray origin
    # Camera coordinates p = P [o + dist d; 1] = (P o_h) + dist (R^T d): per ray and camera, then per point.
    o_cam = (P[..., :3] @ ray_origins[..., None, :, None])[..., 0] + P[..., 3]  # [*bs, m, 3]
    d_cam = (P[..., :3] @ d[..., None, :, None])[..., 0]  # [*bs, m, 3]
    p = o_cam.unsqueeze(-3) + dist[..., :, None, None] * d_cam.unsqueeze(-3)  # [*bs, S, m, 3]
    z = -p[..., 2]
    fx, fy, cx, cy, width, height = (K[..., None, :, i] for i in range(6))
    z_safe = torch.where(z > 0, z, torch.ones_like(z))
    u = cx + fx * p[..., 0] / z_safe
    v = cy - fy * p[..., 1] / z_safe
    visible = (z > 0) & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    # Angle between the query direction and the camera's ray through x: x - c_j is p in camera coordinates.
    p_norm = torch.linalg.vector_norm(p, dim=-1).clamp(min=torch.finfo(dtype).tiny)
    cos = ((p * d_cam.unsqueeze(-3)).sum(-1) / p_norm).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    sigma = math.radians(sigma_deg)
    angular = torch.exp(-0.5 * (theta / sigma) ** 2)
    r_query = pixel_widths[..., None, None] * dist[..., None]  # [*bs, S, 1]
    r_train = z_safe / torch.sqrt(fx * fy)
    resolution = torch.clamp(r_query / r_train, max=1.0)
    return torch.where(visible, angular * resolution, torch.zeros_like(angular))


def candidate_cameras(
    index: CameraIndex,
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    t_rep: Float[Tensor, " num_rays"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
) -> Int[Tensor, "num_rays m"]:
    """Per ray, the ``min(candidates, num_cams)`` cameras of best quality at the point ``o + t_rep d`` (ties broken
    by the smaller angle): one ``[rays, cameras]`` evaluation and ``topk``."""
    m = min(params.candidates, len(index))
    q = camera_quality(index, ray_origins, ray_directions, t_rep[:, None], pixel_widths, params.sigma_deg)[:, 0]
    # Tie-break (cameras that do not see the point score 0): prefer the camera pointing most along the ray.
    w2c = index.w2c.to(ray_directions)
    axes = -w2c[:, 2, :3]  # camera-to-world -z: the viewing direction
    d = torch.nn.functional.normalize(ray_directions, dim=-1)
    key = q + 1e-6 * (1.0 + d @ axes.T)
    return torch.topk(key, m, dim=-1).indices


def coverage_scores(
    index: CameraIndex,
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    ts: Float[Tensor, "num_rays num_points"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
    t_rep: Float[Tensor, " num_rays"] | None = None,
) -> Float[Tensor, "num_rays num_points"]:
    """The NeRF score ``S`` (module docstring) of every point ``o + t d``: the mean of its ``k`` best camera
    qualities among the ray's candidates (:func:`candidate_cameras` at ``t_rep``; every camera when ``t_rep`` is None
    or there are at most ``candidates`` cameras)."""
    if len(index) == 0:
        return torch.zeros_like(ts)
    ids = None
    if t_rep is not None and len(index) > params.candidates:
        ids = candidate_cameras(index, ray_origins, ray_directions, t_rep, pixel_widths, params)
    q = camera_quality(index, ray_origins, ray_directions, ts, pixel_widths, params.sigma_deg, ids)
    top = torch.topk(q, min(params.k, q.shape[-1]), dim=-1).values
    return top.sum(-1) / params.k

