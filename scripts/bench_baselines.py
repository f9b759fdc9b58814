"""Point-cloud registration baselines vs nerfuser_ns on generated scenes (NeRFuser, Table 1).

For every scene (its runs trained by ``scripts/build_demo.py``) and every ordered pair of its NeRFs (source j, target
i), the source cloud is registered to the target cloud by each Open3D baseline (point-to-plane ICP from the identity,
FGR and FPFH + RANSAC, optionally refined by ICP), given the ground-truth relative scale as the paper does (they solve
SE(3) only), and scored with the paper's r_err / t_err / s_err and failure rule against the ground truth. Two kinds
of clouds, both in each NeRF's own frame and rendered from the same poses (the registration's pose sampling, default
the run's training poses):

* ``nerf``: the NeRF's depth renders back-projected (the paper's "NeRF-extracted point-cloud" rows);
* ``gt``: the ground-truth scene's depth at the same poses (the paper's "RGB-D-fused point-cloud" rows).

With ``--registrations NAME=REGISTRATION_JSON`` (ns-nerfuser-register / bench_registration output) the same pairs are
scored for nerfuser_ns; a listed file that does not exist (the registration failed) counts as failures.

Clouds are cached as .ply in ``<output dir>/baselines_work`` (keyed by the renderer and the settings), results are
rewritten atomically after every case, and cases already in the output are skipped when ``--resume``.

Example (the scenes and runs built with scripts/build_demo.py, registrations by scripts/bench_registration.py):
    OMP_NUM_THREADS=1 python scripts/bench_baselines.py \\
        --scenes demo=demo/scene:demo/runs \\
                 oc1=outputs/bench/scenes/object-centric-1:outputs/bench/runs/object-centric-1 \\
                 street0=outputs/bench/scenes/street-0:outputs/bench/runs/street-0 \\
        --registrations demo=outputs/bench/registration_cases/demo-training-24.json \\
                        oc1=outputs/bench/registration_cases/oc1-training-24.json \\
                        street0=outputs/bench/registration_cases/street0-training-24.json
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import tyro

from nerfuser_ns.bench.baselines import PCRConfig, PointCloudConfig
from nerfuser_ns.files import atomic_path, write_text_atomic

VARIANTS = ("icp", "fgr", "ransac", "fgr+icp", "ransac+icp")
"""Baseline variants: a method, optionally followed by ICP refinement (``+icp``)."""
KIND_TITLES = {
    "nerf": "NeRF-extracted point clouds",
    "gt": "Ground-truth RGB-D fused point clouds",
    "nerfuser": "nerfuser_ns (registration from re-rendering)",
}


@dataclass
class BenchBaselinesConfig:
    """Register every ordered NeRF pair of generated scenes with point-cloud baselines; score against ground truth."""

    scenes: list[str] = field(default_factory=lambda: ["demo=demo/scene:demo/runs"])
    """Scenes as NAME=SCENE_DIR:RUNS_DIR (runs at RUNS_DIR/<capture>/nerfacto-cpu/demo/config.yml)."""
    registrations: list[str] = field(default_factory=list)
    """nerfuser_ns results as NAME=REGISTRATION_JSON; a listed file that does not exist counts as failed cases."""
    variants: list[str] = field(default_factory=lambda: list(VARIANTS))
    """Baselines to run: icp, fgr, ransac, and fgr+icp / ransac+icp (refined by point-to-plane ICP)."""
    clouds: list[Literal["nerf", "gt"]] = field(default_factory=lambda: ["nerf", "gt"])
    """Point clouds to register: nerf (depth renders of the NeRFs) and gt (ground-truth depth, same poses)."""
    source: Literal["hemisphere", "training", "both"] = "training"
    """Poses the clouds are rendered from (the registration's pose sampling)."""
    num_views: int = 24
    """Training poses per NeRF (evenly spaced through the run's list), or hemisphere poses."""
    width: int = 160
    """Render width."""
    height: int = 120
    """Render height."""
    fov_deg: float = 65.0
    """Render horizontal field of view."""
    nerf_cloud: PointCloudConfig = field(default_factory=lambda: PointCloudConfig(crop_half_size=2.0))
    """Extraction settings of the NeRF clouds (cropped to twice nerfacto's scene box: contracted space is poor)."""
    gt_cloud: PointCloudConfig = field(default_factory=PointCloudConfig)
    """Extraction settings of the ground-truth clouds."""
    pcr: PCRConfig = field(default_factory=PCRConfig)
    """Registration settings (method and refinement are set per variant)."""
    threads: int = 1
    """torch threads (set OMP_NUM_THREADS too: Open3D reads it)."""
    output: Path = Path("outputs/bench/baselines.json")
    """JSON results (a markdown summary is written beside it)."""
    resume: bool = True
    """Skip cases already in the output file (clouds are cached in <output dir>/baselines_work either way)."""


# ---------------------------------------------------------------------------------------------------------------------
# Report


def _f(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _summary_rows(cases: list[dict]) -> list[dict]:
    """One row per (clouds, method): the paper's means over successful cases and the success rate over all."""
    order = [(k, m) for k in ("nerf", "gt") for m in VARIANTS] + [("nerfuser", "nerfuser")]
    groups: dict[tuple[str, str], list[dict]] = {}
    for c in cases:
        groups.setdefault((c["clouds"], c["method"]), []).append(c)
    rows = []
    for key in sorted(groups, key=lambda k: order.index(k) if k in order else len(order)):
        group = groups[key]
        ok = [c for c in group if not c["failure"]]
        scored = [c for c in group if c.get("r_err_deg") is not None]

        def mean(k, cs=ok):
            return statistics.fmean(c[k] for c in cs) if cs else None

        def median(k, cs=scored):
            return statistics.median(c[k] for c in cs) if cs else None

        rows.append({
            "clouds": key[0], "method": key[1], "cases": len(group), "successes": len(ok),
            "success_rate": len(ok) / len(group), "scenes": len({c["scene"] for c in group}),
            "mean_r_err_deg_successes": mean("r_err_deg"), "mean_t_err_successes": mean("t_err"),
            "mean_s_err_successes": mean("s_err"), "median_r_err_deg": median("r_err_deg"),
            "median_t_err": median("t_err"), "median_s_err": median("s_err"),
        })  # fmt: skip
    return rows


def _fmt(x, digits: int) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _markdown(report: dict) -> str:
    lines = [
        f"# Point-cloud registration baselines vs nerfuser_ns ({report['date']})",
        "",
        f"`{report['command']}` on {report['machine']['platform']}, {report['machine']['cpus']} CPUs, Open3D "
        f"{report['machine']['open3d']}.",
        "",
        "Every ordered NeRF pair (source -> target) of every scene. Baselines get the ground-truth relative scale and "
        "solve SE(3) (their s_err is 0 by construction: N/A). r_err / t_err / s_err: means over the successful cases "
        "(as the paper reports them); medians over all scored cases in brackets; success: the paper's rule (not NaN, "
        "r <= 5 deg, t <= 0.2 target units, s <= 0.1) over all cases.",
        "",
        "| registration | r_err (deg) | t_err | s_err | success | cases (scenes) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    section = None
    for row in report["summary"]:
        if row["clouds"] != section:
            section = row["clouds"]
            lines.append(f"| **{KIND_TITLES.get(section, section)}** | | | | | |")
        s_err = (
            "N/A"
            if row["clouds"] != "nerfuser"
            else f"{_fmt(row['mean_s_err_successes'], 4)} [{_fmt(row['median_s_err'], 4)}]"
        )
        lines.append(
            f"| {row['method']} | {_fmt(row['mean_r_err_deg_successes'], 3)} [{_fmt(row['median_r_err_deg'], 2)}] | "
            f"{_fmt(row['mean_t_err_successes'], 4)} [{_fmt(row['median_t_err'], 3)}] | {s_err} | "
            f"{row['successes']}/{row['cases']} = {row['success_rate']:.2f} | {row['cases']} ({row['scenes']}) |"
        )
    lines += [
        "",
        "## Cases",
        "",
        "| case | r_err (deg) | t_err | s_err | failure | fitness | voxel | points src / tgt | s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in report["cases"]:
        if c["status"] != "ok":
            lines.append(f"| {c['case']} | - | - | - | True ({c['status']}: {c.get('error', '')}) | - | - | - | - |")
            continue
        pts = f"{c['points'][0]} / {c['points'][1]}" if c.get("points") else "-"
        lines.append(
            f"| {c['case']} | {_fmt(c['r_err_deg'], 3)} | {_fmt(c['t_err'], 4)} | {_fmt(c['s_err'], 4)} | "
            f"{c['failure']} | {_fmt(c.get('fitness'), 3)} | {_fmt(c.get('voxel_size'), 4)} | {pts} | "
            f"{_fmt(c.get('seconds'), 1)} |"
        )
    lines += ["", "## Clouds", "", "| cloud | points | extraction s |", "| --- | --- | --- |"]
    for key, info in sorted(report["clouds"].items()):
        lines.append(f"| {key} | {info['points']} | {_fmt(info.get('seconds'), 1)} |")
    return "\n".join(lines) + "\n"


def _write(cfg: BenchBaselinesConfig, report: dict) -> None:

    report["summary"] = _summary_rows(report["cases"])
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    write_text_atomic(cfg.output.with_suffix(".md"), _markdown(report))


# ---------------------------------------------------------------------------------------------------------------------
# Main


def _parse_variant(variant: str) -> tuple[str, bool]:
    method, _, refine = variant.partition("+")
    if variant not in VARIANTS:
        raise SystemExit(f"--variants: unknown {variant!r}; choose from {', '.join(VARIANTS)}")
    return method, refine == "icp"


def _errors(T_hat, T_true) -> dict:
    from nerfuser_ns import sim3

    e = sim3.sim3_errors(T_hat, T_true)
    return {
        "r_err_deg": _f(e.r_err_deg), "t_err": _f(e.t_err), "s_err": _f(e.s_err), "failure": bool(e.is_failure()),
    }  # fmt: skip


class _SceneClouds:
    """The point clouds of one scene's NeRFs (``nerf``) and of its ground truth in their frames (``gt``), extracted on
    first use from the NeRF's sampled poses and cached as .ply under ``work`` (keyed by renderer and settings)."""

    def __init__(
        self, cfg: BenchBaselinesConfig, scene, layout, nerfs: list, sampling, work: Path, report: dict, console
    ):
        self.cfg, self.scene, self.layout, self.nerfs, self.sampling = cfg, scene, layout, nerfs, sampling
        self.work, self.report, self.console = work, report, console
        self.poses: dict[int, object] = {}
        self.clouds: dict[tuple[str, int], object] = {}

    def get(self, kind: str, idx: int):
        import open3d as o3d

        from nerfuser_ns import registration, sim3
        from nerfuser_ns.bench import baselines
        from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer

        if (kind, idx) in self.clouds:
            return self.clouds[(kind, idx)]
        nerf, name = self.nerfs[idx], self.scene.captures[idx]
        if kind == "nerf":
            renderer, ccfg = nerf, self.cfg.nerf_cloud
        else:  # the ground-truth scene seen through the NeRF's frame
            frame_to_capture = sim3.invert_sim3(nerf.data_to_nerf)
            renderer = SceneFrameRenderer.from_layout(self.layout, name, frame_to_capture=frame_to_capture)
            ccfg = self.cfg.gt_cloud
        key_src = {"renderer": renderer.cache_key(), "sampling": asdict(self.sampling), "cloud": asdict(ccfg)}
        key = hashlib.sha256(json.dumps(key_src, sort_keys=True, default=str).encode()).hexdigest()[:12]
        path = self.work / self.scene.name / f"{kind}-{name}-{key}.ply"
        label = f"{self.scene.name}/{kind}/{name}"
        if path.is_file():
            self.clouds[(kind, idx)] = o3d.io.read_point_cloud(str(path))
            return self.clouds[(kind, idx)]
        if idx not in self.poses:
            self.poses[idx] = registration.sample_poses(nerf, self.sampling)[0]  # the NeRF's poses, in its frame
        poses = self.poses[idx]
        t = time.perf_counter()
        with self.console.status(f"extracting {label} ({len(poses)} views)"):
            cloud = baselines.extract_point_cloud(renderer, poses, self.sampling.intrinsics(), ccfg)
        seconds = time.perf_counter() - t
        with atomic_path(path) as tmp:
            o3d.io.write_point_cloud(str(tmp), cloud)
        cloud = o3d.io.read_point_cloud(str(path))  # as a resumed run sees it (colours stored as 8 bits)
        self.report["clouds"][label] = {
            "points": len(cloud.points), "seconds": round(seconds, 1), "views": len(poses), "file": str(path),
        }  # fmt: skip
        self.console.print(f"{label}: {len(cloud.points)} points in {seconds:.0f} s")
        self.clouds[(kind, idx)] = cloud
        return cloud


def main(cfg: BenchBaselinesConfig) -> None:
    import torch
    from rich.console import Console

    from nerfuser_ns import sim3
    from nerfuser_ns.bench import baselines, evaluation, scenes
    from nerfuser_ns.registration import PoseSamplingConfig
    from nerfuser_ns.renderers import NerfstudioRenderer

    try:  # before any work
        open3d_version = baselines.open3d_version()
    except baselines.BaselineError as e:
        raise SystemExit(f"bench_baselines: {e}") from None
    torch.set_num_threads(cfg.threads)
    console = Console()
    variants = [(v, *_parse_variant(v)) for v in cfg.variants]
    try:
        scene_runs = [evaluation.SceneRuns.parse(s) for s in cfg.scenes]
    except evaluation.EvaluationError as e:
        raise SystemExit(f"bench_baselines: {e}") from None
    registrations = {}
    for spec in cfg.registrations:
        name, _, path = spec.partition("=")
        if not name or not path:
            raise SystemExit(f"--registrations: expected NAME=REGISTRATION_JSON, got {spec!r}")
        registrations[name] = Path(path)
    unknown = sorted(set(registrations) - {s.name for s in scene_runs})
    if unknown:
        raise SystemExit(f"--registrations: no scene named {unknown[0]!r} in --scenes")
    sampling = PoseSamplingConfig(
        source=cfg.source, num_poses=cfg.num_views, max_training_poses=cfg.num_views, width=cfg.width,
        height=cfg.height, fov_deg=cfg.fov_deg,
    )  # fmt: skip
    sampling.intrinsics()  # checks the render size and field of view before anything is rendered

    report = {
        "command": "python scripts/bench_baselines.py " + " ".join(sys.argv[1:]),
        "machine": {
            "platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
            "open3d": open3d_version, "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        },
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "settings": {
            "sampling": asdict(sampling), "nerf_cloud": asdict(cfg.nerf_cloud), "gt_cloud": asdict(cfg.gt_cloud),
            "pcr": {k: v for k, v in asdict(cfg.pcr).items() if k != "_target"}, "variants": cfg.variants,
        },
        "cases": [],
        "clouds": {},
    }  # fmt: skip
    if cfg.resume and cfg.output.is_file():
        old = json.loads(cfg.output.read_text())
        report["cases"] = old.get("cases", [])
        report["clouds"] = old.get("clouds", {})
    done = {c["case"] for c in report["cases"]}
    work = cfg.output.parent / "baselines_work"

    for scene in scene_runs:
        names = scene.captures
        k = len(names)
        to_world = scene.nerf_to_world()
        pairs = [(j, i) for i in range(k) for j in range(k) if i != j]  # (source, target)
        T_true = {(j, i): sim3.relative_sim3(to_world[i], to_world[j]) for j, i in pairs}  # source j -> target i

        # nerfuser_ns: the registration's transforms into its common frame, re-expressed per pair.
        if scene.name in registrations:
            path = registrations[scene.name]
            estimated = evaluation.registered_transforms(path, scene) if path.is_file() else None
            for j, i in pairs:
                case = f"{scene.name}/nerfuser/{names[j]}->{names[i]}/nerfuser"
                if case in done:
                    continue
                rec = {"case": case, "scene": scene.name, "clouds": "nerfuser", "method": "nerfuser",
                       "source": names[j], "target": names[i], "registration": str(path)}  # fmt: skip
                if estimated is None:
                    rec.update(status="no registration", error=f"{path} does not exist (the registration failed)",
                               r_err_deg=None, t_err=None, s_err=None, failure=True)  # fmt: skip
                else:
                    T_hat = sim3.relative_sim3(estimated[i], estimated[j])
                    rec.update(status="ok", **_errors(T_hat, T_true[(j, i)]), T_estimate=T_hat.tolist())
                report["cases"].append(rec)
            _write(cfg, report)

        todo = [(kind, j, i, v) for kind in cfg.clouds for j, i in pairs for v in variants
                if f"{scene.name}/{kind}/{names[j]}->{names[i]}/{v[0]}" not in done]  # fmt: skip
        if not todo:
            continue
        console.rule(f"{scene.name}: {len(todo)} cases")
        layout = scenes.layout_from_ground_truth(scene.scene_dir)
        nerfs = [
            NerfstudioRenderer(p, name=n, data_override=d)
            for n, p, d in zip(names, scene.configs, scene.capture_dirs(), strict=True)
        ]
        clouds = _SceneClouds(cfg, scene, layout, nerfs, sampling, work, report, console)

        for kind, j, i, (variant, method, refine) in todo:
            case = f"{scene.name}/{kind}/{names[j]}->{names[i]}/{variant}"
            rec = {"case": case, "scene": scene.name, "clouds": kind, "method": variant, "source": names[j],
                   "target": names[i]}  # fmt: skip
            T = T_true[(j, i)]
            try:
                src, tgt = clouds.get(kind, j), clouds.get(kind, i)
                pcr = replace(cfg.pcr, method=method, refine_with_icp=refine)
                res = pcr.setup().register(src, tgt, scale=float(sim3.decompose_sim3(T)[2]))
            except baselines.BaselineError as e:
                rec.update(status="error", error=str(e), r_err_deg=None, t_err=None, s_err=None, failure=True)
            else:
                rec.update(
                    status="ok", **_errors(res.T, T), fitness=res.fitness, inlier_rmse=_f(res.inlier_rmse),
                    voxel_size=res.voxel_size, points=[res.num_source_points, res.num_target_points],
                    seconds=round(res.seconds, 2), T_estimate=res.T.tolist(),
                )  # fmt: skip
            report["cases"].append(rec)
            console.print(
                f"{case}: r {_fmt(rec['r_err_deg'], 3)} deg, t {_fmt(rec['t_err'], 4)}, "
                f"{'FAIL' if rec['failure'] else 'ok'}"
            )
            _write(cfg, report)
    _write(cfg, report)
    for row in report["summary"]:
        console.print(
            f"{row['clouds']:8s} {row['method']:10s} success {row['successes']}/{row['cases']} "
            f"r {_fmt(row['mean_r_err_deg_successes'], 3)} t {_fmt(row['mean_t_err_successes'], 4)}"
        )
    console.print(f"wrote {cfg.output} and {cfg.output.with_suffix('.md')}")


def entrypoint() -> None:
    main(tyro.cli(BenchBaselinesConfig))


if __name__ == "__main__":
    entrypoint()
