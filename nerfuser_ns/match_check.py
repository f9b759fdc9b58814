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

The database is opened read-only with Python's ``sqlite3`` (COLMAP's own ``scripts/python/database.py`` reads it the
same way): ``pycolmap.Database.open`` migrates an older COLMAP's database in place, and a check never writes its inputs.
"""

from __future__ import annotations

import sqlite3
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from jaxtyping import Float

from nerfuser_ns import sim3

MIN_INLIERS = 30
"""Verified pairs with fewer inlier matches are not judged (too few to tell a fold from a few stray matches)."""
SAMPSON_PX = 4.0
"""A match lies on its epipolar line when its Sampson distance is below this many pixels."""
EXPLAINED_SHARE = 0.5
"""A pair is explained when at least this share of its inliers lie on their epipolar lines."""
MAX_UNEXPLAINED_SHARE = 0.02
"""A capture with more than this share of its judged pairs unexplained is reported folded."""
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
    reason: str | None = None

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

    def views(self) -> list[tuple[str, int]]:
        """Image names by how many unexplained pairs they are in, most first: where to look."""
        counts = Counter(name for pair in self.unexplained for name in pair)
        return sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))

    def to_record(self) -> dict:
        return {"checked": self.checked, "pairs": self.pairs, "unexplained_pairs": len(self.unexplained),
                "unexplained_share": round(self.unexplained_share, 4), "folded": self.folded,
                "reason": self.reason}  # fmt: skip


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


def match_check(reconstruction: pycolmap.Reconstruction, database: Path | str) -> MatchCheck:
    """Judge every verified pair of ``database`` whose two images ``reconstruction`` posed."""
    names, keypoints, pairs = read_verified_pairs(database)
    posed = {image.name: image for image in reconstruction.images.values()}
    judged, unexplained = 0, []
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
        if np.mean(d * focal < SAMPSON_PX) < EXPLAINED_SHARE:
            unexplained.append((n1, n2))
    return MatchCheck(checked=True, pairs=judged, unexplained=unexplained)


def check_dataset_matches(path: Path | str) -> MatchCheck:
    """:func:`match_check` on an ``ns-process-data`` output folder (or its transforms.json): its
    ``colmap/database.db`` and ``colmap/sparse/0``; not checked (with the reason) where they are missing."""
    folder = Path(path)
    folder = folder.parent if folder.is_file() else folder
    database, model = folder / "colmap" / "database.db", folder / "colmap" / "sparse" / "0"
    if not database.is_file() or not model.is_dir():
        reason = f"no COLMAP database and model under {folder / 'colmap'} (posed another way, or it was removed)"
        return MatchCheck(checked=False, reason=reason)
    try:
        reconstruction = pycolmap.Reconstruction(str(model))
    except (RuntimeError, ValueError) as e:
        raise ValueError(f"{model}: not a readable COLMAP model ({e})") from None
    return match_check(reconstruction, database)
