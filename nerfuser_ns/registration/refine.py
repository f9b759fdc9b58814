"""Registration step 4: refine the estimated SIM(3)s by a rigid-set bundle adjustment.

Each NeRF's cameras move together (their poses are known in the NeRF's frame), so the unknowns are 7 per NeRF,
fitted to feature tracks seen by two NeRFs or more; the maths is :mod:`nerfuser_ns.bundle`'s. The tracks come from
the SfM (mode ``sfm``, :func:`refine_transforms`) or from the inlier keypoint matches across NeRFs (mode
``known-geometry``, :func:`refine_on_matches`: there the rendered depth only starts the points, so its noise along
the ray does not bias the transforms).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float, Int
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from nerfuser_ns import bundle, sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import RegistrationError, json_float
from nerfuser_ns.registration.known_geometry import LiftedFeatures
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.sfm import SfMResult, load_observations


def refine_transforms(
    views: Sequence[ViewSet], sfm: SfMResult, T_to_C: Float[np.ndarray, "k 4 4"], ref: int, intr: Intrinsics,
    loss_scale_px: float,
) -> tuple[np.ndarray, dict]:
    """Rigid-set bundle adjustment (:func:`nerfuser_ns.bundle.refine_sim3_bundle`) from the estimator's transforms.

    Returns the refined NeRF -> reference transforms and a summary; keeps the initial ones (``used`` False) when the
    refinement does not lower the reprojection error or no point is seen by two NeRFs.
    """
    T0 = sim3.to_reference_frame(T_to_C, ref)
    obs = load_observations(sfm)
    pose = {n: (i, vs.c2w[k]) for i, vs in enumerate(views) for k, n in enumerate(vs.image_names)}
    names = [str(n) for n in obs["names"]]
    if any(n not in pose for n in names):
        raise RegistrationError(f"{sfm.folder}: SfM model images do not match the renders; delete the folder")
    cam_nerf = np.array([pose[n][0] for n in names], dtype=int)
    cam_c2w = np.stack([pose[n][1] for n in names])
    # Only points seen by two NeRFs tie the transforms together.
    pairs = np.unique(np.stack([obs["obs_point"], cam_nerf[obs["obs_cam"]]], 1), axis=0)
    linked = np.bincount(pairs[:, 0], minlength=len(obs["points"])) >= 2
    keep = linked[obs["obs_point"]]
    summary = {"used": False, "points": int(linked.sum()), "observations": int(keep.sum())}
    if keep.sum() == 0:
        return T0, {**summary, "reason": "no 3D point is seen by two NeRFs"}
    new_id = np.cumsum(linked) - 1
    points = sim3.transform_points(sim3.invert_sim3(T_to_C[ref]), obs["points"][linked])
    res = bundle.refine_sim3_bundle(
        T0, cam_c2w, cam_nerf, (intr.fx, intr.fy, intr.cx, intr.cy), points, obs["obs_cam"][keep],
        new_id[obs["obs_point"][keep]], obs["obs_xy"][keep], ref=ref, loss_scale_px=loss_scale_px,
    )
    return _accept(res, T0, summary)


def _accept(res: bundle.BundleResult, T0: np.ndarray, summary: dict) -> tuple[np.ndarray, dict]:
    """The refined transforms with the solver's summary, or ``T0`` (``used`` False) when the refinement did not lower
    the reprojection error."""
    summary.update({
        "rms_px_before": json_float(res.rms_px_before), "rms_px_after": json_float(res.rms_px_after),
        "median_px_after": json_float(res.median_px_after), "inlier_fraction": json_float(res.inlier_fraction),
        "iterations": res.iterations, "solver": res.message,
    })  # fmt: skip
    if not (np.isfinite(res.T_to_ref).all() and res.rms_px_after <= res.rms_px_before):
        return T0, {**summary, "reason": "the refinement did not lower the reprojection error"}
    change = sim3.sim3_errors(res.T_to_ref, T0)
    summary["used"] = True
    summary["change"] = [{"r_deg": json_float(change.r_err_deg[i]), "t": json_float(change.t_err[i]),
                          "s": json_float(change.s_err[i])} for i in range(len(T0))]  # fmt: skip
    return res.T_to_ref, summary


def refine_on_matches(
    views: Sequence[ViewSet], feats: Sequence[LiftedFeatures],
    matches: Sequence[tuple[int, int, Int[np.ndarray, " m"], Int[np.ndarray, " m"]]],
    T_to_ref: Float[np.ndarray, "k 4 4"], ref: int, intr: Intrinsics, loss_scale_px: float, depth_sigma: float,
) -> tuple[np.ndarray, dict]:
    """Rigid-set bundle adjustment from keypoint matches across NeRFs (``matches``: (a, b, ia, ib), indices into
    ``feats[a]`` / ``feats[b]``). Matches sharing a keypoint join into one track; a track's point starts at the mean of
    its lifted points in the reference frame. Residuals: the reprojections, and each keypoint's rendered depth with
    relative noise ``depth_sigma`` (exact depth then holds the points; a NeRF's noisy depth yields to the images).

    Returns the refined NeRF -> reference transforms and a summary; keeps ``T_to_ref`` (``used`` False) when the
    refinement does not lower the reprojection error or there is no match.
    """
    T_to_ref = sim3.to_homogeneous(T_to_ref)
    offset = np.cumsum([0] + [len(f.view) for f in feats])
    a_nodes = [offset[a] + ia for a, _, ia, _ in matches]
    b_nodes = [offset[b] + ib for _, b, _, ib in matches]
    summary: dict = {"used": False, "points": 0, "observations": 0}
    if not matches or sum(len(n) for n in a_nodes) == 0:
        return T_to_ref, {**summary, "reason": "no keypoint is matched across NeRFs"}
    src, dst = np.concatenate(a_nodes), np.concatenate(b_nodes)
    n = int(offset[-1])
    graph = coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    nodes = np.unique(np.concatenate([src, dst]))  # keypoints in some match
    track, obs_point = np.unique(label[nodes], return_inverse=True)
    cam_offset = np.cumsum([0] + [len(vs.c2w) for vs in views])
    obs_cam = np.concatenate([cam_offset[i] + f.view for i, f in enumerate(feats)])[nodes]
    obs_xy = np.concatenate([f.xy for f in feats])[nodes]
    lifted = np.concatenate([sim3.transform_points(T_to_ref[i], f.points) for i, f in enumerate(feats)])[nodes]
    distance = np.concatenate([f.distance for f in feats])[nodes]
    counts = np.bincount(obs_point, minlength=len(track))
    points = np.stack([np.bincount(obs_point, lifted[:, c], minlength=len(track)) for c in range(3)], 1)
    points /= counts[:, None]
    cam_nerf = np.concatenate([np.full(len(vs.c2w), i) for i, vs in enumerate(views)])
    cam_c2w = np.concatenate([vs.c2w for vs in views])
    summary.update(points=len(track), observations=len(nodes), depth_sigma=json_float(depth_sigma))
    res = bundle.refine_sim3_bundle(T_to_ref, cam_c2w, cam_nerf, (intr.fx, intr.fy, intr.cx, intr.cy), points,
                                    obs_cam, obs_point, obs_xy, ref=ref, loss_scale_px=loss_scale_px,
                                    obs_distance=distance, distance_sigma=depth_sigma)  # fmt: skip
    return _accept(res, T_to_ref, summary)
