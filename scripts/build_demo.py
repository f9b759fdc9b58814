"""Build the demo scene's two NeRFs (the ones shipped in demo/runs/), from scratch, on the CPU.

1. Generates the object-centric ground-truth scene (deterministic by seed) into ``--scene-dir``.
2. Trains one ``nerfacto-cpu`` run per capture into ``--runs-dir`` (run folders as ``ns-train`` writes them).
3. Evaluates each run on its held-out views (nerfstudio's eval split) and writes ``train_report.json``.
4. Slims the checkpoints to what rendering needs (no optimizer state) so they can ship with the repo.

Example (about 25 minutes on a 2-core CPU):
    python scripts/build_demo.py
The equivalent stock command for one capture is:
    ns-train nerfacto-cpu --data demo/scene/capture_a --output-dir demo/runs --experiment-name capture_a \\
        --timestamp demo --max-num-iterations 2000
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class BuildDemoConfig:
    """Regenerate the demo scene and (re)train its NeRFs on the CPU."""

    scene_dir: Path = Path("demo/scene")
    """Where the generated ground-truth scene goes (not shipped: it regenerates in under a minute)."""
    runs_dir: Path = Path("demo/runs")
    """Where the trained runs go (shipped with the repo)."""
    layout: Literal["object-centric", "street", "drive"] = "object-centric"
    """Scene layout (the demo is object-centric; benchmarks also build street and drive scenes)."""
    num_captures: int = 3
    """Training captures of a street or drive scene."""
    seed: int = 0
    """Scene seed (the layout, textures and cameras)."""
    train_seed: int = 42
    """Training seed (--machine.seed)."""
    max_num_iterations: int = 2000
    """Training steps per NeRF."""
    scene_only: bool = False
    """Only generate the scene (used by the demo when shipped NeRFs exist)."""
    captures: tuple[str, ...] = ()
    """Which captures to train (default: all of the scene's; the report keeps the entries of the others)."""
    force: bool = False
    """Retrain runs whose recorded inputs (dataset, steps, seed) are unchanged (they are kept otherwise)."""
    threads: int = 0
    """torch CPU threads (0: all cores). Use 1 when other jobs share the CPU: oversubscribed OpenMP threads slow
    torch down 5-9x."""


def main(cfg: BuildDemoConfig) -> None:
    from rich.console import Console

    from nerfuser_ns.bench.scenes import benchmark_params, generate_scene

    console = Console()
    t0 = time.perf_counter()
    params = benchmark_params(cfg.layout, cfg.seed)
    if "num_captures" in params:
        params["num_captures"] = cfg.num_captures
    layout = generate_scene(cfg.scene_dir, cfg.layout, supersample=2, **params)
    console.print(f"scene: {cfg.scene_dir} ({time.perf_counter() - t0:.1f} s)")
    if cfg.scene_only:
        return
    import torch

    from nerfuser_ns.bench.training import train_captures
    from nerfuser_ns.files import write_text_atomic

    torch.set_num_threads(cfg.threads or max(1, os.cpu_count() or 1))
    report = train_captures(
        cfg.scene_dir, cfg.runs_dir, list(cfg.captures) or [c.name for c in layout.captures],
        max_num_iterations=cfg.max_num_iterations, seed=cfg.train_seed, force=cfg.force, log=console.print,
    )  # fmt: skip
    report["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__}
    report["command"] = "python scripts/build_demo.py " + " ".join(sys.argv[1:])
    out = cfg.runs_dir / "train_report.json"
    write_text_atomic(out, json.dumps(report, indent=2) + "\n")
    console.print(f"report: {out}")


def entrypoint() -> None:
    main(tyro.cli(BuildDemoConfig))


if __name__ == "__main__":
    entrypoint()
