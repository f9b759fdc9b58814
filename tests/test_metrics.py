"""Image metrics against values known in closed form."""

from __future__ import annotations

import math

import pytest
import torch

from nerfuser_ns.metrics import image_metrics


def test_psnr_of_known_error_and_identity():
    target = torch.full((2, 16, 16, 3), 0.5)
    pred = target + 0.1  # MSE 0.01 -> 20 dB
    scores = image_metrics(pred, target, lpips=False)
    assert scores["psnr"] == pytest.approx(20.0, abs=1e-3)
    same = image_metrics(target.clone(), target, lpips=False)
    assert same["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert math.isnan(same["lpips"])


def test_psnr_is_mean_over_images():
    target = torch.zeros(2, 8, 8, 3)
    pred = torch.stack([torch.full((8, 8, 3), 0.1), torch.full((8, 8, 3), 0.01)])  # 20 dB and 40 dB
    assert image_metrics(pred, target, lpips=False)["psnr"] == pytest.approx(30.0, abs=1e-3)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="expected two"):
        image_metrics(torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 9, 3))
