"""A SIM(3) pose graph over NeRFs: pairwise registrations (edges) joined into one frame.

Conventions (those of :mod:`nerfuser_ns.sim3` and the registration record): an edge ``(i, j, T)`` holds
``T = T_j->i``, which maps points of NeRF j's frame into NeRF i's frame (``p_i = T @ [p_j, 1]``, the record's
``T_j_to_i``); the result gives per NeRF ``T_to_reference`` (``p_ref = T @ [p, 1]``), so an edge predicts
``T_j->i = T_i->ref^-1 @ T_j->ref``.

Steps (:func:`solve_pose_graph`):

1. Consistency: every triangle of the graph, and for an edge in no triangle its shortest cycle, composes to the
   identity when its edges agree. While a cycle exceeds the thresholds (:data:`CYCLE_MAX_ROTATION_DEG`,
   :data:`CYCLE_MAX_TRANSLATION` of the first NeRF's length scale, :data:`CYCLE_MAX_LOG_SCALE`; a cycle of L edges is
   allowed ``sqrt(L / 3)`` times them, as independent errors add up), the edge in most failing cycles (then in fewest
   passing ones, then of least weight) is dropped and the cycles are formed again. Only edges on a cycle can be
   dropped, so the graph stays connected; an edge on no cycle (a bridge) cannot be verified and is reported so.
2. Initial values: the edges chained from the reference along a maximum-weight spanning tree.
3. Fundamental cycles: one per kept edge off that tree, with its residual (reported).
4. A robust least-squares solve with GTSAM (``Similarity3`` values, ``BetweenFactorSimilarity3`` factors with a
   Huber or Cauchy noise model whose sigmas shrink with the edge weight, a prior on the reference,
   Levenberg-Marquardt), then every transform re-expressed in the reference's frame exactly.

Residuals are (rotation angle in degrees, translation norm relative to the length scale of the frame it is measured
in, ``|log s|``). GTSAM is optional (the ``city`` extra); without it only the solve raises.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from jaxtyping import Float

from nerfuser_ns import sim3

try:
    import gtsam
except ImportError:  # optional: the "city" extra; only the solve needs it
    gtsam = None

GTSAM_MISSING = 'the pose-graph solve needs GTSAM: pip install "nerfuser_ns[city]"'
CYCLE_MAX_ROTATION_DEG = 5.0
"""A cycle (of 3 edges) whose composed rotation exceeds this fails (the known-geometry mode's limit on pairs)."""
CYCLE_MAX_TRANSLATION = 0.1
"""... or whose composed translation exceeds this fraction of the length scale of the cycle's first NeRF."""
CYCLE_MAX_LOG_SCALE = 0.1
"""... or whose composed scale is off by more than this in ``|log s|`` (about 10%, the known-geometry limit)."""
CYCLE_REFERENCE_LENGTH = 3
"""Cycles of this many edges get the thresholds as they are; longer ones ``sqrt(L / 3)`` times them."""
ROTATION_SIGMA_DEG = 0.5
"""Noise of the heaviest edge's rotation; an edge of weight w has ``sqrt(w_max / w)`` times every sigma."""
TRANSLATION_SIGMA = 0.01
"""Noise of the heaviest edge's translation, relative to the length scale of the frame the error is measured in."""
LOG_SCALE_SIGMA = 0.01
"""Noise of the heaviest edge's ``log s``."""
ROBUST_K = 1.345
"""Huber / Cauchy parameter on whitened residuals (Huber's 95%-efficiency value)."""
REFERENCE_PRIOR_SIGMA = 1e-8
"""The prior that fixes the reference (its result is then set to the identity exactly)."""

EdgeStatus = Literal["kept", "unverified", "dropped"]


class PoseGraphError(ValueError):
    """A pose graph that cannot be solved (bad edges, NeRFs no edge reaches, GTSAM missing); one-line message."""


def require_gtsam() -> None:
    """Raise :class:`PoseGraphError` with the install line when GTSAM is missing."""
    if gtsam is None:
        raise PoseGraphError(GTSAM_MISSING)


@dataclass(frozen=True)
class Edge:
    """One pairwise registration."""

    i: int
    j: int
    T: Float[np.ndarray, "4 4"]
    """``T_j->i``: maps points of NeRF j's frame into NeRF i's frame."""
    weight: float = 1.0
    """Confidence (e.g. inlier matches): the spanning tree prefers heavy edges and the solve trusts them more."""


@dataclass(frozen=True)
class Residual:
    """How far a composed transform is from what it should be."""

    rotation_deg: float
    translation: float
    """Translation norm over the length scale of the frame it is measured in."""
    log_scale: float
    """``|log s|``."""


@dataclass
class EdgeResult:
    """One edge after the check and the solve."""

    i: int
    j: int
    weight: float
    status: EdgeStatus
    """kept: on a cycle that passed; unverified: on no cycle (a bridge); dropped: disagreed with the rest."""
    reason: str
    cycles_passed: int
    """Verifying cycles through it that passed in the final check."""
    in_tree: bool
    """On the spanning tree the initial values were chained along."""
    residual: Residual
    """The measured ``T_j->i`` against the solved one (``dT = T_meas @ T_solved^-1``, in i's frame)."""


@dataclass
class CycleResult:
    """A fundamental cycle of the spanning tree: the off-tree edge ``edges[0]`` closed through the tree."""

    nodes: list[int]
    """NeRFs along the cycle (the first is not repeated at the end)."""
    edges: list[int]
    """Edge indices along the cycle."""
    residual: Residual
    """Of the measured edges composed around the cycle, in the first NeRF's frame."""
    passed: bool


@dataclass
class PoseGraphResult:
    """The solved graph."""

    reference: int
    T_to_reference: Float[np.ndarray, "n 4 4"]
    """Per NeRF: maps its points into the reference NeRF's frame (the reference's is the identity)."""
    T_initial: Float[np.ndarray, "n 4 4"]
    """The kept edges chained from the reference along the spanning tree (the solve's start)."""
    tree: list[int]
    """Edge indices of the maximum-weight spanning tree over the kept edges."""
    edges: list[EdgeResult]
    cycles: list[CycleResult]
    solver: dict = field(default_factory=dict)
    """GTSAM's summary: iterations, the robust cost before and after."""

    @property
    def dropped(self) -> list[EdgeResult]:
        return [e for e in self.edges if e.status == "dropped"]


# ---------------------------------------------------------------------------------------------------------------------
# Graph helpers


def _node_names(num_nodes: int, names: Sequence[str] | None) -> list[str]:
    if names is None:
        return [f"NeRF {n}" for n in range(num_nodes)]
    if len(names) != num_nodes:
        raise PoseGraphError(f"{len(names)} names for {num_nodes} NeRFs")
    return list(names)


def validate_edges(num_nodes: int, edges: Sequence[Edge], names: Sequence[str] | None = None) -> None:
    """Nodes in range, no self-loop, no pair twice, finite SIM(3)s with a positive scale, positive weights."""
    label = _node_names(num_nodes, names)
    seen = {}
    for n, e in enumerate(edges):
        if not (0 <= e.i < num_nodes and 0 <= e.j < num_nodes) or e.i == e.j:
            raise PoseGraphError(f"edge {n} ({e.i}, {e.j}): needs two distinct NeRFs in 0..{num_nodes - 1}")
        pair = (min(e.i, e.j), max(e.i, e.j))
        if pair in seen:
            raise PoseGraphError(f"{label[pair[0]]} / {label[pair[1]]}: given twice (edges {seen[pair]} and {n}); "
                                 "keep one")
        seen[pair] = n
        T = np.asarray(e.T, dtype=np.float64)
        if T.shape not in ((4, 4), (3, 4)) or not np.isfinite(T).all() or np.linalg.det(T[:3, :3]) <= 0:
            raise PoseGraphError(f"{label[e.i]} / {label[e.j]}: the transform is not a finite SIM(3) with s > 0")
        if not (math.isfinite(e.weight) and e.weight > 0):
            raise PoseGraphError(f"{label[e.i]} / {label[e.j]}: weight {e.weight} must be finite and > 0")


def _adjacency(num_nodes: int, edges: Sequence[Edge], active: np.ndarray) -> list[dict[int, int]]:
    """``adj[v][u]`` = index of the active edge between v and u."""
    adj: list[dict[int, int]] = [{} for _ in range(num_nodes)]
    for n in np.flatnonzero(active):
        adj[edges[n].i][edges[n].j] = int(n)
        adj[edges[n].j][edges[n].i] = int(n)
    return adj


def unreachable(num_nodes: int, edges: Sequence[Edge], reference: int, active: np.ndarray | None = None) -> list[int]:
    """Nodes no chain of (active) edges links to ``reference``."""
    active = np.ones(len(edges), bool) if active is None else active
    adj = _adjacency(num_nodes, edges, active)
    seen, todo = {reference}, [reference]
    while todo:
        for u in adj[todo.pop()]:
            if u not in seen:
                seen.add(u)
                todo.append(u)
    return [n for n in range(num_nodes) if n not in seen]


def spanning_tree(num_nodes: int, edges: Sequence[Edge], reference: int, active: np.ndarray | None = None) -> list[int]:
    """Edge indices of a maximum-weight spanning tree grown from ``reference`` (Prim; ties: the lower edge index)."""
    active = np.ones(len(edges), bool) if active is None else active
    adj = _adjacency(num_nodes, edges, active)
    done, tree = {reference}, []
    heap = [(-edges[n].weight, n, u) for u, n in adj[reference].items()]
    heapq.heapify(heap)
    while heap:
        _, n, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        tree.append(n)
        for w, m in adj[u].items():
            if w not in done:
                heapq.heappush(heap, (-edges[m].weight, m, w))
    return tree


def chain_tree(
    num_nodes: int, edges: Sequence[Edge], tree: Sequence[int], reference: int
) -> Float[np.ndarray, "n 4 4"]:
    """``T_to_reference`` of every node the tree reaches, composed along it (NaN for the others)."""
    T = np.full((num_nodes, 4, 4), np.nan)
    T[reference] = np.eye(4)
    adj = _adjacency(num_nodes, edges, np.isin(np.arange(len(edges)), list(tree)))
    todo = deque([reference])
    while todo:
        v = todo.popleft()
        for u, n in sorted(adj[v].items()):
            if np.isnan(T[u, 0, 0]):
                e = edges[n]  # p_ref = T_v p_v and p_i = T_e p_j
                T[u] = T[v] @ (sim3.to_homogeneous(e.T) if e.i == v else sim3.invert_sim3(e.T))
                todo.append(u)
    return T


def _bfs_path(adj: list[dict[int, int]], start: int, end: int, exclude: int) -> list[int] | None:
    """Edge indices of a path with the fewest edges from ``start`` to ``end`` avoiding edge ``exclude`` (None: none)."""
    back = {start: (-1, -1)}
    todo = deque([start])
    while todo and end not in back:
        v = todo.popleft()
        for u, n in sorted(adj[v].items()):
            if n != exclude and u not in back:
                back[u] = (v, n)
                todo.append(u)
    if end not in back:
        return None
    path, v = [], end
    while v != start:
        v, n = back[v]
        path.append(n)
    return path[::-1]


def _walk(edges: Sequence[Edge], start: int, path: Sequence[int]) -> list[int]:
    """Nodes visited from ``start`` along edge indices ``path`` (``start`` first, the end last)."""
    nodes = [start]
    for n in path:
        e = edges[n]
        nodes.append(e.j if nodes[-1] == e.i else e.i)
    return nodes


def verifying_cycles(num_nodes: int, edges: Sequence[Edge], active: np.ndarray) -> tuple[list[list[int]], np.ndarray]:
    """Cycles that check the active edges: every triangle, and for an edge in none its shortest cycle. Each cycle is
    a list of edge indices starting with its closing edge ``(i, j)``, then the path from j back to i; repeats
    (the same edge set) are left out. Also returns which active edges lie on no cycle (bridges)."""
    adj = _adjacency(num_nodes, edges, active)
    cycles, seen = [], set()
    on_cycle = np.zeros(len(edges), bool)
    for n in np.flatnonzero(active):
        e = edges[n]
        common = sorted(set(adj[e.i]) & set(adj[e.j]))
        paths = [[adj[e.j][k], adj[k][e.i]] for k in common]
        if not paths:
            p = _bfs_path(adj, e.j, e.i, exclude=int(n))
            paths = [] if p is None else [p]
        for p in paths:
            cycle = [int(n), *p]
            on_cycle[cycle] = True
            key = frozenset(cycle)
            if key not in seen:
                seen.add(key)
                cycles.append(cycle)
    return cycles, active & ~on_cycle


# ---------------------------------------------------------------------------------------------------------------------
# Residuals (vectorised over cycles / edges)


def compose_cycles(edges: Sequence[Edge], cycles: Sequence[Sequence[int]]) -> Float[np.ndarray, "c 4 4"]:
    """Each cycle's edges composed: ``T_{v0 v1} @ T_{v1 v2} @ ... @ T_{v(L-1) v0}`` (``T_ab`` maps b into a), a map
    of the first node's frame to itself (the identity when the edges agree). The first edge is taken from its ``i``
    to its ``j``; the cycles are padded with identities and multiplied together step by step."""
    if not cycles:
        return np.zeros((0, 4, 4))
    T = sim3.to_homogeneous(np.stack([e.T for e in edges]))
    steps = np.concatenate([T, sim3.invert_sim3(T), np.eye(4)[None]])  # forward, backward, padding
    length = max(len(c) for c in cycles)
    index = np.full((len(cycles), length), 2 * len(edges))
    for c, cycle in enumerate(cycles):
        nodes = _walk(edges, edges[cycle[0]].i, cycle)
        # leaving a via edge (a, b) = T_b->a; leaving b via it = its inverse
        index[c, : len(cycle)] = [n if edges[n].i == a else len(edges) + n for n, a in zip(cycle, nodes, strict=False)]
    mats = steps[index]  # [c, L, 4, 4]
    out = mats[:, 0]
    for k in range(1, length):
        out = out @ mats[:, k]
    return out


def residuals(
    dT: Float[np.ndarray, "m 4 4"], length: Float[np.ndarray, " m"]
) -> tuple[Float[np.ndarray, " m"], Float[np.ndarray, " m"], Float[np.ndarray, " m"]]:
    """Rotation angle (deg), translation norm / ``length`` and ``|log s|`` of transforms that should be identities."""
    err = sim3.sim3_errors(dT, np.broadcast_to(np.eye(4), dT.shape))
    return (np.atleast_1d(err.r_err_deg), np.atleast_1d(err.t_err) / length, np.atleast_1d(err.s_err))


def exceeds(
    r: np.ndarray, t: np.ndarray, s: np.ndarray, num_edges: np.ndarray, max_rotation_deg: float,
    max_translation: float, max_log_scale: float,
) -> np.ndarray:
    """Whether cycle residuals exceed the thresholds (loosened by ``sqrt(L / 3)`` for cycles of L > 3 edges); NaN
    exceeds."""
    f = np.sqrt(np.maximum(np.asarray(num_edges, dtype=np.float64) / CYCLE_REFERENCE_LENGTH, 1.0))
    ok = (r <= f * max_rotation_deg) & (t <= f * max_translation) & (s <= f * max_log_scale)
    return ~ok


def edge_residuals(
    edges: Sequence[Edge], T_to_reference: Float[np.ndarray, "n 4 4"], lengths: Float[np.ndarray, " n"]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge's measured ``T_j->i`` against the one the solution implies, in i's frame."""
    i = np.array([e.i for e in edges])
    j = np.array([e.j for e in edges])
    measured = sim3.to_homogeneous(np.stack([e.T for e in edges]))
    implied = sim3.relative_sim3(T_to_reference[i], T_to_reference[j])
    return residuals(measured @ sim3.invert_sim3(implied), lengths[i])


# ---------------------------------------------------------------------------------------------------------------------
# Consistency check


def consistency_check(
    num_nodes: int, edges: Sequence[Edge], lengths: Float[np.ndarray, " n"],
    max_rotation_deg: float = CYCLE_MAX_ROTATION_DEG, max_translation: float = CYCLE_MAX_TRANSLATION,
    max_log_scale: float = CYCLE_MAX_LOG_SCALE, names: Sequence[str] | None = None,
) -> tuple[np.ndarray, dict[int, str], np.ndarray, np.ndarray]:
    """Drop edges one at a time while a verifying cycle exceeds the thresholds (see the module's docstring).

    Returns the kept edges (mask), the reason for each dropped edge, per edge the passing cycles through it in the
    final check, and the kept edges on no cycle (unverifiable bridges).
    """
    label = _node_names(num_nodes, names)
    kept = np.ones(len(edges), bool)
    reasons: dict[int, str] = {}
    while True:
        cycles, bridges = verifying_cycles(num_nodes, edges, kept)
        n_pass = np.zeros(len(edges), int)
        if not cycles:
            return kept, reasons, n_pass, bridges
        first = np.array([edges[c[0]].i for c in cycles])
        r, t, s = residuals(compose_cycles(edges, cycles), lengths[first])
        fail = exceeds(r, t, s, np.array([len(c) for c in cycles]), max_rotation_deg, max_translation, max_log_scale)
        n_fail = np.zeros(len(edges), int)
        for cycle, bad in zip(cycles, fail, strict=True):
            (n_fail if bad else n_pass)[cycle] += 1
        if not fail.any():
            return kept, reasons, n_pass, bridges
        weight = np.array([e.weight for e in edges])
        # most failing cycles, then fewest passing ones, then the lightest, then the first
        order = np.lexsort((np.arange(len(edges)), weight, n_pass, -n_fail))
        worst = int(order[0])
        bad_cycles = [c for c, cycle in enumerate(cycles) if fail[c] and worst in cycle]
        w = max(bad_cycles, key=lambda c: r[c])
        kept[worst] = False
        e = edges[worst]
        reasons[worst] = (
            f"{label[e.i]} / {label[e.j]} disagrees with the rest: on {n_fail[worst]} failing and {n_pass[worst]} "
            f"passing cycles (worst {r[w]:.1f} deg, translation {t[w]:.3f} of the length scale, |log s| {s[w]:.3f})"
        )


# ---------------------------------------------------------------------------------------------------------------------
# The solve


def _to_gtsam(T: Float[np.ndarray, "4 4"]):
    """Our ``[[sR, t], [0, 1]]`` as GTSAM's Similarity3, which maps ``p`` to ``s (R p + t')``: ``t' = t / s``."""
    R, t, s = sim3.decompose_sim3(T)
    return gtsam.Similarity3(gtsam.Rot3(sim3.project_to_so3(R)), t / s, float(s))


def _from_gtsam(S) -> Float[np.ndarray, "4 4"]:
    """GTSAM's matrix ``[[R, t'], [0, 1/s]]`` is ours divided by s."""
    M = np.asarray(S.matrix(), dtype=np.float64)
    return M / M[3, 3]


def optimise(
    num_nodes: int, edges: Sequence[Edge], T_initial: Float[np.ndarray, "n 4 4"], reference: int,
    lengths: Float[np.ndarray, " n"], robust: Literal["huber", "cauchy"] = "huber", robust_k: float = ROBUST_K,
    rotation_sigma_deg: float = ROTATION_SIGMA_DEG, translation_sigma: float = TRANSLATION_SIGMA,
    log_scale_sigma: float = LOG_SCALE_SIGMA, max_iterations: int = 100,
) -> tuple[Float[np.ndarray, "n 4 4"], dict]:
    """Robust SIM(3) pose-graph optimisation of ``edges`` with GTSAM, from ``T_initial`` (every node reached), the
    reference held by a prior; returns ``T_to_reference`` (the reference's exactly the identity) and a summary."""
    require_gtsam()
    if robust not in ("huber", "cauchy"):
        raise PoseGraphError(f"robust loss {robust!r}: use huber or cauchy")
    graph = gtsam.NonlinearFactorGraph()
    prior = gtsam.noiseModel.Isotropic.Sigma(7, REFERENCE_PRIOR_SIGMA)
    graph.add(gtsam.PriorFactorSimilarity3(reference, gtsam.Similarity3(), prior))
    w_max = max((e.weight for e in edges), default=1.0)
    estimator = (gtsam.noiseModel.mEstimator.Huber if robust == "huber" else gtsam.noiseModel.mEstimator.Cauchy)
    for e in edges:
        # The factor's error lives in j's frame (Logmap of T_meas^-1 T_i^-1 T_j), about j's origin: its translation
        # holds the edge's own translation error (j's length scale sets the unit) and its rotation error times the
        # lever from j's origin to i's (a pair registers about their shared content, somewhere between the two).
        f = math.sqrt(w_max / e.weight)
        lever = float(np.linalg.norm(sim3.invert_sim3(e.T)[:3, 3]))
        sigma_t = math.hypot(translation_sigma * lengths[e.j], math.radians(rotation_sigma_deg) * lever)
        sigmas = f * np.array([math.radians(rotation_sigma_deg)] * 3 + [sigma_t] * 3 + [log_scale_sigma])
        noise = gtsam.noiseModel.Robust.Create(estimator.Create(robust_k), gtsam.noiseModel.Diagonal.Sigmas(sigmas))
        graph.add(gtsam.BetweenFactorSimilarity3(e.i, e.j, _to_gtsam(e.T), noise))
    values = gtsam.Values()
    for n in range(num_nodes):
        values.insert(n, _to_gtsam(T_initial[n]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    T = np.stack([_from_gtsam(result.atSimilarity3(n)) for n in range(num_nodes)])
    T = sim3.to_reference_frame(T, reference)  # the prior holds it only up to its sigma
    summary = {"solver": "gtsam Levenberg-Marquardt", "robust": robust, "robust_k": robust_k,
               "iterations": int(optimizer.iterations()), "cost_before": float(graph.error(values)),
               "cost_after": float(graph.error(result))}  # fmt: skip
    return T, summary


def solve_pose_graph(
    num_nodes: int, edges: Sequence[Edge], reference: int = 0, lengths: Sequence[float] | np.ndarray | None = None,
    names: Sequence[str] | None = None, max_rotation_deg: float = CYCLE_MAX_ROTATION_DEG,
    max_translation: float = CYCLE_MAX_TRANSLATION, max_log_scale: float = CYCLE_MAX_LOG_SCALE,
    robust: Literal["huber", "cauchy"] = "huber", robust_k: float = ROBUST_K,
) -> PoseGraphResult:
    """Check, chain and solve a SIM(3) pose graph (see the module's docstring); the result in ``reference``'s frame.

    ``lengths``: per node a length scale in its own units (e.g. its scene's size); translations are compared
    relative to it (default 1). ``names`` label the nodes in messages. Raises :class:`PoseGraphError` (one line) on
    bad edges, nodes no edge reaches (named), or when GTSAM is missing.
    """
    label = _node_names(num_nodes, names)
    if num_nodes < 1:
        raise PoseGraphError("a pose graph needs at least one NeRF")
    if not 0 <= reference < num_nodes:
        raise PoseGraphError(f"reference {reference} out of range for {num_nodes} NeRFs")
    lengths = np.ones(num_nodes) if lengths is None else np.asarray(lengths, dtype=np.float64)
    if lengths.shape != (num_nodes,) or not (np.isfinite(lengths) & (lengths > 0)).all():
        raise PoseGraphError(f"lengths must be {num_nodes} finite positive numbers, got {lengths.tolist()}")
    validate_edges(num_nodes, edges, names)
    lost = unreachable(num_nodes, edges, reference)
    if lost:
        raise PoseGraphError(f"{', '.join(label[n] for n in lost)}: no chain of registered pairs links "
                             f"{'it' if len(lost) == 1 else 'them'} to the reference {label[reference]}")  # fmt: skip
    require_gtsam()

    kept, reasons, n_pass, bridges = consistency_check(num_nodes, edges, lengths, max_rotation_deg, max_translation,
                                                       max_log_scale, names)  # fmt: skip
    tree = spanning_tree(num_nodes, edges, reference, kept)
    T_initial = chain_tree(num_nodes, edges, tree, reference)

    # fundamental cycles: each kept off-tree edge (i, j) closed by the tree path from j back to i
    in_tree = set(tree)
    tree_adj = _adjacency(num_nodes, edges, np.isin(np.arange(len(edges)), tree))
    off_tree = [int(n) for n in np.flatnonzero(kept) if n not in in_tree]
    cycles = [[n, *(_bfs_path(tree_adj, edges[n].j, edges[n].i, exclude=-1) or [])] for n in off_tree]
    first = np.array([edges[c[0]].i for c in cycles], dtype=int)
    cr, ct, cs = residuals(compose_cycles(edges, cycles), lengths[first]) if cycles else (np.zeros(0),) * 3
    cfail = exceeds(cr, ct, cs, np.array([len(c) for c in cycles]), max_rotation_deg, max_translation, max_log_scale)

    used = [edges[n] for n in np.flatnonzero(kept)]
    T, solver = optimise(num_nodes, used, T_initial, reference, lengths, robust, robust_k)
    er, et, es = edge_residuals(edges, T, lengths) if edges else (np.zeros(0),) * 3

    results = []
    for n, e in enumerate(edges):
        if not kept[n]:
            status, reason = "dropped", reasons[n]
        elif bridges[n]:
            status, reason = "unverified", "on no cycle (a bridge of the graph): nothing can confirm or refute it"
        else:
            status, reason = "kept", f"on {n_pass[n]} passing cycles"
        results.append(EdgeResult(e.i, e.j, float(e.weight), status, reason, int(n_pass[n]), n in in_tree,
                                  Residual(float(er[n]), float(et[n]), float(es[n]))))  # fmt: skip
    cycle_results = [
        CycleResult(_walk(edges, edges[c[0]].i, c)[:-1], c, Residual(float(cr[k]), float(ct[k]), float(cs[k])),
                    not bool(cfail[k]))
        for k, c in enumerate(cycles)
    ]  # fmt: skip
    return PoseGraphResult(reference, T, T_initial, tree, results, cycle_results, solver)
