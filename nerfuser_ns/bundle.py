"""Rigid-set bundle adjustment: refine each NeRF's SIM(3) directly on the SfM's image evidence.

The paper's estimator (:func:`nerfuser_ns.sim3.estimate_sim3_from_poses`) fits each NeRF's SIM(3) to the camera
poses the SfM estimated, one camera at a time. But the renders of one NeRF are not independent cameras: their poses
are known exactly in the NeRF's frame, so all of them move together under the NeRF's SIM(3). Bundle adjustment with
that constraint has 7 unknowns per NeRF (plus the 3D points) instead of 6 per camera, and fits them to every
feature observation at once, so noisy or slightly misplaced SfM cameras no longer pass their error into the
estimate.

Unknowns: ``T_i`` (NeRF i -> reference frame) for every NeRF but the reference (its cameras fix the gauge, scale
included) and the 3D points seen by at least two NeRFs (a point seen by one NeRF only moves with that NeRF and says
nothing about the transforms). Residuals: reprojection errors in pixels (and, where each observation's distance
from its camera was measured, e.g. as rendered depth, that distance's error relative to its noise) under a robust
loss, minimised by ``scipy.optimize.least_squares`` with a sparse Jacobian.

Pure numpy/scipy on float64 arrays; pycolmap only provides the observations (see ``nerfuser_ns.registration``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Int
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from nerfuser_ns import sim3


@dataclass
class BundleResult:
    """Outcome of :func:`refine_sim3_bundle`."""

    T_to_ref: Float[np.ndarray, "k 4 4"]
    """Refined NeRF -> reference transforms (the reference's is the identity)."""
    points: Float[np.ndarray, "p 3"]
    """Refined 3D points (reference frame)."""
    rms_px_before: float
    """Root-mean-square reprojection error of the initial transforms and points, pixels."""
    rms_px_after: float
    median_px_after: float
    inlier_fraction: float
    """Observations within ``3 * loss_scale_px`` after refinement."""
    num_observations: int
    num_points: int
    iterations: int
    """Function evaluations of the solver."""
    success: bool
    message: str


def _delta(x: Float[np.ndarray, "m 7"]) -> Float[np.ndarray, "m 4 4"]:
    """SIM(3) increments from (rotation vector, translation, log scale)."""
    return sim3.make_sim3(sim3.so3_exp(x[:, :3]), x[:, 3:6], np.exp(x[:, 6]))


def project(
    M: Float[np.ndarray, "o 3 4"], points: Float[np.ndarray, "o 3"], K: tuple[float, float, float, float]
) -> Float[np.ndarray, "o 2"]:
    """Pixel coordinates of ``points`` under the affine world -> OpenGL-camera maps ``M`` (pinhole ``K``).

    The maps may carry a scale (a camera in a scaled frame): the pixel does not depend on it.
    """
    fx, fy, cx, cy = K
    p = np.einsum("oij,oj->oi", M[:, :, :3], points) + M[:, :, 3]
    z = -p[:, 2]  # OpenGL cameras look down -z
    z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    return np.stack([fx * p[:, 0] / z + cx, fy * -p[:, 1] / z + cy], axis=-1)


def refine_sim3_bundle(
    T_to_ref: Float[np.ndarray, "k 4 4"],
    cam_c2w: Float[np.ndarray, "m 4 4"],
    cam_nerf: Int[np.ndarray, " m"],
    K: tuple[float, float, float, float],
    points: Float[np.ndarray, "p 3"],
    obs_cam: Int[np.ndarray, " o"],
    obs_point: Int[np.ndarray, " o"],
    obs_xy: Float[np.ndarray, "o 2"],
    ref: int = 0,
    loss_scale_px: float = 1.0,
    max_nfev: int = 100,
    obs_distance: Float[np.ndarray, " o"] | None = None,
    distance_sigma: float | None = None,
) -> BundleResult:
    """Refine the NeRF -> reference SIM(3)s by bundle adjustment over rigid camera sets.

    Args:
        T_to_ref: initial transforms, one per NeRF; ``T_to_ref[ref]`` must be the identity.
        cam_c2w: camera-to-world poses of the cameras, each in its own NeRF's frame (OpenGL axes, SE(3)).
        cam_nerf: the NeRF of each camera.
        K: shared pinhole intrinsics ``(fx, fy, cx, cy)``; pixel centres at half-integers as COLMAP.
        points: initial 3D points in the reference frame.
        obs_cam, obs_point, obs_xy: observations: camera index, point index, pixel.
        ref: the reference NeRF (held fixed).
        loss_scale_px: soft-L1 loss scale (pixels): residuals well above it count linearly, so outliers barely pull.
        max_nfev: solver iterations cap.
        obs_distance, distance_sigma: optional measured distance of each observation's point from its camera (in
            that camera's NeRF units, e.g. rendered depth) and its relative noise: each adds the residual
            ``(|p| - d) / (distance_sigma d)``, in units of ``loss_scale_px`` so that both kinds share the robust
            loss. Reported pixel errors count the reprojections only.
    """
    T_to_ref = sim3.to_homogeneous(T_to_ref)
    k = len(T_to_ref)
    cam_nerf = np.asarray(cam_nerf, dtype=int)
    obs_cam = np.asarray(obs_cam, dtype=int)
    obs_point = np.asarray(obs_point, dtype=int)
    obs_xy = np.asarray(obs_xy, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if not 0 <= ref < k:
        raise ValueError(f"reference index {ref} out of range for {k} NeRFs")
    if not np.allclose(T_to_ref[ref], np.eye(4), atol=1e-9):
        raise ValueError(f"T_to_ref[{ref}] (the reference) must be the identity")
    if len(obs_cam) != len(obs_point) or len(obs_cam) != len(obs_xy):
        raise ValueError("observation arrays differ in length")
    if len(obs_cam) == 0:
        raise ValueError("no observations to adjust")
    free = [i for i in range(k) if i != ref]
    slot = np.full(k, -1)
    slot[free] = np.arange(len(free))
    w2c = sim3.invert_sim3(sim3.to_homogeneous(cam_c2w))[:, :3, :]  # per camera, in its NeRF's frame
    n_t, n_p = 7 * len(free), 3 * len(points)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = T_to_ref.copy()
        if free:
            # Left increments, in the reference frame: the reference's gauge stays put.
            T[free] = _delta(x[:n_t].reshape(-1, 7)) @ T_to_ref[free]
        return T, x[n_t:].reshape(-1, 3)

    with_distance = obs_distance is not None and distance_sigma is not None
    if with_distance:
        obs_distance = np.asarray(obs_distance, dtype=np.float64)
        if len(obs_distance) != len(obs_cam) or not distance_sigma > 0:
            raise ValueError("obs_distance must match the observations and distance_sigma be > 0")
        distance_unit = distance_sigma * obs_distance / loss_scale_px

    def residuals(x: np.ndarray) -> np.ndarray:
        T, P = unpack(x)
        # world (reference) -> camera: w2c of the camera in its NeRF, after reference -> NeRF.
        M = w2c @ sim3.invert_sim3(T)[cam_nerf]
        r = (project(M[obs_cam], P[obs_point], K) - obs_xy).ravel()
        if not with_distance:
            return r
        p = np.einsum("oij,oj->oi", M[obs_cam][:, :, :3], P[obs_point]) + M[obs_cam][:, :, 3]
        return np.concatenate([r, (np.linalg.norm(p, axis=-1) - obs_distance) / distance_unit])

    # Sparsity: a residual depends on its NeRF's 7 increments and its point's 3 coordinates.
    rows = np.arange(len(obs_cam))
    obs_slot = slot[cam_nerf[obs_cam]]
    moving = rows[obs_slot >= 0]
    r_idx = [2 * rows + r for r in (0, 1) for _ in range(3)]
    c_idx = [n_t + 3 * obs_point + c for _ in (0, 1) for c in range(3)]
    r_idx += [2 * moving + r for r in (0, 1) for _ in range(7)]
    c_idx += [7 * obs_slot[moving] + c for _ in (0, 1) for c in range(7)]
    n_rows = 2 * len(obs_cam)
    if with_distance:  # one more row per observation, on the same unknowns
        r_idx += [n_rows + rows for _ in range(3)] + [n_rows + moving for _ in range(7)]
        c_idx += [n_t + 3 * obs_point + c for c in range(3)] + [7 * obs_slot[moving] + c for c in range(7)]
        n_rows += len(obs_cam)
    r_all, c_all = np.concatenate(r_idx), np.concatenate(c_idx)
    sparsity = coo_matrix((np.ones(len(r_all), np.int8), (r_all, c_all)), shape=(n_rows, n_t + n_p)).tocsr()

    x0 = np.concatenate([np.zeros(n_t), points.ravel()])
    r0 = residuals(x0)
    sol = least_squares(
        residuals, x0, jac_sparsity=sparsity, method="trf", loss="soft_l1", f_scale=loss_scale_px,
        x_scale="jac", max_nfev=max_nfev, tr_solver="lsmr", ftol=1e-10, xtol=1e-10,
    )
    T, P = unpack(sol.x)
    m = 2 * len(obs_cam)  # the reprojections (distance residuals follow them)
    err = np.linalg.norm(sol.fun[:m].reshape(-1, 2), axis=-1)
    return BundleResult(
        T_to_ref=T,
        points=P,
        rms_px_before=float(np.sqrt(np.mean(r0[:m] ** 2) * 2)),
        rms_px_after=float(np.sqrt(np.mean(err**2))),
        median_px_after=float(np.median(err)),
        inlier_fraction=float(np.mean(err <= 3 * loss_scale_px)),
        num_observations=len(obs_cam),
        num_points=len(points),
        iterations=int(sol.nfev),
        success=bool(sol.status > 0),
        message=str(sol.message),
    )
