"""The twin check of the SfM mode (ours): whether the SfM took a twin of repeated structure for the true link.

On repeated structure (opposite walls alike, a row of equal houses) a free SfM can link two NeRFs by the wrong copy,
and the cross-render self-check passes that link, since almost everything it renders looks right (measured: a room
of stock nerfacto runs linked 180 deg wrong, NCC 0.965). Known geometry keeps every link its 3D matches support and
lets the worst cross-rendered view choose (:mod:`.pairwise`); this check brings that choice to the SfM's result, on
the renders the SfM mode already made (with depth):

1. Each NeRF's keypoints lifted to 3D, 3D-3D matches of each checked pair, and its SIM(3) hypotheses
   (:func:`.pairwise.matches_per_pair`, :func:`.known_geometry.sim3_hypotheses`).
2. Each NeRF's own symmetries (:func:`self_symmetries`): its keypoints matched with those of its other views, the
   matches of one point with itself left out, and SIM(3) hypotheses fitted to the rest; those within 10% of scale 1
   (a scene maps onto itself only by an isometry) are where its content repeats. A twin of the SfM's link ``T`` is
   then ``S_a T`` or ``T S_b``. This finds the true link where the cross-NeRF matches hardly support it: on a room
   of stock nerfacto runs, 2895 of 3702 matches fit the half-turn twin and RANSAC found no other link, while each
   run's own strongest symmetry (76 and 111 matches) was the half turn, and composed with the twin lay 0.45 and 0.35
   deg from the truth.
3. The hypotheses and twins that differ from the SfM's link (:func:`.known_geometry.is_distinct`: more than 5 deg or
   ten RANSAC thresholds apart at the matches' centre) are the rivals. None: the pair passes.
4. The SfM's link and its rivals cross-rendered on the same views, those where their inlier counts differ most first
   (:func:`.pairwise.score_hypotheses`), each scored by its worst view's NCC.
5. A rival that scores ``ambiguity_margin`` (0.05) above the SfM's link refuses the link (the automatic choice then
   registers on known geometry from the same renders); a rival within the margin that passes the self-check's
   threshold is reported as a warning: the overlap looks symmetric as far as the renders show.

Off by default (``--twin-check``): it needs NeRFs that render views far from their own cameras well. On stock
nerfacto runs of the generated room (each capture in one half, looking around) step 2 does find the true link next to
the SfM's half-turn twin, but the twin renders better at every view: it lays each run's cameras over the other run's
own training views, where the other renders well, and the truth asks each run for views from the far half of the
room (worst view 0.76 for the twin, -0.17 for the truth; ``reports/twin_check_room4.md``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import RegistrationConfig, json_float
from nerfuser_ns.registration.known_geometry import (
    Hypothesis,
    LiftedFeatures,
    is_distinct,
    lift_keypoints,
    match_pair,
    sim3_hypotheses,
)
from nerfuser_ns.registration.pairwise import match_nerfs, ransac_max_error, score_hypotheses, view_similarity
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.renderers import Renderer


@dataclass
class TwinVerdict:
    """The twin check of the registration: a refusal (one line) or None, and what the record keeps."""

    refusal: str | None
    """Why the SfM's link is refused (a rival renders better in its worst view), or None."""
    warning: str | None
    """A rival within the margin that passes the self-check's threshold (the overlap looks symmetric), or None."""
    summary: dict
    """Per checked pair: its 3D matches, hypotheses, the SfM link's and the best rival's worst-view NCC."""


def relative_link(T_to_ref: np.ndarray, a: int, b: int) -> np.ndarray:
    """``T_b->a`` implied by two NeRFs' transforms into the reference frame (``p_a = T_a^-1 T_b p_b``)."""
    return sim3.invert_sim3(T_to_ref[a]) @ T_to_ref[b]


SYMMETRY_VIEWS = 32
"""Views per NeRF (evenly spread over its kept renders) whose keypoints are matched with each other for its own
symmetries: every pair of them, 496 at 32, a bounded cost on the most views."""
MAX_SYMMETRY_SCALE_LOG = 0.1
"""A self-map of a NeRF's content is a symmetry only within this of scale 1 (``|log s|``; the paper's scale rule)."""


def self_symmetries(feats: LiftedFeatures, views: ViewSet, config: RegistrationConfig) -> list[np.ndarray]:
    """The SIM(3)s ``S`` under which a NeRF's own lifted keypoints repeat (``p ~ S p``, most supported first): the
    keypoints of :data:`SYMMETRY_VIEWS` spread views matched across every two of them, matches of a point with itself
    (closer than ten RANSAC thresholds) left out, sequential RANSAC on the rest, near-isometries kept."""
    kg = config.known_geometry
    kept = np.flatnonzero(views.kept)
    chosen = kept[np.unique(np.linspace(0, len(kept) - 1, min(SYMMETRY_VIEWS, len(kept))).round().astype(int))]
    pairs = [(int(i), int(j)) for n, i in enumerate(chosen) for j in chosen[n + 1 :]]
    m = match_pair(feats, feats, pairs, kg.ratio)
    if len(m.ia) == 0:
        return []
    max_error = kg.ransac_max_error * float(np.median(feats.distance[m.ia]))
    p, q = feats.points[m.ia], feats.points[m.ib]
    apart = np.linalg.norm(p - q, axis=-1) > 10 * max_error
    hyps = sim3_hypotheses(q[apart], p[apart], max_error, kg, config.sfm.seed)
    return [h.T for h in hyps if abs(np.log(sim3.decompose_sim3(h.T)[2])) <= MAX_SYMMETRY_SCALE_LOG]


