"""Blending of several registered NeRFs (NeRFuser, Sec. 3.3).

Pure, vectorised torch math; nothing here touches a model, a camera object or the network.
Every function takes tensors that are already expressed in the COMMON frame (the frame the query
camera lives in): ray distances, sample intervals, origins and depths must all be in its units.

Conventions
-----------
* The NeRF axis is always the leading one: ``[N, *bs, ...]``.
* Ray samples are given WITHOUT nerfstudio's trailing singleton: ``starts/ends/weights`` are
  ``[N, *bs, K]`` (squeeze ``RaySamples.frustums.starts[..., 0]``), colours ``[N, *bs, K, 3]``.
* ``weights`` are termination probabilities ``p_k = T_k alpha_k`` (``RaySamples.get_weights``); they may sum
  to less than one along a ray, the remainder being the NeRF's background term.

Methods (``BlendMethod``)
-------------------------
* ``"nerf"``: use one fixed (reference) NeRF's rendering, no blending.
* ``"nearest"``: the NeRF whose origin is nearest to the camera centre.
* ``"idw-2d"``: image-wise IDW on camera-centre-to-origin distances (Block-NeRF).
* ``"idw-3d"``: pixel-wise IDW on the distance of each NeRF's expected surface point to its origin (Block-NeRF).
* ``"idw-sample"``: NeRFuser's sample-wise IDW on merged ray samples (:mod:`nerfuser_ns.merging` +
  ``idw_sample_blend``).
* ``"coverage"`` (ours, not the paper's): IDW-Sample with each merged sample's weights over NeRFs taken from how well
  each NeRF's training cameras saw it (:mod:`nerfuser_ns.coverage`, ``coverage_weights``) instead of from the
  distances to the NeRF origins. Without every NeRF's training cameras it is IDW-Sample.
* ``"coverage-3d"`` (ours, not the paper's): IDW-3D's blend of each NeRF's own rendering per pixel, with weights from
  each NeRF's coverage score at its own surface point (its median depth on the ray) instead of that point's distance
  to its origin (``pixel_coverage_scores`` + ``coverage_weights``). Without every NeRF's training cameras it is
  IDW-2D.

The distance test (``distance_mask``) leaves out of every IDW method the NeRFs whose origin is more than ``tau``
times as far from the camera as the nearest one's. For two NeRFs this is the paper's test (the ratio of the two
distances above ``tau``: the nearest NeRF alone); for more it keeps the nearest NeRFs and drops only the far ones, as
the authors' reference code does, instead of letting a far NeRF take the samples nearest to it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, get_args

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from nerfuser_ns.coverage import CameraIndex, CoverageParams, coverage_scores
from nerfuser_ns.merging import (
    MergedSamples,
    expected_depth,
    furthest_last_mids,
    last_sample_mids,
    median_depth,
    median_mids,
    merge_samples,
    merged_sample_distances,
)

if TYPE_CHECKING:  # the settings value imports this module's method names
    from nerfuser_ns.blend_settings import BlendSettings

BlendMethod = Literal["nerf", "nearest", "idw-2d", "idw-3d", "idw-sample", "coverage", "coverage-3d"]
"""Blending methods of the paper's Table 2 (the plain NeRF, nearest NeRF, IDW-2D, IDW-3D and IDW-Sample) and ours,
``coverage`` (IDW-Sample weighted by each NeRF's training-camera coverage) and ``coverage-3d`` (each NeRF's own
rendering weighted by that coverage at its surface point)."""

SAMPLE_METHODS: tuple[str, ...] = ("idw-sample", "coverage")
"""The methods that blend merged ray samples (the others blend per-NeRF renderings)."""

COVERAGE_METHODS: tuple[str, ...] = ("coverage", "coverage-3d")
"""The methods that need every NeRF's training cameras (ours)."""

BLEND_METHODS: tuple[str, ...] = get_args(BlendMethod)
PAPER_BLEND_METHODS: tuple[str, ...] = BLEND_METHODS[:5]
"""The paper's methods (Table 2), without ours."""

PAPER_OBJECT_CENTRIC: tuple[float, float] = (5.0, 1.8)
"""(gamma, tau) the paper uses on its object-centric indoor scenes (the default of every tool)."""
PAPER_MISSION_BAY: tuple[float, float] = (10.0, 1.2)
"""(gamma, tau) the paper uses on Mission Bay (street scenes)."""


def _pad_right(x: Tensor, ndim: int) -> Tensor:
    """Appends singleton dims so that ``x`` broadcasts against a tensor with ``ndim`` dims sharing its leading dims."""
    return x.reshape(x.shape + (1,) * (ndim - x.ndim))


