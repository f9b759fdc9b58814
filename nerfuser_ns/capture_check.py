"""Has COLMAP folded a run's capture? A check from its training cameras alone, before any registration.

On repeated structure (a room whose walls look alike from either side) COLMAP can pose a part of a capture by the
wrong copy of the structure: a block of views lands a half turn away from where it was filmed, the bundle adjustment
accepts it, and the run is trained on the folded poses. No registration can mend that run.

Views filmed in sequence (a video's frames, photos named in the order they were taken) turn by small steps from one
to the next. A view posed by the wrong copy sits roughly a half turn away from its correctly posed neighbour, so in
file order the capture shows a *jump*: a turn of more than :data:`FOLD_TURN_DEG` between neighbours whose typical
(median) turn is below :data:`SEQUENCE_STEP_DEG`. A multi-camera rig exported per exposure interleaves its cameras
in file order (camera 1, 2, ... of one exposure, then the next): each camera's views are then a sequence at a fixed
lag, the number of cameras, and the smallest lag up to :data:`MAX_RIG_CAMERAS` whose median turn is below the step
and at which the turns between neighbours repeat as a rigid rig's do (:func:`_is_rig`) is taken, each camera's views
checked as a sequence of their own (their frame numbers modulo the lag). Captures
whose file order is no sequence at any such lag (unordered photos) cannot be checked this way and are reported as
unchecked, never as folded. A rig exported camera by camera (all of camera 1's views, then camera 2's) is one
sequence with a turn at each change of camera: where two cameras look more than :data:`FOLD_TURN_DEG` apart (front
and back) that change reads as a jump, a false alarm to rule out by looking at the views named.

The views between jumps alternate between the two sides of the fold; the smaller side is reported as the suspect
views. Each side alone is a consistent capture (its views posed against the same copy), so a folded capture can be
trained on its larger side (:func:`write_larger_side`); that side may miss the views of the place's unique objects
(on our rooms the folded block held every far view of the door), which a registration needs to tell the place from
its copy. Neighbours whose file names' frame numbers lie more than :data:`MAX_FRAME_GAP` apart are not compared
(views are missing between them). A fold by a translation (a copy further along a street) is not detected.

COLMAP's camera can drift too. ``ns-process-data`` gives COLMAP a camera with a focal length per axis and refines the
principal point; where the views do not fix them (a car's rig moving along one line, every camera level) the bundle
adjustment trades the vertical focal length and principal point against the scene's depth, and the capture's
geometry comes out stretched along the vertical: no similarity transform then maps one run onto another, and every
view's rotation is off by a common tilt in its own frame. Camera pixels are square, so a vertical over horizontal
focal length more than :data:`MAX_ASPECT_DEVIATION` from 1 is reported (:func:`intrinsics_check`).
"""

from __future__ import annotations

import json
import re
import shutil
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.files import atomic_dir, write_text_atomic

FOLD_TURN_DEG = 120.0
"""A turn between neighbouring views (file order) above this is a jump: a half turn less a sequence's largest steps."""
SEQUENCE_STEP_DEG = 30.0
"""A capture whose median turn between neighbours is above this is not filmed in file order: not checked."""
MAX_FRAME_GAP = 2
"""Neighbours in file order whose frame numbers differ by more are not compared (views between them are missing;
nerfstudio's training split leaves out every tenth, a gap of 2)."""
MAX_RIG_CAMERAS = 12
"""The most cameras of a rig whose interleaved views (one exposure after another) the check looks for: lags 1 to
this (a fixed bound, larger than the common rigs of 2 to 8 cameras)."""
MEDOID_SAMPLES = 256
"""A rig's mounting (the typical turn between two of its cameras) is the medoid of at most this many exposures."""
MAX_FRAME_SPAN = 16
"""Frame numbers ending the file names count frames only where they span at most this many per view (a larger side
or a training split keeps at least every second view); otherwise (timestamps) the views are taken in file order."""
MAX_ASPECT_DEVIATION = 0.02
"""COLMAP's vertical over horizontal focal length may differ from 1 by at most this: sensors have square pixels and
COLMAP recovers their ratio to well within it where the views fix it (within 0.004 on our street and row-house
captures); drifted drive captures showed 1.07 to 1.41."""
SQUARE_PIXEL_ADVICE = (
    "pose it again with one focal length: ns-process-data images ... --camera-type simple_pinhole "
    "(images without lens distortion; with distortion, COLMAP's SIMPLE_RADIAL camera, then ns-process-data "
    "--skip-colmap: nerfuser_ns's docs/your_own_captures.md), and check again"
)
"""What to do about a capture whose intrinsics drifted."""
REPOSED_FOLDER_SUFFIX = "_reposed"
"""Where ``ns-nerfuser-check-capture`` suggests posing a drifted capture again: beside it, named as it with this."""
RADIAL_FOLDER_SUFFIX = "_radial"
"""The SIMPLE_RADIAL posing's dataset goes beside the capture's, named as it with this suffix."""
REPOSE_FOLDER_NAME = "images_to_repose"
"""Where ``ns-nerfuser-check-capture --write-images-to-repose`` copies a capture's images but its few misposed views
(beside its transforms.json), to be posed again by ``ns-process-data images``."""
LARGER_SIDE_NAME = "transforms_larger_side.json"
"""Where ``ns-nerfuser-check-capture --write-larger-side`` writes a folded capture's larger side (beside its
transforms.json)."""