def explained(T: np.ndarray, points_b: np.ndarray, points_a: np.ndarray, max_error: float) -> Hypothesis:
    """``T`` as a hypothesis of the pair, with the 3D matches it maps within ``max_error``."""
    residual = np.linalg.norm(sim3.transform_points(T, points_b) - points_a, axis=-1)
    return Hypothesis(T, np.flatnonzero(residual <= max_error))


def twin_check(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], T_to_ref: np.ndarray, pairs: Sequence[tuple[int, int]],
    intr: Intrinsics, config: RegistrationConfig, console: Console,
) -> TwinVerdict:
    """The twin check (module docstring) of the SfM's transforms ``T_to_ref`` on the checked ``pairs``; ``views``
    must carry depth."""
    kg = config.known_geometry
    names = [r.name for r in renderers]
    with console.status("twin check: SIFT keypoints lifted to 3D with the rendered depth"):
        feats = [lift_keypoints(vs, intr, kg, config.sfm.num_threads, config.sfm.verbose) for vs in views]
    thin = [names[i] for i, f in enumerate(feats) if len(f.view) < kg.min_inliers]
    if thin:  # known geometry could not judge these NeRFs either: nothing to compare with
        return TwinVerdict(None, None, {"skipped": f"too few keypoints with reliable depth: {', '.join(thin)}"})
    similarity = view_similarity(feats, views, config)
    with console.status("twin check: each NeRF's own symmetries"):
        symmetries = {n: self_symmetries(feats[n], views[n], config) for n in sorted({i for p in pairs for i in p})}
    margin = kg.ambiguity_margin
    refusal = warning = None
    records = []
    for a, b in pairs:
        m = match_nerfs(feats, views, similarity, a, b, config)
        max_error = ransac_max_error(feats, m, config)
        points_a, points_b = feats[a].points[m.ia], feats[b].points[m.ib]
        T_sfm = relative_link(T_to_ref, a, b)
        sfm_link = explained(T_sfm, points_b, points_a, max_error)
        hyps = sim3_hypotheses(points_b, points_a, max_error, kg, config.sfm.seed) if len(m.ia) else []
        twins = [S @ T_sfm for S in symmetries[a]] + [T_sfm @ S for S in symmetries[b]]
        hyps += [explained(T, points_b, points_a, max_error) for T in twins]
        centre = np.median(points_b, axis=0) if len(points_b) else np.zeros(3)
        rivals: list[Hypothesis] = []
        for h in hyps:
            if is_distinct(h.T, [sfm_link, *rivals], centre, 10 * max_error):
                rivals.append(h)
        record = {"names": [names[a], names[b]], "matches": len(m.ia), "sfm_inliers": len(sfm_link.inliers),
                  "hypotheses": len(hyps) - len(twins), "symmetries": [len(symmetries[a]), len(symmetries[b])],
                  "rivals": len(rivals)}  # fmt: skip
        if rivals:
            with console.status(f"twin check: cross-rendering the SfM's link of {names[a]} / {names[b]} against "
                                f"{len(rivals)} other transform(s) its rendered depth supports"):  # fmt: skip
                score_hypotheses(renderers, views, feats, m, [sfm_link, *rivals], intr, config)
            sfm_score = sfm_link.score if sfm_link.score is not None and np.isfinite(sfm_link.score) else -np.inf
            scores = np.array([h.score if h.score is not None and np.isfinite(h.score) else -np.inf for h in rivals])
            best = rivals[int(np.argmax(scores))]
            angle = float(sim3.rotation_angle_deg(sim3.decompose_sim3(best.T)[0] @ sim3.decompose_sim3(T_sfm)[0].T))
            shift = float(np.linalg.norm(sim3.transform_points(best.T, centre) - sim3.transform_points(T_sfm, centre)))
            record |= {"sfm_ncc": json_float(sfm_score), "rival_ncc": json_float(scores.max()),
                       "rival_rotation_deg": json_float(angle), "rival_shift": json_float(shift),
                       "rival_inliers": len(best.inliers), "rival_T_j_to_i": np.asarray(best.T).tolist()}  # fmt: skip
            what = (f"{names[a]} / {names[b]}: another transform ({angle:.0f} deg, {shift:.2g} units from the SfM's "
                    f"link, {len(best.inliers)} 3D matches against {len(sfm_link.inliers)})")  # fmt: skip
            if scores.max() >= sfm_score + margin:
                record["verdict"] = "twin"
                refusal = refusal or (
                    f"twin check: {what} renders better in its worst view than the SfM's link (NCC "
                    f"{scores.max():.2f} against {sfm_score:.2f}): the SfM linked repeated structure by the wrong "
                    "copy; --mode known-geometry chooses between them"
                )
            elif scores.max() >= config.ncc_threshold and scores.max() >= sfm_score - margin:
                record["verdict"] = "ambiguous"
                warning = warning or (f"twin check: {what} renders about as well in its worst view (NCC "
                                      f"{scores.max():.2f} against {sfm_score:.2f}): the overlap looks symmetric; "
                                      "views that see something unique to one side would tell them apart")  # fmt: skip
            else:
                record["verdict"] = "passed"
        else:
            record["verdict"] = "passed"
        records.append(record)
    return TwinVerdict(refusal, warning, {"pairs": records})
