"""Tests for nerfuser_ns.blending (pure tensor math, CPU, tiny tensors)."""

import math
import time

import numpy as np
import pytest
import torch

from nerfuser_ns import sim3
from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.blending import (
    BLEND_METHODS,
    PAPER_BLEND_METHODS,
    apply_distance_test,
    blend,
    camera_to_origin_distances,
    coverage_weights,
    distance_mask,
    distance_ratio,
    distance_test,
    idw_2d,
    idw_3d,
    idw_3d_weights,
    idw_sample_blend,
    idw_weights,
    image_blend_weights,
    nearest_blend,
    nearest_index,
    render_samples,
)
from nerfuser_ns.coverage import CameraIndex, CoverageParams, coverage_scores
from nerfuser_ns.merging import (
    MergedSamples,
    expected_depth,
    last_sample_mids,
    median_depth,
    merge_samples,
    merged_sample_distances,
    sample_distances,
)

GAMMAS = [0.01, 1.0, 100.0, 1e4]


def random_nerf_samples(n, r, k, contiguous=True, seed=0, dtype=torch.float64):
    """Sorted samples per NeRF per ray (contiguous bins or with gaps) with p summing to < 1."""
    g = torch.Generator().manual_seed(seed)
    if contiguous:
        t = torch.sort(torch.rand(n, r, k + 1, generator=g, dtype=dtype) * 5 + 0.1, dim=-1).values
        starts, ends = t[..., :-1], t[..., 1:]
    else:
        t = torch.sort(torch.rand(n, r, 2 * k, generator=g, dtype=dtype) * 5 + 0.1, dim=-1).values
        starts, ends = t[..., 0::2], t[..., 1::2]
    p = torch.rand(n, r, k, generator=g, dtype=dtype)
    p = p / p.sum(-1, keepdim=True) * torch.rand(n, r, 1, generator=g, dtype=dtype)
    rgbs = torch.rand(n, r, k, 3, generator=g, dtype=dtype)
    bg = torch.rand(n, r, 3, generator=g, dtype=dtype)
    return starts, ends, p, rgbs, bg


def rays(r, seed=1, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(r, 3, generator=g, dtype=dtype)
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g, dtype=dtype), dim=-1)
    return o, d


# ---------------------------------------------------------------------------------------------------------------------
# merge_samples


@pytest.mark.parametrize("contiguous", [True, False])
def test_merge_conserves_mass_and_sorts(contiguous):
    starts, ends, p, rgbs, _ = random_nerf_samples(3, 7, 5, contiguous=contiguous)
    merged = merge_samples(starts, ends, p, rgbs)
    m = merged.starts.shape[-1]
    assert m == (3 * 6 - 1 if contiguous else 2 * 3 * 5 - 1)
    assert merged.weights.shape == (3, 7, m) and merged.rgbs.shape == (3, 7, m, 3)
    torch.testing.assert_close(merged.weights.sum(-1), p.sum(-1), rtol=1e-12, atol=1e-12)
    assert torch.all(merged.deltas >= 0)
    assert torch.equal(merged.ends[..., :-1], merged.starts[..., 1:])
    assert torch.all(merged.weights >= 0)
    # Each NeRF's rendering (without background) is preserved: colour is constant within a source sample.
    torch.testing.assert_close(render_samples(merged.weights, merged.rgbs), render_samples(p, rgbs))


def test_merge_mass_density_is_uniform_within_source_sample():
    # One NeRF with a single sample [0, 4] of mass 0.8, another splitting it at 1 and 3: 0.2, 0.4, 0.2.
    starts = torch.tensor([[[0.0, 4.0]], [[1.0, 3.0]]])
    ends = torch.tensor([[[4.0, 5.0]], [[3.0, 3.5]]])
    p = torch.tensor([[[0.8, 0.1]], [[0.5, 0.5]]])
    rgbs = torch.rand(2, 1, 2, 3)
    merged = merge_samples(starts, ends, p, rgbs, contiguous=False)
    # Boundaries: 0, 1, 3, 3, 3.5, 4, 4, 5.
    torch.testing.assert_close(merged.starts[0], torch.tensor([0.0, 1.0, 3.0, 3.0, 3.5, 4.0, 4.0]))
    torch.testing.assert_close(merged.weights[0, 0], torch.tensor([0.2, 0.4, 0.0, 0.1, 0.1, 0.0, 0.1]))
    torch.testing.assert_close(merged.weights[1, 0], torch.tensor([0.0, 0.5, 0.0, 0.5, 0.0, 0.0, 0.0]))
    assert torch.equal(merged.rgbs[1, 0, 0], torch.zeros(3))  # uncovered by NeRF 1
    assert torch.equal(merged.rgbs[0, 0, 1], rgbs[0, 0, 0])


@pytest.mark.parametrize("contiguous", [True, False])
def test_merge_single_nerf_reproduces_input(contiguous):
    starts, ends, p, rgbs, bg = random_nerf_samples(1, 5, 6, contiguous=contiguous)
    merged = merge_samples(starts, ends, p, rgbs)
    nonzero = merged.deltas > 0
    if contiguous:
        assert torch.all(nonzero)
        assert torch.equal(merged.starts, starts[0]) and torch.equal(merged.ends, ends[0])
        assert torch.equal(merged.weights, p) and torch.equal(merged.rgbs, rgbs)
    else:
        # Intervals of positive length are exactly the samples and the gaps between them.
        torch.testing.assert_close(merged.weights.sum(-1), p.sum(-1), rtol=1e-14, atol=0)
    o, d = rays(5)
    dist, bg_dist = merged_sample_distances(merged, o, d, torch.zeros(1, 3, dtype=o.dtype))
    for gamma in GAMMAS:
        out = idw_sample_blend(merged, dist, gamma, background_rgbs=bg, background_distances=bg_dist)
        torch.testing.assert_close(out.rgb, render_samples(p[0], rgbs[0], bg[0]), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.nerf_share, torch.ones(1, 5, dtype=p.dtype))


