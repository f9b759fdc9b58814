"""Datasets and run folders as nerfstudio's tools leave them, without training: a dataset as ``ns-process-data``
writes it (``applied_transform`` / ``applied_scale``) and a run folder as ``ns-train`` leaves it on a dataset.

Imported as ``dataset_helpers`` (pytest puts this folder on ``sys.path``; the tests are not a package)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml
from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config
from PIL import Image

from nerfuser_ns import sim3

COLMAP_TO_STORED = np.array([[0.0, 1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, -1.0, 0.1]])  # a rotation + shift


def process_data_like_dataset(folder: Path, world_c2w: np.ndarray, applied_scale: float) -> tuple[Path, np.ndarray]:
    """A dataset as ns-process-data writes it: poses of an arbitrary "COLMAP" frame, stored after applied_transform and
    applied_scale, both keys recorded. Returns the folder and the stored-frame -> world SIM(3)."""
    world_to_colmap = sim3.make_sim3(sim3.so3_exp(np.array([0.3, -0.5, 1.1])), np.array([2.0, -1.0, 0.5]), 3.0)
    A = np.eye(4)
    A[:3, :4] = COLMAP_TO_STORED
    colmap_to_stored = np.diag([applied_scale] * 3 + [1.0]) @ A
    world_to_stored = colmap_to_stored @ world_to_colmap
    stored = sim3.transform_poses(world_to_stored, world_c2w)
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, c2w in enumerate(stored):
        image = np.full((6, 8, 3), 30 * i % 256, dtype=np.uint8)
        Image.fromarray(image).save(folder / "images" / f"frame_{i + 1:05d}.png")
        frames.append({"file_path": f"images/frame_{i + 1:05d}.png", "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames,
            "applied_transform": COLMAP_TO_STORED.tolist(), "applied_scale": applied_scale}  # fmt: skip
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder, sim3.invert_sim3(world_to_stored)


def run_on(root: Path, data: Path, name: str = "x") -> Path:
    """A run folder (config.yml + dataparser_transforms.json as ns-train writes them) on ``data``; nothing trained."""
    config = nerfacto_cpu_config(10)
    config.experiment_name, config.timestamp, config.output_dir = name, "run", root
    config.pipeline.datamanager.data = data
    run_dir = root / name / "nerfacto-cpu" / "run"
    run_dir.mkdir(parents=True)
    (run_dir / "config.yml").write_text(yaml.dump(config))
    parser = config.pipeline.datamanager.dataparser
    parser.data = data
    parser.setup().get_dataparser_outputs("train").save_dataparser_transform(run_dir / "dataparser_transforms.json")
    return run_dir / "config.yml"
