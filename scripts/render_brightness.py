"""How bright each NeRF renders its own training views against its training images (a diagnostic of appearance
matching).

Reads a registration's work folder: every render folder with training-pose views (``--sampling.source training`` or
``both``) is paired, view by view, with the run's training image at the nearest training camera (the renders are at
the poses the camera optimiser left, which differ from the dataset's by a fraction of a degree). Per colour channel,
the gain from the renders to the images by the estimator of the registration's reference colour
(:func:`nerfuser_ns.registration.reference_colour.fit_reference_colour`: ratio of the summed linear colours over the
pixels the render shows opaque and neither image clips), printed as render / image (its inverse). 1 means the NeRF
renders its views as bright as it was shown them.

With ``--configs``, runs are rendered here instead, at every n-th training camera, twice: with the average of the
per-image appearance embeddings (what nerfstudio and the fused model use for any view that is not a training image)
and with each image's own embedding.

Example:
    python scripts/render_brightness.py outputs/bench/appearance_bracket/jittered_registration_work
    python scripts/render_brightness.py --registrations outputs/practitioner/drive-9/registration.json
    python scripts/render_brightness.py --configs demo/runs/capture_a/nerfacto-cpu/demo/config.yml
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import tyro
from PIL import Image

from nerfuser_ns import runs
from nerfuser_ns.registration import render_folders
from nerfuser_ns.registration.reference_colour import fit_reference_colour, read_image
from nerfuser_ns.registration.render_cache import POSES_FILE, ViewSet

MAX_POSE_DIFFERENCE = 0.05
"""Largest element-wise difference of a render's camera from the nearest training camera (NeRF units)."""


@dataclass
class RenderBrightness:
    """Per run, linear-RGB ratio of its renders at its training poses to its training images."""

    work_dirs: tyro.conf.Positional[list[Path]] = field(default_factory=list)
    """Work folders of ns-nerfuser-register (holding renders/<key>/poses.json) whose renders name their run by its
    config.yml (older registrations); for newer ones, which name runs by experiment/method/timestamp, pass the
    registration file with --registrations."""
    registrations: list[Path] = field(default_factory=list)
    """Registration files (registration.json): each NeRF's render folder, read with the run the file names."""
    configs: list[Path] = field(default_factory=list)
    """Runs to render at their training cameras, with the average and with each image's own appearance embedding."""
    views: int = 12
    """--configs: training cameras rendered per run (evenly spaced)."""


def brightness(folder: Path, config: Path | None = None) -> tuple[str, int, np.ndarray]:
    """The run of one render folder, the views compared, and the per-channel ratio render / training image
    (``config``: the run's config.yml; default: the run the folder records)."""
    rendered = ViewSet.from_folder(folder)
    views = runs.training_views(config if config is not None else rendered.name)
    cameras = views.cameras.camera_to_worlds.cpu().numpy()
    accumulation = rendered.load_accumulation()
    renders, images = [], []
    for k, source in enumerate(rendered.sources):
        if source != "training":
            continue
        c2w = rendered.c2w[k, :3]
        nearest = int(np.argmin(np.abs(cameras - c2w[None]).sum(axis=(1, 2))))
        if np.abs(cameras[nearest] - c2w).max() > MAX_POSE_DIFFERENCE:
            continue
        render, image = rendered.load_rgb(k).astype(np.float64), read_image(views.image_filenames[nearest])
        acc = accumulation[k]
        if render.shape != image.shape:
            (h, w), (ih, iw) = render.shape[:2], image.shape[:2]
            if abs(w / h - iw / ih) > 0.01 * iw / ih:
                continue
            # The render camera is the training camera at another size (same field of view): compare at the image's.
            render = np.stack([_resize(render[..., c], iw, ih) for c in range(3)], axis=-1)
            acc = _resize(acc, iw, ih)
        renders.append((render, acc))
        images.append(image)
    return rendered.name, len(renders), _render_over_image(renders, images)


def _resize(channel: np.ndarray, width: int, height: int) -> np.ndarray:
    """One float channel resampled to width x height (bilinear)."""
    return np.asarray(Image.fromarray(channel.astype(np.float32)).resize((width, height), Image.Resampling.BILINEAR),
                      dtype=np.float64)  # fmt: skip


def _render_over_image(renders: list, images: list) -> np.ndarray:
    """Per channel render / image (NaN when too few pixels to fit)."""
    colour_map, _ = fit_reference_colour(renders, images)
    return np.full(3, np.nan) if colour_map is None else 1.0 / np.diag(colour_map[:, :3])


def embedding_brightness(config: Path, num_views: int) -> dict[str, np.ndarray]:
    """Per channel render / training image at evenly spaced training cameras, with the average appearance embedding
    (nerfstudio's for novel views) and with each image's own (the field in training mode, the rest in eval)."""
    model = runs.load_run(config).model.eval()
    views = runs.training_views(config)
    out = {}
    for label in ("average embedding", "own embedding"):
        renders, images = [], []
        for i in np.linspace(0, len(views.cameras) - 1, num_views).round().astype(int):
            bundle = views.cameras.generate_rays(camera_indices=int(i), keep_shape=True).to(model.device)
            model.field.train(label == "own embedding")  # nerfacto's field picks the image's embedding when training
            try:
                with torch.no_grad():
                    outputs = model.get_outputs_for_camera_ray_bundle(bundle)
            finally:
                model.field.eval()
            renders.append((outputs["rgb"].clamp(0, 1).double().cpu().numpy(),
                            outputs["accumulation"][..., 0].cpu().numpy()))  # fmt: skip
            images.append(read_image(views.image_filenames[i]))
        out[label] = _render_over_image(renders, images)
    return out


def main(cfg: RenderBrightness) -> None:
    for config in cfg.configs:
        ratios = embedding_brightness(config, cfg.views)
        print(f"{config}: render / training image per channel, "
              + ", ".join(f"{k} {np.round(v, 3).tolist()}" for k, v in ratios.items()))
    folders = [(folder, None) for work in cfg.work_dirs for folder in sorted((work / "renders").glob("*/"))
               if (folder / POSES_FILE).is_file()]  # fmt: skip
    for path in cfg.registrations:
        folders += [(f.folder, f.config) for f in render_folders(path) if f.folder is not None]
    seen = set()
    for folder, config in folders:
        try:
            run, count, ratio = brightness(folder, config)
        except runs.RunLoadError as e:
            raise SystemExit(f"{folder}: its run cannot be loaded ({e}); pass the registration file with "
                             f"--registrations") from None  # fmt: skip
        if count == 0 or (run, tuple(np.round(ratio, 3))) in seen:
            continue
        seen.add((run, tuple(np.round(ratio, 3))))
        print(f"{run}: {count} views, render / training image per channel {np.round(ratio, 3).tolist()}")


if __name__ == "__main__":
    main(tyro.cli(RenderBrightness))
