"""The main job on the bundled demo scene: scene -> NeRFs -> renders (-> registration -> blending as they land).

1. Generates the object-centric ground-truth demo scene (deterministic, ~40 s) unless it is there already.
2. Loads the two shipped nerfacto-cpu runs (``demo/runs/``) from their own config.yml, or trains them from
   scratch with ``--rebuild`` (~15 minutes on 2 CPU cores).
3. Renders every world-frame test view from each NeRF (mapped into the NeRF's frame with the ground-truth
   SIM(3)) and scores it against the ground-truth image: the paper's single-"NeRF" baseline.
4. Registers the two NeRFs from their re-renderings with ``ns-nerfuser-register`` (their training poses,
   320x240; renders and SfM are cached in ``<output-dir>/registration_work``) and reports its error against the
   ground truth (``--no-register`` skips it).
5. Fuses the two NeRFs (common frame: capture_a's NeRF frame) with the ground-truth and with the estimated
   transforms and renders the test views with every blend method in one pass (NeRF, Nearest, IDW-2D, IDW-3D,
   IDW-Sample), scored the same way.

Outputs go to ``--output-dir``: PNG renders and ``summary.json``.

Example:
    python scripts/demo.py            # or: make demo (sets up the environment first)
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

from nerfuser_ns.files import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class DemoConfig:
    """Run nerfuser_ns's main job on the bundled two-NeRF demo scene."""

    scene_dir: Path = ROOT / "demo/scene"
    """The demo scene (generated here if missing)."""
    runs_dir: Path = ROOT / "demo/runs"
    """The demo runs (shipped; rebuilt with --rebuild)."""
    output_dir: Path = ROOT / "outputs/demo"
    """Where renders and summary.json go."""
    rebuild: bool = False
    """Train the demo NeRFs from scratch instead of using the shipped ones."""
    max_test_views: int = 12
    """How many world-frame test views to render."""
    register: bool = True
    """Register the NeRFs from their re-renderings (about 5 minutes on 2 CPU cores; cached for re-runs)."""
    registration_poses: int = 24
    """Training poses per NeRF rendered for the registration."""


def run_configs(runs_dir: Path) -> dict[str, Path]:
    return {name: runs_dir / name / "nerfacto-cpu" / "demo" / "config.yml" for name in ("capture_a", "capture_b")}


