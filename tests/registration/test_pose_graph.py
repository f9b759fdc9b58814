"""The SIM(3) pose graph against ground truth: noisy dense graphs, a flipped edge, a tree, a disconnected graph, the
choice of the reference, and the one line when GTSAM is missing; then the graph mode end to end on ground-truth
scene renderers (three street segments, the neighbours given, an unrelated NeRF)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.registration import pairwise, render_cache, retrieval
from nerfuser_ns.registration import pose_graph as pg
from nerfuser_ns.registration.distributed import RAY_CPUS_PER_TASK, RayExecutor, SerialExecutor
from nerfuser_ns.scripts.register import print_summary


def ground_truth(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """NeRF -> world SIM(3)s of a world scene of size ~1, and each NeRF's length scale (that size in its units)."""
    T = sim3.random_sim3(rng, scale_range=(0.2, 5.0), size=(n,))
    return T, 1.0 / sim3.decompose_sim3(T)[2]


def measure(T_world, lengths, pairs, rng, rot_deg=0.2, trans=0.002, log_s=0.002, weight=100.0) -> list[pg.Edge]:
    """Edges ``T_j->i`` from the truth with a small error about the world's origin, where the scene is (a pair
    registers about the content it shares): ``T_i^-1 N T_j``, translations of N in world units."""
    edges = []
    for i, j in pairs:
        noise = sim3.make_sim3(sim3.so3_exp(rng.normal(scale=np.radians(rot_deg), size=3)),
                               rng.normal(scale=trans, size=3), np.exp(rng.normal(scale=log_s)))
        edges.append(pg.Edge(i, j, sim3.invert_sim3(T_world[i]) @ noise @ T_world[j], weight))  # fmt: skip
    return edges


def errors_to_truth(T_hat: np.ndarray, T_world: np.ndarray, ref: int, lengths: np.ndarray):
    """Rotation (deg), translation (relative to the reference's length scale) and scale errors per NeRF."""
    err = sim3.sim3_errors(T_hat, sim3.to_reference_frame(T_world, ref))
    return err.r_err_deg, err.t_err / lengths[ref], err.s_err


DENSE_6 = [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4), (3, 5), (4, 5), (0, 5), (1, 4), (0, 3)]


def test_noisy_dense_graph_beats_chaining_the_spanning_tree():
    """Over four draws: every NeRF near the truth, and the solve's errors, summed, well below those of chaining the
    spanning tree (one path of measurements per NeRF, where the solve averages over the cycles)."""
    solved, chained = np.zeros(3), np.zeros(3)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        T_world, lengths = ground_truth(rng, 6)
        edges = measure(T_world, lengths, DENSE_6, rng)
        out = pg.solve_pose_graph(6, edges, reference=0, lengths=lengths)
        assert all(e.status == "kept" for e in out.edges) and not out.dropped
        assert len(out.tree) == 5 and len(out.cycles) == len(DENSE_6) - 5 and all(c.passed for c in out.cycles)
        r, t, s = errors_to_truth(out.T_to_reference, T_world, 0, lengths)
        assert r.max() < 0.5 and t.max() < 0.02 and s.max() < 0.004, (seed, r, t, s)
        solved += [r.sum(), t.sum(), s.sum()]
        chained += [x.sum() for x in errors_to_truth(out.T_initial, T_world, 0, lengths)]
        np.testing.assert_array_equal(out.T_to_reference[0], np.eye(4))
        # cycle residuals are those of the noise (tenths of a degree), edge residuals after the solve as well
        assert max(c.residual.rotation_deg for c in out.cycles) < 2.0
        assert max(e.residual.rotation_deg for e in out.edges) < 1.0
    assert (solved < 0.7 * chained).all(), (solved, chained)


def test_flipped_edge_is_dropped_and_named():
    """Repeated structure links one pair the wrong way round (a half turn) with many inliers: the cycles through it
    fail, it is dropped (named in the reason), and the result is as without it."""
    rng = np.random.default_rng(1)
    T_world, lengths = ground_truth(rng, 6)
    edges = measure(T_world, lengths, DENSE_6, rng)
    bad = DENSE_6.index((1, 3))
    flip = sim3.make_sim3(np.diag([-1.0, -1.0, 1.0]))
    edges[bad] = pg.Edge(1, 3, edges[bad].T @ flip, weight=1000.0)  # the heaviest: the tree would take it
    names = [f"n{k}" for k in range(6)]
    out = pg.solve_pose_graph(6, edges, reference=0, lengths=lengths, names=names)
    assert [(e.i, e.j) for e in out.dropped] == [(1, 3)]
    assert out.edges[bad].reason.startswith("n1 / n3 disagrees with the rest")
    assert out.edges[bad].residual.rotation_deg > 170  # against the solution: still the half turn
    assert bad not in out.tree and all(e.status == "kept" for n, e in enumerate(out.edges) if n != bad)
    r, t, s = errors_to_truth(out.T_to_reference, T_world, 0, lengths)
    assert r.max() < 0.5 and t.max() < 0.02 and s.max() < 0.004, (r, t, s)


