"""The registration pipeline: the automatic pose-source cascade, one attempt composed of the steps, and the
nerfstudio-run entry point.

One attempt (:func:`register_once`), mode ``sfm`` (the paper's): render
(:mod:`~nerfuser_ns.registration.render_cache`) -> SfM (:mod:`~nerfuser_ns.registration.sfm`) -> per-NeRF SIM(3)
(:mod:`~nerfuser_ns.registration.estimate`) -> rigid-set bundle adjustment (:mod:`~nerfuser_ns.registration.refine`)
-> cross-render self-check (:mod:`~nerfuser_ns.registration.self_check`) -> the record
(:mod:`~nerfuser_ns.registration.record`). Mode ``known-geometry`` (ours, :func:`register_known_geometry`): render
with depth -> keypoints lifted to 3D, candidate view pairs, 3D-3D matches, SIM(3) hypotheses scored by the self-check
(:mod:`~nerfuser_ns.registration.known_geometry`, :mod:`~nerfuser_ns.registration.retrieval`) -> joint solve ->
rigid-set bundle adjustment on the matches -> self-check -> the record. Mode ``graph`` (ours, for many NeRFs,
:func:`register_graph`): render with depth -> keypoints lifted to 3D -> candidate NeRF pairs (retrieval, or the
neighbours given) -> each pair registered on known geometry and cross-render checked (an edge, or a rejected pair) ->
cycle check and robust pose-graph solve (:mod:`~nerfuser_ns.registration.pose_graph`) -> self-check -> the record.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import (
    CONSOLE,
    DEFAULT_RENDER_SIZE,
    SUGGESTION,
    PoseSamplingConfig,
    RegistrationConfig,
    RegistrationError,
    RegistrationFailed,
    json_float,
    json_matrix,
    validate_settings,
)
from nerfuser_ns.registration.distributed import Executor, SerialExecutor, make_executor
from nerfuser_ns.registration.estimate import estimate_transforms
from nerfuser_ns.registration.known_geometry import (
    Hypothesis,
    LiftedFeatures,
    Matches3D,
    joint_solve,
    lift_keypoints,
    match_pair,
    sim3_hypotheses,
)
from nerfuser_ns.registration.pose_graph import Edge, PoseGraphError, require_gtsam, solve_pose_graph
from nerfuser_ns.registration.record import (
    build_known_geometry_result,
    build_result,
    graph_section,
    work_dir_for,
    write_registration,
)
from nerfuser_ns.registration.refine import refine_on_matches, refine_transforms
from nerfuser_ns.registration.render_cache import ViewSet, check_kept_views, render_key, render_views_cached
from nerfuser_ns.registration.retrieval import (
    assign_words,
    build_vocabulary,
    candidate_nerf_pairs,
    candidate_pairs,
    nerf_pair_scores,
    tfidf_similarity,
    view_histograms,
)
from nerfuser_ns.registration.self_check import (
    CrossRenderCheck,
    best_views,
    covisibility,
    cross_render_check,
    failure_message,
    passed,
    spanning_pairs,
    view_nccs,
)
from nerfuser_ns.registration.sfm import check_registered_views, run_sfm
from nerfuser_ns.renderers import NerfstudioRenderer, Renderer


@dataclass
class SamplingChoice:
    """One pose-sampling setting to try, and why it was chosen."""

    config: RegistrationConfig
    """The registration settings with a concrete pose source and render camera."""
    reason: str
    """Why this source and camera (printed and recorded)."""


def _training_cameras_available(renderer: Renderer) -> str | None:
    """None when the renderer's training poses can be read, else the reason why not (one line)."""
    try:
        poses = renderer.training_poses()
    except (RegistrationError, ValueError, OSError) as e:  # runs.RunLoadError is a ValueError
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    return None if poses is not None and len(poses) > 0 else "it has no training poses"


