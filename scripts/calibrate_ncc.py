"""Calibrate the registration self-check (cross-render NCC) on real NeRF renders.

For each scene, the registration's own renders of every NeRF (cached: the same sampling settings reuse them) are
cross-rendered through the ground-truth transform and through perturbed ones (rotation, translation, scale, each
alone), exactly as ``ns-nerfuser-register``'s self-check does, and the NCC is recorded. A good threshold lies above
every score of a transform the paper counts as a failure (r > 5 deg, t > 0.2, s > 0.1) and below the scores of
accurate ones; the report states both bounds.

Example:
    python scripts/calibrate_ncc.py --scenes demo=demo/scene:demo/runs \\
        oc1=outputs/bench/scenes/object-centric-1:outputs/bench/runs/object-centric-1
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

# fmt: off
PERTURBATIONS: list[tuple[str, float]] = [
    ("none", 0.0),
    ("rotation_deg", 0.5), ("rotation_deg", 1.0), ("rotation_deg", 2.0), ("rotation_deg", 5.0),
    ("rotation_deg", 10.0), ("rotation_deg", 30.0),
    ("translation", 0.02), ("translation", 0.05), ("translation", 0.1), ("translation", 0.2), ("translation", 0.4),
    ("log_scale", 0.02), ("log_scale", 0.05), ("log_scale", 0.1), ("log_scale", 0.2),
]
# fmt: on
"""(kind, size) applied to the ground-truth transform; translations in the reference NeRF's units."""


@dataclass
class CalibrateNccConfig:
    """Cross-render NCC of real NeRFs under exact and perturbed transforms."""

    scenes: list[str] = field(default_factory=lambda: ["demo=demo/scene:demo/runs"])
    """Scenes as NAME=SCENE_DIR:RUNS_DIR."""
    poses: int = 48
    """Training poses per NeRF (the registration's --sampling.max-training-poses)."""
    width: int = 192
    """Render width (as the registration renders)."""
    height: int = 144
    """Render height."""
    views: int = 4
    """Views per direction (the registration's --self-check-views)."""
    seed: int = 0
    """Seed of the perturbation axes."""
    work_dir: Path = Path("outputs/bench/ncc_work")
    """Renders (reused by later runs with the same settings)."""
    output: Path = Path("outputs/bench/ncc_calibration.json")
    """JSON results (a markdown summary is written beside it)."""


def perturb(T, kind: str, size: float, rng):  # noqa: ANN001, ANN201
    import numpy as np

    from nerfuser_ns import sim3

    if kind == "none":
        return T
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "rotation_deg":
        from scipy.spatial.transform import Rotation

        R = Rotation.from_rotvec(np.deg2rad(size) * axis).as_matrix()
        # rotate about the NeRF's own origin (in the reference frame), so the translation error stays 0
        D = sim3.make_sim3(R, T[:3, 3] - R @ T[:3, 3], 1.0)
    elif kind == "translation":
        D = sim3.make_sim3(np.eye(3), size * axis, 1.0)
    else:
        c = T[:3, 3]
        s = float(np.exp(size))
        D = sim3.make_sim3(np.eye(3), c - s * c, s)
    return D @ T


def main(cfg: CalibrateNccConfig) -> None:
    import numpy as np
    from rich.console import Console

    from nerfuser_ns import registration, sim3
    from nerfuser_ns.bench.evaluation import SceneRuns
    from nerfuser_ns.files import write_text_atomic
    from nerfuser_ns.registration import PoseSamplingConfig, RegistrationConfig
    from nerfuser_ns.renderers import NerfstudioRenderer

    console = Console()
    rng = np.random.default_rng(cfg.seed)
    sampling = PoseSamplingConfig(
        source="training", max_training_poses=cfg.poses, width=cfg.width, height=cfg.height, fov_deg=65.0
    )
    # the threshold was calibrated on the SfM mode's results
    reg_cfg = RegistrationConfig(mode="sfm", sampling=sampling, self_check_views=cfg.views)
    rows = []
    for spec in cfg.scenes:
        scene = SceneRuns.parse(spec)
        renderers = [
            NerfstudioRenderer(p, name=c, data_override=d)
            for p, c, d in zip(scene.configs, scene.captures, scene.capture_dirs(), strict=True)
        ]
        views = [
            registration.render_views_cached(r, sampling, cfg.work_dir / scene.name / "renders", console)
            for r in renderers
        ]
        truth = scene.nerf_to_common()
        for i in range(1, len(renderers)):
            for kind, size in PERTURBATIONS:
                T = np.stack(truth)
                T[i] = perturb(truth[i], kind, size, rng)
                t = time.perf_counter()
                # NeRF i against its predecessor (street captures are consecutive segments; the registration checks
                # overlapping neighbours too), on evenly spread views: the registration picks the views that see
                # the most shared points, so its own scores for a correct transform are higher than these
                (check,) = registration.cross_render_check(
                    renderers, views, T, [(i - 1, i)], sampling.intrinsics(), reg_cfg
                )
                e = sim3.sim3_errors(T[i], truth[i])
                rows.append(
                    {
                        "scene": scene.name,
                        "nerf": scene.captures[i],
                        "kind": kind,
                        "size": size,
                        "r_err_deg": float(e.r_err_deg),
                        "t_err": float(e.t_err),
                        "s_err": float(e.s_err),
                        "failure": bool(e.is_failure()),
                        "ncc": check.score,
                        "ncc_prev_in_i": check.ncc_i_in_j,
                        "ncc_i_in_prev": check.ncc_j_in_i,
                        "seconds": time.perf_counter() - t,
                    }
                )
                console.print(f"{scene.name}/{scene.captures[i]} {kind} {size}: ncc {check.score:.3f}")
    fails = [r["ncc"] for r in rows if r["failure"] and np.isfinite(r["ncc"])]
    exact = [r["ncc"] for r in rows if r["kind"] == "none"]
    accurate = [r["ncc"] for r in rows if r["r_err_deg"] <= 1.0 and r["t_err"] <= 0.05 and r["s_err"] <= 0.05]
    summary = {
        "max_ncc_of_failures": max(fails) if fails else None,
        "min_ncc_exact": min(exact) if exact else None,
        "min_ncc_accurate": min(accurate) if accurate else None,
    }
    report = {
        "command": "python scripts/calibrate_ncc.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "summary": summary,
        "rows": rows,
    }
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    lines = [
        f"# Self-check NCC calibration ({report['date']})",
        "",
        f"`{report['command']}`",
        "",
        "| scene | NeRF | perturbation | r_err | t_err | s_err | paper failure | NCC (worse direction) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['nerf']} | {r['kind']} {r['size']:g} | {r['r_err_deg']:.2f} | "
            f"{r['t_err']:.3f} | {r['s_err']:.3f} | {'yes' if r['failure'] else 'no'} | {r['ncc']:.3f} |"
        )
    lines += [
        "",
        f"Highest NCC of a failing transform: {summary['max_ncc_of_failures']}; lowest NCC of the exact "
        f"transform: {summary['min_ncc_exact']}; lowest of accurate ones (r <= 1 deg, t <= 0.05, s <= 0.05): "
        f"{summary['min_ncc_accurate']}.",
    ]
    write_text_atomic(cfg.output.with_suffix(".md"), "\n".join(lines) + "\n")
    console.print(summary)


def entrypoint() -> None:
    main(tyro.cli(CalibrateNccConfig))


if __name__ == "__main__":
    entrypoint()
