"""Registration step 6: the record assembled from the steps' outputs (:class:`~.record.RegistrationResult`, the
schema :mod:`.record` owns), per mode: :func:`build_result` (``sfm``), :func:`build_known_geometry_result`
(``known-geometry`` and ``graph``) and the graph mode's own section (:func:`graph_section`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from jaxtyping import Float, Int

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import RegistrationConfig, json_float, json_matrix
from nerfuser_ns.registration.estimate import NerfEstimate
from nerfuser_ns.registration.pose_graph import PoseGraphResult, Residual
from nerfuser_ns.registration.record import (
    NerfResult,
    PairCheck,
    PairResult,
    RegistrationResult,
    Residuals,
    SfMSummary,
    ViewCounts,
    colour_maps_to_reference,
    colour_record,
    matrix,
    training_cameras_of,
)
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.self_check import CrossRenderCheck, camera_residuals, passed
from nerfuser_ns.registration.sfm import SfMResult
from nerfuser_ns.renderers import Renderer


def _pair_results(
    T_to_ref: Float[np.ndarray, "k 4 4"], overlap: np.ndarray, checks: Sequence[CrossRenderCheck],
    config: RegistrationConfig,
) -> list[PairResult]:
    """Every NeRF pair (i < j): its relative transform, its overlap and its self-check when it was checked."""
    check_of = {(c.i, c.j): c for c in checks}
    pairs = []
    for i in range(len(T_to_ref)):
        for j in range(i + 1, len(T_to_ref)):
            c = check_of.get((i, j))
            pairs.append(PairResult(
                i, j, matrix(sim3.relative_sim3(T_to_ref[i], T_to_ref[j])), int(overlap[i, j]),
                None if c is None else PairCheck(
                    json_float(c.score), json_float(c.ncc_i_in_j), json_float(c.ncc_j_in_i), c.views,
                    config.ncc_threshold, passed(c, config), colour_record(c.colour_j_to_i),
                    colour_record(c.colour_i_to_j), int(c.colour_pixels), json_float(c.depth_i_in_j),
                    json_float(c.depth_j_in_i), config.depth_threshold,
                ),
            ))  # fmt: skip
    return pairs


def build_result(
    *,
    renderers: Sequence[Renderer],
    views: Sequence[ViewSet],
    sfm: SfMResult,
    estimates: Sequence[NerfEstimate],
    T_to_ref: Float[np.ndarray, "k 4 4"],
    T_to_C: Float[np.ndarray, "k 4 4"],
    refinement: dict | None,
    overlap: np.ndarray,
    checks: Sequence[CrossRenderCheck],
    config: RegistrationConfig,
    intrinsics: Intrinsics,
    timings: dict[str, float],
) -> RegistrationResult:
    """The result of the steps' outputs: ``T_to_C`` / ``T_to_ref`` are the final transforms (refined when refined),
    ``timings`` this run's seconds per step (render, features, matching, mapping, solve, self_check)."""
    k = len(renderers)
    pairs = _pair_results(T_to_ref, overlap, checks, config)
    colours = colour_maps_to_reference(k, config.reference % k, checks)
    nerfs = []
    residuals = camera_residuals(views, estimates, T_to_C)  # against the final transform (refined, aligned)
    for i, (r, vs, ne, (rot, cen)) in enumerate(zip(renderers, views, estimates, residuals, strict=True)):
        est = ne.estimate
        registered = sum(1 for n, kept in zip(vs.image_names, vs.kept, strict=True) if kept and n in sfm.c2w)
        config_path = getattr(r, "config_path", None)
        nerfs.append(NerfResult(
            name=r.name,
            config=None if config_path is None else str(Path(config_path).absolute()),
            checkpoint=r.checkpoint_identity() if hasattr(r, "checkpoint_identity") else None,
            T_to_reference=matrix(T_to_ref[i]),
            scale_to_reference=float(sim3.decompose_sim3(T_to_ref[i])[2]),
            T_to_sfm=matrix(T_to_C[i]),
            views=ViewCounts(len(vs.c2w), int(vs.kept.sum()), registered,
                             {s: vs.sources.count(s) for s in sorted(set(vs.sources))}),
            render_folder=str(vs.folder),
            renders_reused=vs.reused,
            estimator=est.method,
            refinement_change=refinement["change"][i] if refinement and refinement["used"] else None,
            cameras_used=est.num_cameras,
            scale_to_sfm=est.scale,
            scale_spread=est.scale_spread,
            scale_outlier_fraction=est.scale_outlier_fraction,
            residuals=Residuals(json_float(np.median(rot)), json_float(np.max(rot)), json_float(np.median(cen)),
                                json_float(np.max(cen))),
            training_cameras=training_cameras_of(r), colour_to_reference=colours[i],
        ))  # fmt: skip
    # What each step costs without the work folder (reused renders and SfM report the time they took when made).
    render_s = [vs.render_seconds for vs in views]
    compute = {"render": None if None in render_s else float(sum(render_s))}
    compute.update({step: sfm.timings.get(step) for step in ("features", "matching", "mapping")})
    compute.update({step: timings[step] for step in ("solve", "colocated", "direct", "self_check") if step in timings})
    return RegistrationResult(
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        reference=config.reference % k,
        nerfs=nerfs,
        pairs=pairs,
        sfm=SfMSummary(sfm.num_images, len(sfm.c2w), sfm.matching, sfm.model_counts, sfm.num_points3D,
                       json_float(sfm.mean_reprojection_error), sfm.reused, asdict(intrinsics)),
        refinement=refinement,
        settings=asdict(config),
        timings_s={step: round(s, 3) for step, s in timings.items()},
        compute_timings_s={step: None if s is None else round(s, 3) for step, s in compute.items()},
    )