def resolve_sampling(renderers: Sequence[Renderer], config: RegistrationConfig) -> list[SamplingChoice]:
    """The pose-sampling settings to try, in order: the user's choice, or for ``source="auto"`` the training poses
    (then training + hemisphere, then the hemisphere) when every run's dataset is readable, else the hemisphere.

    The render camera defaults to the reference run's training cameras' horizontal field of view and aspect, with
    ``size`` pixels along the longer side; :data:`DEFAULT_RENDER_SIZE` when they are unknown.
    """
    sc = config.sampling
    k = len(renderers)
    missing = {}
    if sc.source == "auto" or sc.width is None or sc.height is None or sc.fov_deg is None:
        for i, r in enumerate(renderers):
            why = _training_cameras_available(r)
            if why is not None:
                missing[i] = why
    width, height, fov = sc.width, sc.height, sc.fov_deg
    camera_note = "render size and field of view as given"
    if width is None or height is None or fov is None:
        ref = config.reference % k if -k <= config.reference < k else 0
        intr = None if ref in missing else getattr(renderers[ref], "training_intrinsics", lambda: None)()
        if intr is not None:
            factor = sc.size / max(intr.width, intr.height)
            auto_w, auto_h = max(8, round(intr.width * factor)), max(8, round(intr.height * factor))
            auto_fov = math.degrees(2 * math.atan2(intr.width / 2, intr.fx))
            camera_note = f"render camera from {renderers[ref].name}'s training cameras"
        else:
            auto_w, auto_h, auto_fov = DEFAULT_RENDER_SIZE
            camera_note = "render camera {}x{} at {:g} deg (the reference run's training cameras are unknown)".format(
                *DEFAULT_RENDER_SIZE)
        width = auto_w if width is None else width
        height = auto_h if height is None else height
        fov = auto_fov if fov is None else fov
    if sc.source != "auto":
        sources = [(sc.source, "as given")]
    elif missing:
        i, why = next(iter(missing.items()))
        sources = [("hemisphere", f"training poses unavailable ({renderers[i].name}: {why})")]
    else:
        sources = [("training", "every run's dataset is readable"),
                   ("both", "the training poses alone did not register"),
                   ("hemisphere", "neither the training poses nor training + hemisphere registered")]  # fmt: skip
    out = []
    for source, why in sources:
        sampling = replace(sc, source=source, width=int(width), height=int(height), fov_deg=float(fov))
        out.append(SamplingChoice(replace(config, sampling=sampling), f"{why}; {camera_note}"))
    return out


def register(
    renderers: Sequence[Renderer],
    config: RegistrationConfig | None = None,
    work_dir: Path | str = Path("nerfuser_register_work"),
    console: Console = CONSOLE,
) -> dict:
    """Register N >= 2 renderers; returns the registration record (what :func:`write_registration` stores).

    With ``sampling.source="auto"`` (the default) the pose sources of :func:`resolve_sampling` are tried in order until
    one registers; each choice and each fallback is printed. Raises :class:`RegistrationError` (one line, naming the
    NeRF) when the result cannot be trusted.
    """
    config = config or RegistrationConfig()
    if len(renderers) < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {len(renderers)}")
    choices = resolve_sampling(renderers, config)
    for choice in choices:
        validate_settings(choice.config)
    tried = []
    for n, choice in enumerate(choices):
        sc = choice.config.sampling
        console.print(f"pose sampling: [bold]{sc.source}[/] ({choice.reason}), renders {sc.width}x{sc.height} at "
                      f"{sc.fov_deg:.1f} deg")  # fmt: skip
        try:
            record = register_once(renderers, choice.config, work_dir, console)
        except RegistrationError as e:
            if n + 1 == len(choices):
                raise
            reason = str(e).splitlines()[0]
            tried.append({"source": sc.source, "error": reason})
            console.print(f"[yellow]{sc.source} poses did not register: {reason}[/]")
            continue
        record["sampling_choice"] = {"requested": config.sampling.source, "source": sc.source,
                                     "reason": choice.reason, "tried_before": tried}  # fmt: skip
        return record
    raise AssertionError("unreachable")  # pragma: no cover


def _check_inputs(renderers: Sequence[Renderer], config: RegistrationConfig) -> tuple[int, int, Intrinsics]:
    """Before anything is rendered: the NeRFs and settings make sense. Returns the reference index, the views each
    NeRF needs in the SfM model, and the render intrinsics."""
    k = len(renderers)
    names = [r.name for r in renderers]
    if k < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {k}")
    if not -k <= config.reference < k:
        raise RegistrationError(f"reference index {config.reference} out of range for {k} NeRFs")
    if config.estimator not in ("nerfuser", "nerfuser-median", "umeyama-ransac"):
        raise RegistrationError(f"unknown estimator {config.estimator!r}")
    keys = [render_key(r, config.sampling) for r in renderers]
    for a in range(k):
        for b in range(a):
            if keys[a] == keys[b]:
                raise RegistrationError(f"{names[a]}: passed twice (same run as {names[b]}); pass distinct runs")
    min_views = max(config.min_registered_views, 3 if config.estimator == "umeyama-ransac" else 2)
    return config.reference % k, min_views, validate_settings(config)


