"""Merging the ray samples of several NeRFs into one set of intervals per ray: IDW-Sample's first step (NeRFuser,
Sec. 3.3), and the distances of merged samples to each NeRF's origin.

Pure, vectorised torch math in the common frame, with the NeRF axis leading (conventions of
:mod:`nerfuser_ns.blending`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor


@dataclass
class MergedSamples:
    """Ray samples of N NeRFs merged into one set of intervals per ray.

    Intervals are sorted along the ray and may have zero length (duplicated boundaries); they carry no mass then.
    """

    starts: Float[Tensor, "*bs num_merged"]
    """Start of each merged interval (common-frame ray distance)."""
    ends: Float[Tensor, "*bs num_merged"]
    """End of each merged interval."""
    weights: Float[Tensor, "num_nerfs *bs num_merged"]
    """Termination mass each NeRF puts in each merged interval; sums per NeRF per ray to its input total."""
    rgbs: Float[Tensor, "num_nerfs *bs num_merged 3"]
    """Colour of each NeRF in each merged interval (that of the covering source sample; 0 where uncovered)."""

    @property
    def midpoints(self) -> Float[Tensor, "*bs num_merged"]:
        """Midpoint of each merged interval, where IDW-Sample measures distances."""
        return 0.5 * (self.starts + self.ends)

    @property
    def deltas(self) -> Float[Tensor, "*bs num_merged"]:
        """Length of each merged interval."""
        return self.ends - self.starts


def _is_contiguous(starts: Tensor, ends: Tensor) -> bool:
    return bool(torch.equal(ends[..., :-1], starts[..., 1:]))


def merge_samples(
    starts: Float[Tensor, "num_nerfs *bs num_samples"],
    ends: Float[Tensor, "num_nerfs *bs num_samples"],
    weights: Float[Tensor, "num_nerfs *bs num_samples"],
    rgbs: Float[Tensor, "num_nerfs *bs num_samples 3"],
    contiguous: bool | None = None,
) -> MergedSamples:
    """Merges the ray samples that N NeRFs proposed along the same rays (NeRFuser, "Merge Ray Samples").

    The merged boundaries are the sorted union of all source boundaries per ray, so every merged interval lies
    inside at most one sample of each NeRF. A source sample's termination mass is spread uniformly over its length
    (a merged interval covering a fraction f of source sample k receives ``f * p_k``) and its colour is constant
    over it; merged intervals outside a NeRF's samples get zero mass and colour from it. Mass is conserved per
    NeRF per ray. A zero-length source sample's mass (physically impossible, alpha = 0, but kept for conservation)
    goes to the zero-length merged interval at its position.

    Args:
        starts, ends: each NeRF's sample intervals in COMMON-frame ray distance, sorted and non-overlapping along the
            ray (gaps allowed).
        weights: termination probabilities ``p_k = T_k alpha_k``.
        rgbs: sample colours.
        contiguous: whether every NeRF's bins are contiguous (``ends[k] == starts[k+1]``, nerfacto's case); then the
            boundaries are the starts plus the last end, ``M = N * (K + 1) - 1``, instead of all starts and ends,
            ``M = 2 * N * K - 1``. None detects it.

    Returns:
        The merged samples; ``M`` intervals per ray.
    """
    n, k = starts.shape[0], starts.shape[-1]
    bs = starts.shape[1:-1]
    if contiguous is None:
        contiguous = _is_contiguous(starts, ends)
    # Boundaries of all NeRFs, per ray: [*bs, B].
    if contiguous:
        bounds = torch.cat([starts, ends[..., -1:]], dim=-1)
    else:
        bounds = torch.cat([starts, ends], dim=-1)
    bounds = bounds.movedim(0, -2).reshape(bs + (-1,))
    bounds = torch.sort(bounds, dim=-1).values
    m_starts, m_ends = bounds[..., :-1], bounds[..., 1:]
    m = m_starts.shape[-1]

    # Candidate source sample of each merged interval: the first one ending after its midpoint. Whether it really
    # covers the interval is decided on the boundaries themselves (robust when the midpoint rounds onto one).
    mids = (0.5 * (m_starts + m_ends)).unsqueeze(0).expand((n,) + bs + (m,)).contiguous()
    idx = torch.searchsorted(ends.contiguous(), mids, right=True).clamp(max=k - 1)
    src_starts = starts.gather(-1, idx)
    src_ends = ends.gather(-1, idx)
    m_s, m_e = m_starts.unsqueeze(0), m_ends.unsqueeze(0)
    covered = (src_starts <= m_s) & (m_e <= src_ends)
    src_delta = src_ends - src_starts
    overlap = m_e - m_s
    frac = torch.where(covered & (src_delta > 0), overlap / torch.where(src_delta > 0, src_delta, 1.0), 0.0)
    m_weights = weights.gather(-1, idx) * frac
    # Colours via one flat index per merged interval: cheaper than gathering with a [..., M, 3] index.
    offsets = torch.arange(idx[..., 0].numel(), device=idx.device).reshape(idx.shape[:-1] + (1,)) * k
    m_rgbs = rgbs.reshape(-1, rgbs.shape[-1])[(idx + offsets).reshape(-1)].reshape(idx.shape + rgbs.shape[-1:])
    m_rgbs = torch.where(covered.unsqueeze(-1), m_rgbs, 0.0)

    # Zero-length source samples: the first copy of their boundary opens a zero-length merged interval (each one
    # contributes two equal boundaries), which takes their mass; no regular mass lands there.
    deg_w = torch.where(ends <= starts, weights, 0.0)
    if bool((deg_w != 0).any()):
        pos = torch.searchsorted(bounds, starts.movedim(0, -2).reshape(bs + (-1,)).contiguous())
        pos = pos.reshape(bs + (n, k)).movedim(-2, 0).clamp(max=m - 1)
        deg_mass = torch.zeros_like(m_weights).scatter_add_(-1, pos, deg_w)
        deg_rgb = torch.zeros_like(m_rgbs).scatter_add_(
            -2, pos.unsqueeze(-1).expand(pos.shape + (3,)), deg_w.unsqueeze(-1) * rgbs
        )
        has_deg = deg_mass > 0
        m_weights = m_weights + deg_mass
        m_rgbs = torch.where(has_deg.unsqueeze(-1), deg_rgb / torch.where(has_deg, deg_mass, 1.0).unsqueeze(-1), m_rgbs)
    return MergedSamples(starts=m_starts, ends=m_ends, weights=m_weights, rgbs=m_rgbs)


def sample_distances(
    ray_origins: Float[Tensor, "*bs 3"],
    ray_directions: Float[Tensor, "*bs 3"],
    ts: Float[Tensor, "*bs num_points"],
    nerf_origins: Float[Tensor, "num_nerfs 3"] | Float[Tensor, "num_nerfs *bs 3"],
) -> Float[Tensor, "num_nerfs *bs num_points"]:
    """Distance of the points ``o + t d`` along each ray to each NeRF origin (all in the common frame).

    As ``sqrt(h^2 + |d|^2 (t - t0)^2)`` with ``t0`` the ray's closest approach to the origin and ``h`` its distance
    there: per-ray terms plus a few ops per point, never an ``[N, *bs, P, 3]`` tensor, and no cancellation.
    ``nerf_origins`` may differ per ray (``[N, *bs, 3]``: slot i of each ray holds some NeRF's origin).
    """
    origins = nerf_origins
    if nerf_origins.ndim == 2:
        origins = nerf_origins.reshape((nerf_origins.shape[0],) + (1,) * (ray_origins.ndim - 1) + (3,))
    rel = ray_origins.unsqueeze(0) - origins  # [N, *bs, 3]
    dd = (ray_directions * ray_directions).sum(-1).clamp(min=torch.finfo(ray_directions.dtype).tiny)  # [*bs]
    t0 = -(rel * ray_directions.unsqueeze(0)).sum(-1) / dd  # [N, *bs]
    h2 = (rel + t0.unsqueeze(-1) * ray_directions.unsqueeze(0)).square().sum(-1)  # [N, *bs]
    along = ts.unsqueeze(0) - t0.unsqueeze(-1)  # [N, *bs, P]
    return torch.sqrt(h2.unsqueeze(-1) + dd.unsqueeze(-1) * along * along)


def merged_sample_distances(
    merged: MergedSamples,
    ray_origins: Float[Tensor, "*bs 3"],
    ray_directions: Float[Tensor, "*bs 3"],
    nerf_origins: Float[Tensor, "num_nerfs 3"] | Float[Tensor, "num_nerfs *bs 3"],
) -> tuple[Float[Tensor, "num_nerfs *bs num_merged"], Float[Tensor, " num_nerfs *bs"]]:
    """IDW-Sample distances: merged midpoints to each origin, and the background's (the ray's far end, the last
    merged boundary) to each origin."""
    ts = torch.cat([merged.midpoints, merged.ends[..., -1:]], dim=-1)
    d = sample_distances(ray_origins, ray_directions, ts, nerf_origins)
    return d[..., :-1], d[..., -1]


def median_depth(
    weights: Float[Tensor, "*bs k"], mids: Float[Tensor, "*bs k"], fallback: Float[Tensor, " *bs"] | None = None
) -> Float[Tensor, " *bs"]:
    """nerfstudio's "median" depth: the midpoint of the sample where the accumulated weight reaches 0.5.

    Where it never does, nerfstudio takes the last sample's midpoint; ``fallback`` (where finite) replaces that.
    """
    cum = torch.cumsum(weights, dim=-1)
    split = torch.full_like(cum[..., :1], 0.5)
    idx = torch.searchsorted(cum.contiguous(), split, side="left").clamp(0, mids.shape[-1] - 1)
    depth = torch.gather(mids, -1, idx)[..., 0]
    if fallback is None:
        return depth
    return torch.where((cum[..., -1] < 0.5) & torch.isfinite(fallback), fallback, depth)


def last_sample_mids(starts: Float[Tensor, "*bs k"], ends: Float[Tensor, "*bs k"]) -> Float[Tensor, " *bs"]:
    """The midpoint of each ray's last sample of positive length (padding and missing rays are zero-length), NaN
    where there is none: one NeRF's median depth where its accumulated weight never reaches 0.5."""
    real = ends > starts
    idx = torch.arange(real.shape[-1], device=real.device).expand_as(real)
    last = torch.where(real, idx, -1).amax(dim=-1, keepdim=True)
    mids = (0.5 * (starts + ends)).gather(-1, last.clamp(min=0))[..., 0]
    return torch.where(last[..., 0] >= 0, mids, torch.nan)


