"""Registration on known geometry (ours, beside the paper's SfM): every render's pose is known in its NeRF's frame and
every NeRF renders depth, so keypoints lift to 3D without an SfM.

Per NeRF (:func:`lift_keypoints`): SIFT keypoints of its renders (COLMAP's extraction, as in the SfM mode), lifted
to 3D in the NeRF's frame, ``X = c + d * r(x)`` with the camera centre ``c``, the unit ray ``r`` through keypoint
``x`` and the rendered ray distance ``d``; kept only where that depth is reliable: the render is opaque and has no
depth edge around the keypoint (:func:`reliable_depth`), and other views of the same NeRF render the same surface
there (:func:`multiview_agreement`: the point's projection into view ``j`` has rendered depth within
``tol * |X - c_j|`` of ``|X - c_j|``). The NeRF's own geometry is fixed by construction: repeated structure inside
one NeRF cannot fold it.

Across NeRFs: candidate view pairs (:mod:`.retrieval`), mutual nearest neighbours with Lowe's ratio test
(:func:`match_descriptors`), giving 3D-3D matches; SIM(3) hypotheses by LO-RANSAC (pycolmap's
``estimate_sim3d_robust``), each next one from the matches the previous ones left over (:func:`sim3_hypotheses`).
The pipeline scores competing hypotheses with the cross-render self-check, then :func:`joint_solve` fits every NeRF's
SIM(3) to all chosen pairs' inlier matches at once (robust least squares, residuals relative to the points' camera
distances, so near and far points weigh alike).
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
import torch
from jaxtyping import Bool, Float, Int
from scipy.ndimage import maximum_filter, minimum_filter
from scipy.optimize import least_squares

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import KnownGeometryConfig
from nerfuser_ns.registration.render_cache import ViewSet

# ---------------------------------------------------------------------------------------------------------------------
# Pure geometry (the tests check these directly)


def pixel_rays(
    c2w: Float[np.ndarray, "4 4"], xy: Float[np.ndarray, "m 2"], intrinsics: Intrinsics
) -> Float[np.ndarray, "m 3"]:
    """Unit rays through image points ``xy`` (pixel corner at 0, pixel centres at +0.5, as COLMAP's keypoints and
    nerfstudio's rays), in the frame of ``c2w`` (OpenGL camera axes)."""
    k = intrinsics
    d = np.stack([(xy[:, 0] - k.cx) / k.fx, -(xy[:, 1] - k.cy) / k.fy, -np.ones(len(xy))], axis=-1)
    d = d @ np.asarray(c2w, dtype=np.float64)[:3, :3].T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def project(
    c2w: Float[np.ndarray, "4 4"], points: Float[np.ndarray, "m 3"], intrinsics: Intrinsics
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, " m"], Bool[np.ndarray, " m"]]:
    """Image points of ``points`` in the camera ``c2w``, their distance from its centre, and whether they lie in
    front of it and inside the image."""
    k = intrinsics
    c2w = np.asarray(c2w, dtype=np.float64)
    p = (points - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame (c2w's rotation is orthonormal)
    z = -p[:, 2]
    safe = np.where(z > 1e-9, z, 1.0)
    xy = np.stack([k.fx * p[:, 0] / safe + k.cx, -k.fy * p[:, 1] / safe + k.cy], axis=-1)
    inside = (z > 1e-9) & (xy[:, 0] >= 0) & (xy[:, 0] < k.width) & (xy[:, 1] >= 0) & (xy[:, 1] < k.height)
    return xy, np.linalg.norm(p, axis=-1), inside


def reliable_depth(
    depth: Float[np.ndarray, "h w"], accumulation: Float[np.ndarray, "h w"], min_accumulation: float,
    max_depth_step: float,
) -> Bool[np.ndarray, "h w"]:
    """Pixels whose 3x3 neighbourhood is opaque (accumulation >= ``min_accumulation``), hit something (depth > 0) and
    has no depth edge (max - min <= ``max_depth_step`` * depth)."""
    opaque = minimum_filter((accumulation >= min_accumulation) & (depth > 0), size=3, mode="nearest")
    spread = maximum_filter(depth, size=3, mode="nearest") - minimum_filter(depth, size=3, mode="nearest")
    return opaque & (spread <= max_depth_step * np.maximum(depth, 1e-12))


def pixel_index(xy: Float[np.ndarray, "m 2"], shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the pixel that contains each image point."""
    rows = np.clip(np.floor(xy[:, 1]).astype(int), 0, shape[0] - 1)
    cols = np.clip(np.floor(xy[:, 0]).astype(int), 0, shape[1] - 1)
    return rows, cols


def bilinear(image: Float[np.ndarray, "h w"], xy: Float[np.ndarray, "m 2"]) -> Float[np.ndarray, " m"]:
    """``image`` interpolated at image points ``xy`` between its pixel centres (edges clamped)."""
    h, w = image.shape
    u = np.clip(xy[:, 0] - 0.5, 0, w - 1)
    v = np.clip(xy[:, 1] - 0.5, 0, h - 1)
    u0, v0 = np.minimum(np.floor(u).astype(int), w - 2 if w > 1 else 0), np.minimum(np.floor(v).astype(int),
                                                                                    h - 2 if h > 1 else 0)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    fu, fv = u - u0, v - v0
    top = image[v0, u0] * (1 - fu) + image[v0, u1] * fu
    bottom = image[v1, u0] * (1 - fu) + image[v1, u1] * fu
    return top * (1 - fv) + bottom * fv


def multiview_agreement(
    points: Float[np.ndarray, "m 3"], source_view: Int[np.ndarray, " m"], c2w: Float[np.ndarray, "n 4 4"],
    depth: Float[np.ndarray, "n h w"], reliable: Bool[np.ndarray, "n h w"], intrinsics: Intrinsics, tolerance: float,
) -> Int[np.ndarray, " m"]:
    """For each point: in how many views other than its own the rendered depth at its projection agrees with its
    distance from that camera (within ``tolerance`` of it, where that view's depth is reliable)."""
    agree = np.zeros(len(points), dtype=int)
    for j in range(len(c2w)):
        xy, dist, inside = project(c2w[j], points, intrinsics)
        inside &= source_view != j
        if not inside.any():
            continue
        rows, cols = pixel_index(xy[inside], depth.shape[1:])
        ok = reliable[j, rows, cols] & (np.abs(depth[j, rows, cols] - dist[inside]) <= tolerance * dist[inside])
        agree[np.flatnonzero(inside)[ok]] += 1
    return agree


def match_descriptors(
    da: Float[np.ndarray, "ma d"], db: Float[np.ndarray, "mb d"], ratio: float
) -> tuple[Int[np.ndarray, " k"], Int[np.ndarray, " k"]]:
    """Mutual nearest neighbours (L2 on L2-normalised descriptors) that pass Lowe's ratio test both ways."""
    if len(da) < 2 or len(db) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    sim = torch.from_numpy(np.ascontiguousarray(da, dtype=np.float32)) @ torch.from_numpy(
        np.ascontiguousarray(db, dtype=np.float32)).T  # fmt: skip
    # nearest = most similar (|a - b|^2 = 2 - 2 a.b): topk on the similarities in place, both ways, and squared
    # distances of the two kept only (half the time of converting the whole matrix)
    s_ab, ab = sim.topk(2, dim=1)  # sorted: nearest first
    s_ba, ba = sim.topk(2, dim=0)
    d2_ab, d2_ba = (2.0 - 2.0 * s_ab).clamp_min(0.0), (2.0 - 2.0 * s_ba).clamp_min(0.0)
    ia = torch.arange(len(da))
    ib = ab[:, 0]
    r2 = ratio**2  # distances are squared
    keep = (ba[0, ib] == ia) & (d2_ab[:, 0] <= r2 * d2_ab[:, 1]) & (d2_ba[0, ib] <= r2 * d2_ba[1, ib])
    return ia[keep].numpy(), ib[keep].numpy()


# ---------------------------------------------------------------------------------------------------------------------
# Per NeRF: features lifted to 3D


@dataclass
class LiftedFeatures:
    """One NeRF's keypoints with reliable depth, in its own frame."""

    view: Int[np.ndarray, " m"]
    """Render each keypoint was detected in."""
    xy: Float[np.ndarray, "m 2"]
    points: Float[np.ndarray, "m 3"]
    """The lifted 3D points (NeRF frame)."""
    distance: Float[np.ndarray, " m"]
    """Each point's distance from its camera (NeRF units)."""
    descriptors: Float[np.ndarray, "m 128"]
    """SIFT descriptors, L2-normalised."""
    counts: dict[str, int] = field(default_factory=dict)
    """Keypoints detected, with reliable depth, and multi-view consistent."""


def extract_sift(
    views: ViewSet, image_ids: Sequence[int], cfg: KnownGeometryConfig, num_threads: int = -1, verbose: bool = False
) -> list[tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 128"]]]:
    """SIFT keypoints (x, y) and L2-normalised float descriptors of a NeRF's renders ``image_ids``: COLMAP's
    extraction (as the SfM mode runs it, in parallel over images) into a scratch database."""
    root = views.folder.parent
    names = [views.image_names[k] for k in image_ids]
    options = pycolmap.FeatureExtractionOptions()
    options.use_gpu = False  # as the SfM mode: COLMAP's GPU SIFT needs an OpenGL / CUDA build
    options.num_threads = num_threads
    options.sift.max_num_features = cfg.max_num_features
    pycolmap.logging.minloglevel = 0 if verbose else 2  # glog: 0 INFO, 1 WARNING, 2 ERROR
    out = []
    with tempfile.TemporaryDirectory(prefix=".sift-", dir=root) as scratch:
        database = Path(scratch) / "features.db"
        pycolmap.extract_features(database, root, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=options, device=pycolmap.Device.cpu)  # fmt: skip
        with pycolmap.Database.open(database) as db:
            for name in names:
                image_id = db.read_image_with_name(name).image_id
                xy = np.asarray(db.read_keypoints(image_id), dtype=np.float64).reshape(-1, 6)[:, :2]
                d = np.asarray(db.read_descriptors(image_id).data, dtype=np.float32).reshape(-1, 128)
                out.append((xy, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)))
    return out


def lift_keypoints(
    views: ViewSet, intrinsics: Intrinsics, cfg: KnownGeometryConfig, num_threads: int = -1, verbose: bool = False
) -> LiftedFeatures:
    """SIFT keypoints of a NeRF's kept renders lifted to 3D with its rendered depth, reliable ones only."""
    kept = np.flatnonzero(views.kept)
    depth, acc = views.load_depth(), views.load_accumulation()
    reliable = np.stack([reliable_depth(depth[k], acc[k], cfg.min_accumulation, cfg.max_depth_step)
                         for k in range(len(depth))])  # fmt: skip
    parts = {"view": [], "xy": [], "desc": []}
    detected = 0
    for k, (xy, desc) in zip(kept, extract_sift(views, kept, cfg, num_threads, verbose), strict=True):
        detected += len(xy)
        rows, cols = pixel_index(xy, depth.shape[1:])
        ok = reliable[k, rows, cols]
        parts["view"].append(np.full(int(ok.sum()), k))
        parts["xy"].append(xy[ok])
        parts["desc"].append(desc[ok])
    view = np.concatenate(parts["view"]).astype(int) if kept.size else np.zeros(0, int)
    xy = np.concatenate(parts["xy"]) if kept.size else np.zeros((0, 2))
    desc = np.concatenate(parts["desc"]) if kept.size else np.zeros((0, 128), np.float32)
    points, dist = np.zeros((len(view), 3)), np.zeros(len(view))
    for k in np.unique(view):
        sel = view == k
        d = bilinear(depth[k], xy[sel])
        points[sel] = views.c2w[k, :3, 3] + d[:, None] * pixel_rays(views.c2w[k], xy[sel], intrinsics)
        dist[sel] = d
    counts = {"detected": detected, "reliable_depth": len(view)}
    if cfg.min_consistent_views > 0:
        # every render of the NeRF can confirm a point, kept for the matching or not
        agree = multiview_agreement(points, view, views.c2w, depth, reliable, intrinsics, cfg.consistency_tolerance)
        keep = agree >= cfg.min_consistent_views
        view, xy, points, dist, desc = view[keep], xy[keep], points[keep], dist[keep], desc[keep]
    counts["consistent"] = len(view)
    return LiftedFeatures(view, xy, points, dist, desc, counts)


# ---------------------------------------------------------------------------------------------------------------------
# Across NeRFs: 3D-3D matches and SIM(3) hypotheses


@dataclass
class Matches3D:
    """3D-3D matches between NeRFs a and b (indices into their :class:`LiftedFeatures`)."""

    a: int
    b: int
    ia: Int[np.ndarray, " k"]
    ib: Int[np.ndarray, " k"]
    view_pairs: int
    """Candidate view pairs matched."""


@dataclass(eq=False)  # identity: two hypotheses are never "equal" by their arrays
class Hypothesis:
    """One SIM(3) hypothesis ``T_b->a`` of a NeRF pair, with the matches that support it."""

    T: Float[np.ndarray, "4 4"]
    inliers: Int[np.ndarray, " k"]
    """Indices into the pair's :class:`Matches3D`."""
    score: float | None = None
    """The cross-render self-check's NCC when it was scored."""


def match_pair(
    fa: LiftedFeatures, fb: LiftedFeatures, view_pairs: Sequence[tuple[int, int]], ratio: float, a: int = 0,
    b: int = 1,
) -> Matches3D:
    """Descriptor matches of every candidate view pair (view of a, view of b), pooled."""
    by_view_a = {int(v): np.flatnonzero(fa.view == v) for v in np.unique(fa.view)}
    by_view_b = {int(v): np.flatnonzero(fb.view == v) for v in np.unique(fb.view)}
    ia, ib = [], []
    for va, vb in view_pairs:
        sa, sb = by_view_a.get(va), by_view_b.get(vb)
        if sa is None or sb is None:
            continue
        ma, mb = match_descriptors(fa.descriptors[sa], fb.descriptors[sb], ratio)
        ia.append(sa[ma])
        ib.append(sb[mb])
    if not ia:
        return Matches3D(a, b, np.zeros(0, int), np.zeros(0, int), len(view_pairs))
    return Matches3D(a, b, np.concatenate(ia).astype(int), np.concatenate(ib).astype(int), len(view_pairs))


def is_distinct(T: np.ndarray, others: Sequence[Hypothesis], centre: np.ndarray, tol: float) -> bool:
    """Whether ``T`` differs from every earlier hypothesis by more than 5 degrees or ``tol`` at the matches' centre."""
    for h in others:
        r = float(sim3.rotation_angle_deg(sim3.decompose_sim3(T)[0] @ sim3.decompose_sim3(h.T)[0].T))
        shift = np.linalg.norm(sim3.transform_points(T, centre) - sim3.transform_points(h.T, centre))
        if r < 5.0 and shift < tol:
            return False
    return True


def ransac_sim3(
    points_b: Float[np.ndarray, "k 3"], points_a: Float[np.ndarray, "k 3"], max_error: float, seed: int = 0
) -> tuple[Float[np.ndarray, "4 4"], Bool[np.ndarray, " k"]] | None:
    """One LO-RANSAC SIM(3) ``T_b->a`` (pycolmap) of the matches and its inlier mask; None when none is found (fewer
    than three matches included)."""
    if len(points_a) < 3:
        return None
    options = pycolmap.RANSACOptions()
    options.max_error = max_error
    options.min_inlier_ratio = 0.01
    options.random_seed = seed
    result = pycolmap.estimate_sim3d_robust(np.ascontiguousarray(points_b), np.ascontiguousarray(points_a), options)
    if result is None:
        return None
    T = sim3.to_homogeneous(np.asarray(result["tgt_from_src"].matrix(), dtype=np.float64))
    return T, np.asarray(result["inlier_mask"], dtype=bool)


def sim3_hypotheses(
    points_b: Float[np.ndarray, "k 3"], points_a: Float[np.ndarray, "k 3"], max_error: float, cfg: KnownGeometryConfig,
    seed: int = 0,
) -> list[Hypothesis]:
    """Distinct SIM(3) hypotheses ``T_b->a`` (``points_a ~ T points_b``), most inliers first: LO-RANSAC on the matches,
    then again on the matches no earlier hypothesis explains, while a hypothesis has ``cfg.min_inliers`` inliers.

    ``max_error`` is the inlier threshold in a's units. Hypotheses with fewer than ``cfg.min_hypothesis_fraction``
    of the first one's inliers are left out; so are repeats of an earlier one.
    """
    remaining = np.arange(len(points_a))
    found: list[Hypothesis] = []
    centre = np.median(points_b, axis=0) if len(points_b) else np.zeros(3)
    for _attempt in range(cfg.max_hypotheses + 2):
        if len(found) >= cfg.max_hypotheses or len(remaining) < max(cfg.min_inliers, 3):
            break
        result = ransac_sim3(points_b[remaining], points_a[remaining], max_error, seed)
        if result is None:
            break
        T, mask = result
        if mask.sum() < cfg.min_inliers:
            break
        # every match the hypothesis explains, not only RANSAC's inliers among the remaining ones, and the transform
        # refitted to all of them: competing hypotheses are then equally precise when the self-check compares them
        inliers = np.flatnonzero(np.linalg.norm(sim3.transform_points(T, points_b) - points_a, axis=-1) <= max_error)
        refit = pycolmap.estimate_sim3d(np.ascontiguousarray(points_b[inliers]),
                                        np.ascontiguousarray(points_a[inliers]))  # fmt: skip
        if refit is not None:
            T = sim3.to_homogeneous(np.asarray(refit.matrix(), dtype=np.float64))
        if found and len(inliers) < cfg.min_hypothesis_fraction * len(found[0].inliers):
            break
        if is_distinct(T, found, centre, 10 * max_error):
            found.append(Hypothesis(T, inliers))
        remaining = remaining[~mask]
    return found


def joint_solve(
    T0: Float[np.ndarray, "k 4 4"], ref: int,
    links: Sequence[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]], loss_scale: float,
) -> tuple[Float[np.ndarray, "k 4 4"], dict]:
    """All NeRF -> reference SIM(3)s fitted at once to 3D matches (``links``: (a, b, X_a, X_b, sigma) with sigma each
    match's camera distance in reference units): minimise soft-L1 of ``|T_a X_a - T_b X_b| / sigma`` with the
    reference fixed. Returns the transforms and a summary (RMS relative residual before / after)."""
    k = len(T0)
    free = [i for i in range(k) if i != ref]

    def transforms(x: np.ndarray) -> np.ndarray:
        T = T0.copy()
        if free:
            inc = x.reshape(len(free), 7)
            delta = sim3.make_sim3(sim3.so3_exp(inc[:, :3]), inc[:, 3:6], np.exp(inc[:, 6]))
            T[free] = delta @ T0[free]
        return T

    def residuals(x: np.ndarray) -> np.ndarray:
        T = transforms(x)
        out = [((sim3.transform_points(T[a], Xa) - sim3.transform_points(T[b], Xb)) / s[:, None]).ravel()
               for a, b, Xa, Xb, s in links]  # fmt: skip
        return np.concatenate(out) if out else np.zeros(0)

    x0 = np.zeros(7 * len(free))
    r0 = residuals(x0)
    if not free or r0.size == 0:
        return T0, {"used": False, "matches": 0}
    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=loss_scale, method="trf", x_scale="jac")
    r1 = residuals(fit.x)

    def rms(r: np.ndarray) -> float:
        return float(np.sqrt(np.mean((r.reshape(-1, 3) ** 2).sum(1))))

    return transforms(fit.x), {
        "used": True, "matches": int(r0.size // 3), "rms_relative_before": rms(r0), "rms_relative_after": rms(r1),
        "median_relative_after": float(np.median(np.linalg.norm(r1.reshape(-1, 3), axis=1))),
        "solver": str(fit.message),
    }
