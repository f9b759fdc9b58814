"""Coverage scores (ours): the vectorised functions against a slow loop twin, and properties that can fail."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfuser_ns import coverage, sim3
from nerfuser_ns.blending import coverage_weights, idw_weights, sample_coverage_scores
from nerfuser_ns.coverage import CameraIndex, CoverageParams, camera_quality, candidate_cameras, coverage_scores
from nerfuser_ns.merging import MergedSamples

F = 50.0
INTR = [F, F, 32.0, 24.0, 64.0, 48.0]  # fx fy cx cy width height


def look_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world 4x4, OpenGL axes (looks along -z)."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    back = centre - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross((0.0, 1.0, 0.0), back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, centre
    return c2w


def random_cameras(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    c2w = np.stack([look_at(rng.normal(size=3) * 2.0, rng.normal(size=3) * 0.3) for _ in range(n)])
    intr = np.tile(INTR, (n, 1)) * rng.uniform(0.7, 1.3, size=(n, 1))
    return c2w, intr


def quality_twin(c2w, intr, o, d, t, pixel_width, sigma_deg) -> float:
    """One camera, one point: the module docstring's formulas, written out."""
    d = np.asarray(d, float) / np.linalg.norm(d)
    x = np.asarray(o, float) + t * d
    R, c = c2w[:3, :3], c2w[:3, 3]
    p = R.T @ (x - c)
    z = -p[2]
    fx, fy, cx, cy, w, h = intr
    if z <= 0:
        return 0.0
    u, v = cx + fx * p[0] / z, cy - fy * p[1] / z
    if not (0 <= u <= w and 0 <= v <= h):
        return 0.0
    ray = (x - c) / np.linalg.norm(x - c)
    theta = math.acos(max(-1.0, min(1.0, float(d @ ray))))
    angular = math.exp(-0.5 * (theta / math.radians(sigma_deg)) ** 2)
    r_query, r_train = pixel_width * t, z / math.sqrt(fx * fy)
    return angular * min(1.0, r_query / r_train)


def rays(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=torch.float64) * 1.5
    target = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3
    d = target - o
    ts = torch.rand(n, 7, generator=g, dtype=torch.float64).sort(-1).values * 2.5 * d.norm(dim=-1, keepdim=True)
    d = torch.nn.functional.normalize(d, dim=-1)
    pw = torch.full((n,), 1.0 / F, dtype=torch.float64) * torch.rand(n, generator=g, dtype=torch.float64).add(0.5)
    return o, d, ts, pw


def index_of(c2w, intr) -> CameraIndex:
    return CameraIndex.from_cameras(torch.tensor(c2w), torch.tensor(intr))


# ----------------------------------------------------------------------------------------------------------------------
# Twins


def test_camera_quality_matches_the_loop_twin():
    c2w, intr = random_cameras(9, seed=1)
    index = index_of(c2w, intr)
    o, d, ts, pw = rays(6, seed=2)
    q = camera_quality(index, o, d, ts, pw, 25.0)  # [R, S, C]
    want = torch.tensor([[[quality_twin(c2w[j], intr[j], o[r], d[r], float(ts[r, s]), float(pw[r]), 25.0)
                           for j in range(9)] for s in range(ts.shape[1])] for r in range(6)])  # fmt: skip
    assert (want > 0).sum() >= 20 and (want == 0).sum() >= 20  # both branches are exercised
    torch.testing.assert_close(q, want, atol=2e-5, rtol=1e-4)  # the index is float32
    # Per-ray subsets of cameras: the same values, gathered.
    ids = torch.stack([torch.randperm(9, generator=torch.Generator().manual_seed(r))[:4] for r in range(6)])
    sub = camera_quality(index, o, d, ts, pw, 25.0, ids)
    torch.testing.assert_close(sub, q.gather(-1, ids[:, None, :].expand(-1, ts.shape[1], -1)))


