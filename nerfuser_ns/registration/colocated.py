"""Registration step 4c (ours): re-render refinement of each linked NeRF pair at co-located views.

The first links come from views each NeRF rendered at its own poses. Where two captures share no camera positions
(a drive: both move forward along a road, one after the other) those views see common content only from far apart,
and the link they give can be several degrees off. Once a link exists, each NeRF can be rendered at the other's views
mapped through it: a pair of renders from (nearly) the same camera, which differ by a small image motion.

For a pair (parent ``a``, child ``b``, ``T: b -> a``) and a view of ``s`` (one of the two) at its pose ``P`` in
``s``'s frame, the other NeRF ``d`` is rendered at ``T_sd P`` (``T_sd`` maps ``s``'s frame into ``d``'s) with depth.
Dense optical flow between the two renders (OpenCV's DIS, both ways, kept where the backward flow returns to the
start: :func:`flow_matches`) gives pixel correspondences on a grid; each is lifted to 3D with its own NeRF's depth in
its own frame (``X = c + z r(x)``, where the depth is reliable:
:func:`~nerfuser_ns.registration.known_geometry.reliable_depth`). Flow, not keypoints: CPU-sized NeRFs render too
blurry for SIFT to match their renders reliably (on a drive pair, 69 SIFT matches per co-located view, 12 with
reliable depth on both sides). The correspondences of every view of both directions are pooled. Gross flow errors
go first: a LO-RANSAC SIM(3) on the lifted points (pycolmap; the inlier threshold a fraction of each match's camera
distance). The link is then the pair's rigid-set bundle adjustment (:mod:`nerfuser_ns.bundle`, as the other
refinements) on the inliers: two cameras per view pair, each known in its own NeRF's frame, one point per
correspondence, its reprojections in both renders (soft-L1, 1 px) and both rendered ray distances with the relative
noise the RANSAC inliers' residuals measure (a 3D-3D fit alone inherits the rendered depth's noise of a few
percent). With ``iterations`` > 1 a round renders again at the new link (the views stay those the starting link
chose), until the link moves less than ``min_change_deg`` / ``min_change``.

Unlike the direct alignment (:mod:`.direct`), which refines by photometry within a degree or so, this re-matches and
moves the link as far as the matches say; the self-check judges the outcome as it judges any link.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import pycolmap
from jaxtyping import Bool, Float
from rich.console import Console

from nerfuser_ns import bundle, sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import ColocatedConfig
from nerfuser_ns.registration.known_geometry import bilinear, pixel_index, pixel_rays, ransac_sim3, reliable_depth
from nerfuser_ns.registration.render_cache import ViewSet, to_uint8
from nerfuser_ns.registration.self_check import nearest_views, tree_edges
from nerfuser_ns.renderers import Renderer

# ---------------------------------------------------------------------------------------------------------------------
# Pure geometry (the tests check these directly)


def lift(
    c2w: Float[np.ndarray, "4 4"], xy: Float[np.ndarray, "m 2"], depth: Float[np.ndarray, "h w"],
    reliable: Bool[np.ndarray, "h w"], intrinsics: Intrinsics,
) -> tuple[Float[np.ndarray, "m 3"], Bool[np.ndarray, " m"]]:
    """Image points ``xy`` of the view ``c2w`` lifted to 3D with its rendered ray distance ``depth``, and whether the
    depth there is reliable (points where it is not are returned but meaningless)."""
    rows, cols = pixel_index(xy, depth.shape)
    d = bilinear(depth, xy) if len(xy) else np.zeros(0)
    return np.asarray(c2w, dtype=np.float64)[:3, 3] + d[:, None] * pixel_rays(c2w, xy, intrinsics), reliable[rows, cols]


def link_change(
    T_new: Float[np.ndarray, "4 4"], T_old: Float[np.ndarray, "4 4"], centre: Float[np.ndarray, " 3"]
) -> dict[str, float]:
    """How far a new link moved from the old one: rotation (deg), the shift of ``centre`` (the target's units) and
    the change of log scale."""
    R_new, _, s_new = sim3.decompose_sim3(T_new)
    R_old, _, s_old = sim3.decompose_sim3(T_old)
    shift = np.linalg.norm(sim3.transform_points(T_new, centre) - sim3.transform_points(T_old, centre))
    return {"r_deg": float(sim3.rotation_angle_deg(R_new @ R_old.T)), "t": float(shift),
            "s": float(abs(np.log(s_new / s_old)))}  # fmt: skip


def grey8(rgb: Float[np.ndarray, "h w 3"]) -> np.ndarray:
    """An RGB image in [0, 1] as 8-bit grey (the luma of its 8-bit values, as the stored PNGs hold them)."""
    grey = np.asarray(to_uint8(rgb), dtype=np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return np.ascontiguousarray(np.clip(np.round(grey), 0, 255).astype(np.uint8))


def flow_matches(
    grey_src: np.ndarray, grey_dst: np.ndarray, stride: int, max_error_px: float
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Pixel correspondences between two 8-bit grey renders of (nearly) the same camera: dense optical flow (OpenCV's
    DIS) both ways, read on a grid of pixel centres every ``stride`` pixels, kept where the target lies inside the
    image and the backward flow returns within ``max_error_px`` of the start. Returns the image points in each."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = dis.calc(grey_src, grey_dst, None)
    bwd = dis.calc(grey_dst, grey_src, None)
    h, w = grey_src.shape
    rows, cols = (g.ravel() for g in np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride])
    xy_src = np.stack([cols + 0.5, rows + 0.5], axis=-1).astype(np.float64)
    xy_dst = xy_src + fwd[rows, cols].astype(np.float64)
    inside = (xy_dst[:, 0] >= 0) & (xy_dst[:, 0] < w) & (xy_dst[:, 1] >= 0) & (xy_dst[:, 1] < h)
    back = np.stack([bilinear(bwd[..., 0], xy_dst), bilinear(bwd[..., 1], xy_dst)], axis=-1)
    ok = inside & (np.linalg.norm(xy_dst + back - xy_src, axis=-1) <= max_error_px)
    return xy_src[ok], xy_dst[ok]


# ---------------------------------------------------------------------------------------------------------------------
# Renders and matches


@dataclass
class ViewMatches:
    """Correspondences of one co-located view pair: a view of the source NeRF and the other NeRF rendered at it.
    Each side's camera (in its own NeRF's frame), image points, lifted points and ray distances."""

    source_c2w: Float[np.ndarray, "4 4"]
    other_c2w: Float[np.ndarray, "4 4"]
    xy_source: Float[np.ndarray, "m 2"]
    xy_other: Float[np.ndarray, "m 2"]
    source: Float[np.ndarray, "m 3"]
    other: Float[np.ndarray, "m 3"]
    distance_source: Float[np.ndarray, " m"]
    distance_other: Float[np.ndarray, " m"]


def colocated_matches(
    src: ViewSet, k: int, depth_src: np.ndarray, acc_src: np.ndarray, dst: Renderer,
    T_src_to_dst: Float[np.ndarray, "4 4"], intrinsics: Intrinsics, cfg: ColocatedConfig,
) -> ViewMatches:
    """Render ``dst`` at ``src``'s view ``k`` mapped through the link, and lift the two renders' flow
    correspondences, each with its own NeRF's depth, where both depths are reliable."""
    pose = sim3.transform_poses(T_src_to_dst, src.c2w[k][None])[0]
    out = dst.render(pose[None], intrinsics, depth=True)
    rgb = np.nan_to_num(np.asarray(out.rgb[0], dtype=np.float32))
    acc = np.nan_to_num(np.asarray(out.accumulation[0], dtype=np.float32))
    depth = np.nan_to_num(np.asarray(out.depth[0], dtype=np.float32))
    xy_s, xy_d = flow_matches(grey8(src.load_rgb(k)), grey8(rgb), cfg.stride, cfg.max_flow_error_px)
    rel_s = reliable_depth(depth_src, acc_src, cfg.min_accumulation, cfg.max_depth_step)
    rel_d = reliable_depth(depth, acc, cfg.min_accumulation, cfg.max_depth_step)
    X_s, ok_s = lift(src.c2w[k], xy_s, depth_src, rel_s, intrinsics)
    X_d, ok_d = lift(pose, xy_d, depth, rel_d, intrinsics)
    ok = ok_s & ok_d
    return ViewMatches(src.c2w[k], pose, xy_s[ok], xy_d[ok], X_s[ok], X_d[ok],
                       np.linalg.norm(X_s[ok] - src.c2w[k][:3, 3], axis=-1),
                       np.linalg.norm(X_d[ok] - pose[:3, 3], axis=-1))  # fmt: skip


