"""The reference NeRF's colour map to its own training images (appearance matching's last step, ours)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from rich.console import Console

from nerfuser_ns import appearance, runs
from nerfuser_ns.registration import RegistrationConfig
from nerfuser_ns.registration.pipeline import match_reference_colours
from nerfuser_ns.registration.record import NerfResult
from nerfuser_ns.registration.reference_colour import (
    block_average_linear,
    compose_with_reference,
    fit_reference_colour,
    reduction_factor,
    reference_colour,
)
from nerfuser_ns.renderers import RenderBatch

GAINS = np.array([0.7, 0.85, 1.2])


def _gain_srgb(srgb: np.ndarray, gains: np.ndarray) -> np.ndarray:
    lin = appearance.srgb_to_linear(torch.from_numpy(srgb)) * torch.from_numpy(gains)
    return appearance.linear_to_srgb(lin.clamp(0, 1)).numpy()


def _view(k: int, h: int, w: int) -> np.ndarray:
    """A smooth, unclipped test picture (sRGB in [0.05, 0.75])."""
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.3 + 0.2 * np.sin(3 * x + k), 0.4 + 0.2 * np.cos(2 * y + k), 0.25 + 0.2 * x * y], -1)
    return np.clip(base, 0.05, 0.75)


class ImagesRenderer:
    """Training images are its own pictures with linear gains applied, saved as 8-bit PNGs; it renders the pictures
    block-averaged (what a NeRF that learned the scene exactly renders at a reduced size)."""

    def __init__(self, folder, gains, num=6, h=300, w=400, missing=False):
        self.name, self.gains, self.h, self.w, self.missing = "ref", gains, h, w, missing
        self.files = []
        for k in range(num):
            path = folder / f"frame_{k:03d}.png"
            Image.fromarray((_gain_srgb(_view(k, h, w), gains) * 255).round().astype(np.uint8)).save(path)
            self.files.append(path)
        self.rendered: list[int] = []

    def training_image_files(self):
        if self.missing:
            raise runs.RunLoadError("config.yml: its dataset /gone is missing; pass the dataset folder")
        return self.files

    def render_training_views(self, indices, factor):
        self.rendered += list(indices)
        return [RenderBatch(block_average_linear(_view(k, self.h, self.w), factor)[None].astype(np.float32),
                            np.ones((1, self.h // factor, self.w // factor), np.float32)) for k in indices]  # fmt: skip


def test_reduction_factor_and_block_average():
    assert reduction_factor(1920, 1080) == 15 and reduction_factor(100, 50) == 1 and reduction_factor(129, 10) == 2
    # black and white average to half the light, not half the sRGB code
    img = np.zeros((4, 6, 3))
    img[:, ::2] = 1.0
    out = block_average_linear(img, 2)
    assert out.shape == (2, 3, 3)
    np.testing.assert_allclose(appearance.srgb_to_linear(torch.from_numpy(out)).numpy(), 0.5, atol=1e-9)
    odd = block_average_linear(np.full((5, 7, 3), 0.3), 2)  # cropped to a multiple of the factor
    assert odd.shape == (2, 3, 3) and np.allclose(odd, 0.3)


def test_fit_recovers_gains_exactly_and_ignores_transparent_pixels():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.05, 0.8, (2, 20, 30, 3))
    acc = np.ones((2, 20, 30))
    acc[:, :5] = 0.2
    images = [_gain_srgb(r, GAINS) for r in rgb]
    images[0][:5] = 0.99  # where the render is transparent the image shows something else: left out
    colour_map, pixels = fit_reference_colour([(r, a) for r, a in zip(rgb, acc, strict=True)], images)
    assert pixels == 2 * 15 * 30
    np.testing.assert_allclose(np.diag(colour_map[:, :3]), GAINS, rtol=1e-9)
    same, _ = fit_reference_colour([(r, None) for r in rgb], list(rgb))
    np.testing.assert_allclose(same, appearance.IDENTITY, atol=1e-12)
    with pytest.raises(ValueError, match="differ in size"):
        fit_reference_colour([(rgb[0], None)], [rgb[0][:10]])


def test_reference_colour_from_training_images(tmp_path):
    renderer = ImagesRenderer(tmp_path, GAINS, num=6)
    rc = reference_colour(renderer, 4)
    assert rc.views == 4 and renderer.rendered == [0, 2, 3, 5]  # evenly spread over the six
    assert rc.pixels == 4 * (300 // 4) * (400 // 4)  # 400 px reduced by 4 to <= 128
    np.testing.assert_allclose(np.diag(rc.colour_map[:, :3]), GAINS, rtol=0.01)  # 8-bit images
    assert rc.to_record()["views"] == 4
    off = reference_colour(renderer, 0)
    assert off.colour_map is None and "--colour-views 0" in off.skipped


@pytest.mark.parametrize("renderer_kind, words", [("missing", "is missing"), ("plain", "no training images")])
def test_reference_colour_without_training_images_says_why(tmp_path, renderer_kind, words):
    renderer = ImagesRenderer(tmp_path, GAINS, num=2, missing=True) if renderer_kind == "missing" else object()
    if renderer_kind == "plain":
        renderer = type("Plain", (), {"name": "plain"})()
    rc = reference_colour(renderer, 4)
    assert rc.colour_map is None and words in rc.skipped and rc.to_record() == {"map": None, "skipped": rc.skipped}


def test_composition_with_the_reference_map():
    ref = np.hstack([np.diag(GAINS), np.zeros((3, 1))])
    other = np.hstack([np.diag([0.5, 0.6, 0.7]), np.zeros((3, 1))])
    out = compose_with_reference([appearance.IDENTITY.copy(), other, None], ref)
    np.testing.assert_allclose(out[0], ref)
    np.testing.assert_allclose(np.diag(out[1][:, :3]), GAINS * [0.5, 0.6, 0.7])
    assert out[2] is None
    assert compose_with_reference([other], None)[0] is other
    np.testing.assert_allclose(appearance.compose(appearance.invert(ref), out[1]), other)


def test_match_reference_colours_updates_the_result_in_place(tmp_path):
    other = np.hstack([np.diag([0.5, 0.6, 0.7]), np.zeros((3, 1))])
    nerfs = [NerfResult.__new__(NerfResult) for _ in range(2)]
    nerfs[0].colour_to_reference, nerfs[1].colour_to_reference = appearance.IDENTITY.copy(), other
    result = type("Result", (), {"nerfs": nerfs, "reference": 0, "reference_colour": None})()
    match_reference_colours(result, ImagesRenderer(tmp_path, GAINS, num=4), 4, Console(quiet=True))
    np.testing.assert_allclose(np.diag(nerfs[0].colour_to_reference[:, :3]), GAINS, rtol=0.01)
    np.testing.assert_allclose(np.diag(nerfs[1].colour_to_reference[:, :3]), GAINS * [0.5, 0.6, 0.7], rtol=0.01)
    assert result.reference_colour["views"] == 4
    assert RegistrationConfig().reference_colour  # on by default (applied only with appearance matching on)


def test_sfm_registration_of_renderers_without_images_records_why(oc_record):
    assert oc_record["reference_colour"]["map"] is None
    assert "no training images" in oc_record["reference_colour"]["skipped"]