def register_once(
    renderers: Sequence[Renderer],
    config: RegistrationConfig,
    work_dir: Path | str,
    console: Console,
) -> dict:
    """One registration with concrete pose-sampling settings (see :func:`register`); returns the record.

    Raises :class:`RegistrationFailed` (with the record) when the self-check rejects the solution.
    """
    if config.mode == "known-geometry":
        return register_known_geometry(renderers, config, work_dir, console)
    if config.mode == "graph":
        return register_graph(renderers, config, work_dir, console)
    work_dir = Path(work_dir)
    ref, min_views, intr = _check_inputs(renderers, config)
    timings: dict[str, float] = {}

    # 1. Render (or reuse the renders of a previous run).
    t0 = time.perf_counter()
    views = [render_views_cached(r, config.sampling, work_dir / "renders", console) for r in renderers]
    timings["render"] = time.perf_counter() - t0
    check_kept_views(views, min_views, config.sampling)

    # 2. One SfM over the union (reused SfM steps take no time in this run).
    sfm = run_sfm(views, intr, config.sfm, work_dir, console)
    for step in ("features", "matching", "mapping"):
        timings[step] = 0.0 if sfm.reused else sfm.timings.get(step, 0.0)
    check_registered_views(sfm, views, min_views)

    # 3. Per NeRF: its SIM(3) into the SfM frame C, then into the reference frame; 4. refined.
    t0 = time.perf_counter()
    estimates = estimate_transforms(views, sfm, config)
    T_to_C = np.stack([e.estimate.T for e in estimates])
    T_to_ref = sim3.to_reference_frame(T_to_C, ref)
    refinement = None
    if config.refine:
        with console.status("refining the transforms (rigid-set bundle adjustment)"):
            T_to_ref, refinement = refine_transforms(views, sfm, T_to_C, ref, intr, config.refine_loss_scale_px)
        T_to_C = T_to_C[ref] @ T_to_ref
    timings["solve"] = time.perf_counter() - t0

    # 5. Overlap between NeRFs (3D points seen by both) and the cross-render self-check.
    overlap = covisibility(views, sfm)
    checked_pairs = spanning_pairs(overlap) if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config,
                                    best_views(views, sfm, checked_pairs))  # fmt: skip
    timings["self_check"] = time.perf_counter() - t0

    # 6. The record; fail clearly when the self-check says the SfM merged the wrong things.
    record = build_result(
        renderers=renderers, views=views, sfm=sfm, estimates=estimates, T_to_ref=T_to_ref, T_to_C=T_to_C,
        refinement=refinement, overlap=overlap, checks=checks, config=config, intrinsics=intr, timings=timings,
    ).to_record()
    failure = failure_message(checks, [r.name for r in renderers], config)
    if failure is not None:
        raise RegistrationFailed(failure, record)
    return record


def _view_similarity(
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


def _match_nerfs(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], similarity: list[list[np.ndarray]], a: int, b: int,
    config: RegistrationConfig,
) -> Matches3D:
    """3D-3D matches of NeRFs a and b over their candidate view pairs."""
    kg = config.known_geometry
    view_pairs = [(i, j) for i, j in candidate_pairs(similarity[a][b], kg.candidate_views, kg.exhaustive_max_pairs)
                  if views[a].kept[i] and views[b].kept[j]]  # fmt: skip
    return match_pair(feats[a], feats[b], view_pairs, kg.ratio, a, b)


def _matches_per_pair(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], config: RegistrationConfig
) -> dict[tuple[int, int], Matches3D]:
    """3D-3D matches of every NeRF pair, over candidate view pairs from a vocabulary of the renders' descriptors."""
    similarity = _view_similarity(feats, views, config)
    return {(a, b): _match_nerfs(feats, views, similarity, a, b, config)
            for a in range(len(feats)) for b in range(a + 1, len(feats))}  # fmt: skip


def _views_by_support(feats: LiftedFeatures, index: np.ndarray, num_views: int) -> list[int]:
    """Views of a NeRF ordered by how many of the given keypoints they hold, most first (views holding none left
    out)."""
    counts = np.bincount(feats.view[index], minlength=num_views)
    return [int(v) for v in np.argsort(-counts, kind="stable") if counts[v] > 0]


def _check_views(
    feats: Sequence[LiftedFeatures], views: Sequence[ViewSet], matches: dict[tuple[int, int], Matches3D],
    chosen: dict[tuple[int, int], Hypothesis], pairs: Sequence[tuple[int, int]],
) -> dict[tuple[int, int], list[int]]:
    """The self-check's views of each checked pair, both ways: those with the chosen hypothesis' inliers first."""
    order = {}
    for i, j in pairs:
        m, h = matches[(i, j)], chosen[(i, j)]
        order[(i, j)] = _views_by_support(feats[i], m.ia[h.inliers], len(views[i].c2w))
        order[(j, i)] = _views_by_support(feats[j], m.ib[h.inliers], len(views[j].c2w))
    return order