def test_scale_outlier_in_a_triangle_rich_graph_is_dropped():
    rng = np.random.default_rng(2)
    T_world, lengths = ground_truth(rng, 5)
    pairs = [(a, b) for a in range(5) for b in range(a + 1, 5)]  # complete graph
    edges = measure(T_world, lengths, pairs, rng)
    bad = pairs.index((2, 4))
    edges[bad] = pg.Edge(2, 4, sim3.scale_matrix(1.5) @ edges[bad].T, weight=100.0)  # 50% scale error, 0 deg
    out = pg.solve_pose_graph(5, edges, reference=2, lengths=lengths)
    assert [(e.i, e.j) for e in out.dropped] == [(2, 4)]
    r, t, s = errors_to_truth(out.T_to_reference, T_world, 2, lengths)
    assert r.max() < 0.5 and t.max() < 0.02 and s.max() < 0.004, (r, t, s)


def test_tree_solves_exactly_and_reports_edges_unverified():
    rng = np.random.default_rng(3)
    T_world, lengths = ground_truth(rng, 5)
    tree = [(0, 1), (1, 2), (3, 1), (4, 3)]  # (3, 1): an edge stored against the direction of the chain
    edges = measure(T_world, lengths, tree, rng, rot_deg=0, trans=0, log_s=0)
    out = pg.solve_pose_graph(5, edges, reference=0, lengths=lengths)
    assert all(e.status == "unverified" and "bridge" in e.reason for e in out.edges) and out.cycles == []
    r, t, s = errors_to_truth(out.T_to_reference, T_world, 0, lengths)
    assert r.max() < 1e-6 and t.max() < 1e-8 and s.max() < 1e-9, (r, t, s)
    np.testing.assert_allclose(out.T_initial, out.T_to_reference, atol=1e-8)


def test_bridge_beside_a_cycle_is_the_only_unverified_edge():
    rng = np.random.default_rng(4)
    T_world, lengths = ground_truth(rng, 4)
    edges = measure(T_world, lengths, [(0, 1), (1, 2), (0, 2), (2, 3)], rng)
    out = pg.solve_pose_graph(4, edges, lengths=lengths)
    assert [e.status for e in out.edges] == ["kept", "kept", "kept", "unverified"]
    assert [e.cycles_passed for e in out.edges] == [1, 1, 1, 0]


def test_disconnected_graph_names_the_unreachable_nerfs():
    rng = np.random.default_rng(5)
    T_world, lengths = ground_truth(rng, 5)
    edges = measure(T_world, lengths, [(0, 1), (1, 2), (3, 4)], rng)
    names = ["a", "b", "c", "d", "e"]
    with pytest.raises(pg.PoseGraphError, match=r"^d, e: no chain of registered pairs links them to the reference a$"):
        pg.solve_pose_graph(5, edges, names=names)


def test_reference_is_choosable():
    rng = np.random.default_rng(6)
    T_world, lengths = ground_truth(rng, 5)
    edges = measure(T_world, lengths, [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4), (1, 3)], rng)
    a = pg.solve_pose_graph(5, edges, reference=0, lengths=lengths)
    b = pg.solve_pose_graph(5, edges, reference=3, lengths=lengths)
    np.testing.assert_array_equal(b.T_to_reference[3], np.eye(4))
    r, t, s = errors_to_truth(b.T_to_reference, T_world, 3, lengths)
    assert r.max() < 0.5 and t.max() < 0.02 and s.max() < 0.004, (r, t, s)
    # the same solution in another frame: b = a re-expressed in NeRF 3's frame
    err = sim3.sim3_errors(b.T_to_reference, sim3.to_reference_frame(a.T_to_reference, 3))
    assert err.r_err_deg.max() < 1e-4 and err.s_err.max() < 1e-6


