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

Evaluation: along a ray (unit ``d``, ``t`` the distance from ``o``) every term is a cheap function of ``t``. With
``p = o_cam + t d_cam`` (``x - c_j`` in camera axes), the depth is ``z = z0 + t zd``; each visibility test, multiplied
by ``z``, is a half-line of ``t``, so ``vis_j = [t_lo <= t <= t_hi]``; ``theta_j = atan2(|(o - c_j) x d|,
(o - c_j) . d + t)``, the cross product the same at every ``t``; ``r_q / r_j = a sqrt(fx fy) t / z``. These constants
are computed once per ray and candidate, then each sample costs a dozen elementwise operations, one camera at a time,
its ``q_j`` folded at once into a running sum of the ``k`` best (on the CPU, where a row stays in cache). Off the CPU
the same operations run on blocks of cameras at once, folded with ``topk``: a GPU pays per kernel, not per row.

Blend weights (normalisation (1) of IDW-Sample, :func:`nerfuser_ns.blending.coverage_weights`): ``w_i ∝ S_i^gamma``
over the NeRFs passing the distance test, i.e. IDW on the pseudo-distance ``1 / S_i``: ``gamma`` keeps its meaning
(0: the mean, inf: the best-covered NeRF alone). Samples that no NeRF taking part covers (every ``S_i = 0``) take
IDW-Sample's weights from the distances to the NeRF origins.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor


@dataclass(frozen=True)
class CoverageParams:
    """Constants of the coverage score (fix them on a validation scene, never on reported test views)."""

    sigma_deg: float = 40.0
    """Width of the angular term ``exp(-theta^2 / (2 sigma^2))``, degrees (chosen on validation seeds of a street and
    a drive by ``scripts/validate_coverage.py``'s fixed rule; 20 before)."""
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


def _camera_frames(
    index: CameraIndex, ray_origins: Float[Tensor, "n 3"], unit_directions: Float[Tensor, "n 3"]
) -> Float[Tensor, "6 num_cams n"]:
    """The rays in the axes of every camera ``j``: ``o - c_j`` (rows 0-2) and ``d`` (rows 3-5), a point of the ray
    being ``p = o_cam + t d_cam``. Two small matrix products."""
    w2c = index.w2c.to(ray_origins)
    m, n = len(index), len(ray_origins)
    rot = w2c[:, :, :3].transpose(0, 1).reshape(3 * m, 3)  # row i * m + j: camera j's axis i
    frames = ray_origins.new_empty((6, m, n))
    torch.mm(rot, ray_origins.T, out=frames[:3].view(3 * m, n))
    torch.mm(rot, unit_directions.T, out=frames[3:].view(3 * m, n))
    frames[:3] += w2c[:, :, 3].T[:, :, None]
    return frames


def _point_quality(
    index: CameraIndex,
    frames: Float[Tensor, "6 num_cams n"],
    dist: Float[Tensor, " n"],
    pixel_widths: Float[Tensor, " n"],
    sigma_deg: float,
) -> Float[Tensor, "num_cams n"]:
    """``q_j`` of one point per ray (at distance ``dist`` along the unit ray) against every camera: the module
    docstring's formulas as written (the candidates' look-up)."""
    fx, fy, cx, cy, width, height = index.intrinsics.to(frames).T[:, :, None]  # [C, 1] each
    d_cam = frames[3:]
    p = torch.addcmul(frames[:3], d_cam, dist)  # [3, C, n]: x - c_j in camera axes
    z = p[2].neg()
    z_safe = z.clamp(min=torch.finfo(z.dtype).tiny)  # where z <= 0 the point is hidden anyway
    u = (p[0] * fx).div_(z_safe).add_(cx)
    v = (p[1] * fy).div_(z_safe).sub_(cy).neg_()
    hidden = (z <= 0) | (u < 0) | (u > width) | (v < 0) | (v > height)
    del u, v
    # The angle between d and the camera's ray through x, x - c_j being p in camera axes.
    p_norm = (p[0] * p[0]).addcmul_(p[1], p[1]).addcmul_(p[2], p[2]).sqrt_().clamp_(min=torch.finfo(z.dtype).tiny)
    cos = (p[0] * d_cam[0]).addcmul_(p[1], d_cam[1]).addcmul_(p[2], d_cam[2]).div_(p_norm).clamp_(-1.0, 1.0)
    q = cos.acos_().square_().mul_(-0.5 / math.radians(sigma_deg) ** 2).exp_()  # A_j
    # P_j = min(1, r_q / r_j) with r_q = a t, r_j = z / sqrt(fx fy)
    q.mul_((torch.sqrt(fx * fy) * (pixel_widths * dist)).div_(z_safe).clamp_(max=1.0))
    return q.masked_fill_(hidden, 0.0)