def _views_matched(
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


def _discriminating_views(feats: LiftedFeatures, index_per_hypothesis: Sequence[np.ndarray], num_views: int,
                          count: int) -> list[int]:
    """Up to ``count`` views of a NeRF where the hypotheses' inlier counts differ most (where one hypothesis explains
    content the others do not), then the best-supported ones."""
    counts = np.stack([np.bincount(feats.view[idx], minlength=num_views) for idx in index_per_hypothesis])
    spread, support = counts.max(0) - counts.min(0), counts.sum(0)
    order = np.lexsort((-support, -spread))
    return [int(v) for v in order if support[v] > 0][:count]


def _score_hypotheses(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], feats: Sequence[LiftedFeatures], m: Matches3D,
    hyps: list[Hypothesis], intr: Intrinsics, config: RegistrationConfig,
) -> None:
    """Each hypothesis of the pair (a, b) scored by cross-rendering, on the same views for every hypothesis (both
    directions, those where their inliers differ most first): its worst view's NCC. Repeated structure makes a wrong
    hypothesis look right in most views; it shows where the scene is not symmetric, in its worst view."""
    a, b = m.a, m.b
    n = config.known_geometry.hypothesis_views
    views_a = _discriminating_views(feats[a], [m.ia[h.inliers] for h in hyps], len(views[a].c2w), n)
    views_b = _discriminating_views(feats[b], [m.ib[h.inliers] for h in hyps], len(views[b].c2w), n)
    for h in hyps:
        # at the resolution the NCC compares anyway (it block-averages by ncc_downsample): 16x fewer rays at 4
        reduce = config.ncc_downsample
        s_ab = view_nccs(views[a], renderers[b], sim3.invert_sim3(h.T), views_a, intr, config, reduce=reduce)
        s_ba = view_nccs(views[b], renderers[a], h.T, views_b, intr, config, reduce=reduce)
        scores = np.concatenate([s_ab, s_ba])
        h.score = float(np.min(scores[np.isfinite(scores)])) if np.isfinite(scores).any() else float("nan")


def _ransac_max_error(feats: Sequence[LiftedFeatures], m: Matches3D, config: RegistrationConfig) -> float:
    """The pair's RANSAC inlier threshold in a's units: a fraction of a's matched points' camera distances."""
    scale = float(np.median(feats[m.a].distance[m.ia])) if len(m.ia) else 1.0
    return config.known_geometry.ransac_max_error * scale


def _pair_hypotheses(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], feats: Sequence[LiftedFeatures], m: Matches3D,
    intr: Intrinsics, config: RegistrationConfig, console: Console,
) -> list[Hypothesis]:
    """The SIM(3) hypotheses ``T_b->a`` of the pair's 3D matches, scored by cross-rendering when they compete."""
    a, b = m.a, m.b
    hyps = sim3_hypotheses(feats[b].points[m.ib], feats[a].points[m.ia], _ransac_max_error(feats, m, config),
                           config.known_geometry, config.sfm.seed)  # fmt: skip
    if len(hyps) > 1:
        with console.status(f"known geometry: scoring {len(hyps)} transforms of {renderers[a].name} / "
                            f"{renderers[b].name} by cross-rendering"):  # fmt: skip
            _score_hypotheses(renderers, views, feats, m, hyps, intr, config)
    return hyps


def _pair_summary(
    feats: Sequence[LiftedFeatures], m: Matches3D, hyps: Sequence[Hypothesis], chosen: int | None,
    config: RegistrationConfig,
) -> dict:
    """What the record keeps of one matched pair: its 3D matches, hypotheses and the chosen one."""
    return {
        "view_pairs": m.view_pairs, "matches": len(m.ia), "ransac_max_error": _ransac_max_error(feats, m, config),
        "hypotheses": [{"T_j_to_i": json_matrix(h.T), "inliers": len(h.inliers),
                        "self_check_ncc": None if h.score is None else json_float(h.score)} for h in hyps],
        "chosen": chosen,
    }  # fmt: skip


def _choose(hyps: list[Hypothesis], names: tuple[str, str], config: RegistrationConfig) -> int:
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


