"""The steps the known-geometry and graph modes share (ours): each NeRF rendered with depth and its keypoints lifted
(:func:`render_and_lift`), candidate view pairs and 3D matches per NeRF pair (:func:`matches_per_pair`), SIM(3)
hypotheses per pair scored by cross-rendering (:func:`pair_hypotheses`), the choice between them
(:func:`choose_hypothesis`, ambiguity included) and the chosen transforms chained from the reference
(:func:`chain_from_reference`). The maths is :mod:`.known_geometry`'s; :mod:`.pipeline` and :mod:`.graph` compose
these steps."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Int
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import (
    SUGGESTION,
    PoseSamplingConfig,
    RegistrationConfig,
    RegistrationError,
    json_float,
    json_matrix,
)
from nerfuser_ns.registration.distributed import Executor, SerialExecutor
from nerfuser_ns.registration.known_geometry import (
    Hypothesis,
    LiftedFeatures,
    Matches3D,
    lift_keypoints,
    match_pair,
    ransac_sim3,
    sim3_hypotheses,
)
from nerfuser_ns.registration.render_cache import ViewSet, check_kept_views, render_views_cached
from nerfuser_ns.registration.retrieval import (
    assign_words,
    build_vocabulary,
    candidate_pairs,
    most_similar_view_pairs,
    tfidf_similarity,
    view_histograms,
)
from nerfuser_ns.registration.self_check import tree_edges, view_nccs
from nerfuser_ns.renderers import Renderer, gives_depth


def view_similarity(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], config: RegistrationConfig
) -> list[list[np.ndarray]]:
    """View-to-view similarity of every two NeRFs (``[a][b]``: ``[n_a, n_b]``) from a vocabulary of the renders'
    descriptors; left-out views have no features and score -inf (never candidates)."""
    kg = config.known_geometry
    vocabulary = build_vocabulary(np.concatenate([f.descriptors for f in feats]), kg.vocabulary_words, config.sfm.seed)
    hists = [view_histograms(assign_words(f.descriptors, vocabulary), f.view, len(vs.c2w), len(vocabulary))
             for f, vs in zip(feats, views, strict=True)]  # fmt: skip
    similarity = tfidf_similarity(hists)
    for a in range(len(feats)):
        for b in range(len(feats)):
            similarity[a][b][~views[a].kept] = -np.inf
            similarity[a][b][:, ~views[b].kept] = -np.inf
    return similarity


def match_nerfs(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], similarity: list[list[np.ndarray]], a: int, b: int,
    config: RegistrationConfig,
) -> Matches3D:
    """3D-3D matches of NeRFs a and b over their candidate view pairs."""
    kg = config.known_geometry
    view_pairs = [(i, j) for i, j in candidate_pairs(similarity[a][b], kg.candidate_views, kg.exhaustive_max_pairs)
                  if views[a].kept[i] and views[b].kept[j]]  # fmt: skip
    return match_pair(feats[a], feats[b], view_pairs, kg.ratio, a, b)


def verified_inliers(
    feats: Sequence[LiftedFeatures], similarity: list[list[np.ndarray]], a: int, config: RegistrationConfig
) -> Int[np.ndarray, " k"]:
    """Geometric verification of NeRF a against every later NeRF b (a task of the graph mode): the inliers of one
    LO-RANSAC SIM(3) on the 3D matches of their ``verify_views`` most similar view pairs (0 for b <= a; left-out
    views, similarity -inf, are never matched)."""
    kg, k = config.known_geometry, len(feats)
    out = np.zeros(k, dtype=int)
    for b in range(a + 1, k):
        m = match_pair(feats[a], feats[b], most_similar_view_pairs(similarity[a][b], config.graph.verify_views),
                       kg.ratio, a, b)  # fmt: skip
        fit = ransac_sim3(feats[b].points[m.ib], feats[a].points[m.ia], ransac_max_error(feats, m, config),
                          config.sfm.seed)  # fmt: skip
        out[b] = 0 if fit is None else int(fit[1].sum())
    return out


def verify_pairs(
    feats: Sequence[LiftedFeatures], similarity: list[list[np.ndarray]], config: RegistrationConfig,
    executor: Executor | None = None,
) -> Int[np.ndarray, "k k"]:
    """Every NeRF pair's verified inliers (:func:`verified_inliers`, one task per NeRF on ``executor``, default: in
    this process), symmetric, 0 on the diagonal."""
    executor = executor or SerialExecutor()
    rows = executor.map(verified_inliers, [(feats, similarity, a, config) for a in range(len(feats))], "verify")
    upper = np.stack(rows)
    return upper + upper.T


def matches_per_pair(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], config: RegistrationConfig
) -> dict[tuple[int, int], Matches3D]:
    """3D-3D matches of every NeRF pair, over candidate view pairs from a vocabulary of the renders' descriptors."""
    similarity = view_similarity(feats, views, config)
    return {(a, b): match_nerfs(feats, views, similarity, a, b, config)
            for a in range(len(feats)) for b in range(a + 1, len(feats))}  # fmt: skip


