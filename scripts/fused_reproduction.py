"""Does the fused scene under a link reproduce each run's own training images? A cue tried against twin links.

For a practitioner case, both runs are fused (``fuse_models``, one blend method, appearance matching off) once under
the registered link and once under the case's pose truth; each fused scene is rendered at spread training views of
each run (the run's own camera-optimised poses and intrinsics, 1/``factor`` size) and scored by PSNR against the
training image (block-averaged to that size), beside the run's own render. A cue would be a link whose fused scene
reproduces the captured images clearly worse than the other's::

    python scripts/fused_reproduction.py --case room:4=outputs/practitioner_v2/room-4 --method coverage \\
        --output reports/fused_reproduction_room4_coverage.json

A case is ``LAYOUT:SEED=FOLDER[,REGISTRATION]`` as in ``scripts/twin_check_cases.py``.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from PIL import Image

from nerfuser_ns import runs, sim3
from nerfuser_ns.bench.practitioner_cases import (
    capture_ground_truth,
    case_layout,
    case_registration,
    reference_links,
    run_config,
)
from nerfuser_ns.blending import BlendMethod
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.model import fuse_models
from nerfuser_ns.registration import read_registration
from nerfuser_ns.registration.record import training_cameras_of
from nerfuser_ns.renderers import NerfstudioRenderer


@dataclass
class FusedReproduction:
    """The fused scene against each run's training images, under the registered link and the pose truth."""

    case: str
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]``."""
    output: Path
    """JSON of every view's PSNR (fused and the run's own render)."""
    method: BlendMethod = "idw-sample"
    """Blend method of the fused scene."""
    factor: int = 4
    """Render at 1/factor of the training size."""
    views: int = 16
    """Training views per run, spread over its cameras."""


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((a - b) ** 2)))


def block_mean(img: np.ndarray, factor: int, width: int, height: int) -> np.ndarray:
    img = img[: height * factor, : width * factor]
    return img.reshape(height, factor, width, factor, -1).mean(axis=(1, 3))


def main(cfg: FusedReproduction) -> None:
    case, case_dir, path = case_registration(cfg.case)
    reg = read_registration(path)
    layout = case_layout(case)
    names = [c.name for c in layout.captures]
    rend = [NerfstudioRenderer(run_config(case_dir, c), name=n["name"]) for c, n in zip(names, reg["nerfs"],
                                                                                        strict=True)]  # fmt: skip
    all_links = reference_links(reg, capture_ground_truth(layout, case_dir, optimized=False))
    links = {key: all_links[key] for key in ("registered", "pose truth")}
    models = [r._load().model for r in rend]
    chosen = []
    for r in rend:
        n = len(r.training_image_files())
        chosen.append(np.unique(np.linspace(0, n - 1, cfg.views).round().astype(int)).tolist())
    own = [[r.render_training_views([j], cfg.factor)[0].rgb[0] for j in idx]
           for r, idx in zip(rend, chosen, strict=True)]  # fmt: skip
    result: dict = {"case": case, "method": cfg.method, "factor": cfg.factor, "links": {}}
    for label, T in links.items():
        nerfs = [(r.name, m, torch.as_tensor(t, dtype=torch.float32), training_cameras_of(r))
                 for r, m, t in zip(rend, models, T, strict=True)]  # fmt: skip
        fused = fuse_models(nerfs, blend_method=cfg.method, appearance_matching=False)
        rows = []
        for i, r in enumerate(rend):
            cams, poses, files = r.training_cameras(), r.training_poses(), r.training_image_files()
            scale = float(sim3.decompose_sim3(T[i])[2])
            for n, j in enumerate(chosen[i]):
                c2w = T[i] @ poses[j]
                c2w[:3, :3] /= scale
                cam = copy.deepcopy(cams[j : j + 1])
                width, height = int(cam.width[0, 0]) // cfg.factor, int(cam.height[0, 0]) // cfg.factor
                cam.camera_to_worlds = torch.as_tensor(c2w[None, :3, :], dtype=torch.float32)
                cam.rescale_output_resolution(1.0 / cfg.factor)
                cam.width, cam.height = torch.full_like(cam.width, width), torch.full_like(cam.height, height)
                rgb = runs.render_views(fused, cam, outputs=("rgb",), progress=False)["rgb"][0].clamp(0, 1).numpy()
                image = np.asarray(Image.open(files[j]).convert("RGB"), dtype=np.float32) / 255.0
                truth = block_mean(image, cfg.factor, width, height)
                rows.append({"nerf": r.name, "view": j, "fused": psnr(rgb, truth), "own": psnr(own[i][n], truth)})
        delta = np.array([x["fused"] - x["own"] for x in rows])
        fused_psnr = np.array([x["fused"] for x in rows])
        summary = {"median_fused": float(np.median(fused_psnr)), "mean_fused": float(fused_psnr.mean()),
                   "median_delta": float(np.median(delta)), "worst_delta": float(delta.min())}  # fmt: skip
        result["links"][label] = {"summary": summary, "views": rows}
        print(f"{case} {cfg.method} {label}: " + ", ".join(f"{k} {v:+.2f}" for k, v in summary.items()), flush=True)
    write_text_atomic(cfg.output, json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main(tyro.cli(FusedReproduction))
