"""Where in the world a practitioner case's 3D matches lie: which support the registered link, which the pose truth.

The known-geometry features of a case's first two runs (SIFT keypoints of the registration's own renders lifted to 3D
with the rendered depth, matched as ``--mode known-geometry`` matches them) are placed in the world by each run's
pose truth. Printed per link (registered, pose truth): its inlier matches and how many lie in a world box; and per run
how many of its lifted keypoints lie in that box. For a room: does either run give keypoints on its one unique
element, the door::

    python scripts/match_locations.py --case room:4=outputs/practitioner_v2/room-4 \\
        --box-min 3.5 0.1 -0.1 --box-max 4.1 1.7 2.3 --output reports/match_locations_room4.md

A case is ``LAYOUT:SEED=FOLDER[,REGISTRATION]`` as in ``scripts/twin_check_cases.py``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout, case_registration
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig, read_registration
from nerfuser_ns.registration.known_geometry import lift_keypoints
from nerfuser_ns.registration.pairwise import match_nerfs, ransac_max_error, view_similarity
from nerfuser_ns.registration.render_cache import ViewSet, load_render_intrinsics
from nerfuser_ns.registration.twin_check import relative_link


@dataclass
class MatchLocations:
    """A case's 3D matches placed in the world."""

    case: str
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]``."""
    box_min: tuple[float, float, float]
    """World box, lower corner (metres)."""
    box_max: tuple[float, float, float]
    """World box, upper corner (metres)."""
    output: Path
    """Markdown report."""


def main(cfg: MatchLocations) -> None:
    case, case_dir, path = case_registration(cfg.case)
    reg = read_registration(path)
    views = [ViewSet.from_folder(n["render_folder"], n["name"]) for n in reg["nerfs"][:2]]
    intr = load_render_intrinsics(views[0].folder)
    config = RegistrationConfig()
    kg = config.known_geometry
    feats = [lift_keypoints(vs, intr, kg, config.sfm.num_threads, False) for vs in views]
    m = match_nerfs(feats, views, view_similarity(feats, views, config), 0, 1, config)
    max_error = ransac_max_error(feats, m, config)
    to_world = [g["nerf_to_world_pose"] for g in capture_ground_truth(case_layout(case), case_dir, optimized=False)]
    ref = reg["reference"]["index"]
    links = {"registered": np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in reg["nerfs"]]),
             "pose truth": sim3.to_reference_frame(np.stack(to_world), ref)}  # fmt: skip
    lo, hi = np.asarray(cfg.box_min), np.asarray(cfg.box_max)

    def in_box(points: np.ndarray) -> np.ndarray:
        return np.all((points >= lo) & (points <= hi), axis=-1)

    pa, pb = feats[0].points[m.ia], feats[1].points[m.ib]
    names = [n["name"] for n in reg["nerfs"][:2]]
    lines = [f"# {case}: where its 3D matches lie", "", f"`python scripts/match_locations.py {' '.join(sys.argv[1:])}`",
             "", f"World box {cfg.box_min} - {cfg.box_max} m; {len(pa)} 3D matches of {names[0]} / {names[1]} "
             f"(RANSAC threshold {max_error:.4g} in {names[0]}'s units).", "",
             "| link | r_err to the pose truth (deg) | inlier matches | in the box | inliers' world centre (m) |",
             "| --- | ---: | ---: | ---: | --- |"]  # fmt: skip
    for label, T in links.items():
        link = relative_link(T, 0, 1)
        r_err = float(sim3.sim3_errors(link, relative_link(links["pose truth"], 0, 1)).r_err_deg)
        inl = np.linalg.norm(sim3.transform_points(link, pb) - pa, axis=-1) <= max_error
        world = sim3.transform_points(to_world[0], pa[inl])
        centre = ", ".join(f"{x:.2f}" for x in np.median(world, axis=0)) if len(world) else "-"
        lines.append(f"| {label} | {r_err:.2f} | {int(inl.sum())} | {int(in_box(world).sum())} | {centre} |")
    lines += ["", "| run | lifted keypoints | in the box | matched points in the box |", "| --- | ---: | ---: | ---: |"]
    for k, (f, matched) in enumerate(zip(feats, (pa, pb), strict=True)):
        lifted = int(in_box(sim3.transform_points(to_world[k], f.points)).sum())
        lines.append(f"| {names[k]} | {len(f.points)} | {lifted} | "
                     f"{int(in_box(sim3.transform_points(to_world[k], matched)).sum())} |")  # fmt: skip
    text = "\n".join(lines) + "\n"
    print(text)
    write_text_atomic(cfg.output, text)


if __name__ == "__main__":
    main(tyro.cli(MatchLocations))
