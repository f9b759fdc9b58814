"""Has COLMAP folded a run's capture? A check from its training cameras alone, before any registration.

On repeated structure (a room whose walls look alike from either side) COLMAP can pose a part of a capture by the
wrong copy of the structure: a block of views lands a half turn away from where it was filmed, the bundle adjustment
accepts it, and the run is trained on the folded poses. No registration can mend that run.

Views filmed in sequence (a video's frames, photos named in the order they were taken) turn by small steps from one
to the next. A view posed by the wrong copy sits roughly a half turn away from its correctly posed neighbour, so in
file order the capture shows a *jump*: a turn of more than :data:`FOLD_TURN_DEG` between neighbours whose typical
(median) turn is below :data:`SEQUENCE_STEP_DEG`. Captures whose file order is no sequence (median turn above it:
unordered photos, a multi-camera rig) cannot be checked this way and are reported as unchecked, never as folded.

The views between jumps alternate between the two sides of the fold; the smaller side is reported as the suspect
views. Each side alone is a consistent capture (its views posed against the same copy), so a folded capture can be
trained on its larger side (:func:`write_larger_side`); that side may miss the views of the place's unique objects
(on our rooms the folded block held every far view of the door), which a registration needs to tell the place from
its copy. Neighbours whose file names' frame numbers lie more than :data:`MAX_FRAME_GAP` apart are not compared
(views are missing between them). A fold by a translation (a copy further along a street) is not detected.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float

from nerfuser_ns import sim3
from nerfuser_ns.files import write_text_atomic

FOLD_TURN_DEG = 120.0
"""A turn between neighbouring views (file order) above this is a jump: a half turn less a sequence's largest steps."""
SEQUENCE_STEP_DEG = 30.0
"""A capture whose median turn between neighbours is above this is not filmed in file order: not checked."""
MAX_FRAME_GAP = 2
"""Neighbours in file order whose frame numbers differ by more are not compared (views between them are missing;
nerfstudio's training split leaves out every tenth, a gap of 2)."""
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
        return (f"{subject}: the capture looks folded by COLMAP: {len(self.jumps)} jump(s) of more than "
                f"{FOLD_TURN_DEG:.0f} deg between neighbouring views in file order (first {first[0]} -> {first[1]}, "
                f"{first[2]:.0f} deg; median turn {self.median_turn_deg:.0f} deg): {self.suspect_views} of "
                f"{self.num_views} views look posed by the wrong copy of repeated structure")  # fmt: skip

    def to_record(self) -> dict:
        return {"num_views": self.num_views, "median_turn_deg": round(self.median_turn_deg, 2),
                "checked": self.checked, "folded": self.folded, "suspect_views": self.suspect_views,
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
    poses may be in any frame and scale: only relative rotations count)."""
    if len(names) != len(c2w):
        raise ValueError(f"fold_check: {len(c2w)} poses but {len(names)} names")
    order = np.argsort(np.asarray([str(n) for n in names]), kind="stable")
    names = [str(names[i]) for i in order]
    n = len(names)
    if n < 3:
        return FoldCheck(n, 0.0, False, (), ())
    turns = neighbour_turns(np.asarray(c2w)[order])
    adjacent = _adjacent(names)
    median = float(np.median(turns[adjacent])) if adjacent.any() else 0.0
    if median > sequence_step_deg or not adjacent.any():
        return FoldCheck(n, median, False, (), ())
    jump_at = np.flatnonzero((turns > fold_turn_deg) & adjacent)
    side = np.zeros(n, dtype=np.int64)
    side[jump_at + 1] = 1
    side = np.cumsum(side) % 2  # each jump crosses the fold
    smaller = 1 if side.sum() <= n - side.sum() else 0  # a tie: the side the first view is not on
    jumps = tuple((names[i], names[i + 1], float(turns[i])) for i in jump_at)
    return FoldCheck(n, median, True, jumps, tuple(names[i] for i in np.flatnonzero(side == smaller)))


def _adjacent(names: Sequence[str]) -> np.ndarray:
    """Which neighbours in file order were filmed next to each other: all of them, unless every file name ends in a
    frame number; then those at most :data:`MAX_FRAME_GAP` frames apart (a dataset without some views, e.g. a larger
    side, or nerfstudio's training split, must not read as jumps where views are missing)."""
    numbers = [re.search(r"(\d+)$", Path(name).stem) for name in names]
    if not all(numbers):
        return np.ones(len(names) - 1, dtype=bool)
    frame = np.array([int(m.group(1)) for m in numbers])
    return np.diff(frame) <= MAX_FRAME_GAP


def dataset_file(path: Path | str) -> Path:
    """A nerfstudio dataset's ``transforms.json`` from the file or its folder; ValueError (one line) if missing."""
    path = Path(path)
    file = path / "transforms.json" if path.is_dir() else path
    if not file.is_file():
        raise ValueError(f"{path}: no transforms.json (give an ns-process-data output folder or its transforms.json)")
    return file


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


def write_larger_side(path: Path | str, check: FoldCheck, output: Path | str) -> Path:
    """Write a copy of the dataset's transforms.json without ``check``'s suspect views (the smaller side of the
    fold) to ``output`` (atomically; never over the dataset's own file). ``ply_file_path`` is dropped: COLMAP's points
    hold both sides'. Train on it with ``ns-train nerfacto --data <output>``."""
    file, output = dataset_file(path), Path(output)
    if output.resolve() == file.resolve():
        raise ValueError(f"{output}: the dataset's own transforms.json; write the larger side to another file")
    meta = json.loads(file.read_text())
    drop = set(check.suspect)
    meta["frames"] = [f for f in meta["frames"] if str(f["file_path"]) not in drop]
    meta.pop("ply_file_path", None)
    meta["nerfuser_larger_side"] = {"source": file.name, "dropped": sorted(drop)}
    # nerfstudio resolves file paths against the json's folder: keep them valid wherever the copy is written
    if output.parent.resolve() != file.parent.resolve():
        for f in meta["frames"]:
            f["file_path"] = str((file.parent / f["file_path"]).resolve())
    write_text_atomic(output, json.dumps(meta, indent=4) + "\n")
    return output