def test_coverage_scores_are_the_mean_of_the_k_best_qualities():
    c2w, intr = random_cameras(9, seed=3)
    index = index_of(c2w, intr)
    o, d, ts, pw = rays(5, seed=4)
    params = CoverageParams(sigma_deg=30.0, k=3, candidates=16)
    got = coverage_scores(index, o, d, ts, pw, params)
    for r in range(5):
        for s in range(ts.shape[1]):
            q = sorted((quality_twin(c2w[j], intr[j], o[r], d[r], float(ts[r, s]), float(pw[r]), 30.0)
                        for j in range(9)), reverse=True)  # fmt: skip
            assert float(got[r, s]) == pytest.approx(sum(q[:3]) / 3, abs=2e-5)


def test_candidates_are_the_best_cameras_at_the_representative_point():
    c2w, intr = random_cameras(12, seed=5)
    index = index_of(c2w, intr)
    o, d, ts, pw = rays(4, seed=6)
    t_rep = ts[:, 3]
    params = CoverageParams(sigma_deg=40.0, k=2, candidates=5)
    ids = candidate_cameras(index, o, d, t_rep, pw, params)
    for r in range(4):
        q = np.array([quality_twin(c2w[j], intr[j], o[r], d[r], float(t_rep[r]), float(pw[r]), 40.0)
                      for j in range(12)])  # fmt: skip
        best = set(np.flatnonzero(q > 0)[np.argsort(-q[q > 0])][:5].tolist())
        assert best <= set(ids[r].tolist())
    # At the representative point the candidates' score is the exact one; with candidates >= cameras, everywhere.
    exact = coverage_scores(index, o, d, ts, pw, params)
    near = coverage_scores(index, o, d, ts, pw, params, t_rep=t_rep)
    torch.testing.assert_close(near[:, 3], exact[:, 3])
    every = CoverageParams(sigma_deg=40.0, k=2, candidates=12)
    torch.testing.assert_close(coverage_scores(index, o, d, ts, pw, every, t_rep=t_rep), exact)


@pytest.mark.parametrize(("k", "candidates", "max_elements"), [(3, 16, 1 << 25), (3, 16, 40), (12, 12, 7)])
def test_the_gpu_blocks_give_the_row_loops_scores(k, candidates, max_elements):
    """The blocked evaluation (GPUs) is the row loop's (CPU) arithmetic: the same scores, in one block or many, with
    more cameras wanted than a ray has (zeros stand in)."""
    c2w, intr = random_cameras(20, seed=12)
    index = index_of(c2w, intr)
    o, d, ts, pw = rays(9, seed=13)
    params = CoverageParams(sigma_deg=30.0, k=k, candidates=candidates)
    frames = coverage._camera_frames(index, o, d)
    ids = coverage._candidates(index, frames, d, ts[:, 3], pw, params)[:, : min(candidates, 8)]
    terms = coverage._candidate_terms(index, frames, pw, ids)
    rows = coverage._sum_of_largest(coverage._qualities(terms, ts, 30.0), k)
    blocked = coverage._sum_of_best_blocked(terms, ts, 30.0, k, max_elements=max_elements)
    assert (rows > 0).any() and (rows < 1e-12).any()  # seen and unseen points both tested
    torch.testing.assert_close(blocked, rows, rtol=1e-12, atol=1e-15)


def _top_level_ops(fn) -> int:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return sum(1 for e in prof.events() if e.name.startswith("aten::") and e.cpu_parent is None)


def test_the_gpu_blocks_issue_a_fraction_of_the_row_loops_operations():
    """Why the blocks exist: a GPU pays per kernel, and the row loop issues ~20 operations per candidate camera. Each
    top-level operation is at least one kernel launch on a GPU."""
    c2w, intr = random_cameras(20, seed=12)
    index = index_of(c2w, intr)
    o, d, ts, pw = rays(9, seed=13)
    params = CoverageParams(k=4, candidates=16)
    frames = coverage._camera_frames(index, o, d)
    terms = coverage._candidate_terms(index, frames, pw, coverage._candidates(index, frames, d, ts[:, 3], pw, params))
    rows = _top_level_ops(lambda: coverage._sum_of_largest(coverage._qualities(terms, ts, 40.0), 4))
    blocks = _top_level_ops(lambda: coverage._sum_of_best_blocked(terms, ts, 40.0, 4))
    assert rows >= 16 * 15 and blocks <= rows / 8, (rows, blocks)