@dataclass
class PairRefinement:
    """What the re-render refinement did to one pair's link."""

    names: list[str]
    rounds: list[dict]
    """Per round: matches, RANSAC inliers, the bundle adjustment's RMS reprojection error before / after, and how far
    the link moved."""
    kept: bool
    """Whether the refined link replaced the one before."""
    reason: str | None = None
    """Why not, when it did not."""


def fit_link(
    Xa: Float[np.ndarray, "m 3"], Xb: Float[np.ndarray, "m 3"], distance_a: Float[np.ndarray, " m"],
    cfg: ColocatedConfig,
) -> tuple[Float[np.ndarray, "4 4"], Bool[np.ndarray, " m"]] | None:
    """``T: b -> a`` by LO-RANSAC on the 3D-3D matches (threshold ``cfg.ransac_max_error`` times the matches' median
    camera distance in a), refitted on its inliers; None when fewer than ``cfg.min_inliers`` support it."""
    if len(Xa) < max(3, cfg.min_inliers):
        return None
    found = ransac_sim3(Xb, Xa, cfg.ransac_max_error * float(np.median(distance_a)), cfg.seed)
    if found is None or found[1].sum() < cfg.min_inliers:
        return None
    T, mask = found
    refit = pycolmap.estimate_sim3d(np.ascontiguousarray(Xb[mask]), np.ascontiguousarray(Xa[mask]))
    return (T if refit is None else sim3.to_homogeneous(np.asarray(refit.matrix(), dtype=np.float64))), mask


