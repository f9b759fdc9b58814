"""Registration modes compared: the paper's SfM (``--mode sfm``) against known geometry (``--mode known-geometry``,
ours), with every other setting at its default, scored against ground truth.

Two kinds of cases:

* ``--scenes LAYOUT:SEED ...``: ground-truth scene renderers (exact depth, exact colours: a perfect NeRF) of generated
  layouts, each capture in its own frame. Cheap; isolates the registration from NeRF quality. The ``room`` layout has
  repeated structure (opposite walls alike, one door breaks the tie).
* ``--practitioner CASE_DIR ...``: the stock nerfacto runs of ``scripts/bench_practitioner.py`` (COLMAP-posed
  captures), scored with that benchmark's ground truth (each capture's COLMAP cameras fitted to the true ones).

Per case and mode: r/t/s errors of every non-reference NeRF, the paper's failure rule, the renders per NeRF and the
time split (render / features / matching / mapping or hypotheses / solve / self-check). Results are rewritten
atomically after every case; ``--resume`` skips cases already in the output.

Example::

    python scripts/bench_known_geometry.py --scenes object-centric:1 street:1 drive:1 room:1 \\
        --practitioner outputs/practitioner/object-centric-1 --pose-counts 32 8 --output outputs/bench/modes.json
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns import registration, runs, sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout, run_config
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import PoseSamplingConfig, RegistrationConfig, RegistrationError
from nerfuser_ns.renderers import NerfstudioRenderer

MODES = ("sfm", "known-geometry")
STEPS_AFTER_RENDER = ("features", "matching", "mapping", "hypotheses", "solve", "colocated", "direct", "self_check")


@dataclass
class BenchKnownGeometry:
    """Compare the registration modes on ground-truth renderers and on the practitioner benchmark's runs."""

    scenes: list[str] = field(default_factory=lambda: ["object-centric:1", "street:1", "drive:1", "room:1"])
    """Generated layouts as LAYOUT:SEED, registered with ground-truth renderers (seed 0 is the validation seed)."""
    practitioner: list[Path] = field(default_factory=list)
    """Case folders of scripts/bench_practitioner.py (trained runs, COLMAP datasets) to register."""
    pose_counts: list[int] = field(default_factory=lambda: [32])
    """Training poses rendered per NeRF (--sampling.max-training-poses), one case per value."""
    modes: list[str] = field(default_factory=lambda: list(MODES))
    """Registration modes to compare."""
    output: Path = Path("outputs/bench/known_geometry.json")
    """JSON results (a markdown table is written beside it)."""
    resume: bool = True
    """Skip cases already in the output."""
    device: str = field(default_factory=runs.default_device)
    """Device the nerfstudio runs render on."""
    refine: bool = True
    """Refine each mode's transforms by its bundle adjustment (the default of ns-nerfuser-register); --no-refine is the
    ablation."""
    fresh_sfm: bool = True
    """Scene cases: run the SfM again rather than reuse a cached one, so both modes' steps after rendering are timed
    in the same run (renders are reused by both: their time is the time they took when made)."""


def _gt_case(spec: str):
    layout_name, _, seed = spec.partition(":")
    layout = scenes.make_layout(layout_name, **scenes.benchmark_params(layout_name, int(seed)))
    renderers = [SceneFrameRenderer.from_layout(layout, c.name) for c in layout.captures]
    return renderers, [c.capture_to_world for c in layout.captures]


def _practitioner_case(case_dir: Path, device: str):
    name, _, seed = case_dir.name.rpartition("-")
    layout = case_layout(f"{name}:{seed}")  # the benchmark's default sizes
    gt = capture_ground_truth(layout, case_dir, optimized=False)  # the stored truth alone
    renderers = [NerfstudioRenderer(run_config(case_dir, c.name), device=device, name=c.name) for c in layout.captures]
    return renderers, [g["nerf_to_world"] for g in gt]


def run_case(renderers, nerf_to_world, mode: str, count: int, work_dir: Path, refine: bool = True) -> dict:
    config = RegistrationConfig(mode=mode, sampling=PoseSamplingConfig(max_training_poses=count), refine=refine)
    t = time.perf_counter()
    try:
        record = registration.register(renderers, config, work_dir, Console(quiet=True)).to_record()
    except RegistrationError as e:
        return {"status": "error", "error": str(e).splitlines()[0], "seconds": round(time.perf_counter() - t, 1)}
    ref = record["reference"]["index"]
    nerfs = []
    for i, n in enumerate(record["nerfs"]):
        if i == ref:
            continue
        T_true = sim3.compose(sim3.invert_sim3(nerf_to_world[ref]), nerf_to_world[i])
        e = sim3.sim3_errors(np.asarray(n["T_to_reference"]), T_true)
        nerfs.append({"name": n["name"], "r_err_deg": float(e.r_err_deg), "t_err": float(e.t_err),
                      "s_err": float(e.s_err), "failure": bool(e.is_failure())})  # fmt: skip
    made = record.get("compute_timings_s", {})
    return {
        "status": "ok", "nerfs": nerfs, "renders_per_nerf": count, "timings_s": record["timings_s"],
        "compute_timings_s": made,
        # as computed: a reused SfM reports the time it took when it was made
        "after_render_s": round(sum(made.get(k) or 0.0 for k in STEPS_AFTER_RENDER), 2),
        "sampling": (record.get("sampling_choice") or {}).get("source"),
        "refinement": {k: v for k, v in (record.get("refinement") or {}).items() if k != "change"} or None,
        "seconds": round(time.perf_counter() - t, 1),
    }  # fmt: skip