@pytest.mark.parametrize("gamma", GAMMAS)
@pytest.mark.parametrize("contiguous", [True, False])
def test_two_identical_nerfs_blend_to_the_single_render(gamma, contiguous):
    starts, ends, p, rgbs, bg = random_nerf_samples(1, 6, 8, contiguous=contiguous)
    dup = [torch.cat([x, x]) for x in (starts, ends, p, rgbs, bg)]
    merged = merge_samples(*dup[:4])
    o, d = rays(6)
    origins = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, -1.0]], dtype=o.dtype)
    dist, bg_dist = merged_sample_distances(merged, o, d, origins)
    out = idw_sample_blend(merged, dist, gamma, background_rgbs=dup[4], background_distances=bg_dist)
    expected = render_samples(p[0], rgbs[0], bg[0])
    torch.testing.assert_close(out.rgb, expected, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.accumulation, p[0].sum(-1), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.nerf_share.sum(0), torch.ones(6, dtype=p.dtype))


def test_merge_zero_length_intervals_no_nan():
    # Duplicated boundaries across and within NeRFs, zero-length source samples (with and without mass).
    starts = torch.tensor([[[1.0, 2.0, 2.0, 3.0]], [[1.0, 2.0, 2.0, 2.0]]])
    ends = torch.tensor([[[2.0, 2.0, 3.0, 4.0]], [[2.0, 2.0, 2.0, 4.0]]])
    p = torch.tensor([[[0.2, 0.0, 0.3, 0.1]], [[0.1, 0.2, 0.3, 0.4]]])
    rgbs = torch.rand(2, 1, 4, 3)
    for contiguous in (None, False):
        merged = merge_samples(starts, ends, p, rgbs, contiguous=contiguous)
        for x in (merged.weights, merged.rgbs):
            assert torch.isfinite(x).all()
        torch.testing.assert_close(merged.weights.sum(-1), p.sum(-1))
        torch.testing.assert_close(render_samples(merged.weights, merged.rgbs), render_samples(p, rgbs))
        dist = torch.rand(2, 1, merged.starts.shape[-1]) + 0.5
        for gamma in (1e-8, 1.0, 1e8):
            out = idw_sample_blend(merged, dist, gamma, background_rgbs=torch.rand(2, 1, 3))
            for x in (out.rgb, out.depth, out.accumulation, out.nerf_share):
                assert torch.isfinite(x).all()


def test_merge_all_rays_degenerate():
    # Every sample at the same point (e.g. a ray clipped to nothing): no NaN, zero mass stays zero.
    z = torch.zeros(2, 3, 4)
    merged = merge_samples(z, z, z, torch.rand(2, 3, 4, 3))
    out = idw_sample_blend(merged, torch.ones(2, 3, merged.starts.shape[-1]), 5.0, background_rgbs=torch.ones(2, 3, 3))
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    torch.testing.assert_close(out.rgb, torch.ones(3, 3))  # all background
    out = idw_sample_blend(merged, torch.ones(2, 3, merged.starts.shape[-1]), 5.0)  # no background, no mass
    assert torch.isfinite(out.rgb).all()
    assert torch.equal(out.rgb, torch.zeros(3, 3))


# ---------------------------------------------------------------------------------------------------------------------
# IDW weights


def test_idw_weights_basic_and_limits():
    d = torch.tensor([[1.0, 2.0, 0.5], [2.0, 2.0, 4.0], [4.0, 1.0, 4.0]])
    w = idw_weights(d, 1.0)
    torch.testing.assert_close(w.sum(0), torch.ones(3))
    torch.testing.assert_close(w[:, 0], torch.tensor([1.0, 0.5, 0.25]) / 1.75)
    torch.testing.assert_close(idw_weights(d, 2.0)[:, 0], torch.tensor([1.0, 0.25, 0.0625]) / 1.3125)
    torch.testing.assert_close(idw_weights(d, 1e-8), torch.full_like(d, 1 / 3))
    torch.testing.assert_close(idw_weights(d, 0.0), torch.full_like(d, 1 / 3))
    torch.testing.assert_close(idw_weights(d, 1e6)[:, 0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(idw_weights(d, 1e6)[:, 2], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(idw_weights(d, float("inf"))[:, 1], torch.tensor([0.0, 0.0, 1.0]))
    # Exact ties at huge gamma share.
    torch.testing.assert_close(idw_weights(torch.tensor([2.0, 2.0, 3.0]), 1e8), torch.tensor([0.5, 0.5, 0.0]))
    for gamma in (1e-8, 1e8, 1e30, float("inf")):
        w = idw_weights(torch.tensor([[1e-30, 1e30], [1e30, 1e-20]]), gamma)
        assert torch.isfinite(w).all()
        torch.testing.assert_close(w.sum(0), torch.ones(2))
    with pytest.raises(ValueError):
        idw_weights(d, -1.0)


def test_idw_weights_zero_distance():
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 2.0]])
    for gamma in (1e-8, 1.0, 1e8):
        w = idw_weights(d, gamma)
        assert torch.isfinite(w).all()
        torch.testing.assert_close(w[:, 0], torch.tensor([1.0, 0.0]))
        torch.testing.assert_close(w[:, 1], torch.tensor([0.5, 0.5]))


def _two_nerf_scene(r=5, k=6, seed=3):
    starts, ends, p, rgbs, bg = random_nerf_samples(2, r, k, seed=seed)
    merged = merge_samples(starts, ends, p, rgbs)
    o, d = rays(r, seed=seed)
    origins = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.5, -1.0]], dtype=o.dtype)
    dist, bg_dist = merged_sample_distances(merged, o, d, origins)
    return merged, dist, bg_dist, bg


def test_idw_sample_gamma_zero_is_per_sample_mean():
    merged, dist, bg_dist, bg = _two_nerf_scene()
    out = idw_sample_blend(merged, dist, 1e-9, background_rgbs=bg, background_distances=bg_dist)
    p = torch.cat([merged.weights, (1 - merged.weights.sum(-1, keepdim=True))], -1)
    c = torch.cat([merged.rgbs, bg.unsqueeze(-2)], -2)
    q = p.mean(0)
    expected = (p.unsqueeze(-1) * c).mean(0).sum(-2) / q.sum(-1, keepdim=True)
    torch.testing.assert_close(out.rgb, expected)
    torch.testing.assert_close(out.weights.sum(-1) + out.background_weight, torch.ones(5, dtype=p.dtype))