# ----------------------------------------------------------------------------------------------------------------------
# Inverse distance weighting


def idw_weights(
    distances: Float[Tensor, " num_nerfs *bs"], gamma: float, mask: Bool[Tensor, " num_nerfs *m"] | None = None
) -> Float[Tensor, " num_nerfs *bs"]:
    """Inverse distance weights ``w_i ∝ d_i^-gamma``, normalised over the NeRF axis (dim 0).

    Computed in log space as ``softmax(-gamma * log d)`` so that large ``gamma`` neither overflows nor underflows
    to 0/0. Limits: ``gamma == 0`` gives the uniform mean, ``gamma == inf`` the one-hot nearest (ties share
    equally). Where some NeRFs are at distance 0, those NeRFs share all the weight (the ``gamma -> 0+`` limit of
    ``0^-gamma`` is infinite too).

    Args:
        distances: non-negative distances of each blending element to each NeRF's origin.
        gamma: blending rate, ``>= 0``.
        mask: NeRFs that take part (``distance_mask``), its dims the leading ones of ``distances``; the others get
            weight 0 and the weights are normalised over the rest. Every element needs one NeRF taking part.

    Returns:
        Weights with the shape of ``distances``, summing to 1 over dim 0.
    """
    if gamma < 0 or math.isnan(gamma):
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    if mask is None:
        keep = torch.ones_like(distances, dtype=torch.bool)
    else:
        keep = _pad_right(mask, distances.ndim).expand_as(distances)
    if gamma == 0:
        k = keep.to(distances.dtype)
        return k / k.sum(dim=0, keepdim=True)
    zero = (distances <= 0) & keep
    # log d relative to the nearest NeRF taking part: >= 0, exactly 0 at the nearest, so the max logit is 0 and
    # softmax never sees inf - inf, even for gamma = 1e30; NeRFs left out are at log d = inf, weight exactly 0.
    log_d = torch.log(distances.clamp(min=torch.finfo(distances.dtype).tiny))
    log_d = torch.where(keep, log_d, math.inf)
    rel = log_d - log_d.min(dim=0, keepdim=True).values
    if math.isinf(gamma):
        w = (rel <= 0).to(distances.dtype)
        w = w / w.sum(dim=0, keepdim=True)
    else:
        w = torch.softmax(-gamma * rel, dim=0)
    any_zero = zero.any(dim=0, keepdim=True)
    w_zero = zero.to(distances.dtype) / zero.sum(dim=0, keepdim=True).clamp(min=1)
    return torch.where(any_zero, w_zero, w)


def nearest_index(distances: Float[Tensor, " num_nerfs *bs"]) -> Int[Tensor, " *bs"]:
    """Index of the NeRF with the smallest distance (the first one on ties)."""
    return torch.argmin(distances, dim=0)


def nearest_weights(distances: Float[Tensor, " num_nerfs *bs"]) -> Float[Tensor, " num_nerfs *bs"]:
    """One-hot weights selecting the nearest NeRF (the first one on ties)."""
    idx = nearest_index(distances)
    return torch.nn.functional.one_hot(idx, distances.shape[0]).movedim(-1, 0).to(distances.dtype)


def distance_ratio(camera_distances: Float[Tensor, " num_nerfs *bs"]) -> Float[Tensor, " *bs"]:
    """Ratio of the second-nearest to the nearest camera-to-NeRF-origin distance.

    For two NeRFs this is the paper's ``max(d_A / d_B, d_B / d_A)``. With one NeRF it is ``inf``; with the
    camera on the nearest origin it is ``inf`` unless the second is there too (then 1).
    """
    if camera_distances.shape[0] < 2:
        return torch.full_like(camera_distances[0], math.inf)
    two = torch.topk(camera_distances, 2, dim=0, largest=False).values
    d1, d2 = two[0], two[1]
    inf = torch.full_like(d1, math.inf)
    ratio_at_zero = torch.where(d2 > 0, inf, torch.ones_like(d1))
    return torch.where(d1 > 0, d2 / d1.clamp(min=torch.finfo(d1.dtype).tiny), ratio_at_zero)


def distance_test(camera_distances: Float[Tensor, " num_nerfs *bs"], tau: float) -> Bool[Tensor, " *bs"]:
    """The paper's distance test: True where ONLY the nearest NeRF is used (every other NeRF is more than ``tau``
    times as far from the camera, i.e. ``distance_ratio > tau``).

    Args:
        camera_distances: distance from the query camera centre to each NeRF's origin (common frame).
        tau: threshold on ``distance_ratio`` (paper: 1.8 on object scenes, 1.2 on Mission Bay).
    """
    return distance_ratio(camera_distances) > tau