@pytest.mark.parametrize(
    ("edges", "message"),
    [
        ([pg.Edge(0, 0, np.eye(4))], r"^edge 0 \(0, 0\): needs two distinct NeRFs in 0..2$"),
        ([pg.Edge(0, 1, np.eye(4)), pg.Edge(1, 0, np.eye(4))], r"^a / b: given twice \(edges 0 and 1\); keep one$"),
        ([pg.Edge(0, 1, np.full((4, 4), np.nan))], r"^a / b: the transform is not a finite SIM\(3\) with s > 0$"),
        ([pg.Edge(0, 1, np.eye(4), weight=0.0)], r"^a / b: weight 0.0 must be finite and > 0$"),
    ],
)
def test_bad_edges_are_refused_with_one_line(edges, message):
    with pytest.raises(pg.PoseGraphError, match=message):
        pg.solve_pose_graph(3, edges, names=["a", "b", "c"])


def test_missing_gtsam_is_one_line(monkeypatch):
    monkeypatch.setattr(pg, "gtsam", None)
    edges = [pg.Edge(0, 1, np.eye(4))]
    message = r'^the pose-graph solve needs GTSAM: pip install "nerfuser_ns\[city\]"$'
    with pytest.raises(pg.PoseGraphError, match=message):
        pg.solve_pose_graph(2, edges)


def test_cycle_composition_follows_the_edge_directions():
    """A triangle given with edges in both directions composes to the identity; a 10 deg error on one edge shows as
    10 deg on the cycle, whichever edge the cycle starts from."""
    rng = np.random.default_rng(7)
    T = sim3.random_sim3(rng, size=(3,))
    edges = [pg.Edge(0, 1, sim3.relative_sim3(T[0], T[1])), pg.Edge(2, 1, sim3.relative_sim3(T[2], T[1])),
             pg.Edge(0, 2, sim3.relative_sim3(T[0], T[2]))]  # fmt: skip
    np.testing.assert_allclose(pg.compose_cycles(edges, [[0, 1, 2], [1, 0, 2]]), np.stack([np.eye(4)] * 2),
                               atol=1e-9)  # fmt: skip
    edges[1] = pg.Edge(2, 1, sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 0.0, 10.0]))) @ edges[1].T)
    r, _, _ = pg.residuals(pg.compose_cycles(edges, [[0, 1, 2], [2, 1, 0]]), np.ones(2))
    np.testing.assert_allclose(r, [10.0, 10.0], atol=1e-9)


def test_nerf_pair_scores_and_candidates():
    """A pair scores the mean of its best view pairs (views left out do not count); candidates are the pairs above
    the threshold plus each NeRF's best partners."""
    sim = [[None] * 3 for _ in range(3)]
    sim[0][1] = np.array([[0.9, 0.1], [0.5, -np.inf]])
    sim[0][2] = np.array([[0.2, 0.1], [0.0, 0.3]])
    sim[1][2] = np.array([[0.05, 0.0], [0.1, 0.0]])
    scores = retrieval.nerf_pair_scores(sim, top=2)
    np.testing.assert_allclose(scores, [[0, 0.7, 0.25], [0.7, 0, 0.075], [0.25, 0.075, 0]])
    assert retrieval.candidate_nerf_pairs(scores, min_score=0.5, top_k=0) == [(0, 1)]
    assert retrieval.candidate_nerf_pairs(scores, min_score=0.5, top_k=1) == [(0, 1), (0, 2)]
    assert retrieval.candidate_nerf_pairs(scores, min_score=2.0, top_k=2) == [(0, 1), (0, 2), (1, 2)]


def test_most_similar_view_pairs_skip_left_out_views():
    sim = np.array([[0.2, 0.9, -np.inf], [0.5, -np.inf, 0.7]])
    assert retrieval.most_similar_view_pairs(sim, 3) == [(0, 1), (1, 2), (1, 0)]
    assert retrieval.most_similar_view_pairs(sim, 10) == [(0, 1), (1, 2), (1, 0), (0, 0)]


