"""Does a capture's COLMAP reconstruction explain COLMAP's own verified matches? A fold check that needs no file order.

:mod:`nerfuser_ns.capture_check` finds a fold as a jump between views filmed in sequence; unordered photos (our street
and row-houses captures) it cannot check. This check reads what ``ns-process-data`` keeps beside the dataset: COLMAP's
database (``colmap/database.db``: keypoints, and per image pair the inlier matches its geometric verification kept)
and the reconstruction (``colmap/sparse/0``). In a consistent reconstruction every verified pair is explained by the
two views' reconstructed poses: its inliers lie on the epipolar lines those poses give. A block of views posed by the
wrong copy of repeated structure keeps its verified matches to the views it was really filmed beside, and those the
folded poses cannot explain.

For a pair with relative pose ``(R, t)`` (view 2 from view 1, from the reconstruction) and undistorted normalised
image points ``x1, x2``, the essential matrix is ``E = [t/|t|]_x R`` and each match's Sampson distance

    d = (x2^T E x1)^2 / ((E x1)_1^2 + (E x1)_2^2 + (E^T x2)_1^2 + (E^T x2)_2^2),

whose square root, times the focal length, is in pixels. A pair is *explained* when at least
:data:`EXPLAINED_SHARE` of its inliers lie within :data:`SAMPSON_PX`; a capture is reported folded when more than
:data:`MAX_UNEXPLAINED_SHARE` of its verified pairs (at least :data:`MIN_INLIERS` inliers each) are not. Pairs whose
views share a centre (no baseline: no epipolar geometry) are not judged.

The constants were fixed on one capture pair (street-8: its folded capture 29 of 521 pairs unexplained, the other 0 of
599) before the check saw any other capture (``reports/match_check_captures.md``).

**The two sides of a fold** (:func:`fold_sides`). Where repeated structure folded a capture of views that look two
ways (a street's two facades), the views form two groups joined by a few pairs, and those the reconstruction does not
explain. The graph of explained pairs is cut in two (its connected components, else the sign of the Fiedler vector of
its normalised Laplacian, the relaxed normalised cut); the cut is a fold's two sides only when each side alone passes
the check (at most :data:`MAX_UNEXPLAINED_SHARE` unexplained within it), few pairs cross it (at most
:data:`MAX_CROSS_SHARE` of the judged pairs) and most of those that do are unexplained (at least
:data:`MIN_CROSS_UNEXPLAINED_SHARE`). Otherwise (a capture folded all through, as our row houses, or one whose sides
keep many pairs, as our rooms, where matches between copies of the room are explained by the fold itself) there are no
sides to train on. These three constants were set on the folded captures on disk (street-8: 24 views face the other
facade, its sides cut exactly; room-7 and row-houses-3/4 refused), not on a fresh one.

**What it cannot see.** Only the pairs COLMAP's matcher compared can contradict a pose: exhaustive matching (what
``ns-process-data --matching-method exhaustive`` runs) compares every pair; sequential matching compares each view
with its neighbours in file order, vocabulary-tree matching with its most similar views. Views posed by a fold against
views they were never compared with then leave no pair to contradict them: a street capture in a walk's order, posed
by sequential matching, passed the check with 25 of its 52 posed views misposed
(``reports/repose_in_order_street20.md``).
The database's ``matches`` table has a row per compared pair, so the check says how many it compared
(:meth:`MatchCheck.blind_spot`).

The database is opened read-only with Python's ``sqlite3`` (COLMAP's own ``scripts/python/database.py`` reads it the
same way): ``pycolmap.Database.open`` migrates an older COLMAP's database in place, and a check never writes its inputs.
"""

from __future__ import annotations

import json
import sqlite3
from collections import Counter
from collections.abc import Collection
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pycolmap
from jaxtyping import Float
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, laplacian

from nerfuser_ns import sim3
from nerfuser_ns.capture_check import path_suffixes

