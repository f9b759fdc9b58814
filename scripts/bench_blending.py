"""Blending benchmark: quality of every blend method and the fused render cost, on generated scenes.

Per scene (its runs trained by ``scripts/build_demo.py``): the world-frame test views are rendered by the fused model
with every blend method in one pass (NeRF, Nearest, IDW-2D, IDW-3D, IDW-Sample) and scored against the ground truth
(PSNR / SSIM / LPIPS when its weights are local), once with the ground-truth transforms and once with the estimated
ones from a registration file when given. Then one chunk of test rays is timed through the fused IDW-Sample model
and through each sub-model's own forward pass on the same rays (paired repeats, median ratio), with the peak
resident memory each pass adds.

gamma / tau default to the paper's per-layout values (object-centric: 5 / 1.8; street and drive: Mission Bay's
10 / 1.2).

Example (after scripts/bench_registration.py wrote the registration files):
    python scripts/bench_blending.py \\
        --scenes demo=demo/scene:demo/runs street0=outputs/bench/scenes/street-0:outputs/bench/runs/street-0 \\
        --registrations demo=outputs/bench/registration_cases/demo-training-24.json \\
                        street0=outputs/bench/registration_cases/street0-training-24.json
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


@dataclass
class BenchBlendingConfig:
    """Score every blend method on generated scenes and time the fused model against its sub-models."""

    scenes: list[str] = field(default_factory=lambda: ["demo=demo/scene:demo/runs"])
    """Scenes as NAME=SCENE_DIR:RUNS_DIR (runs at RUNS_DIR/<capture>/nerfacto-cpu/demo/config.yml)."""
    registrations: list[str] = field(default_factory=list)
    """Estimated transforms as NAME=REGISTRATION_JSON (ns-nerfuser-register output); scenes without one are scored
    with the ground-truth transforms only."""
    max_test_views: int = 12
    """Test views per scene."""
    quality: bool = True
    """Score the blend methods (--no-quality: only the render cost)."""
    coverage: bool = True
    """Also score ``coverage`` and ``coverage-3d`` (ours: weighted by the runs' training-camera coverage) beside the
    paper's methods; the runs' training cameras are read from their datasets (the scene's capture folders)."""
    gamma: float | None = None
    """Blending rate (None: the paper's value for the scene's layout)."""
    tau: float | None = None
    """Distance test (None: the paper's value for the scene's layout)."""
    gammas: list[float] = field(default_factory=list)
    """Also sweep these blending rates with the ground-truth transforms (the paper's gamma ablation; the samples are
    queried once and re-blended per gamma), e.g. --gammas 1 3 10 30 100."""
    timing_rays: int = 4096
    """Rays in the timed chunk."""
    timing_repeats: int = 15
    """Repeats of the timing, each running the fused pass and every sub-model's once in a shuffled order; the
    reported ratio is the median of the per-repeat ratios."""
    seed: int = 0
    """Seed of the timed rays."""
    cost_methods: list[str] = field(default_factory=lambda: ["idw-sample"])
    """Blend methods whose render cost is timed (e.g. --cost-methods idw-sample coverage)."""
    device: str | None = None
    """Torch device the NeRFs render on (default: cuda when torch sees a GPU, else cpu)."""
    output: Path = Path("outputs/bench/blending.json")
    """JSON results (a markdown summary is written beside it)."""


def _markdown(report: dict) -> str:
    lines = [
        f"# Blending benchmark ({report['date']})",
        "",
        f"`{report['command']}` on {report['machine']['platform']}, {report['machine']['cpus']} CPUs, "
        f"torch {report['machine']['torch']}"
        + (f", rendering on {report['machine']['gpu']}" if report["machine"].get("gpu") else "")
        + ".",
        "",
        "PSNR (dB) / SSIM on the world-frame test views; LPIPS "
        + ("included." if report["lpips_available"] else "not available (no local AlexNet weights)."),
        "",
    ]
    for s in report["scenes"]:
        head = f"{s['name']} ({s['layout']}, {s['test_views']} test views, gamma {s['gamma']}, tau {s['tau']})"
        lines += [f"## {head}", ""]
        labels = list(s["quality"])
        if labels:
            lines.append("| method | " + " | ".join(f"{lbl} T" for lbl in labels) + " |")
            lines.append("| --- |" + " --- |" * len(labels))
        for m in s["quality"][labels[0]] if labels else ():
            cells = []
            name = f"{m} (ours)" if m.startswith("coverage") else m
            for lbl in labels:
                q = s["quality"][lbl][m]
                lp = f" / {q['lpips']:.3f}" if report["lpips_available"] else ""
                cells.append(f"{q['psnr']:.2f} / {q['ssim']:.3f}{lp}")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        for lbl in labels:
            q = s["quality"][lbl]
            lines.append("")
            lines.append(
                f"{lbl} T: IDW-Sample - Nearest = {q['idw-sample']['psnr'] - q['nearest']['psnr']:+.2f} dB, "
                f"- IDW-2D = {q['idw-sample']['psnr'] - q['idw-2d']['psnr']:+.2f} dB, "
                f"- IDW-3D = {q['idw-sample']['psnr'] - q['idw-3d']['psnr']:+.2f} dB."
                + (f" Coverage (ours) - IDW-Sample = {q['coverage']['psnr'] - q['idw-sample']['psnr']:+.2f} dB."
                   if "coverage" in q else "")
            )
        sweep = s.get("gamma_sweep") or {}
        if sweep:
            methods = ("nearest", "idw-2d", "idw-3d", "idw-sample")
            lines += [
                "",
                f"Gamma sweep (ground-truth T, tau {s['tau']}), PSNR (dB):",
                "",
                "| gamma | " + " | ".join(methods) + " |",
                "| --- |" + " --- |" * len(methods),
            ]
            for g in sorted(sweep, key=float):
                best = max(sweep[g][m]["psnr"] for m in methods)
                cells = [f"{sweep[g][m]['psnr']:.2f}" for m in methods]
                cells = [f"**{c}**" if sweep[g][m]["psnr"] == best else c for c, m in zip(cells, methods, strict=True)]
                lines.append(f"| {float(g):g} | " + " | ".join(cells) + " |")
        for c in (s.get("costs") or {"": s["cost"]}).values():
            lines += _cost_lines(c)
        lines.append("")
    return "\n".join(lines) + "\n"


def _cost_lines(c: dict) -> list[str]:
    subs = " + ".join(f"{t * 1000:.0f}" for t in c["sub_s"])
    lines = [
        "",
        f"Cost ({c['num_rays']} rays, {c['repeats']} repeats, each running every pass once in a shuffled order): "
        f"median fused {c['method']} {c['fused_s'] * 1000:.0f} ms vs sub-models {subs} ms; median per-repeat "
        f"ratio **{c['ratio']:.3f}**"
        + (" (quartiles {:.3f}-{:.3f})".format(*c["ratio_quartiles"]) if "ratio_quartiles" in c else "")
        + "; peak memory added "
        f"per chunk: fused {c['fused_peak_mib']:.0f} MiB, sub-models "
        + ", ".join(f"{m:.0f}" for m in c["sub_peak_mib"])
        + " MiB.",
    ]
    if "ratio_used" in c:
        used = " + ".join(f"{t * 1000:.0f}" for t in c["sub_used_s"])
        rays = ", ".join(str(r) for r in c["used_rays"])
        lines += [
            "",
            f"The fused model queries each sub-model only on the rays whose distance test it passes ({rays} of "
            f"{c['num_rays']}); against the sub-models on just those rays ({used} ms) the ratio is "
            f"**{c['ratio_used']:.3f}** (quartiles {c['ratio_used_quartiles'][0]:.3f}-"
            f"{c['ratio_used_quartiles'][1]:.3f}): the merge and blend overhead.",
        ]
    return lines


def main(cfg: BenchBlendingConfig) -> None:
    import torch
    from rich.console import Console

    from nerfuser_ns import runs, runtime
    from nerfuser_ns.bench import evaluation
    from nerfuser_ns.bench.evaluation import SceneRuns
    from nerfuser_ns.blending import BLEND_METHODS, COVERAGE_METHODS, PAPER_BLEND_METHODS, PAPER_OBJECT_CENTRIC
    from nerfuser_ns.files import write_text_atomic

    console = Console()
    try:  # before any work
        device = str(runs.check_device(cfg.device or runs.default_device()))
    except runs.RunLoadError as e:
        raise SystemExit(f"bench_blending: {e}") from None
    for method in cfg.cost_methods:
        if method not in BLEND_METHODS:
            raise SystemExit(f"--cost-methods: unknown blend method {method!r}; choose from {', '.join(BLEND_METHODS)}")
    if "coverage" in cfg.cost_methods and not cfg.coverage:
        raise SystemExit("--cost-methods coverage needs the runs' training cameras: drop --no-coverage")
    registrations = {}
    for spec in cfg.registrations:
        name, _, path = spec.partition("=")
        if not name or not path:
            raise SystemExit(f"--registrations: expected NAME=REGISTRATION_JSON, got {spec!r}")
        registrations[name] = Path(path)
    try:
        scenes = [SceneRuns.parse(s) for s in cfg.scenes]
    except evaluation.EvaluationError as e:
        raise SystemExit(f"bench_blending: {e}") from None
    unknown = sorted(set(registrations) - {s.name for s in scenes})
    if unknown:
        raise SystemExit(f"--registrations: no scene named {unknown[0]!r} in --scenes")
    report = {
        "command": "python scripts/bench_blending.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "device": device, "gpu": torch.cuda.get_device_name() if device.startswith("cuda") else None},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "lpips_available": runtime.lpips_weights_available(),
        "scenes": [],
    }
    for scene in scenes:
        layout = scene.ground_truth["layout"]
        gamma, tau = evaluation.PAPER_SETTINGS.get(layout, PAPER_OBJECT_CENTRIC)
        gamma = cfg.gamma if cfg.gamma is not None else gamma
        tau = cfg.tau if cfg.tau is not None else tau
        console.rule(f"{scene.name} ({layout}, gamma {gamma}, tau {tau})")
        pairs = zip(scene.captures, scene.configs, strict=True)
        models = [(n, runs.load_run(p, device=device).model) for n, p in pairs]
        cams, target = scene.test_views(max_views=cfg.max_test_views)
        transforms = {"ground-truth": scene.nerf_to_common()}
        if scene.name in registrations:
            transforms["estimated"] = evaluation.registered_transforms(registrations[scene.name], scene)
        quality = {}
        nerf_cameras = evaluation.training_cameras(scene, models) if cfg.coverage else None
        methods = (*PAPER_BLEND_METHODS, *COVERAGE_METHODS) if cfg.coverage else PAPER_BLEND_METHODS
        for label, T in transforms.items() if cfg.quality else ():
            quality[label] = evaluation.blend_metrics(
                models, T, cams, target, gamma=gamma, tau=tau, methods=methods, nerf_cameras=nerf_cameras,
                description=f"{scene.name}: {label} T",
            )  # fmt: skip
            console.print(label, {m: round(q["psnr"], 2) for m, q in quality[label].items()})
        sweep = {}
        if cfg.gammas:
            result = evaluation.gamma_sweep(models, transforms["ground-truth"], cams, target, cfg.gammas, tau=tau)
            sweep = {str(g): v for g, v in result.items()}
            console.print("gamma sweep", {g: round(v["idw-sample"]["psnr"], 2) for g, v in sweep.items()})
        costs = {}
        for method in cfg.cost_methods:
            cost = evaluation.measure_render_cost(
                models, transforms["ground-truth"], cams, num_rays=cfg.timing_rays, repeats=cfg.timing_repeats,
                method=method, seed=cfg.seed, gamma=gamma, tau=tau, nerf_cameras=nerf_cameras,
            )  # fmt: skip
            costs[method] = cost.as_dict()
            console.print(
                f"cost ({method}): ratio {cost.ratio:.3f} (fused {cost.fused_s:.3f} s, subs {cost.sub_s}); "
                f"against the queried rays only {cost.ratio_used:.3f} (rays {cost.used_rays})"
            )
        report["scenes"].append({
            "name": scene.name, "scene_dir": str(scene.scene_dir), "layout": layout, "gamma": gamma, "tau": tau,
            "test_views": len(cams), "registration": str(registrations.get(scene.name)), "quality": quality,
            "gamma_sweep": sweep, "cost": costs[cfg.cost_methods[0]],
            "costs": costs,
        })  # fmt: skip
        write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
        write_text_atomic(cfg.output.with_suffix(".md"), _markdown(report))
    console.print(f"wrote {cfg.output} and {cfg.output.with_suffix('.md')}")


def entrypoint() -> None:
    main(tyro.cli(BenchBlendingConfig))


if __name__ == "__main__":
    entrypoint()
