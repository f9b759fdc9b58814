"""How bright each NeRF renders its own training views against its training images (a diagnostic of appearance
matching).

Reads a registration's work folder: every render folder with training-pose views (``--sampling.source training`` or
``both``) is paired, view by view, with the run's training image at the nearest training camera (the renders are at
the poses the camera optimiser left, which differ from the dataset's by a fraction of a degree). Per colour channel,
the ratio of the summed linear colours over the pixels where the render is opaque (accumulation >= 0.95) and neither
image is clipped. 1 means the NeRF renders its views as bright as it was shown them.

With ``--configs``, runs are rendered here instead, at every n-th training camera, twice: with the average of the
per-image appearance embeddings (what nerfstudio and the fused model use for any view that is not a training image)
and with each image's own embedding.

Example:
    python scripts/render_brightness.py outputs/bench/appearance_bracket/jittered_registration_work
    python scripts/render_brightness.py --configs demo/runs/capture_a/nerfacto-cpu/demo/config.yml
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import tyro
from PIL import Image

from nerfuser_ns import runs
from nerfuser_ns.appearance import srgb_to_linear

MIN_ACCUMULATION = 0.95
MAX_POSE_DIFFERENCE = 0.05
"""Largest element-wise difference of a render's camera from the nearest training camera (NeRF units)."""


@dataclass
class RenderBrightness:
    """Per run, linear-RGB ratio of its renders at its training poses to its training images."""

    work_dirs: tyro.conf.Positional[list[Path]] = field(default_factory=list)
    """Work folders of ns-nerfuser-register (holding renders/<key>/poses.json)."""
    configs: list[Path] = field(default_factory=list)
    """Runs to render at their training cameras, with the average and with each image's own appearance embedding."""
    views: int = 12
    """--configs: training cameras rendered per run (evenly spaced)."""


def _linear(path: Path) -> np.ndarray:
    srgb = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)
    return srgb_to_linear(srgb).numpy()


def brightness(folder: Path) -> tuple[str, int, np.ndarray]:
    """The run of one render folder, the views compared, and the per-channel ratio render / training image."""
    meta = json.loads((folder / "poses.json").read_text())
    views = runs.training_views(meta["renderer"])
    cameras = views.cameras.camera_to_worlds.numpy()
    accumulation = np.load(folder / "accumulation.npz")
    accumulation = accumulation[accumulation.files[0]]
    rendered, shown, count = np.zeros(3), np.zeros(3), 0
    for k, view in enumerate(meta["views"]):
        if view["source"] != "training":
            continue
        c2w = np.asarray(view["c2w"])[:3]
        nearest = int(np.argmin(np.abs(cameras - c2w[None]).sum(axis=(1, 2))))
        if np.abs(cameras[nearest] - c2w).max() > MAX_POSE_DIFFERENCE:
            continue
        render, image = _linear(folder / view["file"]), _linear(views.image_filenames[nearest])
        if render.shape != image.shape:
            continue
        r, s = _ratio(render, image, accumulation[k])
        rendered, shown, count = rendered + r, shown + s, count + 1
    return meta["renderer"], count, rendered / np.maximum(shown, 1e-12)


def _ratio(render: np.ndarray, image: np.ndarray, accumulation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mask = (accumulation >= MIN_ACCUMULATION) & (render.max(-1) < 0.99) & (image.max(-1) < 0.99)
    return render[mask].sum(0), image[mask].sum(0)


def embedding_brightness(config: Path, num_views: int) -> dict[str, np.ndarray]:
    """Per channel render / training image at evenly spaced training cameras, with the average appearance embedding
    (nerfstudio's for novel views) and with each image's own (the field in training mode, the rest in eval)."""
    model = runs.load_run(config).model.eval()
    views = runs.training_views(config)
    out = {}
    for label in ("average embedding", "own embedding"):
        rendered, shown = np.zeros(3), np.zeros(3)
        for i in np.linspace(0, len(views.cameras) - 1, num_views).round().astype(int):
            bundle = views.cameras.generate_rays(camera_indices=int(i), keep_shape=True).to(model.device)
            model.field.train(label == "own embedding")  # nerfacto's field picks the image's embedding when training
            try:
                with torch.no_grad():
                    outputs = model.get_outputs_for_camera_ray_bundle(bundle)
            finally:
                model.field.eval()
            render = srgb_to_linear(outputs["rgb"].clamp(0, 1)).cpu().numpy()
            r, s = _ratio(render, _linear(views.image_filenames[i]), outputs["accumulation"][..., 0].cpu().numpy())
            rendered, shown = rendered + r, shown + s
        out[label] = rendered / np.maximum(shown, 1e-12)
    return out


def main(cfg: RenderBrightness) -> None:
    for config in cfg.configs:
        ratios = embedding_brightness(config, cfg.views)
        print(f"{config}: render / training image per channel, "
              + ", ".join(f"{k} {np.round(v, 3).tolist()}" for k, v in ratios.items()))
    seen = set()
    for work in cfg.work_dirs:
        for folder in sorted((work / "renders").glob("*/")):
            if not (folder / "poses.json").is_file():
                continue
            run, count, ratio = brightness(folder)
            if count == 0 or (run, tuple(np.round(ratio, 3))) in seen:
                continue
            seen.add((run, tuple(np.round(ratio, 3))))
            print(f"{run}: {count} views, render / training image per channel {np.round(ratio, 3).tolist()}")


if __name__ == "__main__":
    main(tyro.cli(RenderBrightness))
