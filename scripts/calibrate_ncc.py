"""Calibrate the registration self-check (cross-render NCC) on real NeRF renders.

For each scene, the registration's own renders of every NeRF (cached: the same sampling settings reuse them) are
cross-rendered through the ground-truth transform and through perturbed ones (rotation, translation, scale, each
alone), exactly as ``ns-nerfuser-register``'s self-check does, and the NCC is recorded. A good threshold lies above
every score of a transform the paper counts as a failure (r > 5 deg, t > 0.2, s > 0.1) and below the scores of
accurate ones; the report states both bounds.

Scenes are generated scenes with runs trained on them (``--scenes``, truth from ``ground_truth.json``) or cases of
the practitioner's benchmark (``--cases``: COLMAP-posed captures and stock nerfacto runs, truth through each
capture's COLMAP tie as ``scripts/bench_practitioner.py`` scores it; the case's own registration, or the solution the
checks refused, is cross-rendered too, beside the truth's perturbations). ``--view-choice nearest`` checks each NeRF
on its views nearest the other NeRF's cameras (under the truth), as the registration checks the views that share the
most SfM points with the other NeRF; on a drive, whose captures overlap only at their ends, evenly spread views
mostly see what the other NeRF never saw. ``--around-solutions`` perturbs the case's solution as well: whether it sits
at a peak of the NCC. ``--depth`` compares depth as the registration does: at each NeRF's views nearest the
other's under the link being checked, whatever ``--view-choice``.

Example:
    python scripts/calibrate_ncc.py --scenes demo=demo/scene:demo/runs \\
        oc1=outputs/bench/scenes/object-centric-1:outputs/bench/runs/object-centric-1
    python scripts/calibrate_ncc.py --scenes --cases drive:5=outputs/practitioner/drive-5 --view-choice nearest \\
        --output reports/ncc_calibration_drive5.json
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns import registration, sim3
from nerfuser_ns.bench.evaluation import SceneRuns
from nerfuser_ns.bench.practitioner_cases import (
    capture_ground_truth,
    case_layout,
    rejected_registration,
    run_config,
)
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import PoseSamplingConfig, RegistrationConfig, read_registration
from nerfuser_ns.registration.self_check import nearest_views
from nerfuser_ns.renderers import NerfstudioRenderer

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
    """Scenes as NAME=SCENE_DIR:RUNS_DIR (none: ``--scenes`` alone)."""
    cases: list[str] = field(default_factory=list)
    """Practitioner cases as LAYOUT:SEED=CASE_DIR (``scripts/bench_practitioner.py``'s case folders, trained)."""
    truth: Literal["stored", "optimized"] = "stored"
    """Cases: the truth through the captures' stored (COLMAP) poses, or through their camera-optimised ones."""
    view_choice: Literal["spread", "nearest"] = "spread"
    """Views checked per direction: evenly spread over the NeRF's views, or those nearest the other NeRF's cameras."""
    around_solutions: bool = False
    """Cases: perturb the case's registration (or refused solution) as well as the truth, to see whether the solution
    sits at a peak of the NCC (a link that rotating or moving raises is not where the content agrees best)."""
    poses: int = 48
    """Training poses per NeRF (the registration's --sampling.max-training-poses)."""
    width: int = 192
    """Render width (as the registration renders)."""
    height: int = 144
    """Render height."""
    fov_deg: float = 65.0
    """Horizontal field of view of the renders (the registration's: its reference run's training cameras'; the same
    value reuses renders the registration stored when ``work_dir`` holds them)."""
    depth: bool = False
    """Store the renders with depth and record the depth check's median log depth ratio per direction beside the
    NCC (renderers that give depth)."""
    views: int = 4
    """Views per direction (the registration's --self-check-views)."""
    seed: int = 0
    """Seed of the perturbation axes."""
    work_dir: Path = Path("outputs/bench/ncc_work")
    """Renders (reused by later runs with the same settings)."""
    output: Path = Path("outputs/bench/ncc_calibration.json")
    """JSON results (a markdown summary is written beside it)."""


@dataclass
class Subject:
    """NeRFs to cross-render: their runs, the true transforms into the first one's frame, and other transforms to
    score beside the truth's perturbations (a registration's solution)."""

    name: str
    captures: list[str]
    renderers: list[NerfstudioRenderer]
    truth: list[np.ndarray]
    solutions: dict[str, list[np.ndarray]] = field(default_factory=dict)


def perturb(T: np.ndarray, kind: str, size: float, rng: np.random.Generator) -> np.ndarray:
    """``T`` moved by a rotation about the NeRF's own origin, a translation or a scale about it of ``size``."""
    if kind == "none":
        return T
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "rotation_deg":
        R = sim3.so3_exp(np.deg2rad(size) * axis)
        # about the NeRF's own origin (in the reference frame), which stays where it was
        D = sim3.make_sim3(R, T[:3, 3] - R @ T[:3, 3], 1.0)
    elif kind == "translation":
        D = sim3.make_sim3(np.eye(3), size * axis, 1.0)
    else:
        return sim3.rescaled_about_origin(T, size)
    return D @ T


def scene_subject(spec: str) -> Subject:
    scene = SceneRuns.parse(spec)
    renderers = [NerfstudioRenderer(p, name=c, data_override=d)
                 for p, c, d in zip(scene.configs, scene.captures, scene.capture_dirs(), strict=True)]  # fmt: skip
    return Subject(scene.name, scene.captures, renderers, scene.nerf_to_common())


def case_subject(spec: str, truth: str) -> Subject:
    case, _, folder = spec.partition("=")
    if not case or not folder:
        raise SystemExit(f"case {spec!r}: expected LAYOUT:SEED=CASE_DIR")
    case_dir = Path(folder)
    layout = case_layout(case)
    captures = [c.name for c in layout.captures]
    gt = capture_ground_truth(layout, case_dir, optimized=truth == "optimized")
    key = "nerf_to_world" if truth == "stored" else "nerf_to_world_optimized"
    if any(key not in g for g in gt):
        raise SystemExit(f"{case_dir}: no {truth} truth for every capture (runs trained with the optimiser on?)")
    renderers = [NerfstudioRenderer(run_config(case_dir, c), name=c) for c in captures]
    subject = Subject(case_dir.name, captures, renderers, list(sim3.to_reference_frame(np.stack([g[key] for g in gt]))))
    for label, path in (("registration", case_dir / "registration.json"), ("refused", rejected_registration(case_dir))):
        if path.is_file():
            reg = read_registration(path)
            T = np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in reg["nerfs"]])
            subject.solutions[label] = list(sim3.to_reference_frame(T))  # into NeRF 0's frame, as the truth
    return subject