@dataclass
class _RayCameraTerms:
    """Per camera and ray, the constants that make each factor of ``q_j`` a few operations of the distance ``t`` along
    the (unit) ray (module docstring, "Evaluation"). Every field is ``[m, n]``, the rays last: the per-point work then
    runs along long contiguous rows of rays (per-ray constants broadcast along a short inner axis of samples cost CPU
    kernels several times more)."""

    along: Tensor
    """``(o - c_j) . d``: ``x - c_j`` has the component ``along + t`` along ``d``..."""
    across: Tensor
    """... and ``|(o - c_j) x d|`` across it, the same at every ``t``."""
    z0: Tensor
    """Depth ``z = z0 + t zd``."""
    zd: Tensor
    t_lo: Tensor
    """The visibility test: ``vis_j = [t_lo <= t <= t_hi]``."""
    t_hi: Tensor
    gain: Tensor
    """``r_q / r_j = gain t / z`` (``gain = a sqrt(fx fy)``)."""


def _ray_camera_terms(
    frames: Float[Tensor, "6 m n"],
    intrinsics: Float[Tensor, "6 m n"] | Float[Tensor, "6 m 1"],
    pixel_widths: Float[Tensor, " n"],
) -> _RayCameraTerms:
    """:class:`_RayCameraTerms` from the rays in the cameras' axes (:func:`_camera_frames`)."""
    o_cam, d_cam = frames[:3], frames[3:]
    along = (o_cam[0] * d_cam[0]).addcmul_(o_cam[1], d_cam[1]).addcmul_(o_cam[2], d_cam[2])
    across = torch.linalg.cross(o_cam, d_cam, dim=0).square_().sum(0).sqrt_()
    fx, fy, cx, cy, width, height = intrinsics
    # Each visibility test is a half-line of t, a + b t >= 0 (the pixel tests multiplied by z > 0), [5, m, n] with
    # the point (x, y, -z) = o_cam + t d_cam: z > 0, u >= 0, u <= W, v >= 0, v <= H; a and b at once ([2, m, n]).
    od = frames.view(2, 3, *frames.shape[1:])  # [o_cam, d_cam]
    x, y, z = od[:, 0], od[:, 1], od[:, 2].neg()
    u_lo = torch.addcmul(fx * x, cx, z)  # z (u - 0)
    v_lo = torch.addcmul(-fy * y, cy, z)  # z (v - 0)
    a, b = torch.stack([z, u_lo, width * z - u_lo, v_lo, height * z - v_lo], dim=1)
    del x, y, u_lo, v_lo
    root = (a / b).neg_()  # where b = 0: +-inf or nan, masked below
    root[0] = torch.nextafter(root[0], b[0] * math.inf)  # z > 0 is strict: the camera centre itself is not seen
    t_lo = root.masked_fill(b <= 0, -math.inf).amax(0)
    t_hi = root.masked_fill_(b >= 0, math.inf).amin(0)
    # b = 0: a test that t does not change, passed everywhere or nowhere.
    never = ((b == 0) & (a < 0)).any(0) | ((b[0] == 0) & (a[0] <= 0))
    return _RayCameraTerms(along=along, across=across, z0=a[0], zd=b[0], t_lo=t_lo.masked_fill_(never, math.inf),
                           t_hi=t_hi, gain=torch.sqrt(fx * fy) * pixel_widths)  # fmt: skip


