"""Rigid-set bundle adjustment (nerfuser_ns.bundle) on synthetic cameras and points with known ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from nerfuser_ns import bundle, sim3
from nerfuser_ns.sampling import look_at

K = (150.0, 150.0, 96.0, 72.0)
W, H = 192, 144


def synthetic(seed: int, k: int = 3, per_nerf: int = 20, noise_px: float = 0.0, outliers: float = 0.0, ref: int = 0):
    """k NeRFs whose cameras look at one point cloud; each NeRF's poses are given in its own frame."""
    rng = np.random.default_rng(seed)
    T_true = np.stack([
        np.eye(4) if i == ref else sim3.make_sim3(sim3.random_rotation(rng), rng.normal(size=3), s)
        for i, s in zip(range(k), np.exp(rng.uniform(-1.5, 1.5, size=k)), strict=True)
    ])  # fmt: skip
    points = rng.uniform(-0.5, 0.5, (300, 3))
    cams, nerf = [], []
    for i in range(k):
        for _ in range(per_nerf):
            d = rng.normal(size=3)
            d[2] = abs(d[2]) + 0.2
            pose_ref = look_at(2.0 * d / np.linalg.norm(d), np.zeros(3))
            cams.append(sim3.transform_poses(sim3.invert_sim3(T_true[i]), pose_ref))
            nerf.append(i)
    cams, nerf = np.stack(cams), np.array(nerf)
    M = sim3.invert_sim3(cams)[:, :3] @ sim3.invert_sim3(T_true)[nerf]
    oc, op = (a.ravel() for a in np.meshgrid(np.arange(len(cams)), np.arange(len(points)), indexing="ij"))
    xy = bundle.project(M[oc], points[op], K)
    seen = (xy[:, 0] > 0) & (xy[:, 0] < W) & (xy[:, 1] > 0) & (xy[:, 1] < H) & (rng.random(len(oc)) < 0.3)
    oc, op, xy = oc[seen], op[seen], xy[seen] + rng.normal(scale=noise_px, size=(int(seen.sum()), 2))
    bad = rng.random(len(oc)) < outliers
    xy[bad] += rng.uniform(-40, 40, (int(bad.sum()), 2))
    # A start like the paper's estimator gives: off by about a degree and a few percent.
    T0 = T_true.copy()
    for i in range(k):
        if i != ref:
            T0[i] = sim3.make_sim3(sim3.so3_exp(rng.normal(scale=0.02, size=3)), rng.normal(scale=0.03, size=3),
                                   np.exp(rng.normal(scale=0.02))) @ T_true[i]  # fmt: skip
    P0 = points + rng.normal(scale=0.01, size=points.shape)
    return T_true, T0, cams, nerf, P0, oc, op, xy


def test_project_centre_and_scale_invariance():
    c2w = look_at(np.array([0.0, -2.0, 0.0]), np.zeros(3))
    M = sim3.invert_sim3(c2w)[None, :3]
    np.testing.assert_allclose(bundle.project(M, np.zeros((1, 3)), K), [[K[2], K[3]]], atol=1e-12)
    p = np.array([[0.1, 0.0, 0.2]])  # right of and above the axis: x > cx, y < cy (pixel rows go down)
    xy = bundle.project(M, p, K)
    assert xy[0, 0] > K[2] and xy[0, 1] < K[3]
    # A camera in a scaled frame sees the same pixel.
    np.testing.assert_allclose(bundle.project(M * 3.7, p, K), xy, atol=1e-9)


@pytest.mark.parametrize("seed,ref", [(0, 0), (1, 0), (2, 1)])
def test_exact_recovery_without_noise(seed, ref):
    T_true, T0, cams, nerf, P0, oc, op, xy = synthetic(seed, ref=ref)
    res = bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc, op, xy, ref=ref)
    e = sim3.sim3_errors(res.T_to_ref, T_true)
    assert res.success and res.rms_px_before > 1.0 and res.rms_px_after < 1e-6
    assert e.r_err_deg.max() < 1e-6 and e.t_err.max() < 1e-7 and e.s_err.max() < 1e-7
    np.testing.assert_array_equal(res.T_to_ref[ref], np.eye(4))  # the reference fixes the gauge


