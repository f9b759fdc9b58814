"""Where a practitioner case's trained NeRF puts its surfaces, against the generated scene seen through the benchmark's
truth: the NeRF's rendered depth over the true depth at the registration's own renders.

A ratio of 1 means the run's content sits at the scale (and place) the stored truth gives it, so a registration's
scale error against that truth is the registration's own; a ratio away from 1 means the trained content itself is off
the truth. Reads the renders ``ns-nerfuser-register`` stored with depth in its work folder (``renders/<key>``: images,
``depth.npz``, ``accumulation.npz``, ``poses.json``) and renders the true depth at the same poses::

    python scripts/depth_vs_truth.py --case drive:6 --case-dir outputs/practitioner/drive-6 \\
        --renders outputs/practitioner/drive-6/registration_work/renders/<key> --capture 1

``--registration R`` (the reference run's renders, ``--capture 0``) compares the two runs with each other instead:
the second run's depth, rendered at the reference run's views nearest its cameras through the link of ``R`` and
through the truth's, over the reference run's own depth (1 where the link puts the second run's surfaces where the
reference run has them: a scale error of the link shows as a ratio away from 1).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout, run_config
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.record import iter_registered_nerfs, matrix
from nerfuser_ns.registration.render_cache import ViewSet, load_render_intrinsics
from nerfuser_ns.renderers import NerfstudioRenderer


@dataclass
class DepthVsTruth:
    """A run's rendered depth over the true depth at the registration's renders of it."""

    case: str
    """``LAYOUT:SEED`` of the case (as ``bench_practitioner.py --cases``)."""
    case_dir: Path
    """The case folder (its COLMAP datasets and runs)."""
    renders: Path
    """One render folder of the registration's work folder, stored with depth (``depth.npz``)."""
    capture: int
    """Index of the capture whose run made those renders."""
    views: int = 12
    """Views compared, evenly spread over the folder's."""
    min_accumulation: float = 0.95
    """Pixels compared: the NeRF is at least this opaque there."""
    registration: Path | None = None
    """Compare the second run's depth through this registration's link (and the truth's) instead of the truth's."""


def depth_ratios(
    nerf: list[np.ndarray], true: list[np.ndarray], accumulation: list[np.ndarray], min_accumulation: float
) -> dict:
    """NeRF over true depth on the pixels both see (opaque in the NeRF, a surface in the scene): the median, and per
    quarter of the true depths its range, median and interquartile range."""
    ratio, depth = [], []
    for d, t, a in zip(nerf, true, accumulation, strict=True):
        ok = (a >= min_accumulation) & np.isfinite(t) & (t > 0) & np.isfinite(d) & (d > 0)
        ratio.append(d[ok] / t[ok])
        depth.append(t[ok])
    ratio, depth = np.concatenate(ratio), np.concatenate(depth)
    if len(ratio) == 0:
        raise ValueError("no pixel is opaque in the NeRF and a surface in the scene")
    edges = np.quantile(depth, [0, 0.25, 0.5, 0.75, 1.0])
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        r = ratio[(depth >= lo) & (depth <= hi)]
        q25, q50, q75 = np.quantile(r, [0.25, 0.5, 0.75])
        bands.append({"true_depth": [float(lo), float(hi)], "median": float(q50), "iqr": [float(q25), float(q75)]})
    return {"pixels": int(len(ratio)), "median": float(np.median(ratio)), "by_true_depth": bands}


def link_ratios(cfg: DepthVsTruth, layout, c2w: np.ndarray, intr: Intrinsics, depth: np.ndarray,
                acc: np.ndarray) -> dict:  # fmt: skip
    """The second run's depth over the reference run's (``--capture 0``'s renders) at the reference's views nearest
    the second run's cameras, through the registration's link and through the stored truth's."""
    if cfg.capture != 0:
        raise SystemExit("--registration compares with the reference run: give its renders and --capture 0")
    gt = capture_ground_truth(layout, cfg.case_dir, optimized=False)
    links = {"truth": sim3.compose(sim3.invert_sim3(gt[0]["nerf_to_world"]), gt[1]["nerf_to_world"]),
             "registration": matrix(list(iter_registered_nerfs(cfg.registration))[1].transform)}
    other = NerfstudioRenderer(run_config(cfg.case_dir, layout.captures[1].name))
    cams = sim3.transform_poses(links["truth"], other.training_poses())[:, :3, 3]
    pick = np.argsort(np.min(np.linalg.norm(c2w[:, None, :3, 3] - cams[None], axis=-1), axis=1))[: cfg.views]
    out = {}
    for label, T in links.items():  # T: second run -> reference
        scale = float(sim3.decompose_sim3(T)[2])
        there = other.render(sim3.transform_poses(sim3.invert_sim3(T), c2w[pick]), intr, depth=True)
        out[label] = depth_ratios([d * scale for d in there.depth], [depth[k] for k in pick],
                                  [np.minimum(acc[k], a) for k, a in zip(pick, there.accumulation, strict=True)],
                                  cfg.min_accumulation)  # fmt: skip
    return out


def main(cfg: DepthVsTruth) -> None:
    if not (cfg.renders / "depth.npz").is_file():
        raise SystemExit(f"{cfg.renders / 'depth.npz'}: missing (a render folder stored with depth is needed: modes "
                         f"known-geometry, graph, or sfm where every run renders depth)")  # fmt: skip
    layout = case_layout(cfg.case)
    if not 0 <= cfg.capture < len(layout.captures):
        raise SystemExit(f"--capture {cfg.capture}: {cfg.case} has {len(layout.captures)} captures")
    views = ViewSet.from_folder(cfg.renders)
    intr, c2w = load_render_intrinsics(cfg.renders), views.c2w
    depth, acc = views.load_depth(), views.load_accumulation()
    if cfg.registration is not None:
        result = link_ratios(cfg, layout, c2w, intr, depth, acc)
        pick = range(min(cfg.views, len(c2w)))
    else:
        truth = capture_ground_truth(layout, cfg.case_dir, optimized=False)[cfg.capture]["nerf_to_world"]
        scene = SceneFrameRenderer(layout.scene, truth, "truth", None)
        pick = np.unique(np.linspace(0, len(c2w) - 1, cfg.views).round().astype(int))
        true = [scene.render(c2w[k : k + 1], intr, depth=True).depth[0] for k in pick]
        result = depth_ratios([depth[k] for k in pick], true, [acc[k] for k in pick], cfg.min_accumulation)
    print(json.dumps({"case": cfg.case, "capture": layout.captures[cfg.capture].name, "renders": str(cfg.renders),
                      "views": len(pick), **result}, indent=2))  # fmt: skip


if __name__ == "__main__":
    main(tyro.cli(DepthVsTruth))