def distance_mask(
    camera_distances: Float[Tensor, " num_nerfs *bs"], tau: float | None
) -> Bool[Tensor, " num_nerfs *bs"]:
    """The NeRFs that take part in blending: those at most ``tau`` times as far from the camera as the nearest.

    The nearest NeRF always takes part (with the camera on an origin, only the NeRFs at distance 0 do). For two
    NeRFs this is the paper's test; for more, far NeRFs are dropped one by one instead of all or none. ``tau=None``
    keeps every NeRF.
    """
    if tau is None:
        return torch.ones_like(camera_distances, dtype=torch.bool)
    return camera_distances <= tau * camera_distances.min(dim=0, keepdim=True).values


def apply_distance_test(
    weights: Float[Tensor, " num_nerfs *bs"],
    camera_distances: Float[Tensor, " num_nerfs *cam"],
    tau: float | None,
) -> Float[Tensor, " num_nerfs *bs"]:
    """Restricts blending weights to the NeRFs that pass the distance test (``distance_mask``), renormalised.

    ``camera_distances`` may have fewer dims than ``weights`` (e.g. ``[N]`` per camera against ``[N, H, W]`` per
    pixel, or ``[N, R]`` per ray against ``[N, R, M]`` per sample): its dims are the leading ones of ``weights``.
    Where the NeRFs taking part have no weight at all, the nearest NeRF gets it. ``tau=None`` disables the test.
    Prefer ``idw_weights(..., mask=distance_mask(...))`` for IDW weights: it cannot underflow.
    """
    if tau is None:
        return weights
    keep = _pad_right(distance_mask(camera_distances, tau), weights.ndim)
    w = torch.where(keep, weights, 0.0)
    total = w.sum(dim=0, keepdim=True)
    one_hot = _pad_right(nearest_weights(camera_distances), weights.ndim).to(weights.dtype).expand_as(weights)
    return torch.where(total > 0, w / torch.where(total > 0, total, 1.0), one_hot)


# ----------------------------------------------------------------------------------------------------------------------
# Image- and pixel-wise baselines


def blend_renders(
    rgbs: Float[Tensor, "num_nerfs *bs 3"], weights: Float[Tensor, " num_nerfs *wbs"]
) -> Float[Tensor, "*bs 3"]:
    """``sum_i w_i I_i``; ``weights`` may be per image (``[N]``), per camera or per pixel (leading dims of ``rgbs``)."""
    return (_pad_right(weights, rgbs.ndim) * rgbs).sum(dim=0)


def camera_to_origin_distances(
    camera_centers: Float[Tensor, "*bs 3"], nerf_origins: Float[Tensor, "num_nerfs 3"]
) -> Float[Tensor, " num_nerfs *bs"]:
    """Euclidean distance from each camera centre (or any point) to each NeRF origin, common frame."""
    origins = nerf_origins.reshape((nerf_origins.shape[0],) + (1,) * (camera_centers.ndim - 1) + (3,))
    return torch.linalg.vector_norm(camera_centers.unsqueeze(0) - origins, dim=-1)


def nearest_blend(
    rgbs: Float[Tensor, "num_nerfs *bs 3"], camera_distances: Float[Tensor, " num_nerfs *cam"]
) -> Float[Tensor, "*bs 3"]:
    """ "Nearest" baseline: the rendering of the NeRF whose origin is nearest to the camera centre."""
    return blend_renders(rgbs, nearest_weights(camera_distances))


def idw_2d_weights(
    camera_distances: Float[Tensor, " num_nerfs *cam"], gamma: float, tau: float | None = None
) -> Float[Tensor, " num_nerfs *cam"]:
    """IDW-2D image-wise weights from camera-centre-to-origin distances, with the optional distance test."""
    return idw_weights(camera_distances, gamma, distance_mask(camera_distances, tau))


def idw_2d(
    rgbs: Float[Tensor, "num_nerfs *bs 3"],
    camera_distances: Float[Tensor, " num_nerfs *cam"],
    gamma: float,
    tau: float | None = None,
) -> Float[Tensor, "*bs 3"]:
    """IDW-2D (Block-NeRF): blend whole per-NeRF renderings with weights from the camera-to-origin distances.

    Args:
        rgbs: per-NeRF renderings of the same view, e.g. ``[N, H, W, 3]``.
        camera_distances: ``[N]`` for one camera (or ``[N, *cam]`` matching leading dims of ``rgbs``).
        gamma: blending rate.
        tau: distance-test threshold; None disables it.
    """
    return blend_renders(rgbs, idw_2d_weights(camera_distances, gamma, tau))


