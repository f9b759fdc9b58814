"""The main job on the bundled demo scene: scene -> NeRFs -> registration -> blending, scored against ground truth.

1. Generates the object-centric ground-truth demo scene (deterministic, ~40 s) unless it is there already.
2. Loads the two shipped nerfacto-cpu runs (``demo/runs/``) from their own config.yml, or trains them from
   scratch with ``--rebuild`` (~15 minutes on 2 CPU cores).
3. Registers the two NeRFs from their re-renderings with ``ns-nerfuser-register`` (its defaults, with 24 training
   poses per NeRF rendered at the training images' 192x144; renders and SfM are cached in
   ``<output-dir>/registration_work``) and reports its error against the ground truth (``--no-register`` skips it,
   ``--registration FILE`` uses an existing registration file instead).
4. Fuses the two NeRFs (common frame: capture_a's NeRF frame) with the ground-truth and with the estimated
   transforms and renders the world-frame test views with every blend method of the paper in one pass (NeRF, i.e.
   capture_a alone, the paper's single-NeRF baseline; Nearest, IDW-2D, IDW-3D, IDW-Sample), scored against the
   ground-truth images.

Outputs go to ``--output-dir``: PNG renders and ``summary.json``.

Example:
    python scripts/demo.py            # or: make demo (sets up the environment first)
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import tyro
from PIL import Image
from rich.console import Console
from rich.table import Table

from nerfuser_ns import runs, sim3
from nerfuser_ns.bench import metrics
from nerfuser_ns.bench.ground_truth import ground_truth_errors, nerf_to_world_from_captures
from nerfuser_ns.bench.scenes import benchmark_params, generate_scene, layout_from_ground_truth
from nerfuser_ns.blending import PAPER_BLEND_METHODS
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.model import fuse_models
from nerfuser_ns.registration import RegistrationError, read_registration
from nerfuser_ns.scripts import register
from nerfuser_ns.spec import FusionSpecError, NerfEntry, read_registered_nerfs

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = "capture_a"


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
    """Register the NeRFs from their re-renderings (about 1.5 minutes on 2 CPU cores; cached for re-runs)."""
    registration: Path | None = None
    """An existing registration file of the demo runs (capture_a's frame) to blend and score instead of registering."""
    registration_size: int = 192
    """Longer side of the registration renders (192: the scene's training images; our evaluation registers at it)."""
    registration_poses: int = 24
    """Training poses per NeRF rendered for the registration."""
    device: str = field(default_factory=runs.default_device)
    """Torch device the NeRFs render on, for the registration and the blends (default: cuda when torch sees a GPU)."""


def run_configs(runs_dir: Path) -> dict[str, Path]:
    return {name: runs_dir / name / "nerfacto-cpu" / "demo" / "config.yml" for name in ("capture_a", "capture_b")}


def register_command(
    configs: Sequence[Path], output: Path, work_dir: Path, size: int, poses: int, device: str
) -> list[str]:
    """``ns-nerfuser-register`` with its defaults but the render size, pose count and device (and the demo's work
    folder)."""
    return [
        "ns-nerfuser-register",
        "--configs", *[str(p) for p in configs],
        "--output", str(output),
        "--work-dir", str(work_dir),
        "--sampling.size", str(size),
        "--sampling.max-training-poses", str(poses),
        "--device", device,
    ]  # fmt: skip


def estimated_errors(
    registration: Path, entries: Sequence[NerfEntry], names: Sequence[str], truth: Sequence[np.ndarray]
) -> dict[str, dict]:
    """The paper's r/t/s errors of the NeRFs of a registration file of the demo runs (in ``names`` order, the first
    being the reference) against the ground-truth NeRF -> world SIM(3)s: the registration never sees the truth."""
    if len(entries) != len(names):
        raise RegistrationError(f"{registration}: {len(entries)} NeRFs, the demo has {len(names)}")
    T = np.stack([e.nerf_to_common for e in entries])
    if not np.allclose(T[0], np.eye(4), atol=1e-9):
        raise RegistrationError(f"{registration}: not in {names[0]}'s frame (its transform is not the identity)")
    errors = ground_truth_errors(T, truth, reference=0)
    return {name: {k: v for k, v in e.items() if k != "T_to_reference_true"}
            for name, e in zip(names, errors, strict=True)}  # fmt: skip


def main(cfg: DemoConfig) -> None:
    device = runs.check_device(cfg.device)  # before any work
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
        generate_scene(cfg.scene_dir, "object-centric", supersample=2, **benchmark_params("object-centric", 0))

    gt = json.loads((cfg.scene_dir / "ground_truth.json").read_text())
    test = layout_from_ground_truth(cfg.scene_dir).test
    test_dir = cfg.scene_dir / gt["test"]["path"]
    frames = json.loads((test_dir / "transforms.json").read_text())["frames"][: cfg.max_test_views]
    c2w_world = np.stack([np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames])
    target = torch.from_numpy(np.stack([
        np.asarray(Image.open(test_dir / f["file_path"]).convert("RGB"), dtype=np.float32) / 255 for f in frames
    ]))  # fmt: skip

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    captures = {c["name"]: np.asarray(c["capture_to_world"], dtype=np.float64) for c in gt["captures"]}
    loaded = {name: runs.load_run(path, device=device) for name, path in configs.items()}
    summary: dict = {"scene": str(cfg.scene_dir), "nerfs": {n: {"config": str(p), "step": loaded[n].step}
                                                            for n, p in configs.items()}}  # fmt: skip
    # world -> capture_a's dataset frame -> its NeRF frame: the fusion's common frame
    world_to_common = loaded[REFERENCE].data_to_nerf @ sim3.invert_sim3(captures[REFERENCE])
    transforms_sets: dict[str, dict[str, np.ndarray]] = {
        "ground truth": {
            name: world_to_common @ captures[name] @ sim3.invert_sim3(run.data_to_nerf) for name, run in loaded.items()
        }  # fmt: skip
    }

    # 3. register from re-renderings (or take the file given)
    reg_path = cfg.registration
    if reg_path is None and cfg.register:
        reg_path = cfg.output_dir / "registration.json"
        command = register_command(list(configs.values()), reg_path, cfg.output_dir / "registration_work",
                                   cfg.registration_size, cfg.registration_poses, cfg.device)  # fmt: skip
        # in this process (the runs' imports are paid once): the same as running the command printed
        console.print(f"[bold]registering the NeRFs from their re-renderings:[/bold] {' '.join(command)}")
        t = time.perf_counter()
        if register.run(tyro.cli(register.RegisterCommand, args=command[1:])) != 0:
            raise SystemExit("demo: registration failed (see above); rerun with --no-register to skip it")
        summary["registration"] = {"seconds": round(time.perf_counter() - t, 1),
                                   "timings_s": read_registration(reg_path).get("timings_s")}  # fmt: skip
    if reg_path is not None:
        names = list(configs)
        truth = nerf_to_world_from_captures([captures[n] for n in names], [loaded[n].data_to_nerf for n in names])
        entries = read_registered_nerfs(reg_path, check_runs=False)
        errors = estimated_errors(reg_path, entries, names, truth)
        summary.setdefault("registration", {}).update(file=str(reg_path), errors=errors)
        transforms_sets["estimated"] = {name: e.nerf_to_common for name, e in zip(names, entries, strict=True)}

    # 4. blend with every set of transforms
    c2w_common = sim3.transform_poses(world_to_common, c2w_world)
    cams = runs.make_cameras(c2w_common[:, :3], test.intrinsics)
    methods = PAPER_BLEND_METHODS  # the paper's Table 2 (ours, coverage, is measured by scripts/bench_blending.py)
    keys = tuple(f"rgb_{m.replace('-', '_')}" for m in methods)
    summary["blending"] = {}
    blend_table = Table(title=f"demo: blending the two NeRFs (PSNR dB / SSIM on {len(frames)} test views; "
                              f"NeRF: {REFERENCE} alone)")  # fmt: skip
    blend_table.add_column("method")
    columns = {}
    # each run's training cameras (its own frame, whatever the transforms) as the registration recorded them: every
    # method renders (render_all_methods), coverage included, and without them it falls back with a warning
    cameras = {} if reg_path is None else {name: e.training_cameras for name, e in zip(names, entries, strict=True)}
    for label, transforms in transforms_sets.items():
        nerfs = [(name, run.model, transforms[name], cameras.get(name)) for name, run in loaded.items()]
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
    for name, err in summary.get("registration", {}).get("errors", {}).items():
        if name != REFERENCE:
            console.print(
                f"registration of {name} in {REFERENCE}'s frame: r_err {err['r_err_deg']:.3f} deg, "
                f"t_err {err['t_err']:.4f}, s_err {err['s_err']:.4f}{' FAILURE' if err['failure'] else ''}"
            )
    console.print(blend_table)
    console.print(f"renders and summary in {cfg.output_dir} ({summary['seconds']} s)")


def entrypoint() -> None:
    try:
        main(tyro.cli(DemoConfig))
    except (RegistrationError, FusionSpecError, runs.RunLoadError) as e:
        raise SystemExit(f"demo: {e}") from None


if __name__ == "__main__":
    entrypoint()