# ----------------------------------------------------------------------------------------------------------------------
# Properties


def one_ray(x=(0.0, 0.0, 0.0), direction=(1.0, 0.0, 0.0), t=2.0):
    d = torch.tensor([direction], dtype=torch.float64)
    d = torch.nn.functional.normalize(d, dim=-1)
    o = torch.tensor([x], dtype=torch.float64) - t * d
    return o, d, torch.tensor([[t]], dtype=torch.float64), torch.tensor([1.0 / F], dtype=torch.float64)


def test_a_camera_along_the_query_direction_beats_one_at_90_degrees():
    o, d, ts, pw = one_ray()
    behind_query = look_at((-2.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # sees x along d
    side = look_at((0.0, -2.0, 0.0), (0.0, 0.0, 0.0))  # sees x at 90 degrees to d, same distance
    q = camera_quality(index_of(np.stack([behind_query, side]), INTR), o, d, ts, pw, 20.0)[0, 0]
    assert q[0] == pytest.approx(1.0) and 0 <= q[1] < 1e-3
    # With a wide angular term the side camera counts, still less.
    q_wide = camera_quality(index_of(np.stack([behind_query, side]), INTR), o, d, ts, pw, 90.0)[0, 0]
    assert q_wide[0] > q_wide[1] > 0.3


def test_a_point_outside_every_frustum_scores_zero():
    o, d, ts, pw = one_ray()
    cams = np.stack([
        look_at((-2.0, 0.0, 0.0), (-4.0, 0.0, 0.0)),  # x is behind it
        look_at((-2.0, 0.0, 0.0), (-2.0, 3.0, 0.1)),  # looks sideways: x outside its field of view
        look_at((-2.0, 0.0, 5.0), (-2.0, 0.0, 9.0), up=(1.0, 0.0, 0.0)),  # looks up, away
    ])  # fmt: skip
    index = index_of(cams, INTR)
    assert torch.equal(camera_quality(index, o, d, ts, pw, 90.0), torch.zeros(1, 1, 3, dtype=torch.float64))
    assert float(coverage_scores(index, o, d, ts, pw, CoverageParams(sigma_deg=90.0))[0, 0]) == 0.0


def test_scores_are_invariant_to_a_similarity_of_cameras_and_rays():
    c2w, intr = random_cameras(10, seed=7)
    o, d, ts, pw = rays(6, seed=8)
    params = CoverageParams(sigma_deg=30.0, k=3, candidates=4)
    before = coverage_scores(index_of(c2w, intr), o, d, ts, pw, params, t_rep=ts[:, 2])
    assert (before > 0).any()
    T = sim3.make_sim3(sim3.random_rotation(np.random.default_rng(0)), np.array([3.0, -1.0, 0.5]), 2.7)
    Tt = torch.tensor(T)
    o2 = o @ Tt[:3, :3].T + Tt[:3, 3]
    d2 = d @ Tt[:3, :3].T / 2.7  # still unit
    ts2 = ts * 2.7
    # The index moved two ways: built from moved poses, and transformed.
    moved = index_of(sim3.transform_poses(T, c2w), intr)
    after = coverage_scores(moved, o2, d2, ts2, pw, params, t_rep=ts2[:, 2])
    torch.testing.assert_close(after, before, atol=2e-5, rtol=1e-4)
    after_t = coverage_scores(index_of(c2w, intr).transformed(T), o2, d2, ts2, pw, params, t_rep=ts2[:, 2])
    torch.testing.assert_close(after_t, before, atol=2e-5, rtol=1e-4)


def test_resolution_term_is_a_footprint_ratio():
    """A camera looking along the query ray from twice the query's distance sees x twice as coarsely: q = 1/2; from
    nearer, q = 1. Scaling the whole scene (query, camera, point) changes nothing."""
    for scale in (1.0, 0.01, 300.0):
        o, d, ts, pw = one_ray(t=2.0 * scale)
        pw = torch.tensor([1.0 / F], dtype=torch.float64)  # the query pixel is as wide as the training pixels
        far = look_at((-4.0 * scale, 0.0, 0.0), (0.0, 0.0, 0.0))
        near = look_at((-1.0 * scale, 0.0, 0.0), (0.0, 0.0, 0.0))
        q = camera_quality(index_of(np.stack([far, near]), INTR), o, d, ts, pw, 20.0)[0, 0]
        torch.testing.assert_close(q, torch.tensor([0.5, 1.0], dtype=torch.float64), atol=1e-5, rtol=0)


def test_index_from_scaled_poses_and_transformed_centres():
    c2w, intr = random_cameras(4, seed=9)
    scaled = c2w.copy()
    scaled[:, :3, :3] *= 3.0  # a pose with a scale: the index keeps the rotation only
    a, b = index_of(c2w, intr), index_of(scaled, intr)
    torch.testing.assert_close(a.w2c, b.w2c)
    torch.testing.assert_close(a.centres, torch.tensor(c2w[:, :3, 3], dtype=torch.float32))
    T = sim3.make_sim3(np.eye(3), np.array([1.0, 2.0, 3.0]), 2.0)
    torch.testing.assert_close(a.transformed(T).centres, torch.tensor(c2w[:, :3, 3] * 2 + [1.0, 2.0, 3.0]).float())
    with pytest.raises(ValueError, match="positive"):
        CameraIndex.from_cameras(c2w, [0.0, F, 32, 24, 64, 48])


def test_params_are_checked():
    with pytest.raises(ValueError, match="candidates"):
        CoverageParams(k=5, candidates=4).checked()
    with pytest.raises(ValueError, match="sigma_deg"):
        CoverageParams(sigma_deg=0.0).checked()


# ----------------------------------------------------------------------------------------------------------------------
# Weights


def test_coverage_weights_are_scores_to_the_gamma_with_the_idw_fallback():
    scores = torch.tensor([[0.8, 0.0, 0.3, 0.0], [0.2, 0.5, 0.3, 0.0], [0.4, 0.0, 0.0, 0.0]])
    distances = torch.tensor([[1.0, 2.0, 3.0, 1.0], [2.0, 1.0, 1.0, 2.0], [1.5, 1.5, 1.5, 4.0]])
    for gamma in (0.5, 3.0):
        w = coverage_weights(scores, distances, gamma)
        want = scores[:, :3] ** gamma / (scores[:, :3] ** gamma).sum(0)
        torch.testing.assert_close(w[:, :3], want)
        torch.testing.assert_close(w[:, 3], idw_weights(distances[:, 3], gamma))  # no NeRF covers it
    torch.testing.assert_close(coverage_weights(scores, distances, 0.0), torch.full_like(scores, 1 / 3))
    inf = coverage_weights(scores, distances, math.inf)
    assert inf[:, 0].tolist() == [1.0, 0.0, 0.0] and inf[:, 1].tolist() == [0.0, 1.0, 0.0]
    # The distance test's mask: NeRF 0 left out; where only it covered, the others fall back to IDW.
    mask = torch.tensor([False, True, True])
    w = coverage_weights(scores, distances, 2.0, mask)
    assert (w[0] == 0).all()
    torch.testing.assert_close(w.sum(0), torch.ones(4))
    torch.testing.assert_close(w[:, 1], torch.tensor([0.0, 1.0, 0.0]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_scores_on_cuda_match_the_cpu():
    c2w, intr = random_cameras(20, seed=10)
    o, d, ts, pw = rays(8, seed=11)
    params = CoverageParams(candidates=6)
    cpu = coverage_scores(index_of(c2w, intr), o, d, ts, pw, params, t_rep=ts[:, 3])
    gpu = coverage_scores(index_of(c2w, intr).to("cuda"), o.cuda(), d.cuda(), ts.cuda(), pw.cuda(), params,
                          t_rep=ts[:, 3].cuda())  # fmt: skip
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-5, rtol=1e-4)


def score_twin(c2w, intr, o, d, ts, pixel_width, params, t_rep=None) -> list[float]:
    """A ray's scores written plainly: per camera, the loop twin's quality; the candidates (the best at ``t_rep``,
    ties to the camera pointing most along the ray) and, per point, the mean of the ``k`` best among them."""
    unit = np.asarray(d, float) / np.linalg.norm(d)
    cams = range(len(c2w))
    if t_rep is not None and len(c2w) > params.candidates:
        key = [quality_twin(c2w[j], intr[j], o, unit, t_rep, pixel_width, params.sigma_deg)
               + 1e-6 * (1.0 + unit @ -c2w[j][:3, 2]) for j in cams]  # fmt: skip
        cams = sorted(cams, key=lambda j: -key[j])[: params.candidates]
    scores = []
    for t in ts:
        q = sorted((quality_twin(c2w[j], intr[j], o, unit, t, pixel_width, params.sigma_deg) for j in cams),
                   reverse=True)  # fmt: skip
        scores.append(sum(q[: params.k]) / params.k)
    return scores


def test_scores_match_the_twin_with_cameras_behind_and_beside_the_points():
    """The fast path (per ray and camera constants, visibility as an interval of t, one camera at a time, a running
    top k) against the plain loop: cameras in front of the points, behind them, looking past them, a narrow one, one
    on a ray (the points on either side of its centre), non-unit directions, candidates fewer than the cameras."""
    rng = np.random.default_rng(12)
    c2w = [look_at(rng.normal(size=3) * 2.0, rng.normal(size=3) * 0.3) for _ in range(7)]  # in front
    c2w += [look_at(c, 2.0 * c) for c in rng.normal(size=(3, 3))]  # looking away: the points are behind them
    c2w += [look_at(c, c + np.cross(c, (0.0, 0.0, 1.0))) for c in rng.normal(size=(2, 3)) * 2.0]  # looking past them
    c2w += [look_at((0.0, -3.0, 0.5), (0.1, 0.0, 0.0))]  # narrow, below: most points outside its image
    o, d, ts, pw = rays(9, seed=13)
    o[0], d[0] = torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    c2w += [look_at((0.0, 0.0, -1.0), (0.0, 0.0, 5.0), up=(0.0, 1.0, 0.0))]  # on ray 0, looking along it
    ts[0] = torch.linspace(0.3, 3.0, ts.shape[1], dtype=torch.float64)  # behind the last camera, then in front
    c2w = np.stack(c2w)
    intr = np.tile(INTR, (len(c2w), 1)) * rng.uniform(0.7, 1.3, size=(len(c2w), 1))
    intr[-2, :2] *= 6.0  # the narrow one
    index = index_of(c2w, intr)
    scale = torch.rand(9, 1, generator=torch.Generator().manual_seed(14), dtype=torch.float64) + 0.5
    d_scaled, ts_scaled = d * scale, ts / scale  # the same points along non-unit directions
    params = CoverageParams(sigma_deg=30.0, k=3, candidates=6)
    t_rep = ts[:, 2]
    points = [[o[r].numpy() + float(t) * d[r].numpy() for t in ts[r]] for r in range(9)]
    twin_q = torch.tensor([[[quality_twin(c2w[j], intr[j], o[r], d[r], float(ts[r, s]), float(pw[r]), 30.0)
                             for j in range(len(c2w))] for s in range(ts.shape[1])] for r in range(9)])  # fmt: skip
    # z = -p_z with p = R^T (x - c): how many (point, camera) pairs have the point behind the camera
    behind = sum(float((c2w[j][:3, :3].T @ (x - c2w[j][:3, 3]))[2]) > 0 for row in points for x in row
                 for j in range(len(c2w)))  # fmt: skip
    assert behind >= 40 and (twin_q == 0).sum() >= 100 and (twin_q > 0).sum() >= 60  # every branch, often
    assert (twin_q[0, :, -1] == 0).any() and (twin_q[0, :, -1] > 0).any()  # either side of the camera on ray 0
    got_q = camera_quality(index, o, d_scaled, ts_scaled, pw, 30.0)
    torch.testing.assert_close(got_q, twin_q, atol=2e-5, rtol=1e-4)  # the index is float32
    for rep in (None, t_rep):  # every camera, then the candidates at t_rep
        got = coverage_scores(index, o, d_scaled, ts_scaled, pw, params, None if rep is None else rep / scale[:, 0])
        want = torch.tensor([score_twin(c2w, intr, o[r], d[r], ts[r].tolist(), float(pw[r]), params,
                                        None if rep is None else float(rep[r])) for r in range(9)])  # fmt: skip
        torch.testing.assert_close(got, want, atol=2e-5, rtol=1e-4)
        assert (want > 0).sum() >= 20
    # float32 rays, as the model's: the same up to float32 rounding
    got32 = coverage_scores(index, o.float(), d_scaled.float(), ts_scaled.float(), pw.float(), params,
                            t_rep=(t_rep / scale[:, 0]).float())  # fmt: skip
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), want, atol=1e-4, rtol=1e-4)
    # No rays, no cameras.
    assert coverage_scores(index, o[:0], d[:0], ts[:0], pw[:0], params, t_rep=t_rep[:0]).shape == (0, ts.shape[1])
    empty = CameraIndex(w2c=index.w2c[:0], intrinsics=index.intrinsics[:0])
    assert camera_quality(empty, o, d, ts, pw, 30.0).shape == (9, ts.shape[1], 0)


def test_blend_skips_only_scores_that_cannot_change_the_weights():
    """``blend`` scores a NeRF only on the rays where it takes part with another (``sample_coverage_scores``'
    ``needed``): the weights do not depend on the other scores (a lone NeRF takes all the weight, one left out none).
    And ``coverage_weights``' one ``idw_weights`` call is the covered / uncovered selection between two."""
    g = torch.Generator().manual_seed(15)
    scores = torch.rand(3, 50, 6, generator=g) * (torch.rand(3, 50, 6, generator=g) > 0.4)
    distances = torch.rand(3, 50, 6, generator=g) + 0.1
    mask = torch.rand(3, 50, generator=g) > 0.6
    mask[torch.randint(0, 3, (50,), generator=g), torch.arange(50)] = True  # every ray keeps one NeRF at least
    needed = mask & (mask.sum(0) > 1)
    assert (mask.sum(0) == 1).any() and (mask.sum(0) == 2).any() and needed.any()
    noise = torch.where(needed[..., None], scores, torch.rand(3, 50, 6, generator=g))
    for gamma in (0.0, 0.7, 5.0, math.inf):
        w = coverage_weights(scores, distances, gamma, mask)
        assert torch.equal(coverage_weights(noise, distances, gamma, mask), w)
        covered = ((scores > 0) & mask[..., None]).any(0, keepdim=True)
        pseudo = torch.where(scores > 0, 1.0 / scores.clamp(min=torch.finfo(scores.dtype).tiny), math.inf)
        pseudo = torch.where(covered, pseudo, torch.ones_like(pseudo))
        two = torch.where(covered, idw_weights(pseudo, gamma, mask), idw_weights(distances, gamma, mask))
        assert torch.equal(w, two)
    # Scores of the needed rays alone: the same as all rays', zeros elsewhere.
    c2w, intr = random_cameras(9, seed=16)
    cameras = [index_of(c2w[:5], intr[:5]), index_of(c2w[3:], intr[3:]), index_of(c2w[::2], intr[::2])]
    o, d, ts, pw = rays(50, seed=17)
    starts = ts[:, :6]
    merged = MergedSamples(starts=starts, ends=torch.cat([starts[:, 1:], ts[:, 6:]], dim=-1),
                           weights=torch.rand(3, 50, 6, generator=g, dtype=torch.float64) * 0.2,
                           rgbs=torch.rand(3, 50, 6, 3, generator=g, dtype=torch.float64))  # fmt: skip
    params = CoverageParams(sigma_deg=30.0, k=2, candidates=3)
    every = sample_coverage_scores(merged, cameras, o, d, pw, params)
    some = sample_coverage_scores(merged, cameras, o, d, pw, params, needed)
    assert (every[needed] > 0).any()
    torch.testing.assert_close(some[needed], every[needed])
    assert (some[~needed] == 0).all()