MIN_INLIERS = 30
"""Verified pairs with fewer inlier matches are not judged (too few to tell a fold from a few stray matches)."""
SAMPSON_PX = 4.0
"""A match lies on its epipolar line when its Sampson distance is below this many pixels."""
EXPLAINED_SHARE = 0.5
"""A pair is explained when at least this share of its inliers lie on their epipolar lines."""
MAX_UNEXPLAINED_SHARE = 0.02
"""A capture with more than this share of its judged pairs unexplained is reported folded."""
MAX_CROSS_SHARE = 0.1
"""Two sides of a fold share at most this share of the judged pairs (:func:`fold_sides`)."""
MIN_CROSS_UNEXPLAINED_SHARE = 0.5
"""Of the pairs across two sides of a fold, at least this share are unexplained (:func:`fold_sides`)."""
MAX_REPOSE_SHARE = 0.1
"""Where no two sides show, the views that lie in every unexplained pair (:func:`pair_cover`) are named to be left out
when the capture is posed again only when they are at most this share of the judged views: a few misposed views, not a
fold through the capture (then another matcher, not fewer views)."""
MIN_VIEW_UNEXPLAINED_SHARE = 0.5
"""...and only when each of them has at least this share of its own judged pairs unexplained: a view posed wrong
contradicts most views it matches, a view posed right contradicts only the misposed ones among them. Set after the
cover had been seen to name the wrong views (drive-17 posed with one focal length: 9 views named, 3 of its 18
misposed, each with at most 34% of its pairs unexplained; street-11's one misposed view: 72%)."""
PAIR_ID_BASE = 2147483647
"""COLMAP's ``pair_id = PAIR_ID_BASE * image_id1 + image_id2`` (``image_id1 < image_id2``)."""


