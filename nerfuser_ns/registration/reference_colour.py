"""Appearance matching's last step (ours): the reference NeRF's colours mapped to its own training images.

The colour maps of the self-check (:mod:`nerfuser_ns.appearance`) take every NeRF to the colours the reference NeRF
renders. A nerfacto run renders every view it did not train on with the average of its per-image appearance
embeddings, and that average does not reproduce the capture: measured on CPU-trained nerfacto runs of our generated
scenes (``scripts/render_brightness.py --configs``), 2-37% brighter per channel than the run's own training images at
the training cameras, where each image's own embedding gives 0.95-0.98. So the fused scene took a brightness no camera
saw, and the maps of the other NeRFs were shrunk towards the identity by the same factor.

This step renders the reference NeRF at ``colour_views`` of its training cameras, evenly spread, at a small size
(each image block-averaged in linear RGB by the same integer factor, so a render pixel and an image pixel cover the
same patch), and fits the per-channel gains from its renders to its images with the estimator of the cross-render
maps (:func:`nerfuser_ns.appearance.fit_colour_map`: ratio of summed linear colours over the pixels the render shows
opaque and neither clips). Every NeRF's map to the reference is then composed with it, the reference's own map
becomes it: with appearance matching on, the fused scene renders in the reference capture's colours.

Needs the reference run's training images (its dataset); without them, or with renderers that have no training
images, the maps stay as the self-check fitted them and the record says why.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image

from nerfuser_ns import appearance, runs
from nerfuser_ns.registration.self_check import block_mean
from nerfuser_ns.renderers import Renderer

TARGET_SIDE = 128
"""Longer side (pixels) of the reduced views: the fit needs many views, not many pixels per view."""


@dataclass
class ReferenceColour:
    """The reference NeRF's colour map to its training images, or why there is none."""

    colour_map: Float[np.ndarray, "3 4"] | None
    views: int = 0
    pixels: int = 0
    skipped: str | None = None

    def to_record(self) -> dict:
        if self.colour_map is None:
            return {"map": None, "skipped": self.skipped}
        return {"map": np.round(self.colour_map, 12).tolist(), "views": self.views, "pixels": self.pixels}


def reduction_factor(width: int, height: int, target_side: int = TARGET_SIDE) -> int:
    """The integer block size bringing the longer side to at most ``target_side`` (1 for small images)."""
    return max(1, -(-max(int(width), int(height)) // target_side))


def block_average_linear(srgb: Float[np.ndarray, "h w 3"], factor: int) -> Float[np.ndarray, "h2 w2 3"]:
    """An sRGB image (floats in [0, 1]) cropped to a multiple of ``factor`` and averaged over ``factor`` x ``factor``
    blocks in linear RGB (light adds up there), returned sRGB-encoded."""
    lin = appearance.srgb_to_linear(torch.from_numpy(np.asarray(srgb[..., :3], dtype=np.float64))).numpy()
    return appearance.linear_to_srgb(torch.from_numpy(block_mean(lin, factor))).numpy()


def read_image(path: Path) -> Float[np.ndarray, "h w 3"]:
    """A training image as sRGB floats in [0, 1] (alpha dropped: nerfstudio composites it on the background)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0


def fit_reference_colour(
    renders: list[tuple[Float[np.ndarray, "h w 3"], Float[np.ndarray, "h w"] | None]],
    images: list[Float[np.ndarray, "h w 3"]],
) -> tuple[Float[np.ndarray, "3 4"] | None, int]:
    """Gains from the renders' colours to the images' (each pair the same size), over the pixels the render shows
    opaque (:data:`nerfuser_ns.appearance.OPAQUE`; every pixel when it has no accumulation); and the pixel count."""
    src, dst = [], []
    for (rgb, acc), image in zip(renders, images, strict=True):
        if rgb.shape != image.shape:
            raise ValueError(f"render {rgb.shape} and image {image.shape} differ in size")
        opaque = np.ones(rgb.shape[:2], dtype=bool) if acc is None else np.nan_to_num(acc) >= appearance.OPAQUE
        src.append(rgb[opaque].reshape(-1, 3))
        dst.append(image[opaque].reshape(-1, 3))
    src_all = np.concatenate([np.zeros((0, 3))] + src)
    dst_all = np.concatenate([np.zeros((0, 3))] + dst)
    return appearance.fit_colour_map(src_all, dst_all), len(src_all)


def reference_colour(renderer: Renderer, num_views: int) -> ReferenceColour:
    """The reference NeRF's map to its training images from ``num_views`` evenly spread training cameras (see the
    module); a :class:`ReferenceColour` without a map (and the reason) when it cannot be fitted."""
    if num_views <= 0:
        return ReferenceColour(None, skipped="colour maps are off (--colour-views 0)")
    if not (hasattr(renderer, "training_image_files") and hasattr(renderer, "render_training_views")):
        return ReferenceColour(None, skipped=f"{renderer.name}: the renderer has no training images")
    try:
        files = renderer.training_image_files()
    except runs.RunLoadError as e:
        return ReferenceColour(None, skipped=str(e).splitlines()[0])
    if not files:
        return ReferenceColour(None, skipped=f"{renderer.name}: no training images")
    indices = np.unique(np.linspace(0, len(files) - 1, min(num_views, len(files))).round().astype(int)).tolist()
    try:
        full = [read_image(files[i]) for i in indices]
    except OSError as e:
        return ReferenceColour(None, skipped=f"{renderer.name}: cannot read its training images ({e})")
    factor = reduction_factor(max(im.shape[1] for im in full), max(im.shape[0] for im in full))
    images = [block_average_linear(im, factor) for im in full]
    batches = renderer.render_training_views(indices, factor)
    renders = [(b.rgb[0], None if b.accumulation is None else b.accumulation[0]) for b in batches]
    if any(r.shape != im.shape for (r, _), im in zip(renders, images, strict=True)):
        return ReferenceColour(None, skipped=f"{renderer.name}: its training images do not have its cameras' sizes")
    colour_map, pixels = fit_reference_colour(renders, images)
    if colour_map is None:
        return ReferenceColour(None, skipped=f"{renderer.name}: too few opaque, unclipped pixels ({pixels})")
    return ReferenceColour(colour_map, len(indices), pixels)


def compose_with_reference(
    maps: list[Float[np.ndarray, "3 4"] | None], reference_map: Float[np.ndarray, "3 4"] | None
) -> list[Float[np.ndarray, "3 4"] | None]:
    """Each NeRF's map to the reference NeRF followed by the reference NeRF's map to its images (None stays None:
    a NeRF without a map is not matched at all)."""
    if reference_map is None:
        return list(maps)
    return [None if m is None else appearance.compose(reference_map, m) for m in maps]
