"""SIM(3) math for registering NeRFs.

Conventions (project-wide):

* A similarity transform is a 4x4 matrix ``T = [[s*R, t], [0, 0, 0, 1]]`` with ``R`` in SO(3), ``s > 0``.
  ``T_AB`` maps points of frame A into frame B: ``p_B = T_AB @ p_A``.
* Camera poses are camera-to-world SE(3) matrices (4x4, or 3x4 without the last row) in nerfstudio's
  OpenGL camera convention. Only camera centres and orientations matter here, so the camera axis convention
  does not enter any formula below.
* A pose ``G_A`` expressed in frame A becomes ``G_B = T_AB @ G_A @ S^-1`` in frame B, ``S = diag(s, s, s, 1)``:
  the camera keeps unit scale (poses are SE(3)), its rotation becomes ``R_T R_G`` and its centre
  ``s R_T t_G + t_T``.

Everything is a pure function on float64 numpy arrays, vectorised over leading batch dimensions.

The registration estimator follows NeRFuser (ICCV 2023), Sec. 3.2 "registration from re-rendering": the same
cameras are known in a NeRF's own frame (the poses we sampled and rendered) and in the frame C of one SfM run
over the renders of all NeRFs. The scale is the median ratio of camera-centre distances, the transform the robust
average of the per-camera bridges ``G_i^C S (G_i^nerf)^-1``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import Bool, Float

ArrayLike = np.ndarray | Sequence[float] | float

# ---------------------------------------------------------------------------------------------------------------------
# Construction, decomposition, inversion


def make_sim3(
    R: Float[np.ndarray, "*bs 3 3"],
    t: Float[np.ndarray, "*bs 3"] | None = None,
    s: float | Float[np.ndarray, "*bs"] = 1.0,
) -> Float[np.ndarray, "*bs 4 4"]:
    """Build ``[[s*R, t], [0, 0, 0, 1]]`` from rotation(s), translation(s) and scale(s) (broadcast together)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.zeros(R.shape[:-2] + (3,)) if t is None else np.asarray(t, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    bs = np.broadcast_shapes(R.shape[:-2], t.shape[:-1], s.shape)
    T = np.zeros(bs + (4, 4))
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def to_homogeneous(M: Float[np.ndarray, "*bs r 4"]) -> Float[np.ndarray, "*bs 4 4"]:
    """Return a 4x4 copy of a 3x4 or 4x4 affine matrix (the last row of a 3x4 input becomes ``[0, 0, 0, 1]``)."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape[-2:] == (4, 4):
        return M.copy()
    if M.shape[-2:] != (3, 4):
        raise ValueError(f"expected [..., 3, 4] or [..., 4, 4] matrices, got shape {M.shape}")
    out = np.zeros(M.shape[:-2] + (4, 4))
    out[..., :3, :] = M
    out[..., 3, 3] = 1.0
    return out


def decompose_sim3(
    T: Float[np.ndarray, "*bs r 4"],
) -> tuple[Float[np.ndarray, "*bs 3 3"], Float[np.ndarray, "*bs 3"], Float[np.ndarray, "*bs"]]:
    """Split a valid SIM(3) (3x4 or 4x4) into ``(R, t, s)`` with ``T = [[s*R, t], [0, 1]]``.

    The scale is ``det(sR)^(1/3)`` (as in the paper's error definition), so ``T`` must be a proper similarity;
    use :func:`project_to_sim3` first for arbitrary matrices.
    """
    T = np.asarray(T, dtype=np.float64)
    A = T[..., :3, :3]
    s = np.cbrt(np.linalg.det(A))
    R = A / s[..., None, None]
    return R, T[..., :3, 3].copy(), s


def invert_sim3(T: Float[np.ndarray, "*bs r 4"]) -> Float[np.ndarray, "*bs 4 4"]:
    """Closed-form inverse ``[[R^T / s, -R^T t / s], [0, 1]]`` of a SIM(3) (also inverts SE(3) poses)."""
    R, t, s = decompose_sim3(T)
    Rt = np.swapaxes(R, -1, -2) / s[..., None, None]
    return make_sim3(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def compose(*Ts: Float[np.ndarray, "*bs 4 4"]) -> Float[np.ndarray, "*bs 4 4"]:
    """Matrix product ``Ts[0] @ Ts[1] @ ...`` (rightmost applied first), broadcasting batch dimensions."""
    if not Ts:
        raise ValueError("compose needs at least one transform")
    out = to_homogeneous(Ts[0])
    for T in Ts[1:]:
        out = out @ to_homogeneous(T)
    return out


def scale_matrix(s: float | Float[np.ndarray, "*bs"]) -> Float[np.ndarray, "*bs 4 4"]:
    """``S = diag(s, s, s, 1)``."""
    s = np.asarray(s, dtype=np.float64)
    return make_sim3(np.broadcast_to(np.eye(3), s.shape + (3, 3)), None, s)


# ---------------------------------------------------------------------------------------------------------------------
# Applying transforms


def transform_points(T: Float[np.ndarray, "*bs r 4"], p: Float[np.ndarray, "*bs 3"]) -> Float[np.ndarray, "*bs 3"]:
    """``T @ [p, 1]`` for points ``p``; batch dimensions of ``T`` and ``p`` broadcast (e.g. ``[4,4]`` and ``[N,3]``)."""
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def transform_poses(T: Float[np.ndarray, "*bs r 4"], c2w: Float[np.ndarray, "*bs c 4"]) -> Float[np.ndarray, "*bs c 4"]:
    """Express camera-to-world poses of frame A in frame B: ``G_B = T_AB @ G_A @ S^-1``.

    The result stays SE(3) (a camera has no scale): rotation ``R_T R_G``, centre ``s R_T t_G + t_T``.
    ``c2w`` may be 3x4 or 4x4; the output has the same number of rows.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-1] != 4 or c2w.shape[-2] not in (3, 4):
        raise ValueError(f"expected poses of shape [..., 3|4, 4], got {c2w.shape}")
    R_T, t_T, s = decompose_sim3(T)
    R = R_T @ c2w[..., :3, :3]
    t = s[..., None] * np.einsum("...ij,...j->...i", R_T, c2w[..., :3, 3]) + t_T
    out = make_sim3(R, t)
    return out if c2w.shape[-2] == 4 else out[..., :3, :]


# ---------------------------------------------------------------------------------------------------------------------
# Projection onto SO(3) / SIM(3)


def project_to_so3(M: Float[np.ndarray, "*bs 3 3"]) -> Float[np.ndarray, "*bs 3 3"]:
    """Nearest rotation (Frobenius norm) to each 3x3 matrix: ``U diag(1, 1, det(U V^T)) V^T`` from its SVD.

    The sign correction makes reflections come out as proper rotations (det = +1).
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def project_to_sim3(M: Float[np.ndarray, "*bs r 4"]) -> Float[np.ndarray, "*bs 4 4"]:
    """Nearest valid SIM(3) to an arbitrary 3x4 / 4x4 matrix.

    The 3x3 block is split by SVD (polar decomposition) into the nearest proper rotation (det +1) and a scale equal to
    the mean singular value; the translation column is kept and the last row reset to ``[0, 0, 0, 1]``.
    """
    M = np.asarray(M, dtype=np.float64)
    A = M[..., :3, :3]
    sv = np.linalg.svd(A, compute_uv=False)
    return make_sim3(project_to_so3(A), M[..., :3, 3], sv.mean(axis=-1))


def so3_hat(v: Float[np.ndarray, "*bs 3"]) -> Float[np.ndarray, "*bs 3 3"]:
    """Cross-product matrices: ``so3_hat(v) @ w == np.cross(v, w)``."""
    v = np.asarray(v, dtype=np.float64)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return K - np.swapaxes(K, -1, -2)


def so3_exp(omega: Float[np.ndarray, "*bs 3"]) -> Float[np.ndarray, "*bs 3 3"]:
    """Rotation matrices from rotation vectors (axis * angle in radians), Rodrigues' formula."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = so3_hat(omega)
    # Taylor expansions near 0 avoid 0/0; the switch point keeps both branches at full double precision.
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_left_jacobian(omega: Float[np.ndarray, "*bs 3"]) -> Float[np.ndarray, "*bs 3 3"]:
    """Left Jacobian ``J`` of :func:`so3_exp`: ``so3_exp(omega + d) = so3_exp(J d) so3_exp(omega) + O(|d|^2)``.

    ``J = I + (1 - cos t) / t^2 [omega]_x + (t - sin t) / t^3 [omega]_x^2`` with ``t = |omega|``.
    """
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    W = so3_hat(omega)
    # Taylor expansions near 0 avoid 0/0 and the cancellation in t - sin t.
    small = theta < 1e-3
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    b = np.where(small, 1 / 6 - theta**2 / 120, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) + a * W + b * (W @ W)


def random_rotation(rng: np.random.Generator, size: tuple[int, ...] = ()) -> Float[np.ndarray, "*size 3 3"]:
    """Uniformly distributed rotations (normalised Gaussian quaternions)."""
    q = rng.normal(size=tuple(size) + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return R.reshape(tuple(size) + (3, 3))


def random_sim3(
    rng: np.random.Generator,
    scale_range: tuple[float, float] = (0.1, 10.0),
    translation_std: float = 1.0,
    size: tuple[int, ...] = (),
) -> Float[np.ndarray, "*size 4 4"]:
    """Random SIM(3) for tests: uniform rotation, Gaussian translation, log-uniform scale in ``scale_range``."""
    lo, hi = scale_range
    if not 0 < lo <= hi:
        raise ValueError(f"scale_range must satisfy 0 < lo <= hi, got {scale_range}")
    size = tuple(size)
    s = np.exp(rng.uniform(np.log(lo), np.log(hi), size=size))
    return make_sim3(random_rotation(rng, size), rng.normal(scale=translation_std, size=size + (3,)), s)


# ---------------------------------------------------------------------------------------------------------------------
# Errors (paper, Sec. 4.2)


def rotation_angle_deg(R: Float[np.ndarray, "*bs 3 3"]) -> Float[np.ndarray, "*bs"]:
    """Rotation angle of (near-)orthonormal matrices in degrees, in [0, 180].

    Uses ``atan2(sin, cos)`` rather than ``arccos((tr - 1) / 2)``, which loses all precision below ~1e-7 rad.
    """
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


@dataclass(frozen=True)
class Sim3Errors:
    """Errors of an estimated SIM(3) against ground truth (NeRFuser, Sec. 4.2). Floats, or arrays for batches."""

    r_err_deg: float | np.ndarray
    """Rotation angle of ``dG`` in degrees."""
    t_err: float | np.ndarray
    """Norm of ``dG``'s translation, in the units of the target (reference) frame."""
    s_err: float | np.ndarray
    """``|log ds|`` with ``ds = det(dS)^(1/3)``."""

    def is_failure(self, r_max_deg: float = 5.0, t_max: float = 0.2, s_max: float = 0.1) -> bool | np.ndarray:
        """The paper's failure rule, see :func:`is_failure`."""
        return is_failure(self.r_err_deg, self.t_err, self.s_err, r_max_deg, t_max, s_max)


def _as_scalar_if_0d(x: np.ndarray) -> float | np.ndarray:
    return float(x) if np.ndim(x) == 0 else x


def sim3_errors(T_hat: Float[np.ndarray, "*bs r 4"], T: Float[np.ndarray, "*bs r 4"]) -> Sim3Errors:
    """Errors of ``T_hat`` against ground truth ``T`` (both mapping B -> A): ``dT = T_hat @ T^-1 = dG dS``.

    ``dT`` maps A to A; its rotation angle, translation norm (in A's units) and ``|log s|`` are the errors.
    Non-finite inputs give NaN errors (counted as failures) rather than raising.
    """
    T_hat = to_homogeneous(T_hat)
    T = to_homogeneous(T)
    with np.errstate(invalid="ignore", divide="ignore"):
        dT = T_hat @ invert_sim3(T)
        R, t, s = decompose_sim3(dT)
        r = rotation_angle_deg(R)
        s_err = np.abs(np.log(s))
    # dT's translation equals dG's translation because dS = diag(s, s, s, 1) leaves the last column alone.
    t_err = np.linalg.norm(t, axis=-1)
    bad = ~(np.isfinite(dT).all(axis=(-2, -1)) & (s > 0))
    r, t_err, s_err = (np.where(bad, np.nan, x) for x in (r, t_err, s_err))
    return Sim3Errors(_as_scalar_if_0d(r), _as_scalar_if_0d(t_err), _as_scalar_if_0d(s_err))


def is_failure(
    r_err_deg: ArrayLike,
    t_err: ArrayLike,
    s_err: ArrayLike,
    r_max_deg: float = 5.0,
    t_max: float = 0.2,
    s_max: float = 0.1,
) -> bool | np.ndarray:
    """Paper's failure rule (Sec. 4.2): any error NaN, ``r > 5 deg``, ``t > 0.2`` or ``s > 0.1``."""
    r, t, s = (np.asarray(x, dtype=np.float64) for x in (r_err_deg, t_err, s_err))
    # NaN compares False with everything, hence the explicit check (inf is caught by the thresholds).
    fail = np.isnan(r) | np.isnan(t) | np.isnan(s) | (r > r_max_deg) | (t > t_max) | (s > s_max)
    return bool(fail) if fail.ndim == 0 else fail


# ---------------------------------------------------------------------------------------------------------------------
# Robust statistics


def geometric_median(
    x: Float[np.ndarray, "n d"], max_iters: int = 200, tol: float = 1e-12, init: np.ndarray | None = None
) -> Float[np.ndarray, " d"]:
    """Geometric median (L1 centre) of points by Weiszfeld iterations; breakdown point 50%.

    Starts from the coordinate-wise median. A point that coincides with the iterate gets a large but finite weight
    (distance clamped), which keeps the iteration well defined and pins it to clusters of identical points.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.median(x, axis=0) if init is None else np.asarray(init, dtype=np.float64)
    spread = float(np.max(np.abs(x - y))) if x.size else 0.0
    if spread == 0.0:  # every point at the start (exact data): that is the median, and 1 / 0 must not be formed
        return y
    eps = 1e-15 * spread
    for _ in range(max_iters):
        d = np.maximum(np.linalg.norm(x - y, axis=-1), eps)
        w = d.min() / d  # 1 / d scaled into (0, 1]: the same iterate, and no overflow for tiny distances
        y_new = (w[:, None] * x).sum(axis=0) / w.sum()
        step = np.linalg.norm(y_new - y)
        y = y_new
        if step <= tol * max(spread, 1e-300):
            break
    return y


def average_rotations_l1(R: Float[np.ndarray, "n 3 3"], max_iters: int = 200) -> Float[np.ndarray, "3 3"]:
    """Robust rotation average: geometric median of the rotation matrices in R^9 (chordal L1), projected to SO(3)."""
    R = np.asarray(R, dtype=np.float64)
    return project_to_so3(geometric_median(R.reshape(-1, 9), max_iters=max_iters).reshape(3, 3))


# ---------------------------------------------------------------------------------------------------------------------
# Registration: NeRF frame -> SfM frame from the same cameras known in both

EstimatorMethod = Literal["weiszfeld", "median", "mean"]


@dataclass(frozen=True)
class Sim3Estimate:
    """A NeRF -> SfM-frame similarity estimated from cameras known in both frames, with diagnostics."""

    T: Float[np.ndarray, "4 4"]
    """``T_nerf->C``: maps points of the NeRF's frame into the SfM frame C."""
    scale: float
    """Scale of ``T`` (one NeRF unit is ``scale`` units of C)."""
    num_cameras: int
    """Cameras used (finite poses in both frames)."""
    scale_spread: float
    """Relative spread of the pairwise distance ratios: median absolute deviation / median (0 for exact data).
    Robust, so it measures the consistency of the bulk of the pairs; see ``scale_outlier_fraction`` for the rest."""
    scale_outlier_fraction: float
    """Fraction of camera pairs whose distance ratio is off the median by more than ``scale_outlier_tol``
    (relative). About ``1 - (1 - f)^2`` when a fraction ``f`` of the cameras is wrong."""
    rot_residuals_deg: Float[np.ndarray, " n"]
    """Per camera: angle between the SfM rotation and the NeRF rotation mapped through ``T`` (NaN if unused)."""
    centre_residuals: Float[np.ndarray, " n"]
    """Per camera: distance between the SfM centre and the mapped NeRF centre, in the NeRF's units (NaN if unused)."""
    method: str
    """Which estimator produced ``T``."""
    used: Bool[np.ndarray, " n"]
    """Cameras that entered the estimate."""
    inliers: Bool[np.ndarray, " n"] | None = None
    """RANSAC inliers, for the RANSAC estimator only."""


def _validate_pose_pairs(G_nerf: np.ndarray, G_sfm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    G_nerf = to_homogeneous(G_nerf)
    G_sfm = to_homogeneous(G_sfm)
    if G_nerf.ndim != 3 or G_nerf.shape != G_sfm.shape:
        raise ValueError(f"expected two pose stacks of equal shape [N, 3|4, 4], got {G_nerf.shape} and {G_sfm.shape}")
    used = np.isfinite(G_nerf).all(axis=(-2, -1)) & np.isfinite(G_sfm).all(axis=(-2, -1))
    if used.sum() < 2:
        raise ValueError(f"need at least 2 cameras with finite poses in both frames, got {int(used.sum())}")
    return G_nerf, G_sfm, used


def pairwise_scale_ratios(
    c_nerf: Float[np.ndarray, "n 3"], c_sfm: Float[np.ndarray, "n 3"], rel_eps: float = 1e-6
) -> Float[np.ndarray, " m"]:
    """Ratios ``|c_i^C - c_j^C| / |c_i^nerf - c_j^nerf|`` over all pairs ``i < j`` (paper, Eq. 3).

    Pairs whose NeRF-frame distance is below ``rel_eps`` times the largest one are skipped (the ratio is undefined).
    """
    iu, ju = np.triu_indices(len(c_nerf), k=1)
    d_nerf = np.linalg.norm(c_nerf[iu] - c_nerf[ju], axis=-1)
    d_sfm = np.linalg.norm(c_sfm[iu] - c_sfm[ju], axis=-1)
    ok = d_nerf > rel_eps * (d_nerf.max() if d_nerf.size else 0.0)
    ratios = d_sfm[ok] / d_nerf[ok]
    if ratios.size == 0 or not np.any(ratios > 0):
        raise ValueError("no camera pair with distinct centres: the scale is undefined")
    return ratios


def _scale_stats(r: np.ndarray, med: float, tol: float) -> tuple[float, float]:
    """Relative MAD of the ratios and the fraction of them off by more than ``tol`` (relative) from the median."""
    dev = np.abs(r / med - 1.0)
    return float(np.median(dev)), float(np.mean(dev > tol))


def pose_residuals(
    T: Float[np.ndarray, "4 4"], G_nerf: Float[np.ndarray, "n r 4"], G_sfm: Float[np.ndarray, "n r 4"]
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, " n"]]:
    """Per-camera disagreement of ``T`` with the camera pairs: rotation (deg) and centre distance in NeRF units."""
    pred = transform_poses(T, to_homogeneous(G_nerf))
    G_sfm = to_homogeneous(G_sfm)
    rot = rotation_angle_deg(np.swapaxes(pred[:, :3, :3], -1, -2) @ G_sfm[:, :3, :3])
    _, _, s = decompose_sim3(T)
    centre = np.linalg.norm(pred[:, :3, 3] - G_sfm[:, :3, 3], axis=-1) / s
    return rot, centre


def estimate_sim3_from_poses(
    G_nerf: Float[np.ndarray, "n r 4"],
    G_sfm: Float[np.ndarray, "n r 4"],
    method: EstimatorMethod = "weiszfeld",
    rel_eps: float = 1e-6,
    scale_outlier_tol: float = 0.05,
) -> Sim3Estimate:
    """Recover ``T_nerf->C`` from one NeRF's sampled poses and their SfM-recovered poses (NeRFuser, Sec. 3.2).

    Scale: median over camera pairs of the centre-distance ratio C / NeRF (robust to < 50% bad pairs).
    Transform: from the per-camera bridges ``T_i = G_i^C S (G_i^nerf)^-1``, averaged by ``method``:

    * ``"weiszfeld"`` (default): rotation = chordal L1 average of the bridge rotations (Weiszfeld, then SVD
      projection); translation = geometric median of ``c_i^C - s R c_i^nerf`` using that rotation, so a camera's
      rotation error does not leak into the translation through the lever arm ``|c_i^nerf|``.
    * ``"median"``: the paper's choice, the element-wise median of the bridges' 3x4 blocks, projected to SIM(3).
    * ``"mean"``: element-wise mean, projected. Not robust; kept as a baseline.

    In all cases the scale of the result is the pairwise median (projection of an averaged block would shrink it).
    Cameras with non-finite poses (e.g. not registered by SfM, filled with NaN) are ignored. ``rel_eps`` and
    ``scale_outlier_tol`` are as in :func:`pairwise_scale_ratios` and :attr:`Sim3Estimate.scale_outlier_fraction`.
    """
    G_nerf, G_sfm, used = _validate_pose_pairs(G_nerf, G_sfm)
    Gn, Gc = G_nerf[used], G_sfm[used]

    ratios = pairwise_scale_ratios(Gn[:, :3, 3], Gc[:, :3, 3], rel_eps)
    s = float(np.median(ratios))
    spread, outlier_frac = _scale_stats(ratios, s, scale_outlier_tol)

    bridges = Gc @ scale_matrix(s) @ invert_sim3(Gn)  # [n, 4, 4], each = T_nerf->C if the camera were perfect
    if method == "weiszfeld":
        R = average_rotations_l1(bridges[:, :3, :3] / s)
        t = geometric_median(Gc[:, :3, 3] - s * Gn[:, :3, 3] @ R.T)
    elif method in ("median", "mean"):
        block = np.median(bridges[:, :3, :], axis=0) if method == "median" else bridges[:, :3, :].mean(axis=0)
        R, t = project_to_so3(block[:, :3]), block[:, 3]
    else:
        raise ValueError(f"unknown method {method!r}; expected 'weiszfeld', 'median' or 'mean'")
    T = make_sim3(R, t, s)

    rot_res = np.full(len(used), np.nan)
    cen_res = np.full(len(used), np.nan)
    rot_res[used], cen_res[used] = pose_residuals(T, Gn, Gc)
    return Sim3Estimate(T, s, int(used.sum()), spread, outlier_frac, rot_res, cen_res, method, used)


def estimate_sim3_umeyama(
    G_nerf: Float[np.ndarray, "n r 4"],
    G_sfm: Float[np.ndarray, "n r 4"],
    robust: bool = True,
    max_error: float = 0.05,
    min_inlier_ratio: float = 0.1,
    seed: int = 0,
    rel_eps: float = 1e-6,
    scale_outlier_tol: float = 0.05,
) -> Sim3Estimate:
    """Umeyama alignment of camera centres NeRF -> C via pycolmap, with LO-RANSAC if ``robust``.

    Uses only camera centres (at least 3, not collinear); orientations serve only for the residual diagnostics.
    ``max_error`` is the RANSAC inlier threshold in the NeRF's units (it is converted to C's units with the
    pairwise median scale, since C's scale is arbitrary); ``seed`` makes RANSAC deterministic (-1: random).
    Raises ``RuntimeError`` if pycolmap finds no solution.
    """
    import pycolmap  # lazy: heavy import, and only this estimator needs it

    G_nerf, G_sfm, used = _validate_pose_pairs(G_nerf, G_sfm)
    Gn, Gc = G_nerf[used], G_sfm[used]
    if len(Gn) < 3:
        raise ValueError(f"Umeyama needs at least 3 cameras, got {len(Gn)}")
    ratios = pairwise_scale_ratios(Gn[:, :3, 3], Gc[:, :3, 3], rel_eps)
    s_med = float(np.median(ratios))
    src = np.ascontiguousarray(Gn[:, :3, 3])
    tgt = np.ascontiguousarray(Gc[:, :3, 3])

    inliers = None
    if robust:
        options = pycolmap.RANSACOptions()
        options.max_error = max_error * s_med  # residuals are measured in the target frame C
        options.min_inlier_ratio = min_inlier_ratio
        options.random_seed = seed
        result = pycolmap.estimate_sim3d_robust(src, tgt, options)  # pycolmap 4.x: dict, or None on failure
        if result is None:
            raise RuntimeError("pycolmap.estimate_sim3d_robust found no similarity")
        sim = result["tgt_from_src"]
        inliers = np.zeros(len(used), dtype=bool)
        inliers[np.flatnonzero(used)] = np.asarray(result["inlier_mask"], dtype=bool)
    else:
        sim = pycolmap.estimate_sim3d(src, tgt)
        if sim is None:
            raise RuntimeError("pycolmap.estimate_sim3d found no similarity")
    T = to_homogeneous(np.asarray(sim.matrix(), dtype=np.float64))
    s = float(decompose_sim3(T)[2])

    rot_res = np.full(len(used), np.nan)
    cen_res = np.full(len(used), np.nan)
    rot_res[used], cen_res[used] = pose_residuals(T, Gn, Gc)
    method = "umeyama_ransac" if robust else "umeyama"
    spread, outlier_frac = _scale_stats(ratios, s_med, scale_outlier_tol)
    return Sim3Estimate(T, s, int(used.sum()), spread, outlier_frac, rot_res, cen_res, method, used, inliers)


# ---------------------------------------------------------------------------------------------------------------------
# Combining several NeRFs


def relative_sim3(
    T_AC: Float[np.ndarray, "*bs 4 4"], T_BC: Float[np.ndarray, "*bs 4 4"]
) -> Float[np.ndarray, "*bs 4 4"]:
    """``T_BA = T_AC^-1 @ T_BC``: maps B's points into A, given both NeRFs' transforms into a common frame C."""
    return invert_sim3(T_AC) @ to_homogeneous(T_BC)


def rescaled_about_origin(T: Float[np.ndarray, "4 4"], log_scale: float) -> Float[np.ndarray, "4 4"]:
    """``T`` (a NeRF -> common frame SIM(3)) with its scale off by ``log_scale``, about the NeRF's origin (which stays
    where ``T`` puts it): a link wrong in scale alone, as the registration's checks must see it."""
    c, s = T[:3, 3], float(np.exp(log_scale))
    return make_sim3(np.eye(3), c - s * c, s) @ to_homogeneous(T)


def to_reference_frame(T_to_C: Float[np.ndarray, "k 4 4"], ref: int = 0) -> Float[np.ndarray, "k 4 4"]:
    """Re-express every NeRF's ``T_i->C`` as ``T_i->ref = T_ref->C^-1 @ T_i->C`` (entry ``ref`` becomes identity)."""
    T_to_C = to_homogeneous(T_to_C)
    if T_to_C.ndim != 3:
        raise ValueError(f"expected [K, 4, 4] transforms, got {T_to_C.shape}")
    if not -len(T_to_C) <= ref < len(T_to_C):
        raise ValueError(f"reference index {ref} out of range for {len(T_to_C)} NeRFs")
    out = relative_sim3(T_to_C[ref], T_to_C)
    out[ref] = np.eye(4)  # exact, not merely ~1e-16 off
    return out