def bundle_link(
    matches: Sequence[tuple[bool, ViewMatches, np.ndarray]], T_ba: Float[np.ndarray, "4 4"], intrinsics: Intrinsics,
    loss_scale_px: float, depth_sigma: float,
) -> bundle.BundleResult:
    """The rigid-set bundle adjustment (:func:`nerfuser_ns.bundle.refine_sim3_bundle`) of the pair on its co-located
    correspondences: per view pair two cameras (one per NeRF, each in its own frame), per correspondence one point
    seen by both, with both renders' ray distances at relative noise ``depth_sigma``. ``matches``: (whether ``a`` is
    the source, the view pair's matches, the correspondences kept)."""
    cams, cam_nerf, points, obs_cam, obs_point, obs_xy, obs_dist = [], [], [], [], [], [], []
    n = 0  # points so far
    for a_is_source, m, keep in matches:
        c, m_keep = len(cams), int(keep.sum())
        cams += [m.source_c2w, m.other_c2w]
        cam_nerf += [0, 1] if a_is_source else [1, 0]
        # each point starts where the source NeRF's depth puts it, in a's frame
        points.append(m.source[keep] if a_is_source else sim3.transform_points(T_ba, m.source[keep]))
        obs_cam.append(np.repeat([c, c + 1], m_keep))
        obs_point.append(np.tile(np.arange(n, n + m_keep), 2))
        obs_xy.append(np.concatenate([m.xy_source[keep], m.xy_other[keep]]))
        obs_dist.append(np.concatenate([m.distance_source[keep], m.distance_other[keep]]))
        n += m_keep
    k = intrinsics
    return bundle.refine_sim3_bundle(np.stack([np.eye(4), T_ba]), np.stack(cams), np.asarray(cam_nerf),
                                     (k.fx, k.fy, k.cx, k.cy), np.concatenate(points), np.concatenate(obs_cam),
                                     np.concatenate(obs_point), np.concatenate(obs_xy), ref=0,
                                     loss_scale_px=loss_scale_px, obs_distance=np.concatenate(obs_dist),
                                     distance_sigma=depth_sigma)  # fmt: skip


