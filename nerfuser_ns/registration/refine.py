"""Registration step 4: refine the estimated SIM(3)s by a rigid-set bundle adjustment.

Each NeRF's cameras move together (their poses are known in the NeRF's frame), so the unknowns are 7 per NeRF,
fitted to the SfM's feature tracks seen by two NeRFs or more; the maths is :mod:`nerfuser_ns.bundle`'s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

from nerfuser_ns import bundle, sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import RegistrationError, json_float
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
    summary.update({
        "rms_px_before": json_float(res.rms_px_before), "rms_px_after": json_float(res.rms_px_after),
        "median_px_after": json_float(res.median_px_after), "inlier_fraction": json_float(res.inlier_fraction),
        "iterations": res.iterations, "solver": res.message,
    })
    if not (np.isfinite(res.T_to_ref).all() and res.rms_px_after <= res.rms_px_before):
        return T0, {**summary, "reason": "the refinement did not lower the reprojection error"}
    change = sim3.sim3_errors(res.T_to_ref, T0)
    summary["used"] = True
    summary["change"] = [{"r_deg": json_float(change.r_err_deg[i]), "t": json_float(change.t_err[i]),
                          "s": json_float(change.s_err[i])} for i in range(len(T0))]  # fmt: skip
    return res.T_to_ref, summary