def views_by_support(feats: LiftedFeatures, index: np.ndarray, num_views: int) -> list[int]:
    """Views of a NeRF ordered by how many of the given keypoints they hold, most first (views holding none left
    out)."""
    counts = np.bincount(feats.view[index], minlength=num_views)
    return [int(v) for v in np.argsort(-counts, kind="stable") if counts[v] > 0]


def check_views(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], matches: dict[tuple[int, int], Matches3D],
    chosen: dict[tuple[int, int], Hypothesis], pairs: Sequence[tuple[int, int]],
) -> dict[tuple[int, int], list[int]]:
    """The self-check's views of each checked pair, both ways: those with the chosen hypothesis' inliers first."""
    order = {}
    for i, j in pairs:
        m, h = matches[(i, j)], chosen[(i, j)]
        order[(i, j)] = views_by_support(feats[i], m.ia[h.inliers], len(views[i].c2w))
        order[(j, i)] = views_by_support(feats[j], m.ib[h.inliers], len(views[j].c2w))
    return order


def views_matched(
    feats: Sequence[LiftedFeatures], matches: dict[tuple[int, int], Matches3D],
    chosen: dict[tuple[int, int], Hypothesis], k: int,
) -> list[int]:
    """Per NeRF: the most of its views that hold inlier matches of one chosen pair."""
    views_matched = [0] * k
    for (a, b), h in chosen.items():
        m = matches[(a, b)]
        for n, idx in ((a, m.ia[h.inliers]), (b, m.ib[h.inliers])):
            views_matched[n] = max(views_matched[n], len(np.unique(feats[n].view[idx])))
    return views_matched


def discriminating_views(feats: LiftedFeatures, index_per_hypothesis: Sequence[np.ndarray], num_views: int,
                          count: int) -> list[int]:
    """Up to ``count`` views of a NeRF where the hypotheses' inlier counts differ most (where one hypothesis explains
    content the others do not), then the best-supported ones."""
    counts = np.stack([np.bincount(feats.view[idx], minlength=num_views) for idx in index_per_hypothesis])
    spread, support = counts.max(0) - counts.min(0), counts.sum(0)
    order = np.lexsort((-support, -spread))
    return [int(v) for v in order if support[v] > 0][:count]


def score_hypotheses(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], feats: Sequence[LiftedFeatures], m: Matches3D,
    hyps: list[Hypothesis], intr: Intrinsics, config: RegistrationConfig,
) -> None:
    """Each hypothesis of the pair (a, b) scored by cross-rendering, on the same views for every hypothesis (both
    directions, those where their inliers differ most first): its worst view's NCC. Repeated structure makes a wrong
    hypothesis look right in most views; it shows where the scene is not symmetric, in its worst view."""
    a, b = m.a, m.b
    n = config.known_geometry.hypothesis_views
    views_a = discriminating_views(feats[a], [m.ia[h.inliers] for h in hyps], len(views[a].c2w), n)
    views_b = discriminating_views(feats[b], [m.ib[h.inliers] for h in hyps], len(views[b].c2w), n)
    for h in hyps:
        # at the resolution the NCC compares anyway (it block-averages by ncc_downsample): 16x fewer rays at 4
        reduce = config.ncc_downsample
        s_ab = view_nccs(views[a], renderers[b], sim3.invert_sim3(h.T), views_a, intr, config, reduce=reduce)
        s_ba = view_nccs(views[b], renderers[a], h.T, views_b, intr, config, reduce=reduce)
        scores = np.concatenate([s_ab, s_ba])
        h.score = float(np.min(scores[np.isfinite(scores)])) if np.isfinite(scores).any() else float("nan")


def ransac_max_error(feats: Sequence[LiftedFeatures], m: Matches3D, config: RegistrationConfig) -> float:
    """The pair's RANSAC inlier threshold in a's units: a fraction of a's matched points' camera distances."""
    scale = float(np.median(feats[m.a].distance[m.ia])) if len(m.ia) else 1.0
    return config.known_geometry.ransac_max_error * scale


def pair_hypotheses(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], feats: Sequence[LiftedFeatures], m: Matches3D,
    intr: Intrinsics, config: RegistrationConfig, console: Console,
) -> list[Hypothesis]:
    """The SIM(3) hypotheses ``T_b->a`` of the pair's 3D matches, scored by cross-rendering when they compete."""
    a, b = m.a, m.b
    hyps = sim3_hypotheses(feats[b].points[m.ib], feats[a].points[m.ia], ransac_max_error(feats, m, config),
                           config.known_geometry, config.sfm.seed)  # fmt: skip
    if len(hyps) > 1:
        with console.status(f"known geometry: scoring {len(hyps)} transforms of {renderers[a].name} / "
                            f"{renderers[b].name} by cross-rendering"):  # fmt: skip
            score_hypotheses(renderers, views, feats, m, hyps, intr, config)
    return hyps