def build_known_geometry_result(
    *,
    renderers: Sequence[Renderer],
    views: Sequence[ViewSet],
    T_to_ref: Float[np.ndarray, "k 4 4"],
    T_initial: Float[np.ndarray, "k 4 4"],
    views_matched: Sequence[int],
    overlap: np.ndarray,
    checks: Sequence[CrossRenderCheck],
    config: RegistrationConfig,
    timings: dict[str, float],
    known_geometry: dict | None,
    graph: dict | None = None,
    refinement: dict | None = None,
) -> RegistrationResult:
    """The result of a known-geometry or graph registration: ``T_initial`` the chosen pairwise hypotheses chained
    from the reference, ``T_to_ref`` after the joint (or pose-graph) solve and the refinement (its summary:
    ``refinement``), ``views_matched`` per NeRF its views with inlier matches, ``overlap`` the inlier matches per NeRF
    pair, ``known_geometry`` / ``graph`` the mode's own summary (stored as is)."""
    k = len(renderers)
    ref = config.reference % k
    pairs = _pair_results(T_to_ref, overlap, checks, config)
    colours = colour_maps_to_reference(k, ref, checks)
    change = sim3.sim3_errors(T_to_ref, T_initial)
    none = Residuals(None, None, None, None)
    nerfs = []
    for i, (r, vs) in enumerate(zip(renderers, views, strict=True)):
        config_path = getattr(r, "config_path", None)
        scale = float(sim3.decompose_sim3(T_to_ref[i])[2])
        nerfs.append(NerfResult(
            name=r.name, config=None if config_path is None else str(Path(config_path).absolute()),
            checkpoint=r.checkpoint_identity() if hasattr(r, "checkpoint_identity") else None,
            T_to_reference=matrix(T_to_ref[i]), scale_to_reference=scale, T_to_sfm=matrix(T_to_ref[i]),
            views=ViewCounts(len(vs.c2w), int(vs.kept.sum()), int(views_matched[i]),
                             {s: vs.sources.count(s) for s in sorted(set(vs.sources))}),
            render_folder=str(vs.folder), renders_reused=vs.reused, estimator=config.mode,
            refinement_change=None if i == ref else {
                "r_deg": json_float(change.r_err_deg[i]), "t": json_float(change.t_err[i]),
                "s": json_float(change.s_err[i])},
            cameras_used=int(views_matched[i]), scale_to_sfm=scale, scale_spread=None, scale_outlier_fraction=None,
            residuals=none, training_cameras=training_cameras_of(r), colour_to_reference=colours[i],
        ))  # fmt: skip
    render_s = [vs.render_seconds for vs in views]
    compute = {"render": None if None in render_s else float(sum(render_s)),
               **{step: s for step, s in timings.items() if step != "render"}}  # fmt: skip
    return RegistrationResult(
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"), reference=ref, nerfs=nerfs, pairs=pairs,
        sfm=None, refinement=refinement, settings=asdict(config),
        timings_s={step: round(s, 3) for step, s in timings.items()},
        compute_timings_s={step: None if s is None else round(s, 3) for step, s in compute.items()},
        known_geometry=known_geometry, graph=graph,
    )


