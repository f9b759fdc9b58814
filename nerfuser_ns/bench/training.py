"""Train a small nerfacto (the ``nerfacto-cpu`` preset) programmatically, as ``ns-train nerfacto-cpu`` would.

The result is a normal nerfstudio run folder (``config.yml``, ``dataparser_transforms.json``,
``nerfstudio_models/step-*.ckpt``) that every nerfstudio command and :func:`nerfuser_ns.runs.load_run` load.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.base_model import Model
from nerfstudio.scripts.train import _set_random_seed

from nerfuser_ns import runtime
from nerfuser_ns.files import atomic_path, write_text_atomic
from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config


@dataclass
class TrainResult:
    config_path: Path
    """The run's config.yml."""
    model: Model
    """The trained model (eval mode)."""
    step: int
    """Step of the saved checkpoint."""
    final_loss: float
    """Total training loss of the last iteration."""
    train_seconds: float
    """Wall time of the training loop (setup and the one-off torch.compile included)."""
    trainer: object
    """The nerfstudio Trainer (its pipeline holds the eval split)."""


def shrink_to_tiny(config: TrainerConfig) -> TrainerConfig:
    """A far smaller nerfacto for tests: same code paths, seconds per step count."""
    model = config.pipeline.model
    model.log2_hashmap_size = 12
    model.num_levels = 4
    model.max_res = 128
    model.hidden_dim = 16
    model.hidden_dim_color = 16
    model.appearance_embed_dim = 4
    model.num_proposal_samples_per_ray = (16, 8)
    model.num_nerf_samples_per_ray = 8
    model.eval_num_rays_per_chunk = 1024
    for args in model.proposal_net_args_list:
        args.update(log2_hashmap_size=10, num_levels=2, max_res=64, hidden_dim=8)
    config.pipeline.datamanager.train_num_rays_per_batch = 256
    config.pipeline.datamanager.eval_num_rays_per_batch = 256
    return config


def train(
    data: Path,
    output_dir: Path,
    experiment_name: str,
    max_num_iterations: int = 3000,
    seed: int = 42,
    timestamp: str = "run",
    tiny: bool = False,
    config: TrainerConfig | None = None,
) -> TrainResult:
    """Train nerfacto-cpu (or ``config``) on a nerfstudio dataset and save a run under ``output_dir``.

    Args:
        data: the dataset folder (transforms.json + images).
        output_dir: where runs go (``<output_dir>/<experiment_name>/<method>/<timestamp>/``).
        experiment_name: the run's experiment name.
        max_num_iterations: training steps.
        seed: ``--machine.seed``.
        timestamp: the run folder's name.
        tiny: shrink the model further (tests).
        config: a TrainerConfig to use instead of the nerfacto-cpu preset.
    """
    runtime.install()
    data = Path(data)
    if not (data / "transforms.json").is_file():
        raise FileNotFoundError(f"{data}: no transforms.json; pass a nerfstudio dataset folder")
    if max_num_iterations < 1:
        raise ValueError(f"max_num_iterations must be >= 1, got {max_num_iterations}")
    if config is None:
        config = nerfacto_cpu_config(max_num_iterations)
    config.max_num_iterations = max_num_iterations
    if tiny:
        shrink_to_tiny(config)
    config.pipeline.datamanager.data = data
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name
    config.timestamp = timestamp
    config.machine.seed = seed
    config.machine.device_type = "cpu" if not torch.cuda.is_available() else config.machine.device_type
    config.save_config()

    start = time.perf_counter()
    _set_random_seed(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    seconds = time.perf_counter() - start
    step = trainer.step

    # the loss at the final weights: one more (gradient-free) look at a training batch
    trainer.pipeline.train()
    with torch.no_grad():
        _, loss_dict, _ = trainer.pipeline.get_train_loss_dict(step=step)
    final_loss = float(sum(v for v in loss_dict.values()))
    trainer.pipeline.eval()
    return TrainResult(
        config_path=config.get_base_dir() / "config.yml",
        model=trainer.pipeline.model,
        step=step,
        final_loss=final_loss,
        train_seconds=seconds,
        trainer=trainer,
    )


RUN_TIMESTAMP = "demo"
"""Run folder name of :func:`train_captures` (``<runs_dir>/<capture>/nerfacto-cpu/demo``)."""


def capture_train_key(data: Path, max_num_iterations: int, seed: int, tiny: bool) -> str:
    """Hash of what a trained run depends on: the dataset's transforms.json and images, and the training settings."""
    data = Path(data)
    h = hashlib.sha256(json.dumps([max_num_iterations, seed, tiny]).encode())
    h.update((data / "transforms.json").read_bytes())
    for image in sorted((data / "images").glob("*")):
        h.update(image.name.encode())
        h.update(image.read_bytes())
    return h.hexdigest()[:16]


def train_captures(
    scene_dir: Path,
    runs_dir: Path,
    captures: list[str],
    max_num_iterations: int = 2000,
    seed: int = 42,
    tiny: bool = False,
    force: bool = False,
    log=print,  # noqa: ANN001 - any print-like callable
) -> dict:
    """Trains one run per capture of a generated scene into ``<runs_dir>/<capture>/nerfacto-cpu/demo`` and records
    each run (steps, time, held-out PSNR/SSIM, input key) in ``<runs_dir>/train_report.json`` (atomically, after
    every run). A run whose recorded key matches its inputs is kept (``force`` retrains); returns the report."""
    runs_dir = Path(runs_dir)
    out = runs_dir / "train_report.json"
    report: dict = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
    for name in captures:
        data = Path(scene_dir) / name
        key = capture_train_key(data, max_num_iterations, seed, tiny)
        entry = report["runs"].get(name, {})
        config = runs_dir / name / "nerfacto-cpu" / RUN_TIMESTAMP / "config.yml"
        if not force and config.is_file() and "input_key" not in entry and entry.get("steps") == max_num_iterations - 1:
            # runs recorded before keys existed (same script, deterministic scene): adopt them once
            entry.update(input_key=key, input_key_adopted=True)
        if not force and entry.get("input_key") == key and config.is_file():
            log(f"{name}: trained run up to date ({config})")
            continue
        result = train(data=data, output_dir=runs_dir, experiment_name=name, max_num_iterations=max_num_iterations,
                       seed=seed, timestamp=RUN_TIMESTAMP, tiny=tiny)  # fmt: skip
        datamanager = result.trainer.pipeline.datamanager
        num_eval = len(datamanager.eval_dataset) if datamanager.eval_dataset is not None else 0
        metrics = result.trainer.pipeline.get_average_eval_image_metrics() if num_eval else {}
        report["runs"][name] = {
            "config": str(result.config_path),
            "steps": result.step,
            "train_seconds": round(result.train_seconds, 1),
            "eval_psnr": round(float(metrics["psnr"]), 3) if metrics else None,
            "eval_ssim": round(float(metrics["ssim"]), 4) if metrics else None,
            "num_eval_images": num_eval,
            "torch_threads": torch.get_num_threads(),
            "input_key": key,
        }
        log(f"{name}: {report['runs'][name]}")
        for ckpt in (result.config_path.parent / "nerfstudio_models").glob("step-*.ckpt"):
            slim_checkpoint(ckpt)
        write_text_atomic(out, json.dumps(report, indent=2) + "\n")
    return report


def slim_checkpoint(path: Path) -> None:
    """Keeps only what loading and rendering need (no optimizer state); written atomically."""
    state = torch.load(path, map_location="cpu", weights_only=False)
    slim = {"step": state["step"], "pipeline": state["pipeline"]}
    with atomic_path(path) as tmp:
        torch.save(slim, tmp)