@dataclass(frozen=True)
class FoldCheck:
    """What :func:`fold_check` found in one capture."""

    num_views: int
    """Views checked."""
    median_turn_deg: float
    """Median turn between neighbouring views in file order."""
    checked: bool
    """False when the file order is no sequence (median turn above :data:`SEQUENCE_STEP_DEG`): nothing is claimed."""
    jumps: tuple[tuple[str, str, float], ...]
    """(view, next view, turn in degrees) for every jump."""
    suspect: tuple[str, ...]
    """The views on the smaller side of the jumps (none without jumps)."""
    rig_cameras: int = 1
    """The lag at which the file order is a sequence: 1 for one camera, the number of cameras of an interleaved rig."""

    @property
    def suspect_views(self) -> int:
        return len(self.suspect)

    @property
    def folded(self) -> bool:
        return self.checked and len(self.jumps) > 0

    def warning(self, subject: str) -> str | None:
        """One line for a folded capture naming ``subject`` (a run or a dataset) and what was seen; None otherwise."""
        if not self.folded:
            return None
        first = self.jumps[0]
        order = "file order" if self.rig_cameras == 1 else f"file order, each of {self.rig_cameras} rig cameras"
        return (f"{subject}: the capture looks folded by COLMAP: {len(self.jumps)} jump(s) of more than "
                f"{FOLD_TURN_DEG:.0f} deg between neighbouring views in {order} (first {first[0]} -> {first[1]}, "
                f"{first[2]:.0f} deg; median turn {self.median_turn_deg:.0f} deg): {self.suspect_views} of "
                f"{self.num_views} views look posed by the wrong copy of repeated structure")  # fmt: skip

    def to_record(self) -> dict:
        return {"num_views": self.num_views, "median_turn_deg": round(self.median_turn_deg, 2),
                "checked": self.checked, "rig_cameras": self.rig_cameras, "folded": self.folded,
                "suspect_views": self.suspect_views,
                "jumps": [[a, b, round(d, 1)] for a, b, d in self.jumps], "suspect": list(self.suspect)}  # fmt: skip


def neighbour_turns(c2w: Float[np.ndarray, "n 4 4"] | Float[np.ndarray, "n 3 4"]) -> Float[np.ndarray, " n_1"]:
    """Rotation angle (degrees) between each view and the next: ``angle(R_i^T R_{i+1})``."""
    R = np.asarray(c2w, dtype=np.float64)[:, :3, :3]
    return np.atleast_1d(sim3.rotation_angle_deg(np.swapaxes(R[:-1], -1, -2) @ R[1:]))