def summary(results: list[dict], mode: str, kind: str | None = None) -> dict:
    rows = [r for r in results if r["mode"] == mode and (kind is None or r["kind"] == kind)]
    errs = [n for r in rows if r["status"] == "ok" for n in r["nerfs"]]
    failed = sum(n["failure"] for n in errs) + sum(r["num_nerfs"] - 1 for r in rows if r["status"] != "ok")
    total = len(errs) + sum(r["num_nerfs"] - 1 for r in rows if r["status"] != "ok")
    med = (lambda k: statistics.median(n[k] for n in errs)) if errs else (lambda k: float("nan"))
    after = [r["after_render_s"] for r in rows if r["status"] == "ok"]
    return {"cases": len(rows), "nerfs": total, "success_rate": (total - failed) / total if total else float("nan"),
            "median_r_err_deg": med("r_err_deg"), "median_t_err": med("t_err"), "median_s_err": med("s_err"),
            "median_after_render_s": statistics.median(after) if after else float("nan")}  # fmt: skip


def write(cfg: BenchKnownGeometry, results: list[dict]) -> None:
    import torch

    report = {
        "command": "python scripts/bench_known_geometry.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "summary": {m: {k: summary(results, m, k) for k in ("scene", "practitioner")} for m in cfg.modes},
        "cases": results,
    }
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    lines = [f"# Registration modes: SfM (the paper's) vs known geometry (ours) ({report['date']})", "",
             f"`{report['command']}` on {report['machine']['platform']}, {report['machine']['cpus']} CPUs.", "",
             "| case | mode | renders / NeRF | NeRF | r_err (deg) | t_err | s_err | failure | render s "
             "| after render s |",
             "| --- | --- | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: |"]  # fmt: skip
    for r in results:
        if r["status"] != "ok":
            lines.append(f"| {r['case']} | {r['mode']} | {r['count']} | - | - | - | - | error: {r['error']} | - | - |")
            continue
        for n in r["nerfs"]:
            render = r["compute_timings_s"].get("render")
            lines.append(
                f"| {r['case']} | {r['mode']} | {r['count']} | {n['name']} | {n['r_err_deg']:.3f} | {n['t_err']:.4f} | "
                f"{n['s_err']:.4f} | {n['failure']} | {'-' if render is None else f'{render:.0f}'} | "
                f"{r['after_render_s']:.1f} |"
            )
    lines += ["", "| mode | cases | kind | NeRFs | success | median r_err (deg) | median t_err | median s_err | "
              "median s after render |", "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for m, by_kind in report["summary"].items():
        for kind, s in by_kind.items():
            if s["cases"]:
                lines.append(f"| {m} | {s['cases']} | {kind} | {s['nerfs']} | {s['success_rate']:.2f} | "
                             f"{s['median_r_err_deg']:.4f} | {s['median_t_err']:.5f} | {s['median_s_err']:.5f} | "
                             f"{s['median_after_render_s']:.1f} |")  # fmt: skip
    write_text_atomic(cfg.output.with_suffix(".md"), "\n".join(lines) + "\n")


def main(cfg: BenchKnownGeometry) -> None:
    console = Console()
    bad = [m for m in cfg.modes if m not in MODES]
    if bad:
        raise SystemExit(f"bench_known_geometry: unknown mode {bad[0]!r}; use {' or '.join(MODES)}")
    missing = [str(p) for p in cfg.practitioner if not (p / "datasets").is_dir()]
    if missing:
        raise SystemExit(f"bench_known_geometry: {missing[0]}: not a practitioner case folder (no datasets/)")
    done = {}
    if cfg.resume and cfg.output.is_file():
        done = {(r["case"], r["mode"], r["count"]): r for r in json.loads(cfg.output.read_text())["cases"]}
    results = list(done.values())
    cases = [("scene", s, s.replace(":", "-")) for s in cfg.scenes]
    cases += [("practitioner", p, p.name) for p in cfg.practitioner]
    for count in cfg.pose_counts:
        for kind, source, name in cases:
            for mode in cfg.modes:
                if (name, mode, count) in done:
                    continue
                console.rule(f"{name} {mode} {count} renders per NeRF")
                if kind == "scene":
                    renderers, nerf_to_world = _gt_case(source)
                    work = cfg.output.parent / "known_geometry_work" / name
                    if mode == "sfm" and cfg.fresh_sfm:
                        shutil.rmtree(work / "sfm", ignore_errors=True)
                else:
                    renderers, nerf_to_world = _practitioner_case(source, cfg.device)
                    work = source / "registration_work"  # the practitioner benchmark's own renders are reused
                result = run_case(renderers, nerf_to_world, mode, count, work, cfg.refine)
                result.update({"case": name, "kind": kind, "mode": mode, "count": count, "refine": cfg.refine,
                               "num_nerfs": len(renderers)})  # fmt: skip
                console.print({k: v for k, v in result.items() if k not in ("compute_timings_s",)})
                results.append(result)
                write(cfg, results)
    write(cfg, results)
    for m in cfg.modes:
        console.print(m, summary(results, m))


def entrypoint() -> None:
    main(tyro.cli(BenchKnownGeometry))


if __name__ == "__main__":
    entrypoint()
