"""How well COLMAP posed each capture of practitioner cases, compared across the image sizes they were rendered at.

``scripts/bench_practitioner.py --stages scene colmap`` renders a case's captures and poses each with
``ns-process-data``; this reads what COLMAP wrote (``transforms.json``) against the generated scene's true poses, as the
benchmark's ground truth does (:func:`nerfuser_ns.bench.practitioner_cases.capture_ground_truth`): views posed, median
rotation and centre error of the single SIM(3) tie to the world, the bend (rotation between the ties of the first
and the second half of a capture) and the misposed views (more than 5 deg off the tie fitted to the rotations). No
trained run is needed::

    python scripts/colmap_quality.py --cases drive:6=outputs/practitioner/drive-6@320x240 \\
        drive:6=outputs/practitioner-640/drive-6@640x480 --output reports/colmap_quality_drive6.md
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from nerfuser_ns.bench.practitioner_cases import (
    case_layout,
    colmap_camera,
    colmap_matching,
    colmap_misposed,
    colmap_tie,
    dataset_transforms,
)
from nerfuser_ns.capture_check import aspect_drifted, check_dataset
from nerfuser_ns.files import write_text_atomic


@dataclass
class ColmapQuality:
    """COLMAP's own pose error per capture, for case folders rendered at given sizes."""

    cases: list[str]
    """``LAYOUT:SEED=CASE_DIR@WIDTHxHEIGHT``: a case folder of ``bench_practitioner.py`` and the image size its
    captures were rendered at (``--width`` / ``--height`` there)."""
    output: Path
    """Markdown report; the records go beside it as JSON."""


def parse_case(text: str) -> tuple[str, Path, int, int]:
    """``LAYOUT:SEED=CASE_DIR@WIDTHxHEIGHT`` as (case, folder, width, height); ValueError (one line) otherwise."""
    try:
        case, rest = text.split("=", 1)
        folder, size = rest.rsplit("@", 1)
        width, height = (int(v) for v in size.lower().split("x"))
        case_layout_name, seed = case.rsplit(":", 1)
        int(seed)
    except ValueError:
        raise ValueError(f"--cases {text!r}: expected LAYOUT:SEED=CASE_DIR@WIDTHxHEIGHT") from None
    return case, Path(folder), width, height


def measure(case: str, folder: Path, width: int, height: int) -> list[dict]:
    """Per capture: views posed, COLMAP's rotation / centre error (median) and bend against the truth."""
    if not (folder / "datasets").is_dir():
        raise SystemExit(f"{folder}: no datasets/ (run bench_practitioner.py --stages scene colmap for {case} first)")
    layout = case_layout(case, width, height)
    rows = []
    matching, camera_type = colmap_matching(folder), colmap_camera(folder)
    for cap in layout.captures:
        g = colmap_tie(cap, folder)[0]
        check = check_dataset(dataset_transforms(folder, cap.name))
        found = sum(colmap_misposed(cap, folder).get(f, False) for f in check.suspect)
        rows.append({"case": case, "folder": str(folder), "size": f"{width}x{height}", "capture": g["capture"],
                     "posed": g["posed_by_colmap"], "views": g["views"], "focal_ratio": g["colmap_focal_ratio"],
                     "camera_drifted": aspect_drifted(g["colmap_focal_ratio"]),
                     "rot_err_deg": g["colmap_rot_err_deg_median"],
                     "pose_tie_rot_err_deg": g["pose_tie_rot_err_deg_median"],
                     "centre_err": g["colmap_centre_err_median"], "bend_deg": g["colmap_bend_deg"],
                     "misposed": g["pose_tie_misposed_views"], "matching": matching, "camera_type": camera_type,
                     "check": "not checked" if not check.checked else check.suspect_views,
                     "check_misposed": found})  # fmt: skip
    return rows


def write_report(rows: list[dict], output: Path, command: str) -> None:
    lines = ["# COLMAP's own pose error per capture, by image size", "", f"`{command}`", "",
             "Per capture: views `ns-process-data` (COLMAP, CPU SIFT, the case's matching) posed; the median rotation "
             "(deg) and centre error (world units) of the one SIM(3) tying its frame to the true poses by the camera "
             "centres; *pose tie*: the median rotation error of the tie fitted to the views' rotations as well (a "
             "drive's centres lie near a line and leave the roll about it loosely fixed, which the first rotation "
             "error carries; this one is COLMAP's own rotation noise); the bend (deg) between the ties of the first "
             "and the second half of its views (0 where one tie fits the whole reconstruction). These bound what any "
             "registration of NeRFs trained on the captures can reach against the benchmark's truth. *Misposed*: "
             "views more than 5 deg off their true rotation after the tie fitted to the views' rotations (a part of "
             "the capture posed by the wrong copy of repeated structure). *Check*: the suspect views "
             "`ns-nerfuser-check-capture` finds from the poses alone (no truth; *not checked* where the file order is "
             "no filmed sequence), and how many of them are misposed. *Camera*: `ns-process-data --camera-type` "
             "(perspective, its default: COLMAP's OPENCV model). *fy/fx*: COLMAP's vertical over horizontal focal "
             "length (1 for square pixels; marked *drifted* beyond 1 +- 0.02, as `ns-nerfuser-check-capture` reports "
             "it).", "",
             "| case | image size | matching | camera | capture | posed | fy/fx | rot err (deg) | pose tie (deg) | "
             "centre err | bend (deg) | misposed | check: suspect (misposed) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for r in rows:
        check = r["check"] if isinstance(r["check"], str) else f"{r['check']} ({r['check_misposed']})"
        ratio = f"{r['focal_ratio']:.3f}" + (" drifted" if r["camera_drifted"] else "")
        lines.append(f"| {r['case']} | {r['size']} | {r['matching']} | {r['camera_type']} | {r['capture']} | "
                     f"{r['posed']}/{r['views']} | "
                     f"{ratio} | {r['rot_err_deg']:.3f} | {r['pose_tie_rot_err_deg']:.3f} | {r['centre_err']:.4f} | "
                     f"{r['bend_deg']:.2f} | {r['misposed']} | {check} |")  # fmt: skip
    write_text_atomic(output, "\n".join(lines) + "\n")
    write_text_atomic(output.with_suffix(".json"), json.dumps(rows, indent=2) + "\n")


def main(cfg: ColmapQuality) -> None:
    try:
        parsed = [parse_case(c) for c in cfg.cases]
    except ValueError as e:
        raise SystemExit(str(e)) from None
    rows = [row for p in parsed for row in measure(*p)]
    write_report(rows, cfg.output, "python scripts/colmap_quality.py " + " ".join(sys.argv[1:]))
    print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(ColmapQuality))