def _qualities(
    terms: _RayCameraTerms, dist: Float[Tensor, "n num_points"], sigma_deg: float
) -> Iterator[Float[Tensor, "num_points n"]]:
    """``q_j`` at distances ``dist`` along the unit rays of ``terms``, one camera ``j`` after the other (``[S, n]``).

    The blend's hot loop. Each row is made in buffers that the next one reuses (consume a row before asking for the
    next; it may be overwritten): a row stays in cache for the dozen passes that make it and for its consumer, where
    ``[m, S, n]`` tensors send every pass to memory (~5x slower on a busy CPU) and each fresh buffer pays its page
    faults. ``t`` runs along the rows' long contiguous axis of rays, per-ray constants broadcast along the samples."""
    t = dist.T.contiguous()  # [S, n]
    c = -0.5 / math.radians(sigma_deg) ** 2
    q, res = torch.empty_like(t), torch.empty_like(t)
    hidden = torch.empty_like(t, dtype=torch.bool)
    per_camera = zip(*(getattr(terms, f.name)[:, None] for f in fields(terms)), strict=True)  # each [1, n]
    for row_terms in per_camera:
        yield _quality_into(q, res, hidden, t, c, *row_terms)


def _quality_into(
    q: Tensor, res: Tensor, hidden: Tensor, t: Tensor, c: float,
    along: Tensor, across: Tensor, z0: Tensor, zd: Tensor, t_lo: Tensor, t_hi: Tensor, gain: Tensor,
) -> Tensor:  # fmt: skip
    """``q_j`` at distances ``t`` from one camera's (or a block's) terms, made in the buffers ``q``, ``res`` and
    ``hidden`` of the broadcast shape; ``c = -1 / (2 sigma^2)``. The row loop and the GPU blocks share it."""
    # theta_j in [0, pi] as acos of the cosine would be, and accurate near 0 and pi
    torch.atan2(across, torch.add(along, t, out=q), out=q)
    q.square_().mul_(c).exp_()  # A_j
    # P_j = min(1, r_q / r_j) = min(1, gain t / z); where hidden, z may be <= 0: masked below.
    torch.div(t, torch.addcmul(z0, t, zd, out=res), out=res)
    q.mul_(res.mul_(gain).clamp_(max=1.0))
    q.masked_fill_(torch.lt(t, t_lo, out=hidden), 0.0)
    return q.masked_fill_(torch.gt(t, t_hi, out=hidden), 0.0)