def expected_points(
    ray_origins: Float[Tensor, "*bs 3"], ray_directions: Float[Tensor, "*bs 3"], depths: Float[Tensor, " num_nerfs *bs"]
) -> Float[Tensor, "num_nerfs *bs 3"]:
    """Expected surface point of each NeRF per ray, ``o + depth_i * d`` (depth along ``d``, common frame units)."""
    return ray_origins.unsqueeze(0) + depths.unsqueeze(-1) * ray_directions.unsqueeze(0)


def idw_3d_weights(
    depths: Float[Tensor, " num_nerfs *bs"],
    ray_origins: Float[Tensor, "*bs 3"],
    ray_directions: Float[Tensor, "*bs 3"],
    nerf_origins: Float[Tensor, "num_nerfs 3"],
    gamma: float,
    camera_distances: Float[Tensor, " num_nerfs *cam"] | None = None,
    tau: float | None = None,
) -> Float[Tensor, " num_nerfs *bs"]:
    """IDW-3D pixel-wise weights: distance of NeRF i's expected surface point to NeRF i's origin."""
    points = expected_points(ray_origins, ray_directions, depths)
    origins = nerf_origins.reshape((nerf_origins.shape[0],) + (1,) * (depths.ndim - 1) + (3,))
    d = torch.linalg.vector_norm(points - origins, dim=-1)
    return idw_weights(d, gamma, None if camera_distances is None else distance_mask(camera_distances, tau))


def idw_3d(
    rgbs: Float[Tensor, "num_nerfs *bs 3"],
    depths: Float[Tensor, " num_nerfs *bs"],
    ray_origins: Float[Tensor, "*bs 3"],
    ray_directions: Float[Tensor, "*bs 3"],
    nerf_origins: Float[Tensor, "num_nerfs 3"],
    gamma: float,
    camera_distances: Float[Tensor, " num_nerfs *cam"] | None = None,
    tau: float | None = None,
) -> Float[Tensor, "*bs 3"]:
    """IDW-3D (Block-NeRF): blend per-NeRF pixels with weights from each NeRF's own expected surface point.

    Args:
        rgbs: per-NeRF pixel colours.
        depths: per-NeRF expected depth along ``ray_directions`` IN COMMON-FRAME UNITS (divide a NeRF's own depth
            by its scale to the common frame).
        ray_origins, ray_directions: the query rays in the common frame.
        nerf_origins: each NeRF's origin in the common frame.
        gamma: blending rate.
        camera_distances, tau: optional distance test (camera-centre-to-origin distances, leading dims of rays).
    """
    w = idw_3d_weights(depths, ray_origins, ray_directions, nerf_origins, gamma, camera_distances, tau)
    return blend_renders(rgbs, w)


def image_blend_weights(
    method: BlendMethod,
    camera_distances: Float[Tensor, " num_nerfs *cam"],
    gamma: float,
    tau: float | None = None,
    surface_distances: Float[Tensor, " num_nerfs *bs"] | None = None,
    reference: int = 0,
) -> Float[Tensor, "num_nerfs ..."]:
    """Weights over per-NeRF renderings for the render-level methods ("nerf", "nearest", "idw-2d", "idw-3d").

    Args:
        method: blending method; "idw-sample" is not render-level (use ``merge_samples`` + ``idw_sample_blend``).
        camera_distances: camera-centre-to-origin distances.
        gamma: blending rate.
        tau: distance-test threshold for the IDW methods; None disables it.
        surface_distances: for "idw-3d", distance of each NeRF's expected surface point to its origin.
        reference: NeRF used by "nerf".
    """
    if method == "nerf":
        w = torch.zeros_like(camera_distances)
        w[reference] = 1.0
        return w
    if method == "nearest":
        return nearest_weights(camera_distances)
    if method == "idw-2d":
        return idw_2d_weights(camera_distances, gamma, tau)
    if method == "idw-3d":
        if surface_distances is None:
            raise ValueError("idw-3d needs surface_distances")
        return idw_weights(surface_distances, gamma, distance_mask(camera_distances, tau))
    raise ValueError(f"{method!r} is not a render-level blending method")


# ----------------------------------------------------------------------------------------------------------------------
# IDW-Sample: blending