def _chain_from_reference(
    chosen: dict[tuple[int, int], Hypothesis], tree: Sequence[tuple[int, int]], ref: int, k: int
) -> np.ndarray:
    """NeRF -> reference SIM(3)s composed along the tree's chosen pairwise transforms (``T_b->a`` for a < b)."""
    T = np.full((k, 4, 4), np.nan)
    T[ref] = np.eye(4)
    done = {ref}
    while len(done) < k:
        for a, b in tree:
            if a in done and b not in done:  # p_ref = T_a p_a = T_a T_b->a p_b
                T[b] = T[a] @ chosen[(a, b)].T
                done.add(b)
            elif b in done and a not in done:
                T[a] = T[b] @ sim3.invert_sim3(chosen[(a, b)].T)
                done.add(a)
    return T


MIN_DEPTH_SIGMA = 1e-4
"""Floor of the relative depth noise the known-geometry refinement assumes (exact depth would weigh infinitely)."""


def _check_depth(renderers: Sequence[Renderer]) -> None:
    """Before anything is rendered: every renderer gives depth (the known-geometry and graph modes lift with it)."""
    for r in renderers:
        if "depth" not in inspect.signature(r.render).parameters:
            raise RegistrationError(f"{r.name}: its renderer gives no depth; use --mode sfm")


def _render_one(
    renderer: Renderer, sampling: PoseSamplingConfig, renders_root: Path, console: Console | None
) -> ViewSet:
    """One NeRF's renders with depth, made or reused (a task of the graph mode: ``console`` None is quiet)."""
    return render_views_cached(renderer, sampling, renders_root, console or Console(quiet=True), depth=True)


