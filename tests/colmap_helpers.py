"""A COLMAP capture as ``ns-process-data`` leaves it (transforms.json, ``colmap/database.db`` and the model
``colmap/sparse/0``) from synthetic street views, once consistent and once with some views posed by the street's
half-turn twin: what the match check (nerfuser_ns.match_check) reads.

Imported as ``colmap_helpers`` (pytest puts this folder on ``sys.path``; the tests are not a package)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nerfuser_ns import sim3
from nerfuser_ns.match_check import PAIR_ID_BASE

FOCAL, WIDTH, HEIGHT = 200.0, 320, 240
NUM_VIEWS = 12
FOLDED = (3, 7, 10)
"""Views the folded model poses by the twin (unordered: spread over the file order)."""

# COLMAP's own table definitions (src/colmap/scene/database.cc), the four this check reads.
SCHEMA = """
CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE,
    camera_id INTEGER NOT NULL);
CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB);
CREATE TABLE matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB);
CREATE TABLE two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL,
    data BLOB, config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB);
"""


def street() -> tuple[np.ndarray, np.ndarray]:
    """World points on two facades and camera-from-world poses [N, 3, 4] (OpenCV axes) of views along the street,
    each turned towards one facade or the other, in no filmed order."""
    rng = np.random.default_rng(0)
    n = 600
    side = np.where(rng.random(n) < 0.5, -4.0, 4.0)
    points = np.stack([side, rng.uniform(-1.5, 1.5, n), rng.uniform(0.0, 12.0, n)], axis=1)  # y down, z along
    poses = []
    for i in rng.permutation(NUM_VIEWS):
        yaw = np.radians(rng.uniform(-35.0, 35.0))
        R_wc = sim3.so3_exp(np.array([0.0, yaw, 0.0]))  # camera-to-world rotation, looking along +z, turned
        centre = np.array([rng.uniform(-0.5, 0.5), 0.0, 1.0 * i - 6.0])
        R = R_wc.T
        poses.append(np.concatenate([R, (-R @ centre)[:, None]], axis=1))
    return points, np.stack(poses)


TWO_WAY_VIEWS = 20
TWO_WAY_RIGHT = tuple(range(1, TWO_WAY_VIEWS - 1, 3))
"""Views of the two-way street that face the right facade (and are folded); the others face the left, but the last,
which looks along the street and sees both (the one view joining the two groups)."""


def two_way_street() -> tuple[np.ndarray, np.ndarray]:
    """As :func:`street`, but each view faces one facade square on (so views facing different facades share no
    match), and one view looks along the street: a capture of two groups of views joined by one view."""
    rng = np.random.default_rng(1)
    n = 1200
    side = np.where(rng.random(n) < 0.5, -4.0, 4.0)
    points = np.stack([side, rng.uniform(-1.5, 1.5, n), rng.uniform(-8.0, 20.0, n)], axis=1)
    poses = []
    for i in range(TWO_WAY_VIEWS):
        yaw = 0.0 if i == TWO_WAY_VIEWS - 1 else 90.0 if i in TWO_WAY_RIGHT else -90.0
        R = sim3.so3_exp(np.radians([0.0, yaw, 0.0])).T
        centre = np.array([0.0, 0.0, -6.0 if i == TWO_WAY_VIEWS - 1 else 0.6 * i])
        poses.append(np.concatenate([R, (-R @ centre)[:, None]], axis=1))
    return points, np.stack(poses)


def project(points: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = points @ pose[:, :3].T + pose[:, 3]
    uv = FOCAL * cam[:, :2] / cam[:, 2:3] + np.array([WIDTH / 2, HEIGHT / 2])
    seen = (cam[:, 2] > 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < WIDTH) & (uv[:, 1] >= 0) & (uv[:, 1] < HEIGHT)
    return uv, seen


def twin(pose: np.ndarray) -> np.ndarray:
    """The pose by the street's half-turn twin: turned 180 deg about the vertical through the street's middle."""
    R = sim3.so3_exp(np.radians([0.0, 180.0, 0.0]))
    half_turn = sim3.make_sim3(R, np.zeros(3))
    cam_from_world = np.concatenate([pose, [[0.0, 0.0, 0.0, 1.0]]])
    return (cam_from_world @ np.linalg.inv(half_turn))[:3]


def write_colmap_capture(
    folder: Path, folded: bool, scene=street, twins: tuple[int, ...] = FOLDED, overlap: int | None = None
) -> Path:
    """An ns-process-data-like folder: transforms.json, colmap/database.db and the text model colmap/sparse/0; with
    ``folded``, the views ``twins`` posed by the half-turn twin. Every pair of views compared (exhaustive matching),
    or with ``overlap`` each view with the next ``overlap`` files only (sequential matching)."""
    points, poses = scene()
    num_views = len(poses)
    names = [f"frame_{i + 1:05d}.png" for i in range(num_views)]
    (folder / "colmap" / "sparse" / "0").mkdir(parents=True)
    con = sqlite3.connect(folder / "colmap" / "database.db")
    con.executescript(SCHEMA)
    seen_by = []
    for i, name in enumerate(names):
        uv, seen = project(points, poses[i])
        con.execute("INSERT INTO images VALUES (?, ?, 1)", (i + 1, name))
        kp = np.zeros((len(points), 6), np.float32)  # one keypoint per world point (SIFT's affine columns beside)
        kp[:, :2] = uv
        con.execute("INSERT INTO keypoints VALUES (?, ?, 6, ?)", (i + 1, len(points), kp.tobytes()))
        seen_by.append(seen)
    for a in range(num_views):
        for b in range(a + 1, num_views if overlap is None else min(num_views, a + overlap + 1)):
            common = np.flatnonzero(seen_by[a] & seen_by[b])
            m, pair_id = np.stack([common, common], axis=1).astype(np.uint32), (a + 1) * PAIR_ID_BASE + b + 1
            con.execute("INSERT INTO matches VALUES (?, ?, 2, ?)", (pair_id, len(m), m.tobytes()))  # compared
            if len(common):
                con.execute("INSERT INTO two_view_geometries (pair_id, rows, cols, data, config) "
                            "VALUES (?, ?, 2, ?, 2)", (pair_id, len(m), m.tobytes()))  # fmt: skip
    con.commit()
    con.close()
    model = folder / "colmap" / "sparse" / "0"
    (model / "cameras.txt").write_text(f"1 PINHOLE {WIDTH} {HEIGHT} {FOCAL} {FOCAL} {WIDTH / 2} {HEIGHT / 2}\n")
    lines = []
    for i, name in enumerate(names):
        pose = twin(poses[i]) if folded and i in twins else poses[i]
        x, y, z, w = Rotation.from_matrix(pose[:, :3]).as_quat()  # COLMAP writes w first
        lines += [f"{i + 1} {w} {x} {y} {z} {' '.join(map(str, pose[:, 3]))} 1 {name}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("")
    frames = [{"file_path": f"images/{n}", "transform_matrix": np.eye(4).tolist()} for n in names]
    (folder / "transforms.json").write_text(json.dumps({"camera_model": "PINHOLE", "fl_x": FOCAL, "fl_y": FOCAL,
                                                        "cx": WIDTH / 2, "cy": HEIGHT / 2, "w": WIDTH, "h": HEIGHT,
                                                        "frames": frames}))  # fmt: skip
    return folder