def test_bridging_pairs_join_the_pieces_by_their_best_untried_partners():
    """Each piece of the registered graph asks for its best-scoring untried pairs to NeRFs outside it; nothing once
    the graph is connected or every joining pair was tried."""
    np.testing.assert_array_equal(retrieval.components(5, [(0, 1), (3, 4), (1, 0)]), [0, 0, 2, 3, 3])
    rng = np.random.default_rng(0)
    scores = rng.uniform(0.6, 0.7, size=(5, 5))
    scores = np.triu(scores, 1) + np.triu(scores, 1).T
    scores[0, 2] = scores[2, 0] = 0.9  # piece {0, 1} and NeRF 2 look most alike through (0, 2)
    scores[2, 4] = scores[4, 2] = 0.95
    linked = [(0, 1), (3, 4)]
    tried = {(0, 1), (3, 4), (0, 3)}
    pairs = retrieval.bridging_pairs(scores, linked, tried, per_component=1)
    assert pairs == [(0, 2), (2, 4)]  # {0, 1}: (0, 2); {2}: (2, 4); {3, 4}: (2, 4) again
    wider = retrieval.bridging_pairs(scores, linked, tried, per_component=3)
    assert set(pairs) <= set(wider) and not set(wider) & tried
    assert all(retrieval.components(5, linked)[a] != retrieval.components(5, linked)[b] for a, b in wider)
    assert retrieval.bridging_pairs(scores, [(0, 1), (1, 2), (2, 3), (3, 4)], set(), per_component=2) == []
    everything = {(a, b) for a in range(5) for b in range(a + 1, 5)}
    assert retrieval.bridging_pairs(scores, linked, everything, per_component=2) == []