def pair_summary(
    feats: Sequence[LiftedFeatures], m: Matches3D, hyps: Sequence[Hypothesis], chosen: int | None,
    config: RegistrationConfig,
) -> dict:
    """What the record keeps of one matched pair: its 3D matches, hypotheses and the chosen one."""
    return {
        "view_pairs": m.view_pairs, "matches": len(m.ia), "ransac_max_error": ransac_max_error(feats, m, config),
        "hypotheses": [{"T_j_to_i": json_matrix(h.T), "inliers": len(h.inliers),
                        "self_check_ncc": None if h.score is None else json_float(h.score)} for h in hyps],
        "chosen": chosen,
    }  # fmt: skip


def choose_hypothesis(hyps: list[Hypothesis], names: tuple[str, str], config: RegistrationConfig) -> int:
    """The index of the best-scored hypothesis; an ambiguity (the runner-up passes the self-check's threshold and
    scores within the margin) is an error naming both scores."""
    if len(hyps) == 1:
        return 0
    scores = np.array([h.score if h.score is not None and np.isfinite(h.score) else -np.inf for h in hyps])
    order = np.argsort(-scores, kind="stable")
    best, second = scores[order[0]], scores[order[1]]
    margin = config.known_geometry.ambiguity_margin
    if second >= config.ncc_threshold and best - second < margin:
        angle = sim3.rotation_angle_deg(sim3.decompose_sim3(hyps[order[0]].T)[0]
                                        @ sim3.decompose_sim3(hyps[order[1]].T)[0].T)  # fmt: skip
        raise RegistrationError(
            f"{names[0]} and {names[1]}: ambiguous: two transforms {float(angle):.0f} deg apart both pass the "
            f"cross-render self-check (NCC {best:.2f} and {second:.2f}, margin {margin}); the overlap looks "
            "symmetric: render views that see something unique to one side (--sampling.source both, more poses)"
        )
    return int(order[0])


def chain_from_reference(
    chosen: dict[tuple[int, int], Hypothesis], tree: Sequence[tuple[int, int]], ref: int, k: int
) -> np.ndarray:
    """NeRF -> reference SIM(3)s composed along the tree's chosen pairwise transforms (``T_b->a`` for a < b)."""
    T = np.full((k, 4, 4), np.nan)
    T[ref] = np.eye(4)
    forward = {tuple(pair) for pair in tree}
    for parent, child in tree_edges(tree, ref):  # p_ref = T_a p_a = T_a T_b->a p_b
        if (parent, child) in forward:
            T[child] = T[parent] @ chosen[(parent, child)].T
        else:
            T[child] = T[parent] @ sim3.invert_sim3(chosen[(child, parent)].T)
    return T


def check_depth(renderers: Sequence[Renderer]) -> None:
    """Before anything is rendered: every renderer gives depth (the known-geometry and graph modes lift with it)."""
    for r in renderers:
        if not gives_depth(r):
            raise RegistrationError(f"{r.name}: its renderer gives no depth; use --mode sfm")


def render_one(
    renderer: Renderer, sampling: PoseSamplingConfig, renders_root: Path, console: Console | None
) -> ViewSet:
    """One NeRF's renders with depth, made or reused (a task of the graph mode: ``console`` None is quiet)."""
    return render_views_cached(renderer, sampling, renders_root, console or Console(quiet=True), depth=True)


def render_and_lift(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path, console: Console, intr: Intrinsics,
    min_views: int, timings: dict[str, float], executor: Executor | None = None,
) -> tuple[list[ViewSet], list[LiftedFeatures]]:
    """Render every NeRF with depth (or reuse the renders) and lift its keypoints to 3D, one task per NeRF on
    ``executor`` (default: in this process); a NeRF with too few reliable keypoints is an error naming it. Adds the
    steps' seconds to ``timings``."""
    executor = executor or SerialExecutor()
    task_console = console if executor.name == "serial" else None
    kg = config.known_geometry
    t0 = time.perf_counter()
    views = executor.map(render_one, [(r, config.sampling, work_dir / "renders", task_console) for r in renderers],
                         "render", uses_gpu=True)  # fmt: skip
    timings["render"] = time.perf_counter() - t0
    check_kept_views(views, min_views, config.sampling)

    t0 = time.perf_counter()
    threads = executor.task_threads(config.sfm.num_threads)
    with console.status("known geometry: SIFT keypoints lifted to 3D with the rendered depth"):
        feats = executor.map(lift_keypoints, [(vs, intr, kg, threads, config.sfm.verbose) for vs in views], "lift")
    for vs, f in zip(views, feats, strict=True):
        if len(f.view) < kg.min_inliers:
            raise RegistrationError(
                f"{vs.name}: only {len(f.view)} of {f.counts['detected']} keypoints have reliable, multi-view "
                f"consistent depth (need {kg.min_inliers}); the renders see too little texture or the NeRF's depth "
                f"is unreliable: {SUGGESTION}, or use --mode sfm"
            )
    timings["features"] = time.perf_counter() - t0
    return views, feats