def test_idw_sample_gamma_inf_is_per_sample_nearest():
    merged, dist, bg_dist, bg = _two_nerf_scene()
    p = torch.cat([merged.weights, (1 - merged.weights.sum(-1, keepdim=True))], -1)
    c = torch.cat([merged.rgbs, bg.unsqueeze(-2)], -2)
    d = torch.cat([dist, bg_dist.unsqueeze(-1)], -1)
    one_hot = (d == d.min(0, keepdim=True).values).to(p.dtype)  # KiloNeRF-like: one NeRF per sample
    q = one_hot * p
    expected = (q.unsqueeze(-1) * c).sum((0, -2)) / q.sum((0, -1)).unsqueeze(-1)
    for gamma in (1e6, float("inf")):
        out = idw_sample_blend(merged, dist, gamma, background_rgbs=bg, background_distances=bg_dist)
        torch.testing.assert_close(out.rgb, expected)
        torch.testing.assert_close(out.nerf_share.sum(0), torch.ones(5, dtype=p.dtype))


@pytest.mark.parametrize("gamma", [1e-8, 0.01, 1.0, 5.0, 1e4, 1e8])
def test_idw_sample_normalisation_and_no_nan(gamma):
    merged, dist, bg_dist, bg = _two_nerf_scene()
    out = idw_sample_blend(merged, dist, gamma, background_rgbs=bg, background_distances=bg_dist)
    for x in (out.rgb, out.depth, out.accumulation, out.weights, out.background_weight, out.nerf_share):
        assert torch.isfinite(x).all()
    ones = torch.ones(5, dtype=dist.dtype)
    torch.testing.assert_close(out.weights.sum(-1) + out.background_weight, ones)  # normalisation (2)
    torch.testing.assert_close(out.accumulation, out.weights.sum(-1))
    torch.testing.assert_close(out.nerf_share.sum(0), ones)
    assert torch.all(out.rgb >= 0) and torch.all(out.rgb <= 1 + 1e-9)
    # Without background: the paper's formula, samples alone normalised to 1.
    out = idw_sample_blend(merged, dist, gamma)
    torch.testing.assert_close(out.weights.sum(-1), ones)
    assert torch.isfinite(out.rgb).all()


def test_idw_sample_vanished_mass_falls_back_to_mean():
    # NeRF 0 is nearest everywhere but empty, and there is no background term: at huge gamma every weighted mass
    # underflows to 0 -> plain mean over NeRFs instead of NaN.
    starts = torch.tensor([[[1.0, 2.0]], [[1.0, 2.0]]])
    ends = torch.tensor([[[2.0, 3.0]], [[2.0, 3.0]]])
    p = torch.tensor([[[0.0, 0.0]], [[0.5, 0.5]]])
    rgbs = torch.tensor([[[[1.0, 0, 0], [1.0, 0, 0]]], [[[0, 1.0, 0], [0, 0, 1.0]]]])
    merged = merge_samples(starts, ends, p, rgbs)
    m = merged.starts.shape[-1]
    dist = torch.stack([torch.ones(1, m), torch.full((1, m), 10.0)])
    out = idw_sample_blend(merged, dist, 1e8)
    torch.testing.assert_close(out.rgb, torch.tensor([[0.0, 0.5, 0.5]]))
    torch.testing.assert_close(out.nerf_share, torch.tensor([[0.0], [1.0]]))


def test_idw_sample_fallback_mean_keeps_the_distance_test():
    # As above with a third NeRF that fails the distance test: the fallback mean must leave it out too.
    starts = torch.tensor([[[1.0, 2.0]]] * 3)
    ends = torch.tensor([[[2.0, 3.0]]] * 3)
    p = torch.tensor([[[0.0, 0.0]], [[0.5, 0.5]], [[1.0, 0.0]]])
    rgbs = torch.tensor([[[[1.0, 0, 0], [1.0, 0, 0]]], [[[0, 1.0, 0], [0, 0, 1.0]]], [[[1.0, 0, 0], [1.0, 0, 0]]]])
    merged = merge_samples(starts, ends, p, rgbs)
    m = merged.starts.shape[-1]
    dist = torch.stack([torch.ones(1, m), torch.full((1, m), 10.0), torch.full((1, m), 20.0)])
    camera = torch.tensor([[1.0], [1.1], [5.0]])
    out = idw_sample_blend(merged, dist, 1e8, camera_distances=camera, tau=1.2)
    torch.testing.assert_close(out.rgb, torch.tensor([[0.0, 0.5, 0.5]]))
    torch.testing.assert_close(out.nerf_share, torch.tensor([[0.0], [1.0], [0.0]]))


def test_idw_sample_hand_computed():
    """1 ray, 2 NeRFs, gamma = 1; numbers derived by hand.

    A: [1,2] p=.5 red, [2,3] p=.25 green, background .25 grey.  B: [1.5,2.5] p=.4 blue, [2.5,3] p=.6 white.
    Merged: [1,1.5] [1.5,2] [2,2.5] [2.5,3] [3,3]; A mass .25 .25 .125 .125 0; B mass 0 .2 .2 .6 0.
    Distances (A, B): (1,3) (1,1) (1,1) (3,1) (1,1), background (3,1) -> w_A .75 .5 .5 .25 .5, .25.
    q_A = .1875 .125 .0625 .03125 0 | bg .0625; q_B = 0 .1 .1 .45 0 | 0; total 1.11875.
    """
    starts = torch.tensor([[[1.0, 2.0]], [[1.5, 2.5]]])
    ends = torch.tensor([[[2.0, 3.0]], [[2.5, 3.0]]])
    p = torch.tensor([[[0.5, 0.25]], [[0.4, 0.6]]])
    red, green, blue, white = torch.eye(3)[0], torch.eye(3)[1], torch.eye(3)[2], torch.ones(3)
    rgbs = torch.stack([torch.stack([red, green]), torch.stack([blue, white])]).unsqueeze(1)
    bg = torch.tensor([[[0.5, 0.5, 0.5]], [[1.0, 1.0, 0.0]]])
    merged = merge_samples(starts, ends, p, rgbs)
    torch.testing.assert_close(merged.starts, torch.tensor([[1.0, 1.5, 2.0, 2.5, 3.0]]))
    torch.testing.assert_close(merged.ends, torch.tensor([[1.5, 2.0, 2.5, 3.0, 3.0]]))
    torch.testing.assert_close(
        merged.weights, torch.tensor([[[0.25, 0.25, 0.125, 0.125, 0.0]], [[0, 0.2, 0.2, 0.6, 0]]])
    )
    dist = torch.tensor([[[1.0, 1.0, 1.0, 3.0, 1.0]], [[3.0, 1.0, 1.0, 1.0, 1.0]]])
    bg_dist = torch.tensor([[3.0], [1.0]])
    out = idw_sample_blend(merged, dist, 1.0, background_rgbs=bg, background_distances=bg_dist)
    z = 1.11875
    torch.testing.assert_close(out.rgb, torch.tensor([[0.79375, 0.575, 0.68125]]) / z)
    torch.testing.assert_close(out.nerf_share, torch.tensor([[0.46875], [0.65]]) / z)
    torch.testing.assert_close(out.weights, torch.tensor([[0.1875, 0.225, 0.1625, 0.48125, 0.0]]) / z)
    torch.testing.assert_close(out.background_weight, torch.tensor([0.0625 / z]))
    torch.testing.assert_close(out.accumulation, torch.tensor([1.05625 / z]))
    torch.testing.assert_close(out.depth, torch.tensor([2.3171875 / 1.05625]))


