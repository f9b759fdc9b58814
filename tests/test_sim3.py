"""Tests for nerfuser_ns.sim3: SIM(3) algebra, the paper's error metric and the registration estimators."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfuser_ns import sim3
from nerfuser_ns.sampling import sample_hemisphere_poses
from nerfuser_ns.sim3 import (
    Sim3Errors,
    compose,
    decompose_sim3,
    estimate_sim3_from_poses,
    estimate_sim3_umeyama,
    geometric_median,
    invert_sim3,
    is_failure,
    make_sim3,
    project_to_sim3,
    project_to_so3,
    random_rotation,
    random_sim3,
    relative_sim3,
    rotation_angle_deg,
    scale_matrix,
    sim3_errors,
    so3_exp,
    to_reference_frame,
    transform_points,
    transform_poses,
)

ROBUST_METHODS = ["weiszfeld", "median"]


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _assert_rotation(R: np.ndarray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=atol)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=atol)


def _simulate_sfm(T_nerf_to_C: np.ndarray, G_nerf: np.ndarray) -> np.ndarray:
    """What an exact SfM returns: the same cameras in frame C, as SE(3) poses (scale dropped)."""
    return transform_poses(T_nerf_to_C, G_nerf)


def _perturb_poses(G: np.ndarray, rot_noise: np.ndarray, centre_noise: np.ndarray) -> np.ndarray:
    """Left-perturb rotations by exp(rot_noise) and shift centres by centre_noise (both per camera)."""
    out = G.copy()
    out[:, :3, :3] = so3_exp(rot_noise) @ G[:, :3, :3]
    out[:, :3, 3] += centre_noise
    return out


def _inject_outliers(G_sfm: np.ndarray, frac: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Replace a fraction of SfM poses by random wrong ones (random rotation, centre anywhere near the scene)."""
    n = len(G_sfm)
    idx = rng.choice(n, size=round(frac * n), replace=False)
    out = G_sfm.copy()
    c = G_sfm[:, :3, 3]
    extent = np.linalg.norm(c - c.mean(0), axis=-1).max()
    out[idx, :3, :3] = random_rotation(rng, (len(idx),))
    out[idx, :3, 3] = c.mean(0) + rng.uniform(-2 * extent, 2 * extent, size=(len(idx), 3))
    return out, idx


def _errors_in_nerf_units(T_hat: np.ndarray, T: np.ndarray) -> Sim3Errors:
    """Errors of the C -> NeRF map, so that t_err is in the NeRF's units (radius-1 hemisphere) like the paper's."""
    return sim3_errors(invert_sim3(T_hat), invert_sim3(T))


# --------------------------------------------------------------------------------------------------------------------
# Algebra


def test_make_decompose_roundtrip_batched():
    rng = _rng(1)
    R = random_rotation(rng, (6,))
    t = rng.normal(size=(6, 3))
    s = np.array([0.05, 0.3, 1.0, 2.0, 20.0, 1e3])
    T = make_sim3(R, t, s)
    assert T.shape == (6, 4, 4)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0, 0, 0, 1.0], (6, 4)))
    R2, t2, s2 = decompose_sim3(T)
    np.testing.assert_allclose(R2, R, atol=1e-14)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_allclose(s2, s, rtol=1e-14)
    # 3x4 input decomposes the same way.
    R3, _t3, s3 = decompose_sim3(T[:, :3])
    np.testing.assert_allclose(R3, R2, atol=0)
    np.testing.assert_allclose(s3, s2, rtol=0)
    _assert_rotation(R2)