def test_noise_and_outliers_degrade_gracefully():
    T_true, T0, cams, nerf, P0, oc, op, xy = synthetic(3, noise_px=0.5, outliers=0.05)
    e0 = sim3.sim3_errors(T0, T_true)
    res = bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc, op, xy)
    e = sim3.sim3_errors(res.T_to_ref, T_true)
    # Bounds from the noise level: 0.5 px over ~150 px focal length and thousands of observations.
    assert e.r_err_deg.max() < 0.1 and e.t_err.max() < 2e-3 and e.s_err.max() < 2e-3
    assert (e.r_err_deg[1:] < e0.r_err_deg[1:] / 5).all()
    assert 0.9 < res.inlier_fraction < 0.99  # the 5% outliers are recognised as such
    assert res.median_px_after < 1.0


@pytest.mark.parametrize("ref", [0, 1])
@pytest.mark.parametrize("with_distance", [False, True])
@pytest.mark.parametrize("rot_scale", [0.3, 1e-5])  # the closed form and the Taylor branch of the left Jacobian
def test_analytic_jacobian_matches_finite_differences(ref, with_distance, rot_scale):
    T_true, T0, cams, nerf, P0, oc, op, xy = synthetic(5, ref=ref)
    sub = op < 40  # few points: the dense finite differences take one residual evaluation per column
    P0, oc, op, xy = P0[:40], oc[sub], op[sub], xy[sub]
    rng = np.random.default_rng(6)
    kw = {"obs_distance": rng.uniform(1.0, 3.0, len(oc)), "distance_sigma": 0.02} if with_distance else {}
    prob = bundle._bundle_problem(T0, cams, nerf, K, P0, oc, op, xy, ref=ref, loss_scale_px=1.5, **kw)
    n_t = 7 * 2  # two moving NeRFs; the reference has no columns
    assert len(prob.x0) == n_t + P0.size
    # Away from zero increments: rotations, translations and log scales all nonzero, points moved.
    x = prob.x0.copy()
    inc = rng.normal(scale=0.2, size=(2, 7))
    inc[:, :3] *= rot_scale / 0.2
    x[:n_t] = inc.ravel()
    x[n_t:] += rng.normal(scale=0.02, size=P0.size)
    J = prob.jacobian(x)
    Jn = approx_derivative(prob.residuals, x, method="3-point")
    n_obs = len(oc)
    assert J.shape == Jn.shape == ((3 if with_distance else 2) * n_obs, len(x))
    np.testing.assert_allclose(J.toarray(), Jn, rtol=1e-6, atol=1e-6 * np.abs(Jn).max())
    # Stored entries: 3 point columns per row, plus the NeRF's 7 for a camera of a moving NeRF.
    moving = nerf[oc] != ref
    per_obs = 3 + 7 * moving
    row_nnz = np.diff(J.indptr)
    np.testing.assert_array_equal(row_nnz[: 2 * n_obs], np.repeat(per_obs, 2))
    if with_distance:
        np.testing.assert_array_equal(row_nnz[2 * n_obs :], per_obs)


def test_bad_inputs():
    T_true, T0, cams, nerf, P0, oc, op, xy = synthetic(4, k=2)
    with pytest.raises(ValueError, match="differ in length"):
        bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc, op[:-1], xy)
    with pytest.raises(ValueError, match="no observations"):
        bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc[:0], op[:0], xy[:0])
    with pytest.raises(ValueError, match="must be the identity"):
        bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc, op, xy, ref=1)
    with pytest.raises(ValueError, match="out of range"):
        bundle.refine_sim3_bundle(T0, cams, nerf, K, P0, oc, op, xy, ref=2)