def main(cfg: CalibrateNccConfig) -> None:
    console = Console()
    rng = np.random.default_rng(cfg.seed)
    sampling = PoseSamplingConfig(
        source="training", max_training_poses=cfg.poses, width=cfg.width, height=cfg.height, fov_deg=cfg.fov_deg
    )
    # the threshold was calibrated on the SfM mode's results; no colour maps (the check's NCC does not use them)
    reg_cfg = RegistrationConfig(mode="sfm", sampling=sampling, self_check_views=cfg.views, colour_views=0)
    subjects = [scene_subject(s) for s in cfg.scenes] + [case_subject(c, cfg.truth) for c in cfg.cases]
    rows = []
    for subject in subjects:
        views = [registration.render_views_cached(r, sampling, cfg.work_dir / subject.name / "renders", console,
                                                  depth=cfg.depth) for r in subject.renderers]  # fmt: skip
        truth = subject.truth
        for i in range(1, len(subject.renderers)):
            # NeRF i against its predecessor (street captures are consecutive segments; the registration checks
            # overlapping neighbours too). The registration checks the views that see the most shared SfM points, so
            # its own scores for a correct transform are higher than those of spread views.
            order = None
            if cfg.view_choice == "nearest":
                T_ij = sim3.relative_sim3(truth[i], truth[i - 1])  # i - 1 -> i
                order = {(i - 1, i): nearest_views(views[i - 1], T_ij, views[i]),
                         (i, i - 1): nearest_views(views[i], sim3.invert_sim3(T_ij), views[i - 1])}  # fmt: skip
            trials = [("truth", kind, size, perturb(truth[i], kind, size, rng)) for kind, size in PERTURBATIONS]
            for label, T_sol in subject.solutions.items():
                if cfg.around_solutions:
                    trials += [(label, kind, size, perturb(T_sol[i], kind, size, rng)) for kind, size in PERTURBATIONS]
                else:
                    trials.append((label, "none", 0.0, T_sol[i]))
            for centre, kind, size, T_i in trials:
                T = np.stack(truth)
                T[i] = T_i
                t = time.perf_counter()
                (check,) = registration.cross_render_check(
                    subject.renderers, views, T, [(i - 1, i)], sampling.intrinsics(), reg_cfg, view_order=order
                )
                e = sim3.sim3_errors(T[i], truth[i])
                rows.append(
                    {
                        "scene": subject.name,
                        "nerf": subject.captures[i],
                        "centre": centre,
                        "kind": kind,
                        "size": size,
                        "r_err_deg": float(e.r_err_deg),
                        "t_err": float(e.t_err),
                        "s_err": float(e.s_err),
                        "failure": bool(e.is_failure()),
                        "ncc": check.score,
                        "ncc_prev_in_i": check.ncc_i_in_j,
                        "ncc_i_in_prev": check.ncc_j_in_i,
                        "depth": check.depth_disagreement,
                        "depth_prev_in_i": check.depth_i_in_j,
                        "depth_i_in_prev": check.depth_j_in_i,
                        "seconds": time.perf_counter() - t,
                    }
                )
                console.print(f"{subject.name}/{subject.captures[i]} {centre} {kind} {size}: ncc {check.score:.3f}, "
                              f"depth log ratio {check.depth_disagreement:+.3f}")  # fmt: skip
    perturbed = [r for r in rows if r["centre"] == "truth"]
    fails = [r["ncc"] for r in perturbed if r["failure"] and np.isfinite(r["ncc"])]
    exact = [r["ncc"] for r in perturbed if r["kind"] == "none"]
    accurate = [r["ncc"] for r in perturbed if r["r_err_deg"] <= 1.0 and r["t_err"] <= 0.05 and r["s_err"] <= 0.05]
    summary = {
        "max_ncc_of_failures": max(fails) if fails else None,
        "min_ncc_exact": min(exact) if exact else None,
        "min_ncc_accurate": min(accurate) if accurate else None,
    }
    if cfg.depth:
        def largest(rs):  # the largest |depth log ratio| (None when nothing was measured)
            values = [abs(r["depth"]) for r in rs if np.isfinite(r["depth"])]
            return max(values) if values else None

        caught = [abs(r["depth"]) for r in perturbed if r["failure"] and np.isfinite(r["depth"])
                  and np.isfinite(r["ncc"]) and r["ncc"] >= reg_cfg.ncc_threshold]  # fmt: skip
        summary.update({
            "max_abs_depth_exact": largest([r for r in perturbed if r["kind"] == "none"]),
            "max_abs_depth_accurate": largest([r for r in perturbed if r["r_err_deg"] <= 1.0 and r["t_err"] <= 0.05
                                               and r["s_err"] <= 0.05]),
            "min_abs_depth_of_failures_the_ncc_passes": min(caught) if caught else None,
        })  # fmt: skip
    report = {
        "command": "python scripts/calibrate_ncc.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "settings": {"truth": cfg.truth, "view_choice": cfg.view_choice, "around_solutions": cfg.around_solutions,
                     "poses": cfg.poses, "fov_deg": cfg.fov_deg, "depth": cfg.depth,
                     "size": [cfg.width, cfg.height], "views": cfg.views},  # fmt: skip
        "summary": summary,
        "rows": rows,
    }
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    lines = [
        f"# Self-check NCC calibration ({report['date']})",
        "",
        f"`{report['command']}`",
        "",
        "| scene | NeRF | transform | perturbation | r_err | t_err | s_err | paper failure | NCC (worse direction) | "
        "depth log ratio (farther from 0) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['nerf']} | {r['centre']} | {r['kind']} {r['size']:g} | {r['r_err_deg']:.2f} | "
            f"{r['t_err']:.3f} | {r['s_err']:.3f} | {'yes' if r['failure'] else 'no'} | {r['ncc']:.3f} | "
            f"{r['depth']:+.3f} |"
        )
    lines += [
        "",
        f"Truth: {cfg.truth}; views: {cfg.view_choice}. Highest NCC of a failing transform: "
        f"{summary['max_ncc_of_failures']}; lowest NCC of the exact transform: {summary['min_ncc_exact']}; lowest of "
        f"accurate ones (r <= 1 deg, t <= 0.05, s <= 0.05): {summary['min_ncc_accurate']} (over the truth and its "
        "perturbations; errors are against the truth in every row).",
    ]
    if cfg.depth:
        lines += ["", f"Depth check: largest |log ratio| of the exact transform {summary['max_abs_depth_exact']}, of "
                      f"accurate ones {summary['max_abs_depth_accurate']}; smallest of failing transforms the NCC "
                      f"passes (>= {reg_cfg.ncc_threshold}) {summary['min_abs_depth_of_failures_the_ncc_passes']}."]
    write_text_atomic(cfg.output.with_suffix(".md"), "\n".join(lines) + "\n")
    console.print(summary)


def entrypoint() -> None:
    main(tyro.cli(CalibrateNccConfig))


if __name__ == "__main__":
    entrypoint()