def _render_and_lift(
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
    views = executor.map(_render_one, [(r, config.sampling, work_dir / "renders", task_console) for r in renderers])
    timings["render"] = time.perf_counter() - t0
    check_kept_views(views, min_views, config.sampling)

    t0 = time.perf_counter()
    with console.status("known geometry: SIFT keypoints lifted to 3D with the rendered depth"):
        feats = executor.map(lift_keypoints, [(vs, intr, kg, config.sfm.num_threads, config.sfm.verbose)
                                              for vs in views])  # fmt: skip
    for vs, f in zip(views, feats, strict=True):
        if len(f.view) < kg.min_inliers:
            raise RegistrationError(
                f"{vs.name}: only {len(f.view)} of {f.counts['detected']} keypoints have reliable, multi-view "
                f"consistent depth (need {kg.min_inliers}); the renders see too little texture or the NeRF's depth "
                f"is unreliable: {SUGGESTION}, or use --mode sfm"
            )
    timings["features"] = time.perf_counter() - t0
    return views, feats


def register_known_geometry(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path | str, console: Console
) -> dict:
    """One registration on known geometry (mode ``known-geometry``, ours); returns the record.

    Raises :class:`RegistrationError` (one line) when a NeRF has too few reliable keypoints, a NeRF matches no other,
    or two hypotheses are equally good; :class:`RegistrationFailed` (with the record) when the self-check rejects the
    solution.
    """
    work_dir = Path(work_dir)
    ref, min_views, intr = _check_inputs(renderers, config)
    _check_depth(renderers)
    kg = config.known_geometry
    names = [r.name for r in renderers]
    k = len(renderers)
    timings: dict[str, float] = {}
    views, feats = _render_and_lift(renderers, config, work_dir, console, intr, min_views, timings)

    t0 = time.perf_counter()
    with console.status("known geometry: matching keypoints across NeRFs"):
        matches = _matches_per_pair(feats, views, config)
    timings["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    hypotheses = {pair: _pair_hypotheses(renderers, views, feats, m, intr, config, console)
                  for pair, m in matches.items()}  # fmt: skip
    timings["hypotheses"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    choice = {pair: _choose(hyps, (names[pair[0]], names[pair[1]]), config)
              for pair, hyps in hypotheses.items() if hyps}  # fmt: skip
    chosen = {pair: hypotheses[pair][n] for pair, n in choice.items()}
    overlap = np.zeros((k, k), dtype=int)
    for (a, b), h in chosen.items():
        overlap[a, b] = overlap[b, a] = len(h.inliers)
    tree = spanning_pairs(overlap)
    for a, b in tree:
        if overlap[a, b] == 0:
            best = max((len(h.inliers) for p, hs in hypotheses.items() if b in p for h in hs), default=0)
            raise RegistrationError(
                f"{names[b]}: no SIM(3) to the other NeRFs has {kg.min_inliers} inlier 3D matches (best {best}); "
                f"the NeRFs may not overlap: {SUGGESTION}"
            )
    T_initial = _chain_from_reference(chosen, tree, ref, k)
    # pairs off the tree join the solve only when they agree with the tree (a wrong link would pull it apart)
    links, linked, dropped = [], [], []
    for (a, b), h in chosen.items():
        implied = sim3.relative_sim3(T_initial[a], T_initial[b])  # b -> a
        err = sim3.sim3_errors(h.T, implied)
        if (a, b) not in tree and (err.r_err_deg > 5.0 or err.s_err > 0.1):
            dropped.append([names[a], names[b]])
            continue
        ia, ib = matches[(a, b)].ia[h.inliers], matches[(a, b)].ib[h.inliers]
        s_a, s_b = (float(sim3.decompose_sim3(T_initial[n])[2]) for n in (a, b))
        sigma = 0.5 * (s_a * feats[a].distance[ia] + s_b * feats[b].distance[ib])
        links.append((a, b, feats[a].points[ia], feats[b].points[ib], sigma))
        linked.append((a, b, ia, ib))
    T_to_ref, solve = joint_solve(T_initial, ref, links, kg.loss_scale)
    refinement = None
    if config.refine and solve["used"]:
        # the depth's noise, as the joint solve's residuals measure it, weighs it against the reprojections
        depth_sigma = max(solve["median_relative_after"], MIN_DEPTH_SIGMA)
        with console.status("refining the transforms (rigid-set bundle adjustment on the matches)"):
            T_to_ref, refinement = refine_on_matches(views, feats, linked, T_to_ref, ref, intr,
                                                     config.refine_loss_scale_px, depth_sigma)  # fmt: skip
    timings["solve"] = time.perf_counter() - t0

    checked_pairs = tree if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config,
                                    _check_views(feats, views, matches, chosen, checked_pairs))  # fmt: skip
    timings["self_check"] = time.perf_counter() - t0
    views_matched = _views_matched(feats, matches, chosen, k)
    summary = {
        "keypoints": {names[i]: f.counts for i, f in enumerate(feats)},
        "pairs": [{"names": [names[a], names[b]], **_pair_summary(feats, m, hypotheses[(a, b)], choice.get((a, b)),
                                                                  config)}
                  for (a, b), m in matches.items()],
        "tree": [[names[a], names[b]] for a, b in tree],
        "dropped_pairs": dropped,
        "joint_solve": solve,
    }  # fmt: skip
    record = build_known_geometry_result(
        renderers=renderers, views=views, T_to_ref=T_to_ref, T_initial=T_initial, views_matched=views_matched,
        overlap=overlap, checks=checks, config=config, timings=timings, known_geometry=summary,
        refinement=refinement,
    ).to_record()
    failure = failure_message(checks, names, config)
    if failure is not None:
        raise RegistrationFailed(failure, record)
    return record


@dataclass
class PairOutcome:
    """One candidate pair registered on known geometry: an edge (``choice``) or a rejection (``rejected``)."""

    matches: Matches3D
    hypotheses: list[Hypothesis]
    choice: int | None
    """Index of the chosen hypothesis (``T_b->a``), None when rejected."""
    rejected: str | None
    """Why the pair gives no edge."""
    check: CrossRenderCheck | None
    """The chosen hypothesis' cross-render check (None when none was run)."""


def _register_pair(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], feats: Sequence[LiftedFeatures],
    similarity: list[list[np.ndarray]], a: int, b: int, intr: Intrinsics, config: RegistrationConfig,
    console: Console | None,
) -> PairOutcome:
    """Register NeRFs a < b on known geometry: 3D matches, hypotheses (competing ones scored by cross-rendering), the
    choice, then the chosen one cross-rendered. A task of the graph mode (``console`` None: quiet)."""
    console = console or Console(quiet=True)
    kg = config.known_geometry
    names = (renderers[a].name, renderers[b].name)
    with console.status(f"graph: registering {names[0]} / {names[1]}"):
        m = _match_nerfs(feats, views, similarity, a, b, config)
    hyps = _pair_hypotheses(renderers, views, feats, m, intr, config, console)
    if not hyps:
        why = f"no SIM(3) has {kg.min_inliers} inlier 3D matches ({len(m.ia)} matches over {m.view_pairs} view pairs)"
        return PairOutcome(m, hyps, None, why, None)
    try:
        n = _choose(hyps, names, config)
    except RegistrationError as e:  # ambiguous: an edge nobody can trust, not a failure of the whole graph
        return PairOutcome(m, hyps, None, str(e).split(": ", 1)[1], None)
    if config.self_check_views <= 0:
        return PairOutcome(m, hyps, n, None, None)
    # shared textures can give unrelated NeRFs a confident SIM(3): cross-render the pair before it joins
    T_pair = np.broadcast_to(np.eye(4), (len(renderers), 4, 4)).copy()
    T_pair[b] = hyps[n].T
    check = cross_render_check(renderers, views, T_pair, [(a, b)], intr, config,
                               _check_views(feats, views, {(a, b): m}, {(a, b): hyps[n]}, [(a, b)]))[0]  # fmt: skip
    if not passed(check, config):
        what = "saw nothing in common" if not np.isfinite(check.score) else f"NCC {check.score:.2f}"
        return PairOutcome(m, hyps, None, f"cross-render self-check failed ({what} < {config.ncc_threshold})", check)
    return PairOutcome(m, hyps, n, None, check)


