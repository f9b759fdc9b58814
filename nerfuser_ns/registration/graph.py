"""Registration of many NeRFs as a SIM(3) pose graph (mode ``graph``, ours): candidate NeRF pairs from the renders,
each registered on known geometry (:mod:`.pairwise`), joined by :mod:`.pose_graph`; tasks in this process or on Ray
(:mod:`.distributed`)."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float, Int
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration.assemble import build_known_geometry_result, graph_section, retrieval_fields
from nerfuser_ns.registration.config import (
    SUGGESTION,
    RegistrationConfig,
    RegistrationError,
    RegistrationFailed,
    json_float,
)
from nerfuser_ns.registration.distributed import Executor, make_executor
from nerfuser_ns.registration.known_geometry import (
    Hypothesis,
    LiftedFeatures,
    Matches3D,
)
from nerfuser_ns.registration.pairwise import (
    check_depth,
    check_views,
    choose_hypothesis,
    match_nerfs,
    pair_hypotheses,
    pair_summary,
    render_and_lift,
    verify_pairs,
    view_similarity,
    views_matched,
)
from nerfuser_ns.registration.pose_graph import Edge, PoseGraphError, require_gtsam, solve_pose_graph
from nerfuser_ns.registration.record import RegistrationResult
from nerfuser_ns.registration.render_cache import (
    ViewSet,
    check_inputs,
)
from nerfuser_ns.registration.retrieval import (
    border_ranks,
    bridging_pairs,
    candidate_nerf_pairs,
    components,
    nerf_pair_scores,
)
from nerfuser_ns.registration.self_check import (
    CrossRenderCheck,
    cross_render_check,
    failure_message,
    pair_failure,
)
from nerfuser_ns.renderers import Renderer


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
        m = match_nerfs(feats, views, similarity, a, b, config)
    hyps = pair_hypotheses(renderers, views, feats, m, intr, config, console)
    if not hyps:
        why = f"no SIM(3) has {kg.min_inliers} inlier 3D matches ({len(m.ia)} matches over {m.view_pairs} view pairs)"
        return PairOutcome(m, hyps, None, why, None)
    try:
        n = choose_hypothesis(hyps, names, config)
    except RegistrationError as e:  # ambiguous: an edge nobody can trust, not a failure of the whole graph
        return PairOutcome(m, hyps, None, str(e).split(": ", 1)[1], None)
    if config.self_check_views <= 0:
        return PairOutcome(m, hyps, n, None, None)
    # shared textures can give unrelated NeRFs a confident SIM(3): cross-render the pair before it joins
    T_pair = np.broadcast_to(np.eye(4), (len(renderers), 4, 4)).copy()
    T_pair[b] = hyps[n].T
    check = cross_render_check(renderers, views, T_pair, [(a, b)], intr, config,
                               check_views(feats, views, {(a, b): m}, {(a, b): hyps[n]}, [(a, b)]))[0]  # fmt: skip
    if (why := pair_failure(check, config)) is not None:
        return PairOutcome(m, hyps, None, why, check)
    return PairOutcome(m, hyps, n, None, check)


def piece_positions(
    k: int, edges: dict[tuple[int, int], np.ndarray], views: Sequence[ViewSet]
) -> Float[np.ndarray, "k 3"]:
    """Each NeRF's mean camera centre in the frame of its piece (the first NeRF of each connected component of
    ``edges``: ``T_b->a`` per pair a < b, composed from that NeRF outwards)."""
    T: list[np.ndarray | None] = [None] * k
    for root in np.unique(components(k, sorted(edges))):
        T[root] = np.eye(4)
        grown = True
        while grown:
            grown = False
            for (a, b), T_ba in edges.items():
                if T[a] is not None and T[b] is None:  # p_root = T_a p_a = T_a T_b->a p_b
                    T[b], grown = T[a] @ T_ba, True
                elif T[b] is not None and T[a] is None:
                    T[a], grown = T[b] @ sim3.invert_sim3(T_ba), True
    return np.stack([sim3.transform_points(T[i], vs.c2w[:, :3, 3]).mean(0) for i, vs in enumerate(views)])


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
) -> RegistrationResult:
    """One registration of many NeRFs as a SIM(3) pose graph (mode ``graph``, ours); returns the result.

    Renders with depth and lifts keypoints as the known-geometry mode, finds candidate NeRF pairs from the renders'
    visual words (or takes ``--graph.neighbours``), registers each candidate pair on known geometry (an edge, or a
    rejected pair with its reason), then checks the edges around cycles and solves them together
    (:func:`~nerfuser_ns.registration.pose_graph.solve_pose_graph`). The spanning tree's pairs are cross-render
    checked. Raises :class:`RegistrationError` (one line) when GTSAM is missing, a NeRF has too few reliable keypoints
    or no registered pair reaches it; :class:`RegistrationFailed` (with the record) when the self-check rejects the
    solution.
    """
    work_dir = Path(work_dir)
    ref, min_views, intr = check_inputs(renderers, config)
    check_depth(renderers)
    try:
        require_gtsam()
    except PoseGraphError as e:
        raise RegistrationError(str(e)) from None
    gc = config.graph
    given = _parse_neighbours(gc.neighbours, [r.name for r in renderers])
    executor = make_executor(gc.executor, gc.ray_address, gc.ray_gpus_per_task, console)
    try:
        return _register_graph(renderers, config, work_dir, console, ref, min_views, intr, given, executor)
    finally:
        executor.close()


PAIR_OUTCOMES_FILE = "graph_pairs.json"
"""Written to the work folder when the registered pairs leave the NeRFs in pieces: what each candidate pair gave."""


def write_pair_outcomes(
    path: Path, names: Sequence[str], scores: Float[np.ndarray, "k k"], verified: Int[np.ndarray, "k k"] | None,
    candidates: Sequence[tuple[int, int]], accepted: Sequence[tuple[int, int]], rejected: dict[tuple[int, int], str],
    source: str, bridging_rounds: int,
) -> Path:
    """Write (atomically) every candidate pair's retrieval score (and verified inliers) and outcome (registered, or
    rejected with the reason) and the pieces the registered pairs leave, so a graph that stayed apart can be read pair
    by pair."""
    piece, registered = components(len(names), accepted), set(accepted)
    pieces = [[names[i] for i in np.flatnonzero(piece == label)] for label in sorted(set(piece.tolist()))]
    record = {
        "candidates_from": source,
        "bridging_rounds": bridging_rounds,
        "pieces": pieces,
        "pairs": [{"names": [names[a], names[b]], **retrieval_fields(scores, verified, a, b),
                   "status": "registered" if (a, b) in registered else "rejected",
                   "reason": rejected.get((a, b))} for a, b in candidates],
    }  # fmt: skip
    return write_text_atomic(path, json.dumps(record, indent=2) + "\n")


def _register_graph(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path, console: Console, ref: int,
    min_views: int, intr: Intrinsics, given: list[tuple[int, int]], executor: Executor,
) -> RegistrationResult:
    """:func:`register_graph` once its inputs are checked, with the executor its tasks run on."""
    gc = config.graph
    names = [r.name for r in renderers]
    k = len(renderers)
    timings: dict[str, float] = {}
    # an earlier run's pair outcomes would describe pairs this run may not try
    (work_dir / PAIR_OUTCOMES_FILE).unlink(missing_ok=True)
    views, feats = render_and_lift(renderers, config, work_dir, console, intr, min_views, timings, executor)

    t0 = time.perf_counter()
    with console.status("graph: candidate NeRF pairs from the renders' visual words"):
        similarity = view_similarity(feats, views, config)
    scores = nerf_pair_scores(similarity, gc.score_views)
    verified = None
    if not given and gc.verify_views > 0:
        console.print(f"graph: verifying all {k * (k - 1) // 2} NeRF pairs (3D matches of their {gc.verify_views} most "
                      "similar view pairs, one RANSAC SIM(3) each)")  # fmt: skip
        verified = verify_pairs(feats, similarity, config, executor)
    # each NeRF's partners ranked by verified inliers where verified, else by the tf-idf score
    rank = scores if verified is None else verified.astype(float)
    candidates = given or candidate_nerf_pairs(rank, gc.min_similarity if verified is None else np.inf, gc.top_k)
    source = "neighbours given" if given else "retrieval"

    def label(a: int, b: int) -> str:
        return f"{names[a]}/{names[b]} (" + (f"{verified[a, b]} inliers)" if verified is not None else
                                             f"{scores[a, b]:.2f})")  # fmt: skip

    console.print(f"graph: {len(candidates)} candidate pairs ({source}): " + ", ".join(label(*p) for p in candidates))
    timings["retrieval"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matches: dict[tuple[int, int], Matches3D] = {}
    hypotheses: dict[tuple[int, int], list[Hypothesis]] = {}
    choice: dict[tuple[int, int], int] = {}
    rejected: dict[tuple[int, int], str] = {}
    pair_checks: dict[tuple[int, int], CrossRenderCheck] = {}
    # one task per pair; in this process it reports progress on the console, as a Ray task it stays quiet
    task_console = console if executor.name == "serial" else None
    batch, bridged = list(candidates), 0
    while True:
        outcomes = executor.map(_register_pair, [(renderers, views, feats, similarity, a, b, intr, config,
                                                  task_console) for a, b in batch], "pair", uses_gpu=True)  # fmt: skip
        for (a, b), out in zip(batch, outcomes, strict=True):
            matches[(a, b)], hypotheses[(a, b)] = out.matches, out.hypotheses
            if out.check is not None:
                pair_checks[(a, b)] = out.check
            if out.rejected is not None:
                rejected[(a, b)] = out.rejected
            else:
                choice[(a, b)] = out.choice
        if given or bridged == gc.bridge_rounds:
            break
        # registered pairs that leave the NeRFs in pieces: each piece tries its next-best partners outside it, from
        # its outlying NeRFs first (two more per piece each round)
        linked = sorted(choice)
        positions = piece_positions(k, {pair: hypotheses[pair][n].T for pair, n in choice.items()}, views)
        batch = bridging_pairs(rank, linked, set(matches), gc.bridge_pairs, border_ranks(k, linked, positions),
                               2 * (bridged + 1))  # fmt: skip
        if not batch:
            break
        bridged += 1
        pieces = len(set(components(k, sorted(choice)).tolist()))
        console.print(f"graph: the {len(choice)} registered pairs leave {pieces} pieces; bridging round {bridged}: "
                      + ", ".join(label(*p) for p in batch))  # fmt: skip
        candidates = candidates + batch
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
        outcomes = write_pair_outcomes(work_dir / PAIR_OUTCOMES_FILE, names, scores, verified, candidates, accepted,
                                       rejected, source, bridged)  # fmt: skip
        raise RegistrationError(
            f"{e} ({len(edges)} of {len(candidates)} candidate pairs registered; each pair's outcome in {outcomes}); "
            f"name overlapping pairs with --graph.neighbours a:b, or {SUGGESTION}"
        ) from None
    timings["solve"] = time.perf_counter() - t0
    T_to_ref = solved.T_to_reference
    for e in solved.dropped:
        console.print(f"[yellow]graph: dropped {e.reason}[/]")

    checked_pairs = [accepted[n] for n in solved.tree] if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config,
                                    check_views(feats, views, matches, chosen, checked_pairs))  # fmt: skip
    timings["self_check"] = time.perf_counter() - t0

    kept = {accepted[n]: chosen[accepted[n]] for n, e in enumerate(solved.edges) if e.status != "dropped"}
    overlap = np.zeros((k, k), dtype=int)
    for (a, b), h in kept.items():
        overlap[a, b] = overlap[b, a] = len(h.inliers)
    section = graph_section(
        names=names, scores=scores, verified=verified, candidates=candidates, source=source,
        pairs={pair: {**pair_summary(feats, matches[pair], hypotheses[pair], choice.get(pair), config),
                      "self_check_ncc": json_float(pair_checks[pair].score) if pair in pair_checks else None}
               for pair in candidates},
        rejected=rejected, accepted=accepted, solved=solved, lengths=lengths,
        keypoints={names[i]: f.counts for i, f in enumerate(feats)},
    )  # fmt: skip
    section["bridging_rounds"] = bridged
    # each task's own seconds (render and lift per NeRF, registration per pair): what a cluster runs side by side
    section["tasks_s"] = {kind: list(t) for kind, t in executor.task_seconds.items()}
    console.print(f"graph tasks ({executor.name}): " + "; ".join(
        f"{len(t)} {kind}, median {sorted(t)[len(t) // 2]:.1f} s, max {max(t):.1f} s"
        for kind, t in executor.task_seconds.items() if t))  # fmt: skip
    result = build_known_geometry_result(
        renderers=renderers, views=views, T_to_ref=T_to_ref, T_initial=solved.T_initial,
        views_matched=views_matched(feats, matches, kept, k), overlap=overlap, checks=checks, config=config,
        timings=timings, known_geometry=None, graph=section,
    )  # fmt: skip
    failure = failure_message(checks, names, config)
    if failure is not None:
        raise RegistrationFailed(failure, result)
    return result