def test_invert_and_compose():
    rng = _rng(2)
    T = random_sim3(rng, (0.05, 20.0), size=(10,))
    Ti = invert_sim3(T)
    np.testing.assert_allclose(T @ Ti, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Ti @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Ti, np.linalg.inv(T), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(invert_sim3(Ti), T, rtol=1e-12, atol=1e-12)
    A, B, C = T[0], T[1], T[2]
    np.testing.assert_allclose(compose(A, B, C), A @ B @ C, atol=0)
    np.testing.assert_allclose(compose(A, B[:3]), A @ B, atol=0)  # 3x4 promoted
    _, _, s = decompose_sim3(compose(A, B))
    assert s == pytest.approx(decompose_sim3(A)[2] * decompose_sim3(B)[2], rel=1e-13)
    with pytest.raises(ValueError):
        compose()


def test_transform_points_matches_matrix_and_composes():
    rng = _rng(3)
    T1, T2 = random_sim3(rng, (0.05, 20.0), size=(2,))
    p = rng.normal(size=(50, 3))
    ph = np.concatenate([p, np.ones((50, 1))], -1)
    np.testing.assert_allclose(transform_points(T1, p), (ph @ T1.T)[:, :3], rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(
        transform_points(T1 @ T2, p), transform_points(T1, transform_points(T2, p)), rtol=1e-12, atol=1e-12
    )
    # Distances scale by s.
    s = decompose_sim3(T1)[2]
    q = transform_points(T1, p)
    assert np.linalg.norm(q[0] - q[1]) == pytest.approx(s * np.linalg.norm(p[0] - p[1]), rel=1e-12)


def test_transform_poses_rule():
    rng = _rng(4)
    T = random_sim3(rng, (0.05, 20.0))
    G = make_sim3(random_rotation(rng, (8,)), rng.normal(size=(8, 3)))
    R_T, _t_T, s = decompose_sim3(T)
    out = transform_poses(T, G)
    # Definition G_B = T G S^-1 ...
    np.testing.assert_allclose(out, T @ G @ np.linalg.inv(scale_matrix(s)), rtol=1e-12, atol=1e-12)
    # ... i.e. rotation R_T R_G, centre s R_T t_G + t_T = T applied to the centre; still SE(3).
    np.testing.assert_allclose(out[:, :3, :3], R_T @ G[:, :3, :3], atol=1e-13)
    np.testing.assert_allclose(out[:, :3, 3], transform_points(T, G[:, :3, 3]), rtol=1e-13, atol=1e-12)
    _assert_rotation(out[:, :3, :3])
    # 3x4 in, 3x4 out; composition of frames.
    np.testing.assert_allclose(transform_poses(T, G[:, :3]), out[:, :3], atol=0)
    T2 = random_sim3(rng, (0.05, 20.0))
    np.testing.assert_allclose(
        transform_poses(T2 @ T, G), transform_poses(T2, transform_poses(T, G)), rtol=1e-11, atol=1e-11
    )
    with pytest.raises(ValueError):
        transform_poses(T, np.zeros((8, 4, 3)))


def test_project_to_sim3_identity_on_valid():
    rng = _rng(5)
    T = random_sim3(rng, (0.05, 20.0), size=(5,))
    np.testing.assert_allclose(project_to_sim3(T), T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(project_to_sim3(T[:, :3]), T, rtol=1e-12, atol=1e-12)


def test_project_to_sim3_noisy_and_reflection():
    rng = _rng(6)
    T = random_sim3(rng, (0.05, 20.0), size=(20,))
    s = decompose_sim3(T)[2]
    noisy = T + rng.normal(scale=1e-3, size=T.shape) * s[:, None, None]
    P = project_to_sim3(noisy)
    R, t, s_p = decompose_sim3(P)
    _assert_rotation(R)
    np.testing.assert_array_equal(P[:, 3], np.broadcast_to([0, 0, 0, 1.0], (20, 4)))
    np.testing.assert_array_equal(t, noisy[:, :3, 3])  # translation kept
    np.testing.assert_allclose(s_p, s, rtol=1e-2)
    assert np.all(rotation_angle_deg(np.swapaxes(R, -1, -2) @ decompose_sim3(T)[0]) < 0.5)

    # A reflection (det < 0) still yields a proper rotation and the input's scale.
    M = np.eye(4)
    M[:3, :3] = 3.0 * np.diag([1.0, 1.0, -1.0]) @ random_rotation(rng)
    P = project_to_sim3(M)
    R, _, s_p = decompose_sim3(P)
    _assert_rotation(R)
    assert np.linalg.det(P[:3, :3]) > 0
    assert s_p == pytest.approx(3.0, rel=1e-12)


def test_project_to_so3_is_nearest():
    rng = _rng(7)
    M = rng.normal(size=(3, 3))
    R = project_to_so3(M)
    _assert_rotation(R)
    d = np.linalg.norm(M - R)
    # No random rotation, nor any small perturbation of R, is closer.
    others = random_rotation(rng, (2000,))
    assert np.all(np.linalg.norm(M - others, axis=(-2, -1)) >= d - 1e-12)
    near = so3_exp(rng.normal(scale=1e-3, size=(200, 3))) @ R
    assert np.all(np.linalg.norm(M - near, axis=(-2, -1)) >= d - 1e-12)


def test_rotation_angle_and_so3_exp():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    angles = np.array([0.0, 1e-9, 1e-5, 0.3, 2.0, math.pi - 1e-6, math.pi])
    R = so3_exp(angles[:, None] * axis)
    _assert_rotation(R)
    np.testing.assert_allclose(rotation_angle_deg(R), np.degrees(angles), rtol=1e-9, atol=1e-12)
    # Precision at tiny angles, where arccos((tr - 1) / 2) returns 0 or garbage.
    assert rotation_angle_deg(R[1]) == pytest.approx(np.degrees(1e-9), rel=1e-6)
    # Around the Taylor switch point the exponential is continuous.
    a, b = so3_exp(np.array([0, 0, 1e-4 - 1e-12])), so3_exp(np.array([0, 0, 1e-4 + 1e-12]))
    np.testing.assert_allclose(a, b, atol=1e-11)


def test_geometric_median_of_identical_or_nearly_identical_points_is_finite():
    """Exact data gives coinciding points (every camera's bridge the same): the median is that point, never NaN; a
    spread of 1e-300 must not overflow the weights either."""
    p = np.array([0.3, -1.2, 2.0])
    np.testing.assert_array_equal(geometric_median(np.tile(p, (7, 1))), p)
    tiny = np.tile(p, (5, 1)) + 1e-300 * np.arange(5)[:, None]
    assert np.all(np.isfinite(geometric_median(tiny)))
    np.testing.assert_allclose(geometric_median(tiny), p, atol=1e-290)


def test_geometric_median_robust():
    rng = _rng(8)
    inliers = np.tile([1.0, -2.0, 3.0], (14, 1))
    outliers = rng.normal(scale=100.0, size=(6, 3))
    gm = geometric_median(np.concatenate([inliers, outliers]))
    np.testing.assert_allclose(gm, [1.0, -2.0, 3.0], atol=1e-9)
    # Without ties it approximates the minimiser of the sum of distances.
    x = rng.normal(size=(30, 2))
    gm = geometric_median(x)

    def cost(y: np.ndarray) -> float:
        return float(np.linalg.norm(x - y, axis=-1).sum())

    for d in rng.normal(scale=1e-3, size=(50, 2)):
        assert cost(gm) <= cost(gm + d) + 1e-12


# --------------------------------------------------------------------------------------------------------------------
# Error metric


def test_errors_known_perturbation():
    rng = _rng(9)
    T = random_sim3(rng, (0.05, 20.0))
    dG = make_sim3(so3_exp(np.radians(3.0) * np.array([0.0, 0.6, 0.8])), np.array([0.1, -0.2, 0.05]))
    dS = scale_matrix(1.05)
    T_hat = dG @ dS @ T
    err = sim3_errors(T_hat, T)
    assert isinstance(err, Sim3Errors)
    assert err.r_err_deg == pytest.approx(3.0, rel=1e-9)
    assert err.t_err == pytest.approx(np.linalg.norm([0.1, -0.2, 0.05]), rel=1e-9)
    assert err.s_err == pytest.approx(abs(math.log(1.05)), rel=1e-9)
    # |t| = 0.229 > 0.2, so the paper's rule flags it; with a shorter t it passes.
    assert err.is_failure()
    ok = sim3_errors(make_sim3(dG[:3, :3], [0.1, 0.0, 0.0]) @ dS @ T, T)
    assert ok.t_err == pytest.approx(0.1, rel=1e-9) and not ok.is_failure()
    # Exact estimate: zero errors; scale below 1 gives the same |log|.
    zero = sim3_errors(T, T)
    assert zero.r_err_deg < 1e-9 and zero.t_err < 1e-12 and zero.s_err < 1e-12
    assert sim3_errors(scale_matrix(1 / 1.05) @ T, T).s_err == pytest.approx(abs(math.log(1.05)), rel=1e-9)


def test_errors_batched_and_nan():
    rng = _rng(10)
    T = random_sim3(rng, size=(4,))
    T_hat = T.copy()
    T_hat[2, 0, 0] = np.nan
    err = sim3_errors(T_hat, T)
    assert err.r_err_deg.shape == (4,)
    assert np.isnan(err.r_err_deg[2]) and np.isnan(err.t_err[2]) and np.isnan(err.s_err[2])
    np.testing.assert_array_equal(err.is_failure(), [False, False, True, False])


@pytest.mark.parametrize(
    "r, t, s, fail",
    [
        (0.0, 0.0, 0.0, False),
        (4.99, 0.199, 0.099, False),
        (5.0, 0.2, 0.1, False),  # thresholds are strict ">"
        (5.01, 0.0, 0.0, True),
        (0.0, 0.21, 0.0, True),
        (0.0, 0.0, 0.11, True),
        (float("nan"), 0.0, 0.0, True),
        (0.0, float("nan"), 0.0, True),
        (0.0, 0.0, float("nan"), True),
        (float("inf"), 0.0, 0.0, True),
    ],
)
def test_failure_rule(r, t, s, fail):
    assert is_failure(r, t, s) is fail
    assert Sim3Errors(r, t, s).is_failure() is fail


def test_failure_rule_custom_thresholds_and_arrays():
    assert is_failure(2.0, 0.0, 0.0, r_max_deg=1.0)
    assert not is_failure(0.0, 0.5, 0.0, t_max=1.0)
    np.testing.assert_array_equal(is_failure([1.0, 6.0, np.nan], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), [False, True, True])


# --------------------------------------------------------------------------------------------------------------------
# Registration: exact recovery


@pytest.mark.parametrize("method", ["weiszfeld", "median", "mean", "umeyama", "umeyama_ransac"])
def test_exact_recovery_three_nerfs(method):
    """3 NeRFs with very different scales, one SfM frame C: recover every T_i->C and the pairwise T_BA."""
    rng = _rng(11)
    T_to_C = np.stack(
        [
            make_sim3(random_rotation(rng), rng.normal(scale=5.0, size=3), s)
            for s in (0.05, 20.0, 1.3)  # scale far from 1 both ways
        ]
    )
    T_hat = []
    for i, T in enumerate(T_to_C):
        # Each NeRF is sampled in its own frame, with different layouts.
        G_nerf = sample_hemisphere_poses(32, radius=1.0 + 0.5 * i, elevation_range_deg=(0, 30 + 10 * i))
        G_sfm = _simulate_sfm(T, G_nerf)
        if method.startswith("umeyama"):
            est = estimate_sim3_umeyama(G_nerf, G_sfm, robust=method == "umeyama_ransac")
        else:
            est = estimate_sim3_from_poses(G_nerf, G_sfm, method=method)
        assert est.method == method
        assert est.num_cameras == 32 and est.used.all()
        assert est.scale == pytest.approx(decompose_sim3(T)[2], rel=1e-10)
        assert est.scale_spread < 1e-10
        assert np.nanmax(est.rot_residuals_deg) < 1e-6 and np.nanmax(est.centre_residuals) < 1e-9
        np.testing.assert_allclose(est.T, T, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(T).max()))
        err = _errors_in_nerf_units(est.T, T)
        assert err.r_err_deg < 1e-7 and err.t_err < 1e-9 and err.s_err < 1e-10
        T_hat.append(est.T)
    T_hat = np.stack(T_hat)

    # Pairwise T_BA = T_AC^-1 T_BC for every ordered pair, errors in A's units.
    for a in range(3):
        for b in range(3):
            T_ba_true = invert_sim3(T_to_C[a]) @ T_to_C[b]
            err = sim3_errors(relative_sim3(T_hat[a], T_hat[b]), T_ba_true)
            assert err.r_err_deg < 1e-7 and err.t_err < 1e-8 and err.s_err < 1e-10, (a, b, err)

    # All NeRFs in NeRF 1's frame.
    in_ref = to_reference_frame(T_hat, ref=1)
    np.testing.assert_array_equal(in_ref[1], np.eye(4))
    for i in range(3):
        err = sim3_errors(in_ref[i], invert_sim3(T_to_C[1]) @ T_to_C[i])
        assert err.r_err_deg < 1e-7 and err.t_err < 1e-8 and err.s_err < 1e-10


def test_estimator_is_frame_equivariant():
    """Changing SfM's gauge by W must change the estimate by exactly W (SfM's frame is arbitrary)."""
    rng = _rng(12)
    G_nerf = sample_hemisphere_poses(24, jitter_deg=3.0, seed=1)
    T = random_sim3(rng, (0.05, 20.0))
    noise = _perturb_poses(_simulate_sfm(T, G_nerf), rng.normal(scale=1e-3, size=(24, 3)), 0.0)
    W = random_sim3(rng, (0.05, 20.0))
    for method in ["weiszfeld", "median"]:
        e1 = estimate_sim3_from_poses(G_nerf, noise, method=method)
        e2 = estimate_sim3_from_poses(G_nerf, transform_poses(W, noise), method=method)
        err = sim3_errors(e2.T, W @ e1.T)
        # The chordal L1 average is exactly equivariant; the element-wise median is not (it works per matrix entry).
        r_tol, t_tol = (1e-7, 1e-8) if method == "weiszfeld" else (0.5, 0.05)
        assert err.r_err_deg < r_tol and err.t_err < t_tol * decompose_sim3(W @ e1.T)[2], (method, err)
        assert e2.scale == pytest.approx(decompose_sim3(W)[2] * e1.scale, rel=1e-9)


# --------------------------------------------------------------------------------------------------------------------
# Registration: noise and outliers


def test_noise_degrades_smoothly():
    rng = _rng(13)
    T = make_sim3(random_rotation(rng), rng.normal(size=3), 7.0)
    G_nerf = sample_hemisphere_poses(32)
    G_sfm = _simulate_sfm(T, G_nerf)
    s = decompose_sim3(T)[2]
    # Common random numbers: the same noise directions, scaled by sigma.
    rot_dir = rng.normal(size=(32, 3))
    cen_dir = rng.normal(size=(32, 3))
    sigmas = [0.0, 1e-4, 1e-3, 1e-2]
    for method in ROBUST_METHODS + ["umeyama_ransac"]:
        errs = []
        for sigma in sigmas:
            noisy = _perturb_poses(G_sfm, sigma * rot_dir, sigma * s * cen_dir)  # sigma in rad / NeRF units
            if method == "umeyama_ransac":
                est = estimate_sim3_umeyama(G_nerf, noisy, max_error=0.1)
            else:
                est = estimate_sim3_from_poses(G_nerf, noisy, method=method)
            errs.append(_errors_in_nerf_units(est.T, T))
        r = np.array([e.r_err_deg for e in errs])
        t = np.array([e.t_err for e in errs])
        sc = np.array([e.s_err for e in errs])
        assert r[0] < 1e-7 and t[0] < 1e-9 and sc[0] < 1e-10
        for k, sigma in enumerate(sigmas[1:], start=1):
            # Averaging over 32 cameras: errors below the per-camera noise (~sigma * sqrt(3)), far from failure.
            assert r[k] < math.degrees(sigma), (method, sigma, r[k])
            assert t[k] < sigma, (method, sigma, t[k])
            assert sc[k] < sigma, (method, sigma, sc[k])
        # ... and growing linearly with the noise: a 10x noise step gives ~10x the error.
        for arr in (r, t, sc):
            ratios = arr[2:] / arr[1:-1]
            assert np.all((ratios > 7) & (ratios < 13)), (method, arr)
        assert not any(e.is_failure() for e in errs)


@pytest.mark.parametrize("frac", [0.1, 0.2])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_outlier_cameras_robust_vs_mean(frac, seed):
    rng = _rng(100 + seed)
    T = make_sim3(random_rotation(rng), rng.normal(scale=3.0, size=3), float(np.exp(rng.uniform(-3, 3))))
    G_nerf = sample_hemisphere_poses(32, jitter_deg=2.0, seed=seed)
    s = decompose_sim3(T)[2]
    clean = _simulate_sfm(T, G_nerf)
    # Mild noise on every camera, gross errors on a few.
    noisy = _perturb_poses(clean, rng.normal(scale=1e-3, size=(32, 3)), rng.normal(scale=1e-3 * s, size=(32, 3)))
    G_sfm, bad = _inject_outliers(noisy, frac, rng)

    for method in ROBUST_METHODS:
        est = estimate_sim3_from_poses(G_nerf, G_sfm, method=method)
        err = _errors_in_nerf_units(est.T, T)
        # Per-camera noise is 1e-3 (rad / NeRF units): the estimate stays at that level.
        assert err.r_err_deg < 0.1 and err.t_err < 2e-3 and err.s_err < 2e-3, (method, err)
        # Diagnostics point at the bad cameras.
        good = np.setdiff1d(np.arange(32), bad)
        assert est.centre_residuals[bad].min() > 10 * est.centre_residuals[good].max()
        assert est.rot_residuals_deg[good].max() < 1.0

    est = estimate_sim3_umeyama(G_nerf, G_sfm, max_error=0.02)
    err = _errors_in_nerf_units(est.T, T)
    assert err.r_err_deg < 0.1 and err.t_err < 2e-3 and err.s_err < 2e-3, ("umeyama_ransac", err)
    assert not est.inliers[bad].any() and est.inliers.sum() >= 32 - len(bad) - 2

    # Non-robust estimators are dragged away by the same outliers: the plain mean of the bridges (its scale is still
    # the pairwise median, hence fine) and plain Umeyama on the centres, by far more than the robust ones.
    err = _errors_in_nerf_units(estimate_sim3_from_poses(G_nerf, G_sfm, method="mean").T, T)
    assert err.r_err_deg > 1.0 and err.t_err > 0.03, err
    err = _errors_in_nerf_units(estimate_sim3_umeyama(G_nerf, G_sfm, robust=False).T, T)
    assert err.t_err > 0.05, err


def test_outliers_scale_spread_diagnostic():
    rng = _rng(14)
    T = random_sim3(rng, (0.05, 20.0))
    G_nerf = sample_hemisphere_poses(32)
    clean = estimate_sim3_from_poses(G_nerf, _simulate_sfm(T, G_nerf))
    dirty = estimate_sim3_from_poses(G_nerf, _inject_outliers(_simulate_sfm(T, G_nerf), 0.2, rng)[0])
    assert clean.scale_spread < 1e-12 and clean.scale_outlier_fraction == 0.0
    # The MAD is robust (it describes the bulk of the pairs, here exact) ...
    assert dirty.scale_spread < 1e-12
    # ... the outlier fraction sees the 6 bad cameras out of 32: 1 - C(26, 2) / C(32, 2) of the pairs involve one
    # (a few random pairs may land within 5% by chance).
    assert dirty.scale_outlier_fraction == pytest.approx(1 - 325 / 496, abs=0.03)
    assert dirty.scale == pytest.approx(clean.scale, rel=1e-9)  # inliers exact: median unaffected


# --------------------------------------------------------------------------------------------------------------------
# Registration: input handling


def test_unregistered_cameras_are_skipped():
    rng = _rng(15)
    T = random_sim3(rng, (0.05, 20.0))
    G_nerf = sample_hemisphere_poses(16)
    G_sfm = _simulate_sfm(T, G_nerf)
    G_sfm[[3, 7]] = np.nan  # SfM did not register these images
    for est in (estimate_sim3_from_poses(G_nerf, G_sfm), estimate_sim3_umeyama(G_nerf, G_sfm)):
        assert est.num_cameras == 14
        np.testing.assert_array_equal(np.flatnonzero(~est.used), [3, 7])
        assert np.isnan(est.rot_residuals_deg[[3, 7]]).all() and np.isnan(est.centre_residuals[[3, 7]]).all()
        err = _errors_in_nerf_units(est.T, T)
        assert err.r_err_deg < 1e-7 and err.t_err < 1e-9 and err.s_err < 1e-10


def test_estimator_accepts_3x4_and_two_cameras():
    rng = _rng(16)
    T = random_sim3(rng, (0.05, 20.0))
    G_nerf = sample_hemisphere_poses(2)
    est = estimate_sim3_from_poses(G_nerf[:, :3], _simulate_sfm(T, G_nerf)[:, :3])
    err = _errors_in_nerf_units(est.T, T)
    assert est.num_cameras == 2 and err.r_err_deg < 1e-7 and err.t_err < 1e-9 and err.s_err < 1e-10


def test_estimator_degenerate_pairs_skipped():
    """Two cameras at the same centre (e.g. a duplicate view) give no usable pair but must not poison the scale."""
    rng = _rng(17)
    T = random_sim3(rng, (0.05, 20.0))
    G_nerf = sample_hemisphere_poses(8)
    G_nerf[1, :3, 3] = G_nerf[0, :3, 3]
    est = estimate_sim3_from_poses(G_nerf, _simulate_sfm(T, G_nerf))
    assert np.isfinite(est.T).all()
    assert est.scale == pytest.approx(decompose_sim3(T)[2], rel=1e-10)


def test_estimator_bad_inputs():
    G = sample_hemisphere_poses(8)
    with pytest.raises(ValueError, match="at least 2"):
        estimate_sim3_from_poses(G[:1], G[:1])
    with pytest.raises(ValueError, match="equal shape"):
        estimate_sim3_from_poses(G, G[:5])
    with pytest.raises(ValueError, match="unknown method"):
        estimate_sim3_from_poses(G, G, method="nope")  # type: ignore[arg-type]
    same_place = np.broadcast_to(G[0], (4, 4, 4)).copy()
    with pytest.raises(ValueError, match="distinct centres"):
        estimate_sim3_from_poses(same_place, same_place)
    with pytest.raises(ValueError, match="at least 3"):
        estimate_sim3_umeyama(G[:2], G[:2])
    with pytest.raises(ValueError, match="out of range"):
        to_reference_frame(np.stack([np.eye(4)] * 2), ref=2)


@pytest.mark.parametrize("log_scale", [0.1, -0.1, 0.02])
def test_rescaled_about_origin_is_off_by_that_log_scale_and_keeps_the_origin(log_scale):
    rng = np.random.default_rng(3)
    T = sim3.make_sim3(sim3.so3_exp(rng.normal(size=3)), rng.normal(size=3), 1.7)
    moved = sim3.rescaled_about_origin(T, log_scale)
    e = sim3.sim3_errors(moved, T)
    assert (float(e.r_err_deg), float(e.s_err)) == pytest.approx((0.0, abs(log_scale)), abs=1e-9)
    assert float(sim3.decompose_sim3(moved)[2]) == pytest.approx(1.7 * np.exp(log_scale))
    assert np.allclose(sim3.transform_points(moved, np.zeros((1, 3))), T[:3, 3])  # the origin stays