def _residual(r: Residual) -> dict:
    return {"rotation_deg": json_float(r.rotation_deg), "translation": json_float(r.translation),
            "log_scale": json_float(r.log_scale)}  # fmt: skip


def retrieval_fields(
    scores: Float[np.ndarray, "k k"], verified: Int[np.ndarray, "k k"] | None, a: int, b: int
) -> dict:
    """What retrieval said of the NeRF pair (a, b): its tf-idf score and verified inliers (None: not verified)."""
    return {"retrieval_score": json_float(scores[a, b]),
            "verified_inliers": None if verified is None else int(verified[a, b])}  # fmt: skip


def graph_section(
    *,
    names: Sequence[str],
    scores: Float[np.ndarray, "k k"],
    verified: Int[np.ndarray, "k k"] | None,
    candidates: Sequence[tuple[int, int]],
    source: str,
    pairs: dict[tuple[int, int], dict],
    rejected: dict[tuple[int, int], str],
    accepted: Sequence[tuple[int, int]],
    solved: PoseGraphResult,
    lengths: Float[np.ndarray, " k"],
    keypoints: dict,
) -> dict:
    """The record's ``graph`` section. ``scores`` are the NeRF pairs' tf-idf retrieval scores, ``verified`` their
    geometric verification's inliers (None: not verified), ``pairs`` each candidate pair's matching summary (3D
    matches, hypotheses, the chosen one), ``rejected`` why a pair gave no edge, ``accepted[n]`` the pair of the pose
    graph's edge n (``solved.edges[n]``)."""
    edge_of = {pair: n for n, pair in enumerate(accepted)}
    edges = []
    for a, b in candidates:
        info = {"i": a, "j": b, "names": [names[a], names[b]], **retrieval_fields(scores, verified, a, b)}
        n = edge_of.get((a, b))
        if n is None:
            info.update(status="rejected", reason=rejected[(a, b)], T_j_to_i=None, weight=None, in_tree=False,
                        cycles_passed=0, residual=None)  # fmt: skip
        else:
            e = solved.edges[n]
            chosen = pairs[(a, b)]["hypotheses"][pairs[(a, b)]["chosen"]]
            info.update(status=e.status, reason=e.reason, T_j_to_i=chosen["T_j_to_i"], weight=e.weight,
                        in_tree=e.in_tree, cycles_passed=e.cycles_passed, residual=_residual(e.residual))  # fmt: skip
        edges.append({**info, **pairs[(a, b)]})
    degree = np.zeros(len(names), int)
    for pair, n in edge_of.items():
        if solved.edges[n].status != "dropped":
            degree[list(pair)] += 1
    return {
        "candidates": {"source": source, "pairs": [[names[a], names[b]] for a, b in candidates]},
        "nodes": [{"name": name, "length_scale": json_float(lengths[i]), "degree": int(degree[i]),
                   "T_initial": json_matrix(solved.T_initial[i]),
                   "T_to_reference": json_matrix(solved.T_to_reference[i])} for i, name in enumerate(names)],
        "edges": edges,
        "cycles": [{"names": [names[v] for v in c.nodes],
                    "pairs": [[names[accepted[n][0]], names[accepted[n][1]]] for n in c.edges],
                    "residual": _residual(c.residual), "passed": c.passed} for c in solved.cycles],
        "tree": [[names[accepted[n][0]], names[accepted[n][1]]] for n in solved.tree],
        "solver": solved.solver,
        "keypoints": keypoints,
        "residuals": "rotation in degrees; translation over the length scale of the frame it is measured in (an "
                     "edge's: its first NeRF's; a cycle's: its first NeRF's); log_scale |log s|",
    }  # fmt: skip