def test_idw_sample_distance_test_override_gives_nearest_render():
    merged, dist, bg_dist, bg = _two_nerf_scene(r=4)
    _, _, p, rgbs, bg = random_nerf_samples(2, 4, 6, seed=3)
    cam_d = torch.tensor([[1.0, 1.0, 1.0, 3.0], [3.0, 1.5, 1.0, 1.0]], dtype=dist.dtype)  # ratios 3, 1.5, 1, 3
    out = idw_sample_blend(
        merged, dist, 2.0, background_rgbs=bg, background_distances=bg_dist, camera_distances=cam_d, tau=2.0
    )
    torch.testing.assert_close(out.rgb[0], render_samples(p[0, 0], rgbs[0, 0], bg[0, 0]))
    torch.testing.assert_close(out.rgb[3], render_samples(p[1, 3], rgbs[1, 3], bg[1, 3]))
    torch.testing.assert_close(out.nerf_share[:, [0, 3]], torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=dist.dtype))
    plain = idw_sample_blend(merged, dist, 2.0, background_rgbs=bg, background_distances=bg_dist)
    torch.testing.assert_close(out.rgb[1:3], plain.rgb[1:3])


def test_idw_sample_distance_test_drops_far_nerfs_only():
    # Three NeRFs, the third far from every camera: with tau it takes no part, and the blend is exactly that of the
    # two near NeRFs alone (weights, colours and backgrounds), even where its origin is nearest to the samples.
    n, r, k = 3, 6, 5
    starts, ends, p, rgbs, bg = random_nerf_samples(n, r, k, seed=11)
    # The third NeRF samples where the first does, so it adds no merged boundaries (only zero-length intervals).
    starts[2], ends[2] = starts[0], ends[0]
    origins = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.0, 4.0]])
    o = torch.tensor([[0.5, 0.2, 0.0]]).expand(r, 3)
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    d[:, 2] = d[:, 2].abs()  # towards the third origin: its samples come nearest to it
    cam_d = camera_to_origin_distances(o, origins)
    assert distance_mask(cam_d, 1.8).tolist() == [[True] * r, [True] * r, [False] * r]

    def blend(sl, tau):
        merged = merge_samples(starts[sl], ends[sl], p[sl], rgbs[sl])
        dist, bg_dist = merged_sample_distances(merged, o, d, origins[sl])
        return idw_sample_blend(merged, dist, 5.0, bg[sl], bg_dist, cam_d[sl], tau)

    three, two = blend(slice(0, 3), 1.8), blend(slice(0, 2), None)
    torch.testing.assert_close(three.rgb, two.rgb)
    torch.testing.assert_close(three.nerf_share[:2], two.nerf_share)
    assert (three.nerf_share[2] == 0).all()
    assert not torch.allclose(blend(slice(0, 3), None).rgb, two.rgb)


