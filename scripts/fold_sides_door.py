"""Which side of each room capture's fold holds the views that see the room's one unique element, its door.

``ns-nerfuser-check-capture --write-larger-side`` keeps a folded capture's larger side. On the rooms of our benchmark
the door is what tells the room from its half-turn twin; this counts, per capture, the views whose image contains the
door's centre (true poses) and how many of them the check put on the smaller side (the views the larger side drops)::

    python scripts/fold_sides_door.py --cases room:4=outputs/practitioner/room-4 room:6=outputs/practitioner/room-6 \\
        --output reports/fold_sides_door.md
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfuser_ns.bench.practitioner_cases import case_layout, colmap_matching, dataset_transforms, frame_index
from nerfuser_ns.capture_check import check_dataset
from nerfuser_ns.files import write_text_atomic

DOOR_CENTRE = np.array([4.0 - 0.04, 0.9, 1.05])
"""The door's centre in the room's world frame (``scenes.make_room``: east wall, y ~ 0.9 m, 2.1 m tall)."""


@dataclass
class FoldSidesDoor:
    """Per room capture: the views that see the door, and how many the fold check puts on the smaller side."""

    cases: list[str]
    """``room:SEED=CASE_DIR`` (a case folder with COLMAP datasets)."""
    output: Path
    """Markdown report; the rows go beside it as JSON."""


def sees(c2w: np.ndarray, intr, point: np.ndarray) -> bool:
    """Whether ``point`` projects inside the image of the (OpenGL-convention) camera ``c2w``."""
    p = c2w[:3, :3].T @ (point - c2w[:3, 3])
    if p[2] >= 0:
        return False
    x, y = intr.fx * p[0] / -p[2] + intr.cx, intr.fy * -p[1] / -p[2] + intr.cy
    return bool(0 <= x < intr.width and 0 <= y < intr.height)


def measure(spec: str) -> list[dict]:
    case, _, folder = spec.partition("=")
    if not case.startswith("room:") or not folder:
        raise SystemExit(f"--cases {spec!r}: expected room:SEED=CASE_DIR")
    folder_path = Path(folder)
    matching = colmap_matching(folder_path)
    rows = []
    for cap in case_layout(case).captures:
        check = check_dataset(dataset_transforms(folder_path, cap.name))
        suspect = {frame_index(s) for s in check.suspect}
        door = [i for i in range(cap.num_views) if sees(cap.c2w_world[i], cap.intrinsics, DOOR_CENTRE)]
        rows.append({"case": case, "folder": folder, "capture": cap.name,
                     "matching": matching,
                     "suspect": len(suspect), "door_views": len(door),
                     "door_views_suspect": sum(1 for i in door if i in suspect)})  # fmt: skip
    return rows


def main(cfg: FoldSidesDoor) -> None:
    rows = [r for spec in cfg.cases for r in measure(spec)]
    lines = ["# Which side of a room capture's fold sees the door", "",
             f"`python scripts/fold_sides_door.py {' '.join(sys.argv[1:])}`", "",
             "Per capture: the views the fold check calls suspect (the smaller side, which `--write-larger-side` "
             "drops), the views whose image holds the door's centre (true poses; capture_a films the west half and "
             "sees the door from afar, capture_b the east half and sees it close), and how many of those are suspect.",
             "", "| case | folder | matching | capture | suspect | door views | door views suspect |",
             "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for r in rows:
        lines.append(f"| {r['case']} | `{r['folder']}` | {r['matching']} | {r['capture']} | {r['suspect']} | "
                     f"{r['door_views']} | {r['door_views_suspect']} |")  # fmt: skip
    write_text_atomic(cfg.output, "\n".join(lines) + "\n")
    write_text_atomic(cfg.output.with_suffix(".json"), json.dumps(rows, indent=2) + "\n")
    print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(FoldSidesDoor))