@dataclass
class MatchCheck:
    """The verdict on one capture; ``checked`` False (with ``reason``) when its COLMAP files are not there."""

    checked: bool
    pairs: int = 0
    """Verified pairs judged."""
    unexplained: list[tuple[str, str]] = field(default_factory=list)
    """The image names of each pair the reconstruction does not explain."""
    explained: list[tuple[str, str]] = field(default_factory=list)
    """The image names of each pair it explains."""
    reason: str | None = None
    compared_pairs: int | None = None
    """Image pairs COLMAP's matcher compared at all (None: the database does not say)."""
    possible_pairs: int | None = None
    """Image pairs of the database's images: what exhaustive matching compares."""

    @property
    def unexplained_share(self) -> float:
        return len(self.unexplained) / self.pairs if self.pairs else 0.0

    @property
    def folded(self) -> bool:
        return self.checked and self.unexplained_share > MAX_UNEXPLAINED_SHARE

    def warning(self, subject: str) -> str | None:
        """One line when the capture looks folded, else None."""
        if not self.folded:
            return None
        return (f"{subject}: COLMAP's reconstruction does not explain {len(self.unexplained)} of its {self.pairs} "
                f"verified image pairs ({100 * self.unexplained_share:.1f}%, above "
                f"{100 * MAX_UNEXPLAINED_SHARE:.0f}%): some views are posed inconsistently with the matches between "
                "them, as when repeated structure folds a capture")  # fmt: skip

    def blind_spot(self) -> str | None:
        """One line when COLMAP compared only some of the image pairs (sequential or vocabulary-tree matching), else
        None: a fold between views it never compared leaves no verified pair to contradict it."""
        if self.compared_pairs is None or not self.possible_pairs or self.compared_pairs >= self.possible_pairs:
            return None
        return (f"COLMAP compared {self.compared_pairs} of its {self.possible_pairs} image pairs (exhaustive matching "
                "compares them all): views posed by a fold against views they were never compared with leave no pair "
                "to contradict them, so this check vouches only for the pairs compared (on a generated street "
                "posed by sequential matching it passed a capture with 25 of 52 views misposed)")  # fmt: skip

    def view_shares(self) -> dict[str, float]:
        """Per view in an unexplained pair, the share of its judged pairs that are unexplained: a view posed wrong
        contradicts most views it matches, a view posed right only the misposed ones among them (or the few it shares
        wrong matches with)."""
        unexplained = Counter(name for pair in self.unexplained for name in pair)
        judged = unexplained + Counter(name for pair in self.explained for name in pair)
        return {name: count / judged[name] for name, count in unexplained.items()}

    def views(self) -> list[tuple[str, int]]:
        """Image names by how many unexplained pairs they are in, most first: where to look."""
        counts = Counter(name for pair in self.unexplained for name in pair)
        return sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))

    @cached_property
    def smaller_side(self) -> tuple[str, ...] | None:
        """The image names of a folded capture's smaller side (:func:`fold_sides`); None when it is not folded or its
        views form no two consistent sides."""
        if not self.folded:
            return None
        sides = fold_sides(self.explained, self.unexplained)
        return None if sides is None else sides[1]

    @cached_property
    def repose_without(self) -> tuple[str, ...] | None:
        """The views to leave out when a folded capture with no two sides is posed again: those that lie in every
        unexplained pair (:func:`pair_cover`), when they are at most :data:`MAX_REPOSE_SHARE` of the judged views and
        each has at least :data:`MIN_VIEW_UNEXPLAINED_SHARE` of its own pairs unexplained; else None (not folded, two
        sides to train on, too many views, or views that look posed right)."""
        if not self.folded or self.smaller_side is not None:
            return None
        cover = pair_cover(self.unexplained)
        judged = {name for pair in [*self.unexplained, *self.explained] for name in pair}
        if len(cover) > MAX_REPOSE_SHARE * len(judged):
            return None
        shares = self.view_shares()
        if any(shares[name] < MIN_VIEW_UNEXPLAINED_SHARE for name in cover):
            return None
        return tuple(sorted(cover))

    def to_record(self) -> dict:
        smaller, repose = self.smaller_side, self.repose_without
        return {"checked": self.checked, "pairs": self.pairs, "unexplained_pairs": len(self.unexplained),
                "unexplained_share": round(self.unexplained_share, 4), "folded": self.folded,
                "smaller_side": None if smaller is None else list(smaller),
                "repose_without": None if repose is None else list(repose), "reason": self.reason,
                "compared_pairs": self.compared_pairs, "possible_pairs": self.possible_pairs}  # fmt: skip


def pair_cover(pairs: Collection[tuple[str, str]]) -> list[str]:
    """Views that together lie in every pair of ``pairs``, taken greedily: the view in most of the pairs not yet
    covered first (ties by name, so the answer is deterministic). One misposed view leaves its unexplained pairs with
    views posed right, so it alone covers them."""
    left, cover = set(pairs), []
    while left:
        counts = Counter(name for pair in left for name in pair)
        name = min(counts, key=lambda n: (-counts[n], n))
        cover.append(name)
        left = {pair for pair in left if name not in pair}
    return cover