def test_sample_distances_match_explicit_points():
    g = torch.Generator().manual_seed(5)
    o = torch.randn(4, 7, 3, generator=g, dtype=torch.float64)
    d = torch.randn(4, 7, 3, generator=g, dtype=torch.float64)
    ts = torch.rand(4, 7, 9, generator=g, dtype=torch.float64) * 10
    origins = torch.randn(3, 3, generator=g, dtype=torch.float64)
    points = o[..., None, :] + ts[..., None] * d[..., None, :]
    explicit = torch.linalg.vector_norm(points[None] - origins[:, None, None, None, :], dim=-1)
    torch.testing.assert_close(sample_distances(o, d, ts, origins), explicit)
    # Per-ray origins: slot j of each ray holds some NeRF's origin (the fused model packs each ray's NeRFs).
    order = torch.randint(0, 3, (2, 4, 7), generator=g)
    per_ray = origins[order]  # [2, 4, 7, 3]
    want = explicit.gather(0, order[..., None].expand(-1, -1, -1, 9))
    torch.testing.assert_close(sample_distances(o, d, ts, per_ray), want)
    # A ray through an origin: distance exactly |t - t0| there, no cancellation noise in float32.
    o1, d1 = torch.tensor([[100.0, 0.0, 0.0]]), torch.tensor([[-1.0, 0.0, 0.0]])
    near = sample_distances(o1, d1, torch.tensor([[100.0, 100.001]]), torch.zeros(1, 3))
    torch.testing.assert_close(near, torch.tensor([[[0.0, 0.001]]]), atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------------------------------------
# Baselines


def test_distance_test_switches_at_tau():
    d = torch.tensor([[1.0, 1.0, 2.0, 1.0, 0.0, 0.0], [1.79, 1.81, 1.0, 1.0, 1.0, 0.0]])
    torch.testing.assert_close(distance_ratio(d)[:4], torch.tensor([1.79, 1.81, 2.0, 1.0]))
    assert distance_test(d, 1.8).tolist() == [False, True, True, False, True, False]
    # N = 3: second-nearest over nearest, whichever NeRFs they are.
    d3 = torch.tensor([[5.0, 1.0], [2.0, 3.0], [1.0, 1.5]])
    torch.testing.assert_close(distance_ratio(d3), torch.tensor([2.0, 1.5]))
    assert distance_test(d3, 1.8).tolist() == [True, False]
    assert distance_test(torch.tensor([[2.0]]), 1.8).tolist() == [True]
    # Who takes part: within tau times the nearest distance (the nearest always; ties at tau included).
    assert distance_mask(d3, 1.8).tolist() == [[False, True], [False, False], [True, True]]
    assert distance_mask(d3, 2.0).tolist() == [[False, True], [True, False], [True, True]]
    assert distance_mask(d3, None).all()
    assert distance_mask(torch.tensor([[0.0], [0.0], [1e-6]]), 100.0).tolist() == [[True], [True], [False]]
    # Two NeRFs: the mask keeps both exactly where the paper's test blends.
    dd = torch.rand(2, 100) + 0.01
    for tau in (1.2, 1.8):
        torch.testing.assert_close(distance_mask(dd, tau).all(0), ~distance_test(dd, tau))
    assert distance_test(torch.tensor([[1.0], [2.0]]), 2.0).tolist() == [
        False
    ]  # strictly greater than tau  # one NeRF: always nearest only


def test_nearest_and_idw_2d():
    rgbs = torch.rand(3, 4, 5, 3)
    d = torch.tensor([2.0, 0.5, 1.0])
    assert nearest_index(d).item() == 1
    torch.testing.assert_close(nearest_blend(rgbs, d), rgbs[1])
    torch.testing.assert_close(idw_2d(rgbs, torch.tensor([1.5, 1.5, 1.5]), 5.0), rgbs.mean(0))
    w = torch.tensor([0.5, 2.0, 1.0])
    torch.testing.assert_close(idw_2d(rgbs, d, 1.0), (w[:, None, None, None] * rgbs).sum(0) / 3.5)
    # Distance test: ratio 2 > 1.8 -> nearest only; < tau -> IDW.
    torch.testing.assert_close(idw_2d(rgbs, d, 1.0, tau=1.8), rgbs[1])
    torch.testing.assert_close(idw_2d(rgbs, d, 1.0, tau=4.5), idw_2d(rgbs, d, 1.0))
    # N = 3, tau 2.5: NeRF 0 (4x the nearest's distance) is left out, NeRFs 1 and 2 blend among themselves.
    torch.testing.assert_close(idw_2d(rgbs, d, 1.0, tau=2.5), (2 * rgbs[1] + rgbs[2]) / 3)
    # Per-camera distances over a batch of images.
    d_cam = torch.tensor([[2.0, 1.0], [1.0, 1.0], [4.0, 1.0]])
    rgbs_b = torch.rand(3, 2, 4, 5, 3)
    out = idw_2d(rgbs_b, d_cam, 1.0, tau=1.8)
    torch.testing.assert_close(out[0], rgbs_b[1, 0])
    torch.testing.assert_close(out[1], rgbs_b[:, 1].mean(0))


def test_idw_3d():
    r = 4
    rgbs = torch.rand(2, r, 3)
    o = torch.zeros(r, 3)
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(r, 3)
    origins = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 4.0]])
    depths = torch.tensor([[2.0, 1.0, 3.0, 1.5], [2.0, 6.0, 3.0, 4.0]])  # surface distances A: 1,0,2,.5 B: 2,2,1,0
    w = idw_3d_weights(depths, o, d, origins, 1.0)
    torch.testing.assert_close(w[:, 0], torch.tensor([2 / 3, 1 / 3]))
    torch.testing.assert_close(w[:, 1], torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(w[:, 2], torch.tensor([1 / 3, 2 / 3]))
    torch.testing.assert_close(w[:, 3], torch.tensor([0.0, 1.0]))
    torch.testing.assert_close(idw_3d(rgbs, depths, o, d, origins, 1.0), (w.unsqueeze(-1) * rgbs).sum(0))
    # Camera at z=0 is 1 from A and 4 from B: distance test forces A everywhere.
    cam_d = camera_to_origin_distances(torch.zeros(3), origins)
    torch.testing.assert_close(cam_d, torch.tensor([1.0, 4.0]))
    torch.testing.assert_close(idw_3d(rgbs, depths, o, d, origins, 1.0, cam_d, tau=1.8), rgbs[0])


def test_image_blend_weights_and_methods():
    assert PAPER_BLEND_METHODS == ("nerf", "nearest", "idw-2d", "idw-3d", "idw-sample")
    assert BLEND_METHODS == PAPER_BLEND_METHODS + ("coverage", "coverage-3d")  # ours after the paper's
    d = torch.tensor([2.0, 1.0])
    torch.testing.assert_close(image_blend_weights("nerf", d, 1.0, reference=0), torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(image_blend_weights("nearest", d, 1.0), torch.tensor([0.0, 1.0]))
    torch.testing.assert_close(image_blend_weights("idw-2d", d, 1.0), torch.tensor([1 / 3, 2 / 3]))
    torch.testing.assert_close(image_blend_weights("idw-2d", d, 1.0, tau=1.5), torch.tensor([0.0, 1.0]))
    sd = torch.tensor([[1.0, 3.0], [1.0, 1.0]])
    torch.testing.assert_close(
        image_blend_weights("idw-3d", d, 1.0, surface_distances=sd)[:, 1], torch.tensor([0.25, 0.75])
    )
    with pytest.raises(ValueError):
        image_blend_weights("idw-sample", d, 1.0)
    w = apply_distance_test(torch.full((2, 3), 0.5), torch.tensor([[1.0, 1.0, 3.0], [1.0, 3.0, 1.0]]), 2.0)
    torch.testing.assert_close(w, torch.tensor([[0.5, 1.0, 0.0], [0.5, 0.0, 1.0]]))
    # Three NeRFs: the far one's weight goes to the others in proportion; none left -> the nearest.
    w3 = torch.tensor([[0.2, 0.0], [0.2, 0.0], [0.6, 1.0]])
    w3 = apply_distance_test(w3, torch.tensor([[1.0], [1.5], [9.0]]), 2.0)
    torch.testing.assert_close(w3, torch.tensor([[0.5, 1.0], [0.5, 0.0], [0.0, 0.0]]))


def test_idw_weights_mask():
    d = torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 1.0], [0.5, 4.0, 0.0]])
    keep = torch.tensor([[True, True, True], [True, True, True], [False, True, False]])
    for gamma in (0.0, 1.0, 7.0, 1e30, math.inf):
        w = idw_weights(d, gamma, keep)
        torch.testing.assert_close(w.sum(0), torch.ones(3))
        assert (w[~keep] == 0).all()
        # Same as IDW over the NeRFs that take part alone.
        torch.testing.assert_close(w[:2, 0], idw_weights(d[:2, 0:1], gamma)[:, 0])
    torch.testing.assert_close(idw_weights(d, 1.0, keep)[:, 1], torch.tensor([2.0, 4.0, 1.0]) / 7)
    torch.testing.assert_close(idw_weights(d, 0.0, keep)[:, 0], torch.tensor([0.5, 0.5, 0.0]))
    # A NeRF left out at distance 0 takes nothing: the zero-distance rule applies among those taking part.
    torch.testing.assert_close(idw_weights(d, 3.0, keep)[:, 2], torch.tensor([1.0, 0.0, 0.0]))
    # A per-ray mask broadcasts over the samples of the ray.
    ds = torch.rand(3, 5, 7) + 0.1
    ray_keep = torch.tensor([[True] * 5, [True, False, True, False, True], [False] * 5])
    w = idw_weights(ds, 4.0, ray_keep)
    assert (w[2] == 0).all() and (w[1, 1] == 0).all()
    torch.testing.assert_close(w[0, 1], torch.ones(7))


