"""Where in the world a practitioner case's 3D matches lie: which support the registered link, which the pose truth.

The known-geometry features of a case's first two runs (SIFT keypoints of the registration's own renders lifted to 3D
with the rendered depth, matched as ``--mode known-geometry`` matches them) are placed in the world by each run's
pose truth. Printed per link (registered, pose truth): its inlier matches and how many lie in a world box; and per run
how many of its keypoints fall in the box's image footprint (its corners projected into each render, occluders not
removed), how many of those have reliable depth, and how many lifted keypoints lie in the box. For a room: does
either run give keypoints on its one unique element, the door, and where are they lost::

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
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout, case_registration, reference_links
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig, read_registration
from nerfuser_ns.registration.known_geometry import extract_sift, lift_keypoints, pixel_index, reliable_depth
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


def footprint_counts(
    views: ViewSet, intr, config: RegistrationConfig, world_to_nerf: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[int, int]:
    """Keypoints detected inside the box's image footprint over the kept renders, and those with reliable depth."""
    kg = config.known_geometry
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners = sim3.transform_points(world_to_nerf, corners)
    kept = np.flatnonzero(views.kept)
    depth, acc = views.load_depth(), views.load_accumulation()
    detected = reliable = 0
    for k, (xy, _) in zip(kept, extract_sift(views, kept, kg, config.sfm.num_threads, False), strict=True):
        c2w = views.c2w[k]
        cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]  # camera axes (OpenGL: looking along -z)
        if np.any(-cam[:, 2] <= 0):
            continue
        u = intr.cx + intr.fx * cam[:, 0] / -cam[:, 2]
        v = intr.cy - intr.fy * cam[:, 1] / -cam[:, 2]
        inside = (xy[:, 0] >= u.min()) & (xy[:, 0] <= u.max()) & (xy[:, 1] >= v.min()) & (xy[:, 1] <= v.max())
        rows, cols = pixel_index(xy[inside], depth.shape[1:])
        ok = reliable_depth(depth[k], acc[k], kg.min_accumulation, kg.max_depth_step)[rows, cols]
        detected += int(inside.sum())
        reliable += int(ok.sum())
    return detected, reliable


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
    gt = capture_ground_truth(case_layout(case), case_dir, optimized=False)
    to_world = [g["nerf_to_world_pose"] for g in gt]
    all_links = reference_links(reg, gt)
    links = {key: all_links[key] for key in ("registered", "pose truth")}
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
    lines += ["", "| run | lifted keypoints | detected in the box's footprint | with reliable depth "
              "| lifted in the box | matched points in the box |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for k, (f, matched) in enumerate(zip(feats, (pa, pb), strict=True)):
        lifted = int(in_box(sim3.transform_points(to_world[k], f.points)).sum())
        detected, reliable = footprint_counts(views[k], intr, config, sim3.invert_sim3(to_world[k]), lo, hi)
        lines.append(f"| {names[k]} | {len(f.points)} | {detected} | {reliable} | {lifted} | "
                     f"{int(in_box(sim3.transform_points(to_world[k], matched)).sum())} |")  # fmt: skip
    text = "\n".join(lines) + "\n"
    print(text)
    write_text_atomic(cfg.output, text)


if __name__ == "__main__":
    main(tyro.cli(MatchLocations))