def refine_pair(
    ra: Renderer, rb: Renderer, va: ViewSet, vb: ViewSet, T_ba: Float[np.ndarray, "4 4"], intrinsics: Intrinsics,
    cfg: ColocatedConfig,
) -> tuple[Float[np.ndarray, "4 4"], PairRefinement]:
    """The link ``T_ba`` (b -> a) re-fitted to the correspondences of co-located renders, round after round: gross
    flow errors removed by a RANSAC SIM(3) on the lifted points, then the pair's rigid-set bundle adjustment on the
    rest, from the RANSAC link (the reprojections are exact where the rendered depth is not; the depth noise it
    assumes is the RANSAC inliers' median relative residual)."""
    depth_a, acc_a = va.load_depth(), va.load_accumulation()
    depth_b, acc_b = vb.load_depth(), vb.load_accumulation()
    T = np.asarray(T_ba, dtype=np.float64)
    rounds: list[dict] = []
    names = [ra.name, rb.name]
    # the views are chosen once, by the starting link: rounds that each pick their own views fit different parts of a
    # capture, which differ where COLMAP bent it
    views_a = nearest_views(va, sim3.invert_sim3(T), vb)[: cfg.views]  # a's views, b rendered there
    views_b = nearest_views(vb, T, va)[: cfg.views]  # b's views, a rendered there
    for _ in range(cfg.iterations):
        T_ab = sim3.invert_sim3(T)
        scale = float(sim3.decompose_sim3(T)[2])
        views: list[tuple[bool, ViewMatches]] = []
        for k in views_a:
            views.append((True, colocated_matches(va, k, depth_a[k], acc_a[k], rb, T_ab, intrinsics, cfg)))
        for k in views_b:
            views.append((False, colocated_matches(vb, k, depth_b[k], acc_b[k], ra, T, intrinsics, cfg)))
        Xa = np.concatenate([np.zeros((0, 3))] + [m.source if s else m.other for s, m in views])
        Xb = np.concatenate([np.zeros((0, 3))] + [m.other if s else m.source for s, m in views])
        da = np.concatenate([np.zeros(0)] + [m.distance_source if s else scale * m.distance_source for s, m in views])
        fit = fit_link(Xa, Xb, da, cfg)
        if fit is None:
            rounds.append({"matches": len(Xa), "inliers": 0})
            if len(rounds) == 1:  # nothing was refined: the link stays
                reason = f"fewer than {cfg.min_inliers} of {len(Xa)} matches support one link"
                return np.asarray(T_ba, dtype=np.float64), PairRefinement(names, rounds, False, reason)
            break
        T_new, mask = fit
        relative = np.linalg.norm(sim3.transform_points(T_new, Xb[mask]) - Xa[mask], axis=-1) / da[mask]
        sigma = max(float(np.median(relative)), 1e-4)
        splits = np.cumsum([0] + [len(m.source) for _, m in views])
        keep = [mask[o:e] for o, e in zip(splits[:-1], splits[1:], strict=True)]
        ba = bundle_link([(s, m, kk) for (s, m), kk in zip(views, keep, strict=True)], T_new, intrinsics,
                         cfg.loss_scale_px, sigma)  # fmt: skip
        entry = {"matches": len(Xa), "inliers": int(mask.sum()), "depth_sigma": sigma,
                 "rms_px_before": float(ba.rms_px_before), "rms_px_after": float(ba.rms_px_after)}  # fmt: skip
        if np.isfinite(ba.T_to_ref).all() and ba.rms_px_after <= ba.rms_px_before:
            T_new = ba.T_to_ref[1]
        change = link_change(T_new, T, np.median(Xb[mask], axis=0))
        entry["change"] = change
        rounds.append(entry)
        T = T_new
        if change["r_deg"] < cfg.min_change_deg and change["t"] < cfg.min_change * float(np.median(da)):
            break
    return T, PairRefinement(names, rounds, True)


def refine_colocated(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], T_to_ref: Float[np.ndarray, "k 4 4"],
    pairs: Sequence[tuple[int, int]], ref: int, intrinsics: Intrinsics, cfg: ColocatedConfig, console: Console,
) -> tuple[Float[np.ndarray, "k 4 4"], dict]:
    """Every pair of the spanning tree re-fitted, parents nearer the reference first; each child's subtree moves with
    it. Returns the transforms and a summary for the registration file."""
    T = np.asarray(T_to_ref, dtype=np.float64).copy()
    summary = []
    for parent, child in tree_edges(pairs, ref):
        T_cp = sim3.relative_sim3(T[parent], T[child])  # child -> parent
        with console.status(f"re-render refinement: {renderers[child].name} rendered at {renderers[parent].name}'s "
                            "views and back"):  # fmt: skip
            T_new, outcome = refine_pair(renderers[parent], renderers[child], views[parent], views[child], T_cp,
                                         intrinsics, cfg)  # fmt: skip
        if outcome.kept:
            # every NeRF whose chain to the reference passes through the child moves with it
            delta = sim3.compose(T[parent], T_new, sim3.invert_sim3(T_cp), sim3.invert_sim3(T[parent]))
            for n in subtree(pairs, ref, child):
                T[n] = delta @ T[n]
        summary.append(asdict(outcome))
    return T, {"pairs": summary}


def subtree(pairs: Sequence[tuple[int, int]], ref: int, root: int) -> list[int]:
    """``root`` and every node below it in the tree of ``pairs`` rooted at ``ref``."""
    children: dict[int, list[int]] = {}
    for parent, child in tree_edges(pairs, ref):
        children.setdefault(parent, []).append(child)
    out, stack = [], [root]
    while stack:
        n = stack.pop()
        out.append(n)
        stack.extend(children.get(n, []))
    return out