def main(cfg: DemoConfig) -> None:
    import numpy as np
    import torch
    from PIL import Image
    from rich.console import Console
    from rich.table import Table

    from nerfuser_ns import runs, sim3
    from nerfuser_ns.bench import metrics
    from nerfuser_ns.bench.ground_truth import nerf_to_world_from_captures, score_registration
    from nerfuser_ns.bench.scenes import layout_from_ground_truth

    console = Console()
    start = time.perf_counter()
    configs = run_configs(cfg.runs_dir)
    if cfg.rebuild or not all(p.is_file() for p in configs.values()):
        why = "--rebuild" if cfg.rebuild else f"no shipped runs in {cfg.runs_dir}"
        console.print(f"[bold]training the demo NeRFs from scratch ({why})")
        build = [
            sys.executable,
            str(ROOT / "scripts/build_demo.py"),
            "--scene-dir",
            str(cfg.scene_dir),
            "--runs-dir",
            str(cfg.runs_dir),
            *(["--force"] if cfg.rebuild else []),
        ]
        subprocess.run(build, check=True, cwd=ROOT)
    elif not (cfg.scene_dir / "ground_truth.json").is_file():
        console.print("[bold]generating the demo scene")
        subprocess.run(
            [sys.executable, str(ROOT / "scripts/build_demo.py"), "--scene-dir", str(cfg.scene_dir), "--scene-only"],
            check=True,
            cwd=ROOT,
        )

    gt = json.loads((cfg.scene_dir / "ground_truth.json").read_text())
    layout = layout_from_ground_truth(cfg.scene_dir)
    test = layout.test
    test_dir = cfg.scene_dir / gt["test"]["path"]
    test_meta = json.loads((test_dir / "transforms.json").read_text())
    frames = test_meta["frames"][: cfg.max_test_views]
    c2w_world = np.stack([np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames])
    gt_images = [
        np.asarray(Image.open(test_dir / f["file_path"]).convert("RGB"), dtype=np.float32) / 255 for f in frames
    ]
    intr = test.intrinsics
    target = torch.from_numpy(np.stack(gt_images))

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    summary: dict = {"scene": str(cfg.scene_dir), "nerfs": {}}
    table = Table(title="demo: each NeRF rendering the world-frame test views (ground-truth SIM(3))")
    for col in ("NeRF", "step", "test views", "PSNR (dB)", "SSIM", "render s/view"):
        table.add_column(col)
    captures = {c["name"]: c for c in gt["captures"]}
    for name, config_path in configs.items():
        run = runs.load_run(config_path)
        capture_to_world = np.asarray(captures[name]["capture_to_world"], dtype=np.float64)
        # world -> dataset (capture) frame -> NeRF frame
        world_to_nerf = run.data_to_nerf @ sim3.invert_sim3(capture_to_world)
        c2w_nerf = sim3.transform_poses(world_to_nerf, c2w_world)
        cams = runs.make_cameras(c2w_nerf[:, :3], intr)
        t = time.perf_counter()
        out = runs.render_views(run.model, cams, outputs=("rgb",), description=f"rendering {name}")
        per_view = (time.perf_counter() - t) / len(frames)
        rgb = out["rgb"].clamp(0, 1)
        scores = metrics.image_metrics(rgb, target)
        (cfg.output_dir / name).mkdir(exist_ok=True)
        for i, img in enumerate(rgb):
            Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)).save(
                cfg.output_dir / name / f"test_{i:03d}.png"
            )
        summary["nerfs"][name] = {
            "config": str(config_path),
            "step": run.step,
            **scores,
            "render_seconds_per_view": round(per_view, 3),
        }
        table.add_row(
            name, str(run.step), str(len(frames)), f"{scores['psnr']:.2f}", f"{scores['ssim']:.3f}", f"{per_view:.2f}"
        )
    # 4. register from re-renderings
    ref = "capture_a"
    transforms_sets: dict[str, dict[str, np.ndarray]] = {}
    loaded = {name: runs.load_run(path) for name, path in configs.items()}
    world_to_common = loaded[ref].data_to_nerf @ sim3.invert_sim3(np.asarray(captures[ref]["capture_to_world"]))
    transforms_sets["ground truth"] = {
        name: world_to_common @ np.asarray(captures[name]["capture_to_world"]) @ sim3.invert_sim3(run.data_to_nerf)
        for name, run in loaded.items()
    }
    if cfg.register:
        from nerfuser_ns import registration
        from nerfuser_ns.spec import read_registered_nerfs

        reg_path = cfg.output_dir / "registration.json"
        command = [
            str(Path(sys.executable).parent / "ns-nerfuser-register"),
            "--configs", *[str(p) for p in configs.values()],
            "--output", str(reg_path),
            "--work-dir", str(cfg.output_dir / "registration_work"),
            "--sampling.source", "training",
            "--sampling.max-training-poses", str(cfg.registration_poses),
            "--sampling.width", "320", "--sampling.height", "240", "--sampling.fov-deg", "65",
        ]  # fmt: skip
        console.print("[bold]registering the NeRFs from their re-renderings")
        t = time.perf_counter()
        result = subprocess.run(command, cwd=ROOT)
        if result.returncode != 0:
            raise SystemExit("demo: registration failed (see above); rerun with --no-register to skip it")
        entries = read_registered_nerfs(reg_path)
        # scored against the truth afterwards: the registration never sees it
        truth = nerf_to_world_from_captures([np.asarray(captures[name]["capture_to_world"]) for name in configs],
                                            [loaded[name].data_to_nerf for name in configs])
        record = score_registration(registration.read_registered_nerfs(reg_path), truth)
        transforms_sets["estimated"] = {
            name: entry.nerf_to_common for name, entry in zip(configs, entries, strict=True)
        }
        summary["registration"] = {
            "file": str(reg_path),
            "seconds": round(time.perf_counter() - t, 1),
            "errors": {n["name"]: n.get("ground_truth") for n in record["nerfs"]},
            "timings_s": record.get("timings_s"),
        }

    # 5. blend with every set of transforms
    from nerfuser_ns.blending import PAPER_BLEND_METHODS
    from nerfuser_ns.model import fuse_models

    c2w_common = sim3.transform_poses(world_to_common, c2w_world)
    cams = runs.make_cameras(c2w_common[:, :3], intr)
    methods = PAPER_BLEND_METHODS  # the paper's Table 2 (ours, coverage, is measured by scripts/bench_blending.py)
    keys = tuple(f"rgb_{m.replace('-', '_')}" for m in methods)
    summary["blending"] = {}
    blend_table = Table(title="demo: blending the two NeRFs (PSNR dB / SSIM on the test views)")
    blend_table.add_column("method")
    columns = {}
    for label, transforms in transforms_sets.items():
        nerfs = [(name, run.model, transforms[name]) for name, run in loaded.items()]
        fused = fuse_models(nerfs, render_all_methods=True, share_outputs=False)
        t = time.perf_counter()
        out = runs.render_views(fused, cams, outputs=keys, description=f"rendering the fused scene ({label})")
        per_view = (time.perf_counter() - t) / len(frames)
        entry = {"gamma": fused.config.gamma, "tau": fused.config.tau,
                 "render_seconds_per_view_all_methods": round(per_view, 3), "methods": {}}  # fmt: skip
        for method, key in zip(methods, keys, strict=True):
            rgb = out[key].clamp(0, 1)
            entry["methods"][method] = metrics.image_metrics(rgb, target)
            folder = cfg.output_dir / "fused" / label.replace(" ", "_") / method
            folder.mkdir(parents=True, exist_ok=True)
            for i, img in enumerate(rgb):
                Image.fromarray((img.numpy() * 255 + 0.5).astype(np.uint8)).save(folder / f"test_{i:03d}.png")
        summary["blending"][label] = entry
        blend_table.add_column(f"{label} T (gamma={fused.config.gamma}, tau={fused.config.tau})")
        columns[label] = [f"{entry['methods'][m]['psnr']:.2f} / {entry['methods'][m]['ssim']:.3f}" for m in methods]
    for i, method in enumerate(methods):
        blend_table.add_row(method, *[col[i] for col in columns.values()])

    summary["seconds"] = round(time.perf_counter() - start, 1)
    out_path = cfg.output_dir / "summary.json"
    write_text_atomic(out_path, json.dumps(summary, indent=2) + "\n")
    console.print(table)
    if "registration" in summary:
        for name, err in summary["registration"]["errors"].items():
            if err:
                console.print(
                    f"registration {Path(name).parts[-4] if len(Path(name).parts) > 3 else name}: "
                    f"r_err {err['r_err_deg']:.3f} deg, t_err {err['t_err']:.4f}, s_err {err['s_err']:.4f}"
                    f"{' FAILURE' if err['failure'] else ''}"
                )
    console.print(blend_table)
    console.print(f"renders and summary in {cfg.output_dir} ({summary['seconds']} s)")


def entrypoint() -> None:
    main(tyro.cli(DemoConfig))


if __name__ == "__main__":
    entrypoint()