def _sum_of_best_blocked(
    terms: _RayCameraTerms, dist: Float[Tensor, "n num_points"], sigma_deg: float, k: int, max_elements: int = 1 << 25
) -> Float[Tensor, "num_points n"]:
    """The sum of the ``k`` best ``q_j`` at distances ``dist``: :func:`_qualities` and :func:`_sum_of_largest`'s
    result from the same elementwise operations, on blocks of cameras at once (``[b, S, n]``, at most
    ``max_elements`` per block) folded with ``topk``. For GPUs, where the row loop's hundreds of small kernels cost
    more than the arithmetic; the CPU keeps the row loop, which stays in cache."""
    t = dist.T.contiguous()[None]  # [1, S, n]
    c = -0.5 / math.radians(sigma_deg) ** 2
    m = terms.along.shape[0]
    block = max(1, min(m, max_elements // max(1, t.numel())))
    top = t.new_zeros((k,) + t.shape[1:])  # zeros stand in for missing cameras, as in the row loop
    buffers = t.new_empty((2, block) + t.shape[1:]), t.new_empty((block,) + t.shape[1:], dtype=torch.bool)
    for start in range(0, m, block):
        block_terms = [getattr(terms, f.name)[start : start + block, None] for f in fields(terms)]  # each [b, 1, n]
        b = len(block_terms[0])
        q = _quality_into(buffers[0][0, :b], buffers[0][1, :b], buffers[1][:b], t, c, *block_terms)
        top = torch.cat([top, q]).topk(k, dim=0).values
    return top.sum(0)


def _sum_of_largest(rows: Iterable[Float[Tensor, "*bs"]], k: int) -> Float[Tensor, "*bs"]:
    """The sum of the ``k`` largest of non-negative ``rows`` (at least one), elementwise, zeros standing in for missing
    ones: each row inserted into a running top ``k`` (descending) with elementwise max / min, in place. Exact (the
    same values, summed largest first as ``topk``'s are) and ~10x cheaper than ``topk`` over a short last axis on
    CPU."""
    top = None
    for x in rows:
        if top is None:
            top, scratch = x.new_zeros((k,) + x.shape), (torch.empty_like(x), torch.empty_like(x))
        for i in range(k - 1):
            out = scratch[i % 2]  # never x: the row (which the caller may reuse) or the previous place's loser
            torch.minimum(top[i], x, out=out)
            torch.maximum(top[i], x, out=top[i])
            x = out  # what fell out of place i goes on down
        torch.maximum(top[k - 1], x, out=top[k - 1])
    assert top is not None
    return top.sum(0)


def _unit(ray_directions: Float[Tensor, "*bs 3"]) -> tuple[Float[Tensor, "*bs 3"], Float[Tensor, "*bs 1"]]:
    """Unit directions and the directions' norms (``t`` along ``d`` is ``t * norm`` along the unit ray)."""
    tiny = torch.finfo(ray_directions.dtype).tiny
    norm = torch.linalg.vector_norm(ray_directions, dim=-1, keepdim=True).clamp(min=tiny)
    return ray_directions / norm, norm


def _candidate_terms(
    index: CameraIndex,
    frames: Float[Tensor, "6 num_cams n"],
    pixel_widths: Float[Tensor, " n"],
    cam_ids: Int[Tensor, "n m"] | None,
) -> _RayCameraTerms:
    """The terms of each ray against its cameras ``cam_ids``, or against every camera."""
    k = index.intrinsics.to(frames).T  # [6, C]
    if cam_ids is None:
        return _ray_camera_terms(frames, k[:, :, None], pixel_widths)
    c, n = frames.shape[1:]
    flat = cam_ids.T * n + torch.arange(n, device=cam_ids.device)  # [m, n]: (camera, ray) in a camera-major layout
    return _ray_camera_terms(frames.view(6, c * n)[:, flat], k[:, cam_ids.T], pixel_widths)


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
    bs, s = ray_origins.shape[:-1], ts.shape[-1]
    if len(index) == 0:
        return ts.new_zeros((*bs, s, 0))
    d, norm = _unit(ray_directions.reshape(-1, 3))
    o = ray_origins.reshape(-1, 3)
    ids = None if cam_ids is None else cam_ids.reshape(len(o), -1)
    terms = _candidate_terms(index, _camera_frames(index, o, d), pixel_widths.reshape(-1), ids)
    q = torch.stack([row.clone() for row in _qualities(terms, ts.reshape(-1, s) * norm, sigma_deg)])  # [m, S, n]
    return q.permute(2, 1, 0).reshape(*bs, s, q.shape[0])


def _candidates(
    index: CameraIndex,
    frames: Float[Tensor, "6 num_cams num_rays"],
    unit_directions: Float[Tensor, "num_rays 3"],
    dist_rep: Float[Tensor, " num_rays"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
) -> Int[Tensor, "num_rays m"]:
    """:func:`candidate_cameras` from the rays in the cameras' axes (:func:`_camera_frames`)."""
    m = min(params.candidates, len(index))
    q = _point_quality(index, frames, dist_rep, pixel_widths, params.sigma_deg).T  # [rays, cameras]
    # Tie-break (cameras that do not see the point score 0): prefer the camera pointing most along the ray.
    axes = -index.w2c[:, 2, :3].to(unit_directions)  # camera-to-world -z: the viewing direction
    key = q + 1e-6 * (1.0 + unit_directions @ axes.T)
    return torch.topk(key, m, dim=-1).indices


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
    d, norm = _unit(ray_directions)
    return _candidates(index, _camera_frames(index, ray_origins, d), d, t_rep * norm[:, 0], pixel_widths, params)


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
    d, norm = _unit(ray_directions)
    frames = _camera_frames(index, ray_origins, d)  # every camera's, for the candidates' look-up and then theirs
    ids = None
    if t_rep is not None and len(index) > params.candidates:
        ids = _candidates(index, frames, d, t_rep * norm[:, 0], pixel_widths, params)
    terms = _candidate_terms(index, frames, pixel_widths, ids)
    if frames.device.type == "cpu":
        best = _sum_of_largest(_qualities(terms, ts * norm, params.sigma_deg), params.k)
    else:
        best = _sum_of_best_blocked(terms, ts * norm, params.sigma_deg, params.k)
    return (best / params.k).T.contiguous()
