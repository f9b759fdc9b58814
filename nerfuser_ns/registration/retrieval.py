"""Candidate view pairs across NeRFs from a visual vocabulary built from the renders' own SIFT descriptors (offline:
no downloaded weights).

The vocabulary is k-means (scikit-learn) over a seeded sample of every render's descriptors; each view becomes a tf-idf
weighted, L2-normalised histogram of its words (a bag of visual words, as in Sivic and Zisserman's Video Google), and
two views are similar when their histograms' cosine is high.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float, Int
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from sklearn.cluster import KMeans

MAX_TRAINING_DESCRIPTORS = 10000
"""k-means runs on at most this many descriptors (a seeded sample)."""


def build_vocabulary(
    descriptors: Float[np.ndarray, "m d"], words: int, seed: int = 0
) -> Float[np.ndarray, "w d"]:
    """Visual words: k-means centres of (a seeded sample of) ``descriptors``; fewer words when there are fewer
    distinct descriptors."""
    rng = np.random.default_rng(seed)
    sample = descriptors if len(descriptors) <= MAX_TRAINING_DESCRIPTORS else descriptors[
        rng.choice(len(descriptors), MAX_TRAINING_DESCRIPTORS, replace=False)]  # fmt: skip
    words = max(1, min(words, len(np.unique(sample, axis=0))))
    # random initial centres: k-means++ costs more than the whole fit here, and retrieval does not need its quality
    kmeans = KMeans(n_clusters=words, init="random", n_init=1, max_iter=20, random_state=seed).fit(sample)
    return kmeans.cluster_centers_.astype(np.float32)


def assign_words(descriptors: Float[np.ndarray, "m d"], vocabulary: Float[np.ndarray, "w d"]) -> Int[np.ndarray, " m"]:
    """The nearest word of each descriptor (squared L2 distance)."""
    d2 = (vocabulary**2).sum(1)[None] - 2.0 * descriptors @ vocabulary.T
    return np.argmin(d2, axis=1)


def view_histograms(
    words: Int[np.ndarray, " m"], view: Int[np.ndarray, " m"], num_views: int, num_words: int
) -> Float[np.ndarray, "n w"]:
    """Raw word counts per view."""
    h = np.zeros((num_views, num_words), dtype=np.float64)
    np.add.at(h, (view, words), 1.0)
    return h


def tfidf_similarity(histograms: Sequence[Float[np.ndarray, "n w"]]) -> list[list[np.ndarray]]:
    """Cosine similarity of tf-idf vectors between every two view sets: ``out[a][b]`` is ``[n_a, n_b]``.

    The inverse document frequency counts the views of every set (a word seen everywhere tells nothing)."""
    allh = np.concatenate(histograms)
    idf = np.log(len(allh) / np.maximum((allh > 0).sum(0), 1))
    vecs = []
    for h in histograms:
        v = h / np.maximum(h.sum(1, keepdims=True), 1.0) * idf
        vecs.append(v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12))
    return [[va @ vb.T for vb in vecs] for va in vecs]


def candidate_pairs(
    similarity: Float[np.ndarray, "na nb"], per_view: int, exhaustive_max: int
) -> list[tuple[int, int]]:
    """View pairs (i of a, j of b) to match: all of them while there are at most ``exhaustive_max``, else each view's
    ``per_view`` most similar views of the other set, both ways (sorted, without repeats)."""
    na, nb = similarity.shape
    if na * nb <= exhaustive_max:
        return [(i, j) for i in range(na) for j in range(nb)]
    pairs = set()
    for i, row in enumerate(similarity):
        pairs.update((i, int(j)) for j in np.argsort(-row, kind="stable")[:per_view])
    for j, col in enumerate(similarity.T):
        pairs.update((int(i), j) for i in np.argsort(-col, kind="stable")[:per_view])
    return sorted(pairs)


def most_similar_view_pairs(similarity: Float[np.ndarray, "na nb"], count: int) -> list[tuple[int, int]]:
    """The ``count`` most similar view pairs (i of a, j of b), most similar first (left-out views, -inf, never)."""
    order = np.argsort(-similarity, axis=None, kind="stable")[:count]
    return [(int(i), int(j)) for i, j in zip(*np.unravel_index(order, similarity.shape), strict=True)
            if np.isfinite(similarity[i, j])]  # fmt: skip


def nerf_pair_scores(similarity: Sequence[Sequence[np.ndarray]], top: int) -> Float[np.ndarray, "k k"]:
    """How much two NeRFs' renders look alike: the mean of their ``top`` most similar view pairs (``-inf`` entries,
    views left out, do not count; 0 when none is left). Symmetric, with 0 on the diagonal."""
    k = len(similarity)
    scores = np.zeros((k, k))
    for a in range(k):
        for b in range(a + 1, k):
            s = np.asarray(similarity[a][b], dtype=np.float64).ravel()
            s = s[np.isfinite(s)]
            best = np.sort(s)[::-1][:top]
            scores[a, b] = scores[b, a] = float(best.mean()) if best.size else 0.0
    return scores


def candidate_nerf_pairs(scores: Float[np.ndarray, "k k"], min_score: float, top_k: int) -> list[tuple[int, int]]:
    """NeRF pairs (a < b) to register: those scoring at least ``min_score``, and each NeRF's ``top_k`` best-scoring
    partners (ties: the lower index), sorted."""
    k = len(scores)
    pairs = {(a, b) for a in range(k) for b in range(a + 1, k) if scores[a, b] >= min_score}
    for a in range(k):
        others = [b for b in np.argsort(-scores[a], kind="stable") if b != a][:top_k]
        pairs.update((min(a, int(b)), max(a, int(b))) for b in others)
    return sorted(pairs)


def components(k: int, linked: Sequence[tuple[int, int]]) -> Int[np.ndarray, " k"]:
    """Connected components of the graph on ``k`` NeRFs whose edges are ``linked``: a label per NeRF (the smallest
    index in its component)."""
    edges = np.asarray(linked, dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(k, k))
    _, label = connected_components(graph, directed=False)
    first = {}
    for i, c in enumerate(label):
        first.setdefault(c, i)
    return np.array([first[c] for c in label])


def border_ranks(
    k: int, linked: Sequence[tuple[int, int]], positions: Float[np.ndarray, "k 3"]
) -> Int[np.ndarray, " k"]:
    """Per NeRF, its rank within its component of ``linked`` by distance from the component's centroid, farthest
    first (0: the most outlying NeRF of its piece; a NeRF alone is rank 0). ``positions``: each NeRF's location (e.g.
    the mean of its camera centres) in a frame shared by its component; only distances inside a component are
    compared, so each component may have its own frame and scale."""
    label = components(k, linked)
    rank = np.zeros(k, dtype=int)
    for c in np.unique(label):
        inside = np.flatnonzero(label == c)
        d = np.linalg.norm(positions[inside] - positions[inside].mean(0), axis=1)
        rank[inside[np.argsort(-d, kind="stable")]] = np.arange(len(inside))
    return rank


def bridging_pairs(
    scores: Float[np.ndarray, "k k"], linked: Sequence[tuple[int, int]], tried: set[tuple[int, int]],
    per_component: int, border: Int[np.ndarray, " k"] | None = None, max_border_rank: int | None = None,
) -> list[tuple[int, int]]:
    """NeRF pairs (a < b) that could join a graph left in pieces: for every component of ``linked``, its
    ``per_component`` best-scoring pairs to NeRFs outside it that are not in ``tried``, sorted. Empty when the graph is
    connected or every joining pair was tried.

    With ``border`` (:func:`border_ranks`) and ``max_border_rank``, a piece first pairs its NeRFs of rank below
    ``max_border_rank`` with the NeRFs of the same ranks of other pieces (pieces meet at their edges, not through their
    middles), and looks beyond them only when no such pair is left untried.

    Retrieval scores rank a NeRF's true neighbours only roughly where the captures look alike everywhere (shared
    materials, repeated facades); asking each piece for its next-best partners connects such graphs at a cost that
    grows with the number of pieces, not with the square of the number of NeRFs.
    """
    k = len(scores)
    label = components(k, linked)
    outer = np.ones(k, dtype=bool) if border is None or max_border_rank is None else border < max_border_rank
    pairs: set[tuple[int, int]] = set()
    for c in np.unique(label):
        inside = np.flatnonzero(label == c)
        if len(inside) == k:
            return []
        options = [(not (outer[a] and outer[b]), -float(scores[a, b]), min(a, b), max(a, b)) for a in inside
                   for b in range(k) if label[b] != c and (min(a, b), max(a, b)) not in tried]  # fmt: skip
        options.sort()
        pairs.update((int(a), int(b)) for _, _, a, b in options[:per_component])
    return sorted(pairs)