@dataclass
class BlendOutputs:
    """Result of ``idw_sample_blend`` for a batch of rays."""

    rgb: Float[Tensor, "*bs 3"]
    """Blended pixel colour, background terms included."""
    depth: Float[Tensor, " *bs"]
    """Expected merged midpoint under the blended weights of the merged samples (background excluded),
    nerfstudio's "expected" depth: ``sum w t / (sum w + eps)`` clipped to the midpoints' range."""
    accumulation: Float[Tensor, " *bs"]
    """Blended weight on the merged samples, i.e. 1 minus the blended background weight."""
    weights: Float[Tensor, "*bs num_merged"]
    """Blended per-sample weights ``sum_i w_ik p_ik`` after both normalisations (background excluded)."""
    background_weight: Float[Tensor, " *bs"]
    """Blended weight of the background pseudo-sample."""
    nerf_share: Float[Tensor, " num_nerfs *bs"]
    """Each NeRF's share of the final pixel weight, ``sum_k w_ik p_ik`` incl. background; sums to 1 per ray."""


def idw_sample_blend(
    merged: MergedSamples,
    distances: Float[Tensor, "num_nerfs *bs num_merged"],
    gamma: float,
    background_rgbs: Float[Tensor, "num_nerfs *bs 3"] | None = None,
    background_distances: Float[Tensor, " num_nerfs *bs"] | None = None,
    camera_distances: Float[Tensor, " num_nerfs *cam"] | None = None,
    tau: float | None = None,
    nerf_weights: Float[Tensor, "num_nerfs *bs num_merged_bg"] | None = None,
) -> BlendOutputs:
    """IDW-Sample (NeRFuser): per merged sample IDW over NeRFs, then volume-rendering-style accumulation.

    ``I = sum_k sum_i w_ik p_ik c_ik`` with (1) ``sum_i w_ik = 1`` per sample and (2) ``sum_k sum_i w_ik p_ik = 1``
    per ray.

    Background: every NeRF keeps its own background term. Each NeRF's residual transmittance
    ``1 - sum_k p_ik`` (clamped at 0) with its background colour (nerfacto "last_sample": the colour of its last
    sample) becomes one extra pseudo-sample after the last merged interval, IDW-weighted like any sample with the
    distances ``background_distances`` (default: those of the last merged midpoint; ``merged_sample_distances``
    gives the far end of the ray). It then takes part in normalisation (2). Consequences: with every NeRF identical,
    or with one NeRF, or where the distance test picks one NeRF, the result is exactly that NeRF's own rendering
    ``sum_k p_k c_k + (1 - sum_k p_k) c_bg``, for any gamma. ``background_rgbs=None`` drops the pseudo-sample: the
    paper's formula as printed, renormalising the merged samples alone to 1 (as if every ray were fully absorbed).

    Degenerate rays: where the blended mass is 0 (all of it sits in samples whose IDW weights underflowed to 0,
    possible for huge gamma), the plain mean over the NeRFs passing the distance test (gamma = 0) is used instead;
    where that is 0 too (no mass at all, only without background), everything is 0.

    Args:
        merged: output of ``merge_samples``.
        distances: distance of each merged midpoint to each NeRF origin (``merged_sample_distances``).
        gamma: blending rate.
        background_rgbs: each NeRF's background colour per ray; None: no background term.
        background_distances: distance of the background pseudo-sample to each NeRF origin.
        camera_distances, tau: optional distance test; failing rays use only the camera's nearest NeRF.
        nerf_weights: normalisation (1) given instead of computed from ``distances`` (the ``coverage`` method's
            ``coverage_weights``), the background pseudo-sample's column last when ``background_rgbs`` is given; the
            distance test's mask must already be in it (``camera_distances`` still chooses the degenerate fallback).

    Returns:
        ``BlendOutputs``.
    """
    p, c = merged.weights, merged.rgbs
    if background_rgbs is not None:
        residual = (1.0 - p.sum(dim=-1)).clamp(min=0.0)
        if background_distances is None:
            background_distances = distances[..., -1]
        p = torch.cat([p, residual.unsqueeze(-1)], dim=-1)
        c = torch.cat([c, background_rgbs.unsqueeze(-2)], dim=-2)
        distances = torch.cat([distances, background_distances.unsqueeze(-1)], dim=-1)

    mask = None if camera_distances is None else distance_mask(camera_distances, tau)
    # normalisation (1), over the NeRFs that pass the distance test
    w = idw_weights(distances, gamma, mask) if nerf_weights is None else nerf_weights
    q = w * p
    total = q.sum(dim=(0, -1))
    # Fallback for rays whose IDW-weighted mass vanished: the plain mean over the NeRFs taking part.
    keep = torch.ones_like(p[:, ..., 0], dtype=p.dtype) if mask is None else _pad_right(mask, p.ndim - 1).to(p.dtype)
    q_mean = p * (keep / keep.sum(dim=0, keepdim=True)).unsqueeze(-1)
    total_mean = q_mean.sum(dim=(0, -1))
    ok = (total > 0).unsqueeze(0).unsqueeze(-1)
    q = torch.where(ok, q, q_mean)
    total = torch.where(total > 0, total, total_mean)
    q = q / torch.where(total > 0, total, 1.0).unsqueeze(0).unsqueeze(-1)  # normalisation (2)

    rgb = (q.unsqueeze(-1) * c).sum(dim=(0, -2))
    per_sample = q.sum(dim=0)
    m = merged.starts.shape[-1]
    sample_w = per_sample[..., :m]
    bg_w = per_sample[..., m] if background_rgbs is not None else torch.zeros_like(per_sample[..., 0])
    accumulation = sample_w.sum(dim=-1)
    mids = merged.midpoints
    depth = (sample_w * mids).sum(dim=-1) / (accumulation + 1e-10)
    depth = torch.clip(depth, mids.amin(dim=-1), mids.amax(dim=-1))
    return BlendOutputs(
        rgb=rgb,
        depth=depth,
        accumulation=accumulation,
        weights=sample_w,
        background_weight=bg_w,
        nerf_share=q.sum(dim=-1),
    )