def _parse_neighbours(items: Sequence[str], names: Sequence[str]) -> list[tuple[int, int]]:
    """``--graph.neighbours a:b ...`` as sorted index pairs (i < j); NeRFs by name or by index."""
    k = len(names)

    def index(token: str, item: str) -> int:
        token = token.strip()
        if names.count(token) == 1:
            return names.index(token)
        if token.lstrip("-").isdigit() and 0 <= int(token) < k:
            return int(token)
        raise RegistrationError(f"--graph.neighbours {item}: {token!r} is neither a NeRF name ({', '.join(names)}) "
                                f"nor an index 0..{k - 1}")  # fmt: skip

    pairs = set()
    for item in items:
        a, _, b = str(item).partition(":")
        i, j = index(a, item), index(b, item)
        if i == j:
            raise RegistrationError(f"--graph.neighbours {item}: a NeRF cannot be its own neighbour")
        pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def register_graph(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path | str, console: Console
) -> dict:
    """One registration of many NeRFs as a SIM(3) pose graph (mode ``graph``, ours); returns the record.

    Renders with depth and lifts keypoints as the known-geometry mode, finds candidate NeRF pairs from the renders'
    visual words (or takes ``--graph.neighbours``), registers each candidate pair on known geometry (an edge, or a
    rejected pair with its reason), then checks the edges around cycles and solves them together
    (:func:`~nerfuser_ns.registration.pose_graph.solve_pose_graph`). The spanning tree's pairs are cross-render
    checked. Raises :class:`RegistrationError` (one line) when GTSAM is missing, a NeRF has too few reliable keypoints
    or no registered pair reaches it; :class:`RegistrationFailed` (with the record) when the self-check rejects the
    solution.
    """
    work_dir = Path(work_dir)
    ref, min_views, intr = _check_inputs(renderers, config)
    _check_depth(renderers)
    try:
        require_gtsam()
    except PoseGraphError as e:
        raise RegistrationError(str(e)) from None
    gc = config.graph
    given = _parse_neighbours(gc.neighbours, [r.name for r in renderers])
    executor = make_executor(gc.executor, gc.ray_address)
    try:
        return _register_graph(renderers, config, work_dir, console, ref, min_views, intr, given, executor)
    finally:
        executor.close()