def furthest_last_mids(
    starts: Float[Tensor, "num_nerfs num_rays k"],
    ends: Float[Tensor, "num_nerfs num_rays k"],
    keep: Bool[Tensor, "num_nerfs num_rays"],
) -> Float[Tensor, " num_rays"]:
    """The median depth of merged samples where the blended weight never reaches 0.5: the furthest of the kept
    NeRFs' own (:func:`last_sample_mids`; -inf where none). The last merged interval would not do: it changes
    discontinuously with the samples, since where two NeRFs' far ends part by a sliver it becomes the sliver (seen:
    6 units of 34 between CPU and CUDA renders, and after a 1e-5 relative change to a NeRF's parameters)."""
    mids = last_sample_mids(starts, ends)
    return torch.where(keep & ~torch.isnan(mids), mids, -math.inf).amax(dim=0)


def expected_depth(weights: Float[Tensor, "*bs k"], mids: Float[Tensor, "*bs k"]) -> Float[Tensor, " *bs"]:
    """nerfstudio's "expected" depth, clipped per ray to the sample range."""
    depth = (weights * mids).sum(-1) / (weights.sum(-1) + 1e-10)
    return torch.clip(depth, mids.amin(-1), mids.amax(-1))


def median_mids(merged: MergedSamples) -> Float[Tensor, "*bs m"]:
    """Merged midpoints for the median depth, zero-length intervals taking the previous real interval's midpoint.

    Merging duplicates boundaries (e.g. identical NeRFs, padding), and the median must not fall on those.
    """
    pos = merged.deltas > 0
    idx = torch.arange(pos.shape[-1], device=pos.device).expand_as(pos)
    last_real = torch.where(pos, idx, 0).cummax(dim=-1).values
    return merged.midpoints.gather(-1, last_real)