def test_bridging_pairs_start_from_the_pieces_outlying_nerfs():
    """Two pieces of a chain of 8 NeRFs (0-3 and 4-7, each in a frame of its own): their outlying NeRFs are the
    chain's ends, and bridging pairs those first although retrieval scores middles higher."""
    rng = np.random.default_rng(1)
    scores = rng.uniform(0.6, 0.7, size=(8, 8))
    scores = np.triu(scores, 1) + np.triu(scores, 1).T
    scores[1, 5] = scores[5, 1] = scores[2, 6] = scores[6, 2] = 0.95  # look alike, do not overlap
    linked = [(0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (6, 7)]
    # piece {4..7} in a frame of its own: mirrored, scaled by 2, shifted; ranks compare distances inside a piece only
    x = np.array([0.0, 1, 2, 3, 10 - 2 * 4, 10 - 2 * 5, 10 - 2 * 6, 10 - 2 * 7])
    positions = np.stack([x, np.zeros(8), np.zeros(8)], 1)
    rank = retrieval.border_ranks(8, linked, positions)
    assert set(rank[[0, 3]]) == {0, 1} and set(rank[[1, 2]]) == {2, 3}
    assert set(rank[[4, 7]]) == {0, 1} and set(rank[[5, 6]]) == {2, 3}
    tried = set(linked)
    by_score = retrieval.bridging_pairs(scores, linked, tried, per_component=1)
    assert by_score == [(1, 5)]
    by_border = retrieval.bridging_pairs(scores, linked, tried, per_component=4, border=rank, max_border_rank=2)
    assert by_border == [(0, 4), (0, 7), (3, 4), (3, 7)]
    # once the outlying pairs are tried, the pieces look beyond them (best score first)
    again = retrieval.bridging_pairs(scores, linked, tried | set(by_border), per_component=1, border=rank,
                                     max_border_rank=2)  # fmt: skip
    assert again == [(1, 5)]


def test_piece_positions_compose_the_pieces_edges():
    """Each NeRF's mean camera centre in its piece's frame (the piece's first NeRF), from the pairwise SIM(3)s."""
    from types import SimpleNamespace

    from nerfuser_ns.registration.graph import piece_positions

    rng = np.random.default_rng(2)
    truth = [np.eye(4)] + [sim3.make_sim3(sim3.so3_exp(rng.normal(size=3)), rng.normal(size=3), np.exp(rng.normal()))
                           for _ in range(3)]  # fmt: skip
    centres = [rng.normal(size=(5, 3)) for _ in range(4)]  # in each NeRF's own frame
    views = []
    for c in centres:
        c2w = np.tile(np.eye(4), (len(c), 1, 1))
        c2w[:, :3, 3] = c
        views.append(SimpleNamespace(c2w=c2w))
    # NeRFs 0, 1, 2 in one piece (edges T_b->a), NeRF 3 alone
    edges = {(0, 1): sim3.invert_sim3(truth[0]) @ truth[1], (1, 2): sim3.invert_sim3(truth[1]) @ truth[2]}
    got = piece_positions(4, edges, views)
    for i in range(3):
        np.testing.assert_allclose(got[i], sim3.transform_points(truth[i], centres[i]).mean(0), atol=1e-9)
    np.testing.assert_allclose(got[3], centres[3].mean(0), atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------------
# The graph mode end to end on ground-truth renderers (exact depth)

W, H = 240, 180
QUIET = Console(quiet=True)


def graph_config(**kw) -> reg.RegistrationConfig:
    sampling = reg.PoseSamplingConfig(source="training", width=W, height=H, fov_deg=60.0, max_training_poses=16)
    return reg.RegistrationConfig(mode="graph", sampling=sampling, self_check_views=2, colour_views=2, **kw)


def truth_in(layout, ref: str, name: str) -> np.ndarray:
    caps = {c.name: c for c in layout.captures}
    return sim3.invert_sim3(caps[ref].capture_to_world) @ caps[name].capture_to_world


@pytest.fixture(scope="module")
def street():
    layout = scenes.make_layout("street", seed=0, num_views=16, num_test_views=1, width=W, height=H, num_captures=3)
    return layout, [SceneFrameRenderer.from_layout(layout, c.name) for c in layout.captures]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("graph_work")


def test_three_street_nerfs_by_retrieval(street, work):
    """Retrieval proposes every pair of three overlapping street segments; each registers, the triangle closes within
    the thresholds, the solve matches the truth; the record has its graph section and reads back; the CLI prints it."""
    layout, renderers = street
    record = reg.register(renderers, graph_config(), work, QUIET).to_record()
    names = [r.name for r in renderers]
    for i in (1, 2):
        err = sim3.sim3_errors(np.array(record["nerfs"][i]["T_to_reference"]), truth_in(layout, names[0], names[i]))
        assert err.r_err_deg < 0.1 and err.t_err < 0.005 and err.s_err < 0.005, (i, err)
    g = record["graph"]
    assert g["candidates"] == {"source": "retrieval", "pairs": [[names[0], names[1]], [names[0], names[2]],
                                                                [names[1], names[2]]]}  # fmt: skip
    assert [e["status"] for e in g["edges"]] == ["kept"] * 3 and len(g["tree"]) == 2
    assert all(e["self_check_ncc"] >= 0.4 and e["hypotheses"][e["chosen"]]["inliers"] >= 30 for e in g["edges"])
    assert all(e["residual"]["rotation_deg"] < 0.1 for e in g["edges"])
    (cycle,) = g["cycles"]
    assert cycle["passed"] and sorted(cycle["names"]) == names and cycle["residual"]["rotation_deg"] < 0.2
    assert [n["degree"] for n in g["nodes"]] == [2, 2, 2] and all(n["length_scale"] > 0 for n in g["nodes"])
    assert "known_geometry" not in record and record["sfm"] is None
    assert {n["estimator"] for n in record["nerfs"]} == {"graph"} and record["settings"]["mode"] == "graph"
    assert reg.RegistrationResult.from_record(record).graph == g
    console = Console(record=True, width=200)
    print_summary(record, console)
    text = console.export_text()
    assert "Pose graph: 3 candidate pairs (retrieval)" in text and "cycles: 1 of 1 within the thresholds" in text


def test_verification_ranks_a_drive_blocks_neighbours_first(tmp_path):
    """Five blocks of a drive, whose generated textures repeat along the street: geometric verification gives each
    block's neighbours the most inliers, and blocks three or more apart fewer than any neighbouring pair."""
    n = 5
    layout = scenes.make_layout("drive", seed=0, num_captures=n, num_views=scenes.DRIVE_RIG_CAMERAS * 12,
                                num_test_views=1, width=160, height=120)  # fmt: skip
    renderers = [SceneFrameRenderer.from_layout(layout, c.name) for c in layout.captures]
    cfg = graph_config()
    cfg.sampling.width, cfg.sampling.height, cfg.sampling.max_training_poses = 160, 120, 8
    ref, min_views, intr = render_cache.check_inputs(renderers, cfg)
    views, feats = pairwise.render_and_lift(renderers, cfg, tmp_path, QUIET, intr, min_views, {})
    similarity = pairwise.view_similarity(feats, views, cfg)
    inliers = pairwise.verify_pairs(feats, similarity, cfg)
    np.testing.assert_array_equal(inliers, inliers.T)
    assert (np.diag(inliers) == 0).all()
    row = pairwise.verified_inliers(feats, similarity, 2, cfg)  # one task: the later NeRFs only
    assert (row[:3] == 0).all() and (row[3:] == inliers[2, 3:]).all(), row
    for a in range(n):
        best = int(np.argmax(np.where(np.arange(n) == a, -1, inliers[a])))
        assert abs(best - a) == 1, (a, inliers[a])
    adjacent = [inliers[a, a + 1] for a in range(n - 1)]
    far = [inliers[a, b] for a in range(n) for b in range(a + 3, n)]
    assert max(far) < min(adjacent), (adjacent, far)


def test_neighbours_given_form_a_tree_in_the_chosen_reference(street, work):
    """Only the pairs named are registered (by name or index); a tree: both edges unverified, no cycle; the result
    in the frame of the reference chosen (the middle segment)."""
    layout, renderers = street
    names = [r.name for r in renderers]
    cfg = graph_config(reference=1)
    cfg.graph.neighbours = (f"{names[0]}:{names[1]}", "2:1")
    record = reg.register(renderers, cfg, work, QUIET).to_record()
    g = record["graph"]
    assert g["candidates"]["source"] == "neighbours given"
    assert [e["names"] for e in g["edges"]] == [[names[0], names[1]], [names[1], names[2]]]
    assert [e["status"] for e in g["edges"]] == ["unverified"] * 2 and g["cycles"] == []
    assert record["reference"] == {"index": 1, "name": names[1]}
    np.testing.assert_array_equal(record["nerfs"][1]["T_to_reference"], np.eye(4))
    for i in (0, 2):
        err = sim3.sim3_errors(np.array(record["nerfs"][i]["T_to_reference"]), truth_in(layout, names[1], names[i]))
        assert err.r_err_deg < 0.1 and err.t_err < 0.005 and err.s_err < 0.005, (i, err)


def test_an_unrelated_nerf_is_rejected_and_named(street, work):
    """An object-centric NeRF beside the street: retrieval proposes it (generated scenes share textures), but no pair
    with it passes the cross-render check, so no edge reaches it: one line naming it."""
    _, renderers = street
    other = scenes.make_layout("object-centric", seed=0, num_views=16, num_test_views=1, width=W, height=H)
    renderers = [*renderers, SceneFrameRenderer.from_layout(other, "capture_a")]
    outcomes = work / "graph_pairs.json"
    with pytest.raises(reg.RegistrationError, match=r"^capture_a: no chain of registered pairs links it to the "
                                                    r"reference capture_0 \(3 of 6 candidate pairs registered; each "
                                                    rf"pair's outcome in {re.escape(str(outcomes))}\); name "
                                                    r"overlapping pairs with --graph.neighbours a:b"):
        reg.register(renderers, graph_config(), work, QUIET)
    # the file says pair by pair what happened: the street's three pairs registered, every pair with the stranger not
    record = json.loads(outcomes.read_text())
    assert record["pieces"] == [["capture_0", "capture_1", "capture_2"], ["capture_a"]]
    status = {tuple(p["names"]): (p["status"], p["reason"]) for p in record["pairs"]}
    assert len(status) == 6
    for pair, (state, reason) in status.items():
        assert (state == "rejected") == ("capture_a" in pair), (pair, state, reason)
        assert (reason is None) == (state == "registered"), (pair, reason)


def test_pieces_left_by_retrieval_are_bridged(street, work):
    """With no candidate from retrieval (``top_k`` 0, an unreachable threshold) every NeRF is a piece of its own: with
    no bridging round they stay apart and the registration says which, writing the pair outcomes; one bridging round
    registers each piece's best partners, the graph solves as with retrieval, and the failure's outcomes are gone."""
    layout, renderers = street
    names = [r.name for r in renderers]
    cfg = graph_config()
    cfg.graph.top_k, cfg.graph.min_similarity, cfg.graph.bridge_rounds = 0, 2.0, 0
    with pytest.raises(reg.RegistrationError, match=r"^capture_1, capture_2: no chain of registered pairs links "
                                                    r"them to the reference capture_0 \(0 of 0 candidate pairs "
                                                    r"registered;"):
        reg.register(renderers, cfg, work, QUIET)
    assert json.loads((work / "graph_pairs.json").read_text())["pairs"] == []
    cfg.graph.bridge_rounds = 1
    record = reg.register(renderers, cfg, work, QUIET).to_record()
    assert not (work / "graph_pairs.json").exists()
    g = record["graph"]
    assert g["bridging_rounds"] == 1 and len(g["candidates"]["pairs"]) == 3
    for i in (1, 2):
        err = sim3.sim3_errors(np.array(record["nerfs"][i]["T_to_reference"]), truth_in(layout, names[0], names[i]))
        assert err.r_err_deg < 0.1 and err.t_err < 0.005 and err.s_err < 0.005, (i, err)


@pytest.mark.parametrize(
    ("neighbours", "message"),
    [
        (("0-1",), r"^--graph.neighbours '0-1': expected a:b with two NeRF names or indices$"),
        (("capture_0:nowhere",), r"^--graph.neighbours capture_0:nowhere: 'nowhere' is neither a NeRF name "
                                 r"\(capture_0, capture_1, capture_2\) nor an index 0..2$"),
        (("1:capture_1",), r"^--graph.neighbours 1:capture_1: a NeRF cannot be its own neighbour$"),
    ],
)
def test_bad_neighbours_are_refused_before_rendering(street, tmp_path, neighbours, message):
    cfg = graph_config()
    cfg.graph.neighbours = neighbours
    with pytest.raises(reg.RegistrationError, match=message):
        reg.register(street[1], cfg, tmp_path, QUIET)
    assert not (tmp_path / "renders").exists()


def test_graph_mode_without_gtsam_is_one_line_before_rendering(street, tmp_path, monkeypatch):
    monkeypatch.setattr(pg, "gtsam", None)
    message = r'^the pose-graph solve needs GTSAM: pip install "nerfuser_ns\[city\]"$'
    with pytest.raises(reg.RegistrationError, match=message):
        reg.register(street[1], graph_config(), tmp_path, QUIET)
    assert not (tmp_path / "renders").exists()


def _power(x: int, e: int) -> int:
    return x**e


def test_serial_executor_keeps_order_and_times_each_task():
    ex = SerialExecutor()
    assert ex.map(_power, [(3, 2), (2, 3), (5, 1)], "power") == [9, 8, 5]
    assert ex.map(_power, [(2, 2)], "power", uses_gpu=True) == [4]  # no GPU asked of this process
    assert len(ex.task_seconds["power"]) == 4 and all(t >= 0 for t in ex.task_seconds["power"])
    assert ex.task_threads(-1) == -1 and ex.task_threads(3) == 3  # one task at a time: every core


def test_ray_tasks_take_their_own_cpus_not_every_core():
    """Ray runs a task per CPU at once: pycolmap's 'all cores' (-1) becomes the task's CPUs; a set count stays."""
    assert RayExecutor.task_threads(-1) == RAY_CPUS_PER_TASK == 1
    assert RayExecutor.task_threads(4) == 4


def test_graph_rejects_negative_ray_gpus(street, tmp_path):
    cfg = graph_config()
    cfg.graph.executor, cfg.graph.ray_gpus_per_task = "ray", -1.0
    with pytest.raises(reg.RegistrationError, match="ray-gpus-per-task must be >= 0"):
        reg.register(street[1], cfg, tmp_path, QUIET)
    assert not (tmp_path / "renders").exists()  # refused before any work


def test_ray_tasks_give_the_serial_result(street, work, tmp_path):
    """Renders, keypoints and pair registrations as Ray tasks on this machine, in a fresh work folder (every render
    made by a task, written to the render cache), give the serial run's transforms and graph exactly (two of the
    segments: the smallest graph, the same tasks)."""
    renderers = street[1][:2]
    serial = reg.register(renderers, graph_config(), work, QUIET).to_record()  # renders reused from the other tests
    cfg = graph_config()
    cfg.graph.executor = "ray"
    distributed = reg.register(renderers, cfg, tmp_path, QUIET).to_record()
    assert [n["T_to_reference"] for n in distributed["nerfs"]] == [n["T_to_reference"] for n in serial["nerfs"]]
    tasks = {kind: len(t) for kind, t in serial["graph"].pop("tasks_s").items()}
    assert {kind: len(t) for kind, t in distributed["graph"].pop("tasks_s").items()} == tasks
    assert tasks == {"render": 2, "lift": 2, "verify": 2, "pair": 1}
    assert distributed["graph"] == serial["graph"]
    assert distributed["reused"]["renders"] == [False] * 2
    assert all((tmp_path / "renders" / n["render_folder"].rsplit("/", 1)[-1] / "depth.npz").is_file()
               for n in distributed["nerfs"])  # fmt: skip