def fold_check(
    c2w: Float[np.ndarray, "n 4 4"] | Float[np.ndarray, "n 3 4"],
    names: Sequence[str],
    fold_turn_deg: float = FOLD_TURN_DEG,
    sequence_step_deg: float = SEQUENCE_STEP_DEG,
) -> FoldCheck:
    """Jumps between neighbouring views of one capture, its views taken in the order of ``names`` (file names; the
    poses may be in any frame and scale: only relative rotations count). Each of an interleaved rig's cameras is
    checked as its own sequence; the smaller side is counted over all of them."""
    if len(names) != len(c2w):
        raise ValueError(f"fold_check: {len(c2w)} poses but {len(names)} names")
    order = np.argsort(np.asarray([str(n) for n in names]), kind="stable")
    names = [str(names[i]) for i in order]
    n = len(names)
    if n < 3:
        return FoldCheck(n, 0.0, False, (), ())
    R = np.asarray(c2w, dtype=np.float64)[order]
    frames = _frame_index(names)
    first_median = None
    for lag in range(1, min(MAX_RIG_CAMERAS, n // 3) + 1):
        streams = [np.flatnonzero(frames % lag == r) for r in range(lag)]
        parts = [(s, neighbour_turns(R[s]), _adjacent(frames[s], lag)) for s in streams if len(s) >= 2]
        compared = np.concatenate([t[a] for _, t, a in parts]) if parts else np.zeros(0)
        median = float(np.median(compared)) if compared.size else 0.0
        first_median = median if first_median is None else first_median
        if compared.size and median <= sequence_step_deg and (lag == 1 or _is_rig(R, frames, lag, sequence_step_deg)):
            break
    else:
        return FoldCheck(n, first_median or 0.0, False, (), ())
    edges = [(int(s[i]), int(s[i + 1]), float(t[i])) for s, t, a in parts for i in np.flatnonzero(a)]
    if lag > 1:
        edges += _rig_neighbour_edges(R, frames, lag)
    jumps = sorted((i, j, t) for i, j, t in edges if t > fold_turn_deg)
    side = _sides(n, [(i, j, t > fold_turn_deg) for i, j, t in edges])
    smaller = 1 if side.sum() <= n - side.sum() else 0  # a tie: the side the first view is not on
    suspect = tuple(names[i] for i in np.flatnonzero(side == smaller)) if jumps else ()
    return FoldCheck(n, median, True, tuple((names[i], names[j], t) for i, j, t in jumps), suspect, rig_cameras=lag)


def _rig_neighbour_edges(
    R: Float[np.ndarray, "n 3 4"] | Float[np.ndarray, "n 4 4"], frames: np.ndarray, lag: int
) -> list[tuple[int, int, float]]:
    """A rig's neighbouring cameras of one exposure (consecutive frame numbers), compared after removing the rig's
    mounting: the turn from camera k to camera k + 1 less its typical turn (the medoid over the exposures). These
    tie the cameras' sequences together, so that a fold is one side of the whole capture, not one per camera."""
    rot = np.asarray(R, dtype=np.float64)[:, :3, :3]
    i = np.flatnonzero(np.diff(frames) == 1)
    if not len(i):
        return []
    turn = np.swapaxes(rot[i], -1, -2) @ rot[i + 1]
    edges = []
    for r in range(lag):
        camera = frames[i] % lag == r
        if not camera.any():
            continue
        k, q = i[camera], turn[camera]
        few = q[:: -(-len(q) // MEDOID_SAMPLES)]  # the medoid of an even subsample: bounded cost on long videos
        apart = sim3.rotation_angle_deg(np.swapaxes(few[:, None], -1, -2) @ few[None])
        mounting = few[int(np.argmin(np.atleast_2d(apart).sum(1)))]
        residual = np.atleast_1d(sim3.rotation_angle_deg(mounting.T @ q))
        edges += [(int(a), int(a) + 1, float(d)) for a, d in zip(k, residual, strict=True)]
    return edges


def _sides(n: int, edges: Sequence[tuple[int, int, bool]]) -> np.ndarray:
    """Each view's side of the fold (0: the first view's), walking the compared neighbours (``(i, j, jump)``; a jump
    crosses the fold). Views no comparison links (missing views between them) join their file-order neighbour's
    side: where nothing was compared, no fold is claimed."""
    graph: list[list[tuple[int, bool]]] = [[] for _ in range(n)]
    for i, j, jump in edges:
        graph[i].append((j, jump))
        graph[j].append((i, jump))
    side = np.full(n, -1, dtype=np.int64)
    for root in range(n):  # in file order: a view not yet reached starts on its predecessor's side
        if side[root] >= 0:
            continue
        side[root] = side[root - 1] if root else 0
        queue = deque([root])
        while queue:
            u = queue.popleft()
            for v, jump in graph[u]:
                if side[v] < 0:
                    side[v] = side[u] ^ int(jump)
                    queue.append(v)
    return side


def _is_rig(
    R: Float[np.ndarray, "n 3 4"] | Float[np.ndarray, "n 4 4"], frames: np.ndarray, lag: int, step_deg: float
) -> bool:
    """Whether views in file order repeat a rig's mounting every ``lag`` views: the turn from each view to the next
    (camera k to camera k + 1 of one exposure) is the turn ``lag`` views later, in the median within ``step_deg``.
    Unordered views can show a small median turn at some lag by chance (streets, row houses); a rigid rig repeats."""
    index = frames - frames.min()
    at = np.full(int(index.max()) + 1, -1)
    at[index] = np.arange(len(R))
    rot = np.asarray(R, dtype=np.float64)[:, :3, :3]
    i = np.arange(len(at) - lag - 1)
    ok = (at[i] >= 0) & (at[i + 1] >= 0) & (at[i + lag] >= 0) & (at[i + lag + 1] >= 0)
    if not ok.any():
        return False
    a, b, c, d = (at[i[ok] + k] for k in (0, 1, lag, lag + 1))
    turn = np.swapaxes(rot[a], -1, -2) @ rot[b]
    later = np.swapaxes(rot[c], -1, -2) @ rot[d]
    return float(np.median(sim3.rotation_angle_deg(np.swapaxes(turn, -1, -2) @ later))) <= step_deg


def _frame_index(names: Sequence[str]) -> np.ndarray:
    """Each view's frame: the number ending its file name (``frame_00012.png``: 12) where every name has its own and
    they count frames, else its place in file order (names without numbers, repeated numbers, or numbers spread over
    more than :data:`MAX_FRAME_SPAN` per view, such as timestamps)."""
    numbers = [re.search(r"(\d+)$", Path(name).stem) for name in names]
    if all(numbers):
        frames = np.array([int(m.group(1)) for m in numbers])
        unique = len(np.unique(frames)) == len(frames)
        if unique and int(frames.max() - frames.min()) <= MAX_FRAME_SPAN * len(frames):
            return frames
    return np.arange(len(names))


def _adjacent(frames: np.ndarray, lag: int = 1) -> np.ndarray:
    """Which neighbours in file order were filmed next to each other (``frames``: :func:`_frame_index` of the whole
    capture, so every stream of a rig is judged alike): those at most :data:`MAX_FRAME_GAP` exposures (``lag`` frames
    each) apart (a dataset without some views, e.g. a larger side, or nerfstudio's training split, must not read as
    jumps where views are missing)."""
    return np.diff(frames) <= MAX_FRAME_GAP * lag


def dataset_file(path: Path | str) -> Path:
    """A nerfstudio dataset's ``transforms.json`` from the file or its folder; ValueError (one line) if missing."""
    path = Path(path)
    file = path / "transforms.json" if path.is_dir() else path
    if not file.is_file():
        raise ValueError(f"{path}: no transforms.json (give an ns-process-data output folder or its transforms.json)")
    return file


def process_data_command(
    images: Path, output_dir: Path, camera_type: str = "perspective", matching_method: str | None = None,
    use_gpu: bool = True, ns_process_data: str = "ns-process-data", num_downscales: int | None = None,
    skip_colmap: bool = False,
) -> list[str]:
    """``ns-process-data images`` on ``images`` into ``output_dir``, naming only the options that differ from its
    defaults: ``camera_type`` (its default ``perspective``, COLMAP's OPENCV camera), ``matching_method`` (``None``:
    its default), ``use_gpu=False`` (``--no-gpu``: CPU SIFT), ``num_downscales`` and ``skip_colmap`` (write the
    dataset from the COLMAP model already in ``output_dir/colmap/sparse/0``). The one builder of this command, for
    the check's advice and the benchmark that measures it."""
    cmd = [ns_process_data, "images", "--data", str(images), "--output-dir", str(output_dir)]
    cmd += [] if camera_type == "perspective" else ["--camera-type", camera_type]
    cmd += [] if matching_method is None else ["--matching-method", matching_method]
    cmd += [] if use_gpu else ["--no-gpu"]
    cmd += [] if num_downscales is None else ["--num-downscales", str(num_downscales)]
    return cmd + (["--skip-colmap"] if skip_colmap else [])


def simple_radial_recipe(
    images: Path, output_dir: Path, matching_method: str = "exhaustive", use_gpu: bool = True,
    ns_process_data: str = "ns-process-data", num_downscales: int | None = None,
) -> dict[str, list[str]]:
    """The posing ``ns-nerfuser-check-capture`` offers a capture folded with one focal length: COLMAP's feature
    extractor with one SIMPLE_RADIAL camera (one focal length, one radial term) shared by every image of ``images``,
    its ``{matching_method}_matcher`` and mapper into ``output_dir/colmap``, then ``ns-process-data images
    --skip-colmap`` writing the dataset into ``output_dir`` from that model (``ns-process-data`` offers no camera
    with one focal length and lens distortion). Each step's command by name, in order; ``output_dir/colmap/sparse``
    must exist before the mapper runs. ``use_gpu=False`` runs SIFT on the CPU (COLMAP built without CUDA)."""
    database, sparse = output_dir / "colmap" / "database.db", output_dir / "colmap" / "sparse"
    cpu_extraction = [] if use_gpu else ["--SiftExtraction.use_gpu", "0"]
    cpu_matching = [] if use_gpu else ["--SiftMatching.use_gpu", "0"]
    return {
        "features": ["colmap", "feature_extractor", "--database_path", str(database), "--image_path", str(images),
                     "--ImageReader.camera_model", "SIMPLE_RADIAL", "--ImageReader.single_camera", "1",
                     *cpu_extraction],
        "matches": ["colmap", f"{matching_method}_matcher", "--database_path", str(database), *cpu_matching],
        "mapper": ["colmap", "mapper", "--database_path", str(database), "--image_path", str(images),
                   "--output_path", str(sparse)],
        "process_data": process_data_command(images, output_dir, ns_process_data=ns_process_data,
                                             num_downscales=num_downscales, skip_colmap=True),
    }  # fmt: skip


def path_suffixes(file_path: str) -> set[str]:
    """Every trailing part of a frame's ``file_path`` (``images/a/b.png``: ``b.png``, ``a/b.png``,
    ``images/a/b.png``): how a frame is found by its own path or by the image name COLMAP stored for it."""
    parts = Path(file_path).parts
    return {Path(*parts[i:]).as_posix() for i in range(len(parts))}


def check_dataset(path: Path | str) -> FoldCheck:
    """:func:`fold_check` on every frame of a nerfstudio dataset (``ns-process-data``'s transforms.json), in the
    order of the frames' file paths."""
    file = dataset_file(path)
    try:
        frames = json.loads(file.read_text())["frames"]
        names = [str(f["file_path"]) for f in frames]
        c2w = np.array([f["transform_matrix"] for f in frames], dtype=np.float64)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{file}: not a nerfstudio transforms.json ({type(e).__name__}: {e})") from None
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"{file}: transform_matrix of shape {c2w.shape[1:]}, expected 4x4")
    return fold_check(c2w, names)


def aspect_drifted(aspect: float) -> bool:
    """Whether a camera's fy/fx is more than :data:`MAX_ASPECT_DEVIATION` from 1 (square pixels)."""
    return abs(aspect - 1.0) > MAX_ASPECT_DEVIATION


@dataclass(frozen=True)
class IntrinsicsCheck:
    """What :func:`intrinsics_check` found in one capture's camera."""

    intrinsics: Intrinsics
    """The capture's camera (the median over its frames where they differ)."""

    @property
    def aspect(self) -> float:
        """Vertical over horizontal focal length (1 for square pixels)."""
        return self.intrinsics.fy / self.intrinsics.fx

    @property
    def drifted(self) -> bool:
        return aspect_drifted(self.aspect)

    @property
    def one_focal_length(self) -> bool:
        """Whether the camera model has one focal length (fy = fx exactly: ``simple_pinhole``, SIMPLE_RADIAL), as
        opposed to square pixels measured by a model with two."""
        return self.intrinsics.fx == self.intrinsics.fy

    def warning(self, subject: str) -> str | None:
        """One line for a drifted camera naming ``subject`` (a run or a dataset); None otherwise."""
        if not self.drifted:
            return None
        k = self.intrinsics
        return (f"{subject}: COLMAP's camera looks drifted: vertical focal length {k.fy:.1f} px against "
                f"{k.fx:.1f} horizontal (ratio {self.aspect:.3f}; square pixels give 1 +- {MAX_ASPECT_DEVIATION}), "
                f"principal point ({k.cx:.1f}, {k.cy:.1f}) in {k.width}x{k.height}: the capture's geometry is "
                "stretched and cannot be registered to another by a similarity")  # fmt: skip

    def to_record(self) -> dict:
        k = self.intrinsics
        return {"fx": round(k.fx, 3), "fy": round(k.fy, 3), "cx": round(k.cx, 3), "cy": round(k.cy, 3),
                "width": k.width, "height": k.height, "aspect": round(self.aspect, 4),
                "drifted": self.drifted}  # fmt: skip


def intrinsics_check(intrinsics: Intrinsics) -> IntrinsicsCheck:
    """Whether a capture's camera keeps square pixels (see the module's last paragraph)."""
    if not (intrinsics.fx > 0 and intrinsics.fy > 0):
        raise ValueError(f"focal lengths ({intrinsics.fx}, {intrinsics.fy}) must be positive")
    return IntrinsicsCheck(intrinsics)


def check_dataset_intrinsics(path: Path | str) -> IntrinsicsCheck:
    """:func:`intrinsics_check` on a nerfstudio dataset's camera: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``
    of each frame or, where a frame has none, of the file (the median over frames, as the registration reads a run's
    training cameras)."""
    file = dataset_file(path)
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h")
    try:
        meta = json.loads(file.read_text())
        values = np.array([[float(f.get(k, meta.get(k))) for k in keys] for f in meta["frames"]], dtype=np.float64)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{file}: no camera intrinsics (fl_x, fl_y, cx, cy, w, h) in a nerfstudio transforms.json "
                         f"({type(e).__name__}: {e})") from None  # fmt: skip
    if len(values) == 0:
        raise ValueError(f"{file}: no frames")
    fx, fy, cx, cy, w, h = np.median(values, axis=0)
    return intrinsics_check(Intrinsics(float(fx), float(fy), float(cx), float(cy), int(round(w)), int(round(h))))


def write_larger_side(
    path: Path | str, drop: Collection[str], output: Path | str, found_by: str = "file order"
) -> Path:
    """Write a copy of the dataset's transforms.json without the frames ``drop`` names (by their file paths or the
    image names COLMAP stored: :func:`path_suffixes`; the smaller side of a fold, as ``found_by`` found it) to
    ``output`` (atomically; never over the dataset's own file). ``ply_file_path`` is dropped: COLMAP's points hold
    both sides'. Train on it with ``ns-train nerfacto --data <output>``."""
    file, output = dataset_file(path), Path(output)
    if output.resolve() == file.resolve():
        raise ValueError(f"{output}: the dataset's own transforms.json; write the larger side to another file")
    meta = json.loads(file.read_text())
    drop = set(drop)
    is_dropped = [bool(path_suffixes(str(f["file_path"])) & drop) for f in meta["frames"]]
    dropped = sorted(str(f["file_path"]) for f, d in zip(meta["frames"], is_dropped, strict=True) if d)
    meta["frames"] = [f for f, d in zip(meta["frames"], is_dropped, strict=True) if not d]
    meta.pop("ply_file_path", None)
    meta["nerfuser_larger_side"] = {"source": file.name, "found_by": found_by, "dropped": dropped}
    # nerfstudio resolves file paths against the json's folder: keep them valid wherever the copy is written
    if output.parent.resolve() != file.parent.resolve():
        for f in meta["frames"]:
            f["file_path"] = str((file.parent / f["file_path"]).resolve())
    write_text_atomic(output, json.dumps(meta, indent=4) + "\n")
    return output


def write_repose_images(path: Path | str, drop: Collection[str], output: Path | str) -> tuple[Path, int]:
    """Copy the dataset's images (the ``images`` folder ``ns-process-data`` wrote) but those ``drop`` names (as COLMAP
    stored them: relative to that folder) into the new folder ``output`` (atomically; never over an existing one), to
    pose the capture again with ``ns-process-data images --data <output>``; the folder and the number of images."""
    images, output = dataset_file(path).parent / "images", Path(output)
    if not images.is_dir():
        raise ValueError(f"{images}: no images folder (ns-process-data writes one); copy the capture's images but "
                         f"{', '.join(sorted(drop))} to a new folder yourself")  # fmt: skip
    if output.exists():
        raise ValueError(f"{output}: already exists (an earlier check wrote it?); remove it to write it again")
    files = sorted(p for p in images.rglob("*") if p.is_file() and not p.name.startswith("."))
    names = {p.relative_to(images).as_posix() for p in files}
    if missing := sorted(set(drop) - names):
        raise ValueError(f"{images}: no image {', '.join(missing)}; the COLMAP model is not of these images")
    kept = [p for p in files if p.relative_to(images).as_posix() not in drop]
    with atomic_dir(output) as tmp:
        for p in kept:
            target = tmp / p.relative_to(images)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, target)
    return output, len(kept)