def coverage_weights(
    scores: Float[Tensor, " num_nerfs *bs"],
    distances: Float[Tensor, " num_nerfs *bs"],
    gamma: float,
    mask: Bool[Tensor, " num_nerfs *m"] | None = None,
) -> Float[Tensor, " num_nerfs *bs"]:
    """Normalisation (1) of the ``coverage`` method (ours): ``w_i ∝ S_i^gamma`` over the NeRFs in ``mask``, i.e. IDW
    on the pseudo-distance ``1 / S_i`` (:mod:`nerfuser_ns.coverage`); IDW-Sample's ``d_i^-gamma`` on ``distances``
    where no NeRF in ``mask`` has a positive score.

    Args:
        scores: coverage scores ``S_i >= 0`` of each element (merged sample) for each NeRF.
        distances: the element's distance to each NeRF origin (the fallback's).
        gamma: sharpness, as IDW's: 0 the mean, inf the best-covered NeRF alone.
        mask: NeRFs that take part (``distance_mask``), its dims the leading ones of ``scores``.
    """
    keep = torch.ones_like(scores, dtype=torch.bool)
    if mask is not None:
        keep = _pad_right(mask, scores.ndim).expand_as(scores)
    covered = ((scores > 0) & keep).any(dim=0, keepdim=True)
    pseudo = torch.where(scores > 0, 1.0 / scores.clamp(min=torch.finfo(scores.dtype).tiny), math.inf)
    # idw_weights treats each element (column over the NeRF axis) on its own and ``covered`` is per element: one call
    # on the pseudo-distances where covered and the distances elsewhere is both calls' selection, at half the cost.
    return idw_weights(torch.where(covered, pseudo, distances), gamma, mask)


def sample_coverage_scores(
    merged: MergedSamples,
    cameras: Sequence[CameraIndex],
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
    needed: Bool[Tensor, "num_nerfs num_rays"] | None = None,
) -> Float[Tensor, "num_nerfs num_rays num_merged_bg"]:
    """Each NeRF's coverage score (cameras in the common frame) at every merged midpoint and at the ray's far end
    (the background pseudo-sample, as ``merged_sample_distances`` places it). Candidate cameras are chosen per ray at
    the merged samples' expected termination point (all NeRFs' mass together). With ``needed``, only NeRF ``i``'s
    rays ``needed[i]`` are scored, the others are 0 (a ray's scores do not depend on the other rays)."""
    ts = torch.cat([merged.midpoints, merged.ends[..., -1:]], dim=-1)
    mass = merged.weights.sum(dim=0)
    total = mass.sum(-1)
    mids = merged.midpoints
    middle = 0.5 * (merged.starts[..., 0] + merged.ends[..., -1])  # massless rays: the middle of the samples' range
    t_rep = torch.where(total > 0, (mass * mids).sum(-1) / torch.where(total > 0, total, 1.0), middle)
    n = len(cameras)
    return _coverage_scores_by_nerf(cameras, ray_origins, ray_directions, ts.expand(n, *ts.shape),
                                    t_rep.expand(n, -1), pixel_widths, params, needed)  # fmt: skip