# ---------------------------------------------------------------------------------------------------------------------
# Vectorisation


def test_vectorised_speed():
    n, r, k = 2, 4096, 48
    starts, ends, p, rgbs, bg = random_nerf_samples(n, r, k, dtype=torch.float32)
    o, d = rays(r, dtype=torch.float32)
    origins = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])

    def run():
        merged = merge_samples(starts, ends, p, rgbs)
        dist, bg_dist = merged_sample_distances(merged, o, d, origins)
        return idw_sample_blend(merged, dist, 5.0, background_rgbs=bg, background_distances=bg_dist)

    run()  # warm-up (allocator, lazy init)
    times = []
    for _ in range(3):  # the best of three: other processes on a shared machine only ever add time
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    assert out.rgb.shape == (r, 3) and torch.isfinite(out.rgb).all()
    assert min(times) < 1.0, f"merge + blend of {r} rays took {min(times):.3f} s (best of 3)"


def test_merged_samples_dataclass():
    ms = MergedSamples(
        starts=torch.tensor([[0.0, 1.0]]),
        ends=torch.tensor([[1.0, 3.0]]),
        weights=torch.zeros(1, 1, 2),
        rgbs=torch.zeros(1, 1, 2, 3),
    )
    torch.testing.assert_close(ms.midpoints, torch.tensor([[0.5, 2.0]]))
    torch.testing.assert_close(ms.deltas, torch.tensor([[1.0, 2.0]]))


# ---------------------------------------------------------------------------------------------------------------------
# blend(): the one entry the model calls, against the reference functions (its twins)


def _blend_inputs(n=3, r=40, k=8, seed=5):
    starts, ends, p, rgbs, bg = random_nerf_samples(n, r, k, seed=seed)
    o, d = rays(r, seed=seed + 1)
    nerf_origins = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed + 2), dtype=torch.float64) * 2
    return starts, ends, p, rgbs, bg, o, d, nerf_origins


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_median_depth_where_half_the_mass_is_never_reached_is_continuous(dtype):
    """Two NeRFs with the same samples but the second's far end, too little mass to reach 0.5: every method's median
    depth is nerfstudio's (the last sample's midpoint) for the NeRFs alike, moves with the far end by at most what
    the end moved, and IDW-Sample takes the furthest NeRF's own. (The last merged interval jumped: where the far ends
    part by a sliver, it became the sliver, half the last sample away.)"""
    starts = torch.tensor([2.0, 8.0, 16.0], dtype=dtype).expand(2, 1, 3).clone()
    p = torch.tensor([0.05, 0.1, 0.07], dtype=dtype).expand(2, 1, 3)
    rgbs = torch.rand(2, 1, 3, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    o, d = torch.zeros(1, 3, dtype=dtype), torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype)
    origins = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]], dtype=dtype)
    settings = BlendSettings(gamma=5.0, tau=None)

    def depths(end_b: float) -> dict[str, float]:
        ends = torch.tensor([8.0, 16.0, 33.7175], dtype=dtype).expand(2, 1, 3).clone()
        ends[1, 0, -1] = end_b
        out = blend(BLEND_METHODS, starts, ends, p, rgbs, torch.zeros(2, 1, 3, dtype=dtype), o, d, origins, settings)
        return {m: float(r["depth"][0]) for m, r in out.items()}

    single = 0.5 * (16.0 + 33.7175)
    ends_b = [33.7175, 33.71751, 33.7176, 33.72, 34.0, 40.0]
    runs = [depths(e) for e in ends_b]
    for method, value in runs[0].items():
        assert value == pytest.approx(single, rel=1e-6), method
    for i in range(1, len(ends_b)):
        for method in BLEND_METHODS:
            step = abs(runs[i][method] - runs[i - 1][method])
            assert step <= 0.5 * (ends_b[i] - ends_b[i - 1]) + 1e-4, (method, ends_b[i - 1], ends_b[i])
    assert runs[-1]["idw-sample"] == pytest.approx(0.5 * (16.0 + 40.0), rel=1e-6)


