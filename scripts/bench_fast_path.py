"""Measure the CPU fast path (compiled hash encoding) against stock nerfacto, in one run.

Rendering (no-grad forward, rays/s) and training (forward + backward of a 1024-ray batch, steps/s) of the
``nerfacto-cpu`` model, each with the fast path off and on, after a warm-up that pays the one-off compile. Also
checks both paths agree. Writes a JSON report.

Example:
    python scripts/bench_fast_path.py --output outputs/bench_fast_path.json
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from nerfuser_ns.files import write_text_atomic


@dataclass
class BenchFastPathConfig:
    """Time nerfacto-cpu rendering and training steps with and without the compiled CPU hash encoding."""

    output: Path = Path("outputs/bench_fast_path.json")
    """Where to write the JSON report."""
    render_rays: int = 16384
    """Rays per timed render pass."""
    train_rays: int = 1024
    """Rays per timed training step."""
    repeats: int = 3
    """Timed repetitions per measurement (the median is reported)."""
    seed: int = 0
    """Seed for the model initialisation and the rays."""
    model: Literal["nerfacto-cpu", "nerfacto"] = "nerfacto-cpu"
    """Model sizes: our CPU preset, or stock nerfacto's defaults (2^19-entry, 16-level hash grid; torch backend)."""


def _rays(n: int, seed: int):
    import torch
    from nerfstudio.cameras.rays import RayBundle

    g = torch.Generator().manual_seed(seed)
    origins = (torch.rand(n, 3, generator=g) - 0.5) * 0.4 + torch.tensor([0.0, 0.0, 0.8])
    targets = (torch.rand(n, 3, generator=g) - 0.5) * 0.6
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    return RayBundle(
        origins=origins,
        directions=directions,
        pixel_area=torch.full((n, 1), 1e-5),
        camera_indices=torch.zeros(n, 1, dtype=torch.long),
    )


def main(cfg: BenchFastPathConfig) -> None:
    import statistics

    import torch
    from nerfstudio.data.scene_box import SceneBox
    from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config
    from rich.console import Console

    from nerfuser_ns import runtime

    console = Console()
    runtime.install()
    torch.manual_seed(cfg.seed)
    if cfg.model == "nerfacto":
        from nerfstudio.configs.method_configs import all_methods

        model_cfg = all_methods["nerfacto"].pipeline.model
        model_cfg.implementation = "torch"
    else:
        model_cfg = nerfacto_cpu_config().pipeline.model
    model = model_cfg.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=8)
    render_bundle = _rays(cfg.render_rays, cfg.seed)
    target = torch.rand(cfg.train_rays, 3, generator=torch.Generator().manual_seed(cfg.seed))

    def render_once() -> torch.Tensor:
        model.eval()
        with torch.no_grad():
            return model(render_bundle)["rgb"]

    def train_once() -> float:
        model.train()
        model.zero_grad(set_to_none=True)
        # a fresh bundle each step: nerfacto's camera optimizer edits the bundle in place during training
        loss = ((model(_rays(cfg.train_rays, cfg.seed + 1))["rgb"] - target) ** 2).mean()
        loss.backward()
        return float(loss)

    def timed(fn) -> float:
        times = []
        for _ in range(cfg.repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return statistics.median(times)

    results: dict = {}
    outputs = {}
    for name, enabled in (("stock", False), ("fast", True)):
        runtime.set_fast_path(enabled)
        t = time.perf_counter()
        outputs[name] = render_once()  # warm-up: the fast path compiles here
        train_once()
        warmup = time.perf_counter() - t
        render_s = timed(render_once)
        train_s = timed(train_once)
        results[name] = {
            "warmup_seconds": round(warmup, 2),
            "render_rays_per_second": round(cfg.render_rays / render_s, 1),
            "train_step_seconds": round(train_s, 4),
            "train_rays_per_second": round(cfg.train_rays / train_s, 1),
        }
        console.print(f"{name}: {results[name]}")
    max_diff = float((outputs["fast"] - outputs["stock"]).abs().max())
    report = {
        "command": f"python scripts/bench_fast_path.py --model {cfg.model} --render-rays {cfg.render_rays}",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
        "model": f"{cfg.model} (random init)",
        "settings": {"render_rays": cfg.render_rays, "train_rays": cfg.train_rays, "repeats": cfg.repeats},
        "results": results,
        "render_speedup": round(
            results["fast"]["render_rays_per_second"] / results["stock"]["render_rays_per_second"], 2
        ),
        "train_speedup": round(results["stock"]["train_step_seconds"] / results["fast"]["train_step_seconds"], 2),
        "max_abs_rgb_difference": max_diff,
    }
    console.print(
        f"render speedup x{report['render_speedup']}, train-step speedup x{report['train_speedup']}, "
        f"max |rgb difference| {max_diff:.2e}"
    )
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    runtime.set_fast_path(None)


def entrypoint() -> None:
    main(tyro.cli(BenchFastPathConfig))


if __name__ == "__main__":
    entrypoint()