def _register_graph(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path, console: Console, ref: int,
    min_views: int, intr: Intrinsics, given: list[tuple[int, int]], executor: Executor,
) -> dict:
    """:func:`register_graph` once its inputs are checked, with the executor its tasks run on."""
    gc = config.graph
    names = [r.name for r in renderers]
    k = len(renderers)
    timings: dict[str, float] = {}
    views, feats = _render_and_lift(renderers, config, work_dir, console, intr, min_views, timings, executor)

    t0 = time.perf_counter()
    with console.status("graph: candidate NeRF pairs from the renders' visual words"):
        similarity = _view_similarity(feats, views, config)
    scores = nerf_pair_scores(similarity, gc.score_views)
    candidates = given or candidate_nerf_pairs(scores, gc.min_similarity, gc.top_k)
    source = "neighbours given" if given else "retrieval"
    console.print(f"graph: {len(candidates)} candidate pairs ({source}): "
                  + ", ".join(f"{names[a]}/{names[b]} ({scores[a, b]:.2f})" for a, b in candidates))  # fmt: skip
    timings["retrieval"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matches: dict[tuple[int, int], Matches3D] = {}
    hypotheses: dict[tuple[int, int], list[Hypothesis]] = {}
    choice: dict[tuple[int, int], int] = {}
    rejected: dict[tuple[int, int], str] = {}
    pair_checks: dict[tuple[int, int], CrossRenderCheck] = {}
    # one task per pair; in this process it reports progress on the console, as a Ray task it stays quiet
    task_console = console if executor.name == "serial" else None
    outcomes = executor.map(_register_pair, [(renderers, views, feats, similarity, a, b, intr, config, task_console)
                                             for a, b in candidates])  # fmt: skip
    for (a, b), out in zip(candidates, outcomes, strict=True):
        matches[(a, b)], hypotheses[(a, b)] = out.matches, out.hypotheses
        if out.check is not None:
            pair_checks[(a, b)] = out.check
        if out.rejected is not None:
            rejected[(a, b)] = out.rejected
        else:
            choice[(a, b)] = out.choice
    timings["pairs"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    accepted = sorted(choice)
    chosen = {pair: hypotheses[pair][n] for pair, n in choice.items()}
    edges = [Edge(a, b, chosen[(a, b)].T, float(len(chosen[(a, b)].inliers))) for a, b in accepted]
    # each NeRF's length scale: how far its lifted keypoints lie from their cameras, in its own units
    lengths = np.array([float(np.median(f.distance)) for f in feats])
    try:
        solved = solve_pose_graph(
            k, edges, ref, lengths, names, gc.max_cycle_rotation_deg, gc.max_cycle_translation,
            gc.max_cycle_log_scale, gc.robust,
        )
    except PoseGraphError as e:
        raise RegistrationError(
            f"{e} ({len(edges)} of {len(candidates)} candidate pairs registered); name overlapping pairs with "
            f"--graph.neighbours a:b, or {SUGGESTION}"
        ) from None
    timings["solve"] = time.perf_counter() - t0
    T_to_ref = solved.T_to_reference
    for e in solved.dropped:
        console.print(f"[yellow]graph: dropped {e.reason}[/]")

    checked_pairs = [accepted[n] for n in solved.tree] if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config,
                                    _check_views(feats, views, matches, chosen, checked_pairs))  # fmt: skip
    timings["self_check"] = time.perf_counter() - t0

    kept = {accepted[n]: chosen[accepted[n]] for n, e in enumerate(solved.edges) if e.status != "dropped"}
    overlap = np.zeros((k, k), dtype=int)
    for (a, b), h in kept.items():
        overlap[a, b] = overlap[b, a] = len(h.inliers)
    section = graph_section(
        names=names, scores=scores, candidates=candidates, source=source,
        pairs={pair: {**_pair_summary(feats, matches[pair], hypotheses[pair], choice.get(pair), config),
                      "self_check_ncc": json_float(pair_checks[pair].score) if pair in pair_checks else None}
               for pair in candidates},
        rejected=rejected, accepted=accepted, solved=solved, lengths=lengths,
        keypoints={names[i]: f.counts for i, f in enumerate(feats)},
    )  # fmt: skip
    record = build_known_geometry_result(
        renderers=renderers, views=views, T_to_ref=T_to_ref, T_initial=solved.T_initial,
        views_matched=_views_matched(feats, matches, kept, k), overlap=overlap, checks=checks, config=config,
        timings=timings, known_geometry=None, graph=section,
    )  # fmt: skip
    record = record.to_record()
    failure = failure_message(checks, names, config)
    if failure is not None:
        raise RegistrationFailed(failure, record)
    return record


def register_runs(
    config_paths: Sequence[Path | str],
    output: Path | str,
    config: RegistrationConfig | None = None,
    work_dir: Path | str | None = None,
    names: Sequence[str] | None = None,
    device: str = "cpu",
    console: Console = CONSOLE,
    data_overrides: Sequence[Path | None] | None = None,
) -> dict:
    """Register trained nerfstudio runs from their config.yml files and write the registration file at ``output``.

    ``work_dir`` defaults to ``<output>_work`` (renders and SfM files, reused by later calls). ``data_overrides[i]``
    is run i's dataset folder where its config's path no longer holds it (training poses are read from it). Raises
    :class:`RegistrationError` or ``runs.RunLoadError`` (one line) on bad input; nothing is written then.
    """
    output = Path(output)
    if names is not None and len(names) != len(config_paths):
        raise RegistrationError(f"{len(names)} names for {len(config_paths)} runs")
    if data_overrides is not None and len(data_overrides) != len(config_paths):
        raise RegistrationError(f"{len(data_overrides)} dataset folders for {len(config_paths)} runs")
    renderers = [
        NerfstudioRenderer(
            c, device=device, name=None if names is None else names[i],
            data_override=None if data_overrides is None else data_overrides[i],
        )
        for i, c in enumerate(config_paths)
    ]  # fmt: skip
    work_dir = Path(work_dir) if work_dir is not None else work_dir_for(output)
    record = register(renderers, config, work_dir, console=console)
    write_registration(record, output)
    return record