@pytest.mark.parametrize("tau", [None, 1.5])
@pytest.mark.parametrize("gamma", [0.5, 4.0])
def test_blend_entry_matches_the_reference_functions(gamma, tau):
    starts, ends, p, rgbs, bg, o, d, origins = _blend_inputs()
    settings = BlendSettings(gamma=gamma, tau=tau)
    out = blend(BLEND_METHODS, starts, ends, p, rgbs, bg, o, d, origins, settings, reference=2)
    cam_d = camera_to_origin_distances(o, origins)
    mids = 0.5 * (starts + ends)
    rgb_i = render_samples(p, rgbs, bg).clamp(0, 1)
    torch.testing.assert_close(out["nerf"]["rgb"], rgb_i[2])
    torch.testing.assert_close(out["nearest"]["rgb"], nearest_blend(rgb_i, cam_d))
    torch.testing.assert_close(out["idw-2d"]["rgb"], idw_2d(rgb_i, cam_d, gamma, tau))
    exp_i = expected_depth(p, mids)
    torch.testing.assert_close(out["idw-3d"]["rgb"], idw_3d(rgb_i, exp_i, o, d, origins, gamma, cam_d, tau))
    # IDW-Sample, ray by ray: merge the samples of the NeRFs passing the distance test only (the others must not
    # split the ray's intervals), then the paper's sample-wise IDW
    keep = distance_mask(cam_d, tau)
    got = out["idw-sample"]
    for ray in range(starts.shape[1]):
        ids = keep[:, ray].nonzero()[:, 0]
        merged = merge_samples(starts[ids, ray : ray + 1], ends[ids, ray : ray + 1], p[ids, ray : ray + 1],
                               rgbs[ids, ray : ray + 1])  # fmt: skip
        dist, d_bg = merged_sample_distances(merged, o[ray : ray + 1], d[ray : ray + 1], origins[ids])
        ref = idw_sample_blend(merged, dist, gamma, bg[ids, ray : ray + 1], d_bg)
        torch.testing.assert_close(got["rgb"][ray : ray + 1], ref.rgb.clamp(0, 1))
        torch.testing.assert_close(got["accumulation"][ray : ray + 1], ref.accumulation)
        assert (got["share"][~keep[:, ray], ray] == 0).all()
    for method in BLEND_METHODS:
        share = out[method]["share"]
        assert share.shape == (3, 40) and torch.isfinite(share).all()


@pytest.mark.parametrize("tau", [None, 1.5])
def test_blend_coverage_matches_its_twins_and_is_idw_sample_without_cameras(tau):
    """``coverage`` in ``blend``, ray by ray: the kept NeRFs' samples merged, each NeRF's coverage score at the merged
    midpoints and the far end (candidates at the merged mass's expected point), ``coverage_weights``, then
    IDW-Sample's accumulation with those weights."""
    starts, ends, p, rgbs, bg, o, d, origins = _blend_inputs()
    gen = torch.Generator().manual_seed(11)
    params = CoverageParams(sigma_deg=35.0, k=2, candidates=3)
    cameras = []
    for i in range(3):  # a few cameras per NeRF around its origin, looking at the rays' region
        centres = origins[i] + torch.randn(5, 3, generator=gen, dtype=torch.float64) * 2
        c2w = torch.stack([_look_at(c, torch.zeros(3, dtype=torch.float64)) for c in centres])
        cameras.append(CameraIndex.from_cameras(c2w, [30.0, 30.0, 16.0, 12.0, 32.0, 24.0]))
    pw = torch.full((40,), 0.02, dtype=torch.float64)
    settings = BlendSettings(method="coverage", gamma=3.0, tau=tau, coverage=params)
    out = blend(["idw-sample", "coverage"], starts, ends, p, rgbs, bg, o, d, origins, settings, cameras=cameras,
                pixel_widths=pw)["coverage"]  # fmt: skip
    cam_d = camera_to_origin_distances(o, origins)
    keep = distance_mask(cam_d, tau)
    covered = 0
    for ray in range(starts.shape[1]):
        ids = keep[:, ray].nonzero()[:, 0]
        sl = slice(ray, ray + 1)
        merged = merge_samples(starts[ids, sl], ends[ids, sl], p[ids, sl], rgbs[ids, sl])
        dist, d_bg = merged_sample_distances(merged, o[sl], d[sl], origins[ids])
        ts = torch.cat([merged.midpoints, merged.ends[..., -1:]], dim=-1)
        mass = merged.weights.sum(0)
        t_rep = (mass * merged.midpoints).sum(-1) / mass.sum(-1)
        scores = torch.stack([coverage_scores(cameras[int(i)], o[sl], d[sl], ts, pw[sl], params, t_rep) for i in ids])
        covered += int((scores > 0).any(0).sum())
        w = coverage_weights(scores, torch.cat([dist, d_bg[..., None]], dim=-1), 3.0)
        ref = idw_sample_blend(merged, dist, 3.0, bg[ids, sl], d_bg, nerf_weights=w)
        torch.testing.assert_close(out["rgb"][sl], ref.rgb.clamp(0, 1))
        torch.testing.assert_close(out["accumulation"][sl], ref.accumulation)
        torch.testing.assert_close(out["share"][ids, ray], ref.nerf_share[:, 0])
    assert covered > 40  # the cameras see many samples: the check is not the fallback alone
    plain = blend(["idw-sample", "coverage"], starts, ends, p, rgbs, bg, o, d, origins, settings)
    for key in plain["idw-sample"]:
        assert torch.equal(plain["coverage"][key], plain["idw-sample"][key])
    assert not torch.allclose(out["rgb"], plain["idw-sample"]["rgb"])


def _cameras_around(origins, gen, spread=2.0):
    """A few cameras per NeRF around its origin, looking at the common origin (the rays' region)."""
    cameras = []
    for origin in origins:
        centres = origin + torch.randn(5, 3, generator=gen, dtype=torch.float64) * spread
        c2w = torch.stack([_look_at(c, torch.zeros(3, dtype=torch.float64)) for c in centres])
        cameras.append(CameraIndex.from_cameras(c2w, [30.0, 30.0, 16.0, 12.0, 32.0, 24.0]))
    return cameras