def fold_sides(
    explained: Collection[tuple[str, str]], unexplained: Collection[tuple[str, str]]
) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
    """The larger and the smaller side of a fold (image names, sorted): the cut of the explained-pair graph described
    in the module's docstring, or None when the cut is no fold's two sides."""
    views = sorted({name for pair in [*explained, *unexplained] for name in pair})
    if len(views) < 2 or not explained:
        return None
    index = {name: i for i, name in enumerate(views)}
    ij = np.array([(index[a], index[b]) for a, b in explained]).T
    graph = coo_matrix((np.ones(ij.shape[1]), (ij[0], ij[1])), shape=(len(views),) * 2)
    graph = (graph + graph.T).tocsr()
    count, component = connected_components(graph, directed=False)
    if count > 1:  # no explained pair joins them: the largest component against the rest
        side = component == np.bincount(component).argmax()
    else:
        # a dense eigensolve: a capture's views number in the hundreds
        _, vectors = np.linalg.eigh(laplacian(graph, normed=True).toarray())
        side = vectors[:, 1] > 0
    if side.sum() < len(views) - side.sum():
        side = ~side
    larger = {views[i] for i in np.flatnonzero(side)}
    # per pair, how many of its views lie on the larger side: 0 or 2 within a side, 1 across
    good = np.array([(a in larger) + (b in larger) for a, b in explained], dtype=int)
    bad = np.array([(a in larger) + (b in larger) for a, b in unexplained], dtype=int)
    for where in (0, 2):  # each side alone passes the check
        total = (good == where).sum() + (bad == where).sum()
        if total == 0 or (bad == where).sum() > MAX_UNEXPLAINED_SHARE * total:
            return None
    cross = (good == 1).sum() + (bad == 1).sum()
    if cross > MAX_CROSS_SHARE * (len(good) + len(bad)) or (bad == 1).sum() < MIN_CROSS_UNEXPLAINED_SHARE * cross:
        return None
    return tuple(sorted(larger)), tuple(v for v in views if v not in larger)


def sampson_distances(
    x1: Float[np.ndarray, "n 2"], x2: Float[np.ndarray, "n 2"], R: Float[np.ndarray, "3 3"], t: Float[np.ndarray, " 3"]
) -> Float[np.ndarray, " n"]:
    """Sampson distance (normalised image units) of each match ``x1 <-> x2`` to the epipolar geometry of the pose
    ``x2 ~ R x1 + t`` (view 2 from view 1); NaN when ``t`` is zero (no baseline, no epipolar geometry)."""
    norm = np.linalg.norm(t)
    if norm < 1e-12:
        return np.full(len(x1), np.nan)
    E = sim3.so3_hat(np.asarray(t, dtype=np.float64) / norm) @ np.asarray(R, dtype=np.float64)
    p1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    p2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    e1, e2 = p1 @ E.T, p2 @ E
    num = np.einsum("ij,ij->i", p2, e1) ** 2
    den = e1[:, 0] ** 2 + e1[:, 1] ** 2 + e2[:, 0] ** 2 + e2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


