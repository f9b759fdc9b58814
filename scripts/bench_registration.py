"""Registration benchmark: ns-nerfuser-register on CPU-trained NeRFs of generated scenes, against ground truth.

Each case is one scene (its runs, as ``scripts/build_demo.py`` trains them) and one pose-sampling setting; every run
of the scene is registered into the first one's frame. Per NeRF the paper's r_err (deg), t_err (reference units),
s_err = |log s| and failure flag are recorded, with the time split (render / features / matching / mapping / solve /
self-check). Results are rewritten (atomically) after every case, so a long run can be stopped and still reports what
it measured; cases already in the output are skipped when ``--resume``.

Example (the scenes and runs built first with scripts/build_demo.py):
    python scripts/bench_registration.py \\
        --scenes demo=demo/scene:demo/runs \\
                 oc1=outputs/bench/scenes/object-centric-1:outputs/bench/runs/object-centric-1 \\
        --pose-counts 32 --seeds 0 1 --output outputs/bench/registration.json
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from nerfuser_ns.bench.evaluation import EvaluationError, SceneRuns
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.files import write_text_atomic


@dataclass
class BenchRegistrationConfig:
    """Register the runs of generated scenes from their re-renderings and score them against ground truth."""

    scenes: list[str] = field(default_factory=lambda: ["demo=demo/scene:demo/runs"])
    """Scenes as NAME=SCENE_DIR:RUNS_DIR (runs at RUNS_DIR/<capture>/nerfacto-cpu/demo/config.yml)."""
    pose_counts: list[int] = field(default_factory=lambda: [32])
    """Training poses per NeRF to render, one case per value, seed and scene."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """Pose draws (0: evenly spaced training poses; others: random subsets)."""
    source: str = "training"
    """Pose source passed to the registration (hemisphere, training or both)."""
    width: int = 192
    """Render width (the generated scenes' training images are 192x144)."""
    height: int = 144
    """Render height."""
    fov_deg: float = 65.0
    """Render horizontal field of view."""
    refine: bool = True
    """Rigid-set bundle adjustment after the paper's estimator (--no-refine: the estimator alone; its cases and
    registration files get a -norefine suffix, so they never stand in for refined ones; use another --output to keep
    the summaries apart)."""
    output: Path = Path("outputs/bench/registration.json")
    """JSON results (a markdown summary is written beside it)."""
    resume: bool = True
    """Skip cases already in the output file."""


def _cases(cfg: BenchRegistrationConfig) -> list[tuple[SceneRuns, int, int]]:
    try:
        scenes = [SceneRuns.parse(spec) for spec in cfg.scenes]
    except EvaluationError as e:
        raise SystemExit(f"bench_registration: {e}") from None
    # every scene once before any scene twice: a run stopped early still covers all scenes
    return [(scene, count, seed) for seed in cfg.seeds for count in cfg.pose_counts for scene in scenes]


def _summary(results: list[dict]) -> dict:
    errs = [n for r in results if r["status"] == "ok" for n in r["nerfs"][1:]]  # the reference is exact
    failures = sum(1 for r in results if r["status"] != "ok") + sum(1 for n in errs if n["failure"])
    total = sum(1 for r in results if r["status"] != "ok") + len(errs)
    med = (lambda k: statistics.median(n[k] for n in errs)) if errs else (lambda k: float("nan"))
    return {
        "cases": len(results),
        "registered_nerfs": total,
        "median_r_err_deg": med("r_err_deg"),
        "median_t_err": med("t_err"),
        "median_s_err": med("s_err"),
        "success_rate": (total - failures) / total if total else float("nan"),
    }


def _write(cfg: BenchRegistrationConfig, results: list[dict]) -> None:
    import torch

    report = {
        "command": "python scripts/bench_registration.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "summary": _summary(results),
        "cases": results,
    }
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    lines = [
        f"# Registration benchmark ({report['date']})",
        "",
        f"`{report['command']}` on {report['machine']['platform']}, {report['machine']['cpus']} CPUs.",
        "",
        "| case | NeRF | views kept / registered | r_err (deg) | t_err | s_err | failure | render s | SfM s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        if r["status"] != "ok":
            lines.append(f"| {r['case']} | - | - | - | - | - | {r['status']}: {r['error']} | - | - |")
            continue
        t = r["timings_s"]
        sfm = sum(t.get(k, 0.0) for k in ("features", "matching", "mapping"))
        for n in r["nerfs"]:
            lines.append(
                f"| {r['case']} | {n['name']} | {n['views']} | {n['r_err_deg']:.4f} | {n['t_err']:.5f} | "
                f"{n['s_err']:.5f} | {n['failure']} | {t.get('render', 0):.0f} | {sfm:.1f} |"
            )
    s = report["summary"]
    lines += [
        "",
        f"Non-reference NeRFs: {s['registered_nerfs']}; median r_err {s['median_r_err_deg']:.4f} deg, "
        f"t_err {s['median_t_err']:.5f}, s_err {s['median_s_err']:.5f}; success rate {s['success_rate']:.2f}.",
    ]
    md = cfg.output.with_suffix(".md")
    write_text_atomic(md, "\n".join(lines) + "\n")


def main(cfg: BenchRegistrationConfig) -> None:
    from rich.console import Console

    from nerfuser_ns import registration, runs
    from nerfuser_ns.registration import PoseSamplingConfig, RegistrationConfig, RegistrationError

    console = Console()
    done: dict[str, dict] = {}
    if cfg.resume and cfg.output.is_file():
        done = {r["case"]: r for r in json.loads(cfg.output.read_text())["cases"]}
    results = list(done.values())
    for scene, count, seed in _cases(cfg):
        label = f"{cfg.source}-{count}-seed{seed}" + ("" if cfg.refine else "-norefine")
        case = f"{scene.name}/{label}"
        if case in done:
            continue
        captures, configs, gt_nerf_to_world = scene.captures, scene.configs, scene.nerf_to_world()
        reg_cfg = RegistrationConfig(
            mode="sfm",  # this benchmark measures the paper's registration
            sampling=PoseSamplingConfig(
                source=cfg.source, max_training_poses=count, num_poses=count, seed=seed, width=cfg.width,
                height=cfg.height, fov_deg=cfg.fov_deg,
            ),
            refine=cfg.refine,
        )  # fmt: skip
        out = cfg.output.parent / "registration_cases" / f"{scene.name}-{label}.json"
        console.rule(case)
        t = time.perf_counter()
        try:
            record = registration.register_runs(
                configs, out, reg_cfg, work_dir=cfg.output.parent / "registration_work" / scene.name,
                names=captures, data_overrides=scene.capture_dirs(),
            )  # fmt: skip
            record = score_registration(record, gt_nerf_to_world)
        except (RegistrationError, runs.RunLoadError) as e:
            results.append({"case": case, "status": "error", "error": str(e), "seconds": time.perf_counter() - t})
            _write(cfg, results)
            continue
        nerfs = []
        for n in record["nerfs"]:
            g = n.get("ground_truth") or {}
            nerfs.append({
                "name": n["name"],
                "views": f"{n['views']['kept']} / {n['views']['registered']}",
                "r_err_deg": g.get("r_err_deg", float("nan")),
                "t_err": g.get("t_err", float("nan")),
                "s_err": g.get("s_err", float("nan")),
                "failure": bool(g.get("failure", True)),
            })  # fmt: skip
        results.append({
            "case": case, "status": "ok", "nerfs": nerfs, "timings_s": record.get("timings_s", {}),
            "seconds": round(time.perf_counter() - t, 1),
        })  # fmt: skip
        _write(cfg, results)
    _write(cfg, results)
    console.print(_summary(results))


def entrypoint() -> None:
    main(tyro.cli(BenchRegistrationConfig))


if __name__ == "__main__":
    entrypoint()