def pixel_coverage_scores(
    cameras: Sequence[CameraIndex],
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    depths: Float[Tensor, "num_nerfs num_rays"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
    needed: Bool[Tensor, "num_nerfs num_rays"] | None = None,
) -> Float[Tensor, "num_nerfs num_rays"]:
    """Each NeRF's coverage score (cameras in the common frame) at its own surface point ``o + depths[i] d`` of
    every ray (``coverage-3d``); candidate cameras chosen at that point. With ``needed``, only NeRF ``i``'s rays
    ``needed[i]`` are scored, the others are 0."""
    return _coverage_scores_by_nerf(cameras, ray_origins, ray_directions, depths[..., None], depths, pixel_widths,
                                    params, needed)[..., 0]  # fmt: skip


def _coverage_scores_by_nerf(
    cameras: Sequence[CameraIndex],
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    ts: Float[Tensor, "num_nerfs num_rays num_points"],
    t_rep: Float[Tensor, "num_nerfs num_rays"],
    pixel_widths: Float[Tensor, " num_rays"],
    params: CoverageParams,
    needed: Bool[Tensor, "num_nerfs num_rays"] | None,
) -> Float[Tensor, "num_nerfs num_rays num_points"]:
    """NeRF ``i``'s scores at the points ``ts[i]`` along the rays, candidate cameras chosen at ``t_rep[i]``; only the
    rays ``needed[i]`` are scored (all without ``needed``), the others are 0."""
    scores = ts.new_zeros(ts.shape)
    for i, c in enumerate(cameras):
        rows = slice(None) if needed is None else needed[i].nonzero()[:, 0]
        scores[i, rows] = coverage_scores(c, ray_origins[rows], ray_directions[rows], ts[i, rows], pixel_widths[rows],
                                          params, t_rep[i, rows])  # fmt: skip
    return scores


def render_samples(
    weights: Float[Tensor, "*bs num_samples"],
    rgbs: Float[Tensor, "*bs num_samples 3"],
    background_rgb: Float[Tensor, "*bs 3"] | None = None,
) -> Float[Tensor, "*bs 3"]:
    """Single-NeRF volume rendering as nerfstudio's ``RGBRenderer``: ``sum_k p_k c_k + (1 - sum_k p_k) c_bg``."""
    rgb = (weights.unsqueeze(-1) * rgbs).sum(dim=-2)
    if background_rgb is not None:
        rgb = rgb + (1.0 - weights.sum(dim=-1, keepdim=True)) * background_rgb
    return rgb


# ----------------------------------------------------------------------------------------------------------------------
# The one entry the fused model calls


def blend(
    methods: Sequence[str],
    starts: Float[Tensor, "num_nerfs num_rays k"],
    ends: Float[Tensor, "num_nerfs num_rays k"],
    weights: Float[Tensor, "num_nerfs num_rays k"],
    rgbs: Float[Tensor, "num_nerfs num_rays k 3"],
    background_rgbs: Float[Tensor, "num_nerfs num_rays 3"],
    ray_origins: Float[Tensor, "num_rays 3"],
    ray_directions: Float[Tensor, "num_rays 3"],
    nerf_origins: Float[Tensor, "num_nerfs 3"],
    settings: BlendSettings,
    reference: int = 0,
    cameras: Sequence[CameraIndex] | None = None,
    pixel_widths: Float[Tensor, " num_rays"] | None = None,
) -> dict[str, dict[str, Tensor]]:
    """Every blend method in ``methods`` on the same per-NeRF ray samples (common-frame distances): per method its
    ``rgb``, ``accumulation``, (median) ``depth``, ``expected_depth`` and per-NeRF ``share`` ``[num_nerfs, num_rays]``.

    The distance test (``settings.tau``) applies to the IDW and coverage methods; ``reference`` is the index
    (among these NeRFs) that ``"nerf"`` shows. ``cameras`` are these NeRFs' training-camera indices in the common
    frame and ``pixel_widths`` the rays' ``sqrt(pixel_area)``: ``coverage`` and ``coverage-3d`` need both and are
    IDW-Sample and IDW-2D without them (the caller warns). The reference functions above (``nearest_blend``,
    ``idw_2d``, ``idw_3d``, ``idw_sample_blend``, ``coverage_weights``) are this entry's twins in the tests.
    """
    tau = settings.tau
    camera_d = camera_to_origin_distances(ray_origins, nerf_origins)  # [N, R]
    mask = distance_mask(camera_d, tau)
    results: dict[str, dict[str, Tensor]] = {}
    per_nerf = None
    if any(m not in SAMPLE_METHODS for m in methods):
        mids = 0.5 * (starts + ends)
        per_nerf = (render_samples(weights, rgbs, background_rgbs).clamp(0.0, 1.0), weights.sum(-1),
                    median_depth(weights, mids, last_sample_mids(starts, ends)),
                    expected_depth(weights, mids))  # fmt: skip
    merged_once: tuple[Tensor, MergedSamples, Tensor] | None = None
    for method in methods:
        if method in SAMPLE_METHODS and merged_once is not None:
            order, merged, far_median = merged_once
        elif method in SAMPLE_METHODS:
            # Each ray merges only the samples of the NeRFs passing its distance test, packed into the first slots
            # (as many as the most any ray of the chunk blends): the others must not split its intervals, so a ray
            # renders the same in any batch, and the sort sees no samples that cannot count.
            slots = int(mask.sum(0).max())
            order = torch.argsort((~mask).to(torch.uint8), dim=0, stable=True)[:slots]  # [S, R]
            keep = mask.gather(0, order)[..., None]
            idx = order[..., None].expand(-1, -1, starts.shape[-1])
            st, en = starts.gather(0, idx), ends.gather(0, idx)
            far = torch.where(keep[..., 0], en[..., -1], -math.inf).amax(dim=0)[None, :, None]
            merged = merge_samples(
                torch.where(keep, st, far),
                torch.where(keep, en, far),
                torch.where(keep, weights.gather(0, idx), 0.0),
                rgbs.gather(0, idx[..., None].expand(-1, -1, -1, rgbs.shape[-1])),
            )
            far_median = furthest_last_mids(st, en, keep[..., 0])
            merged_once = (order, merged, far_median)
        if method in SAMPLE_METHODS:
            d, d_bg = merged_sample_distances(merged, ray_origins, ray_directions, nerf_origins[order])
            nerf_weights = None
            if method == "coverage" and cameras is not None:
                if pixel_widths is None:
                    raise ValueError("coverage blending needs the rays' pixel widths (sqrt of pixel_area)")
                # Only where a NeRF takes part with another does its score matter: a ray's lone NeRF takes all the
                # weight (coverage_weights' both branches), one left out by the distance test none, whatever the scores.
                needed = mask & (mask.sum(0) > 1)
                scores = sample_coverage_scores(merged, cameras, ray_origins, ray_directions, pixel_widths,
                                                settings.coverage, needed)  # fmt: skip
                slot_scores = scores.gather(0, order[..., None].expand(-1, -1, scores.shape[-1]))
                slot_mask = None if tau is None else distance_mask(camera_d.gather(0, order), tau)
                nerf_weights = coverage_weights(slot_scores, torch.cat([d, d_bg[..., None]], dim=-1), settings.gamma,
                                                slot_mask)  # fmt: skip
            out = idw_sample_blend(
                merged,
                d,
                settings.gamma,
                background_rgbs=background_rgbs.gather(0, order[..., None].expand(-1, -1, background_rgbs.shape[-1])),
                background_distances=d_bg,
                camera_distances=camera_d.gather(0, order) if tau is not None else None,
                tau=tau,
                nerf_weights=nerf_weights,
            )
            results[method] = {
                "rgb": out.rgb.clamp(0.0, 1.0),
                "accumulation": out.accumulation,
                "depth": median_depth(out.weights, median_mids(merged), far_median),
                "expected_depth": out.depth,
                "share": torch.zeros_like(camera_d).scatter_(0, order, out.nerf_share),
            }
            continue
        assert per_nerf is not None
        rgb_i, acc_i, depth_i, exp_i = per_nerf
        surface_d = None
        if method == "coverage-3d":
            if cameras is None:  # the caller warned: IDW-2D, the image-level method with the same distance test
                w = image_blend_weights("idw-2d", camera_d, settings.gamma, tau)
            else:
                if pixel_widths is None:
                    raise ValueError("coverage-3d blending needs the rays' pixel widths (sqrt of pixel_area)")
                # as for coverage: a ray's lone NeRF takes all the weight whatever its score
                scores = pixel_coverage_scores(cameras, ray_origins, ray_directions, depth_i, pixel_widths,
                                               settings.coverage, mask & (mask.sum(0) > 1))  # fmt: skip
                w = coverage_weights(scores, camera_d, settings.gamma, mask)
        else:
            if method == "idw-3d":
                pts = expected_points(ray_origins, ray_directions, exp_i)
                surface_d = torch.linalg.vector_norm(pts - nerf_origins[:, None, :], dim=-1)
            w = image_blend_weights(method, camera_d, settings.gamma, tau,  # type: ignore[arg-type]
                                    surface_distances=surface_d, reference=reference)  # fmt: skip
        results[method] = {
            "rgb": blend_renders(rgb_i, w),
            "accumulation": (w * acc_i).sum(0),
            "depth": (w * depth_i).sum(0),
            "expected_depth": (w * exp_i).sum(0),
            "share": w,
        }
    return results