def read_verified_pairs(
    database: Path | str, min_inliers: int = MIN_INLIERS
) -> tuple[dict[int, str], dict[int, np.ndarray], list[tuple[int, int, np.ndarray]]]:
    """From a COLMAP database, read-only: image names by id, keypoint positions ``[k, 2]`` (pixels) by id, and each
    verified pair with at least ``min_inliers`` inlier matches as ``(image_id1, image_id2, matches [m, 2])``."""
    # immutable: no lock and no -shm/-wal files beside a WAL database (COLMAP's); the file is only read
    uri = f"{Path(database).resolve().as_uri()}?mode=ro&immutable=1"
    try:
        with sqlite3.connect(uri, uri=True) as con:
            names = dict(con.execute("SELECT image_id, name FROM images"))
            keypoints = {
                image_id: np.frombuffer(data, np.float32).reshape(rows, cols)[:, :2].astype(np.float64)
                for image_id, rows, cols, data in con.execute("SELECT image_id, rows, cols, data FROM keypoints")
                if rows > 0
            }
            pairs = []
            for pair_id, rows, data in con.execute(
                "SELECT pair_id, rows, data FROM two_view_geometries WHERE rows >= ?", (min_inliers,)
            ):
                id2 = pair_id % PAIR_ID_BASE
                pairs.append(((pair_id - id2) // PAIR_ID_BASE, id2, np.frombuffer(data, np.uint32).reshape(rows, 2)))
    except sqlite3.Error as e:
        raise ValueError(f"{database}: not a readable COLMAP database ({e})") from None
    return names, keypoints, pairs


def compared_pairs(database: Path | str) -> tuple[int, int] | None:
    """``(pairs compared, pairs of its images)`` of a COLMAP database, read-only: its ``matches`` table holds one row
    per image pair the matcher compared, matched or not; None for a database without that table."""
    uri = f"{Path(database).resolve().as_uri()}?mode=ro&immutable=1"
    try:
        with sqlite3.connect(uri, uri=True) as con:
            images = con.execute("SELECT COUNT(*) FROM images").fetchone()[0]
            compared = con.execute("SELECT COUNT(*) FROM matches").fetchone()[0]
    except sqlite3.OperationalError:  # no matches table (a database written by another tool)
        return None
    except sqlite3.Error as e:
        raise ValueError(f"{database}: not a readable COLMAP database ({e})") from None
    return int(compared), images * (images - 1) // 2


def match_check(
    reconstruction: pycolmap.Reconstruction, database: Path | str, views: Collection[str] | None = None
) -> MatchCheck:
    """Judge every verified pair of ``database`` whose two images ``reconstruction`` posed (and ``views`` names, image
    names as COLMAP stores them, where given)."""
    names, keypoints, pairs = read_verified_pairs(database)
    posed = {image.name: image for image in reconstruction.images.values()}
    if views is not None:
        views = set(views)
        posed = {name: image for name, image in posed.items() if name in views}
    judged, unexplained, explained = 0, [], []
    for id1, id2, matches in pairs:
        n1, n2 = names.get(id1), names.get(id2)
        if n1 not in posed or n2 not in posed or id1 not in keypoints or id2 not in keypoints:
            continue
        a, b = posed[n1], posed[n2]
        cam_a, cam_b = reconstruction.cameras[a.camera_id], reconstruction.cameras[b.camera_id]
        x1 = np.asarray(cam_a.cam_from_img(keypoints[id1][matches[:, 0]]), dtype=np.float64)
        x2 = np.asarray(cam_b.cam_from_img(keypoints[id2][matches[:, 1]]), dtype=np.float64)
        rel = b.cam_from_world() * a.cam_from_world().inverse()
        d = sampson_distances(x1, x2, np.asarray(rel.rotation.matrix()), np.asarray(rel.translation))
        if np.isnan(d).all():
            continue
        focal = 0.5 * (cam_a.mean_focal_length() + cam_b.mean_focal_length())  # normalised units to pixels
        judged += 1
        (explained if np.mean(d * focal < SAMPSON_PX) >= EXPLAINED_SHARE else unexplained).append((n1, n2))
    compared, possible = compared_pairs(database) or (None, None)
    return MatchCheck(checked=True, pairs=judged, unexplained=unexplained, explained=explained,
                      compared_pairs=compared, possible_pairs=possible)  # fmt: skip


def check_dataset_matches(path: Path | str) -> MatchCheck:
    """:func:`match_check` on an ``ns-process-data`` output folder (or a transforms file in it: then of its frames
    alone, as a run trained on ``transforms_larger_side.json`` saw them): its ``colmap/database.db`` and
    ``colmap/sparse/0``; not checked (with the reason) where they are missing."""
    folder = Path(path)
    views = None
    if folder.is_file():
        try:
            views = set().union(*(path_suffixes(str(f["file_path"])) for f in json.loads(folder.read_text())["frames"]))
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise ValueError(f"{folder}: not a transforms file with frames ({e})") from None
        folder = folder.parent
    database, model = folder / "colmap" / "database.db", folder / "colmap" / "sparse" / "0"
    if not database.is_file() or not model.is_dir():
        reason = f"no COLMAP database and model under {folder / 'colmap'} (posed another way, or it was removed)"
        return MatchCheck(checked=False, reason=reason)
    try:
        reconstruction = pycolmap.Reconstruction(str(model))
    except (RuntimeError, ValueError) as e:
        raise ValueError(f"{model}: not a readable COLMAP model ({e})") from None
    return match_check(reconstruction, database, views)