@pytest.mark.parametrize("tau", [None, 1.5])
def test_blend_coverage_3d_matches_its_twin_and_is_idw_2d_without_cameras(tau):
    """``coverage-3d`` in ``blend``, ray by ray: each kept NeRF's coverage score at its own median-depth point
    (candidates there), ``coverage_weights`` on those scores with the camera distances as the fallback, then the
    weighted mean of the NeRFs' own renderings; a ray's lone kept NeRF takes it all."""
    starts, ends, p, rgbs, bg, o, d, origins = _blend_inputs()
    params = CoverageParams(sigma_deg=35.0, k=2, candidates=3)
    cameras = _cameras_around(origins, torch.Generator().manual_seed(11))
    pw = torch.full((40,), 0.02, dtype=torch.float64)
    settings = BlendSettings(method="coverage-3d", gamma=3.0, tau=tau, coverage=params)
    out = blend(["idw-2d", "coverage-3d"], starts, ends, p, rgbs, bg, o, d, origins, settings, cameras=cameras,
                pixel_widths=pw)  # fmt: skip
    cam_d = camera_to_origin_distances(o, origins)
    keep = distance_mask(cam_d, tau)
    rgb_i = render_samples(p, rgbs, bg).clamp(0, 1)
    depth_i = median_depth(p, 0.5 * (starts + ends), last_sample_mids(starts, ends))
    covered = 0
    for ray in range(starts.shape[1]):
        ids = keep[:, ray].nonzero()[:, 0]
        sl = slice(ray, ray + 1)
        t = depth_i[ids, sl]  # [n, 1]
        scores = torch.stack([coverage_scores(cameras[int(i)], o[sl], d[sl], t[j][:, None], pw[sl], params, t[j])[:, 0]
                              for j, i in enumerate(ids)])  # fmt: skip
        if len(ids) > 1:
            covered += int((scores > 0).any())
        w = coverage_weights(scores, cam_d[ids, sl], 3.0) if len(ids) > 1 else torch.ones(1, 1, dtype=scores.dtype)
        torch.testing.assert_close(out["coverage-3d"]["rgb"][sl], (w[..., None] * rgb_i[ids, sl]).sum(0))
        torch.testing.assert_close(out["coverage-3d"]["share"][ids, ray], w[:, 0])
        assert (out["coverage-3d"]["share"][~keep[:, ray], ray] == 0).all()
    assert covered > 10  # the cameras see many of the points: the check is not the fallback alone
    assert not torch.allclose(out["coverage-3d"]["rgb"], out["idw-2d"]["rgb"])
    plain = blend(["idw-2d", "coverage-3d"], starts, ends, p, rgbs, bg, o, d, origins, settings)
    for key in plain["idw-2d"]:
        assert torch.equal(plain["coverage-3d"][key], plain["idw-2d"][key])


def test_coverage_3d_prefers_the_nerf_whose_cameras_saw_its_surface_and_keeps_identical_nerfs_exact():
    """Two NeRFs with the same samples and origin: the one whose training cameras stand by the query camera and look
    along its rays takes the weight from one whose cameras look the other way; with the same cameras too, the blend
    is the single NeRF's rendering (any weights of equal renders)."""
    starts, ends, p, rgbs, bg, _, _, _ = _blend_inputs(n=1, r=12)
    two = [torch.cat([x, x]) for x in (starts, ends, p, rgbs, bg)]
    gen = torch.Generator().manual_seed(3)
    o = torch.zeros(12, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.cat([0.2 * torch.randn(12, 2, generator=gen, dtype=torch.float64),
                                                 torch.ones(12, 1, dtype=torch.float64)], dim=-1), dim=-1)  # fmt: skip
    origins = torch.zeros(2, 3, dtype=torch.float64)  # same origin: only the cameras tell the NeRFs apart
    centres = 0.05 * torch.randn(4, 3, generator=gen, dtype=torch.float64)
    forward = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    seeing = torch.stack([_look_at(c, c + forward) for c in centres])
    away = torch.stack([_look_at(c, c - forward) for c in centres])
    intr = [30.0, 30.0, 16.0, 12.0, 32.0, 24.0]
    pw = torch.full((12,), 0.02, dtype=torch.float64)
    settings = BlendSettings(method="coverage-3d", gamma=5.0, tau=None, coverage=CoverageParams(k=2, candidates=4))
    cams = [CameraIndex.from_cameras(seeing, intr), CameraIndex.from_cameras(away, intr)]
    share = blend(["coverage-3d"], *two, o, d, origins, settings, cameras=cams, pixel_widths=pw)["coverage-3d"]["share"]
    assert (share[0] > 0.99).all(), share
    same = [CameraIndex.from_cameras(seeing, intr)] * 2
    out = blend(["coverage-3d"], *two, o, d, origins, settings, cameras=same, pixel_widths=pw)["coverage-3d"]
    torch.testing.assert_close(out["rgb"], render_samples(p, rgbs, bg).clamp(0, 1)[0])
    torch.testing.assert_close(out["share"], torch.full((2, 12), 0.5, dtype=torch.float64))


def test_coverage_3d_weights_are_invariant_to_a_similarity_of_everything():
    """NeRFs, their cameras and the query rays moved by one SIM(3) together (distances scale, pixel widths are angles):
    the same weights and colours."""
    starts, ends, p, rgbs, bg, o, d, origins = _blend_inputs()
    cameras = _cameras_around(origins, torch.Generator().manual_seed(11))
    pw = torch.full((40,), 0.02, dtype=torch.float64)
    settings = BlendSettings(method="coverage-3d", gamma=3.0, tau=1.5, coverage=CoverageParams(k=2, candidates=3))
    before = blend(["coverage-3d"], starts, ends, p, rgbs, bg, o, d, origins, settings, cameras=cameras,
                   pixel_widths=pw)["coverage-3d"]  # fmt: skip
    s = 2.7
    T = torch.tensor(sim3.make_sim3(sim3.random_rotation(np.random.default_rng(0)), np.array([3.0, -1.0, 0.5]), s))
    A, t = T[:3, :3], T[:3, 3]
    after = blend(["coverage-3d"], starts * s, ends * s, p, rgbs, bg, o @ A.T + t, d @ A.T / s, origins @ A.T + t,
                  settings, cameras=[c.transformed(T) for c in cameras], pixel_widths=pw)["coverage-3d"]  # fmt: skip
    assert (before["share"] > 0.01).sum(0).gt(1).sum() > 5  # blended rays, not only lone NeRFs
    torch.testing.assert_close(after["share"], before["share"], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(after["rgb"], before["rgb"], atol=1e-6, rtol=1e-5)


def _look_at(centre, target):
    back = torch.nn.functional.normalize(centre - target, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=back.dtype), back),
                                          dim=0)  # fmt: skip
    return torch.stack([right, torch.linalg.cross(back, right), back, centre], dim=-1)
