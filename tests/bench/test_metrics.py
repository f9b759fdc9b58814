"""Image metrics against values known in closed form."""

from __future__ import annotations

import math

import pytest
import torch

from nerfuser_ns.bench.metrics import image_metrics, per_image_psnr, selection_score


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
    assert per_image_psnr(pred, target).tolist() == pytest.approx([20.0, 40.0], abs=1e-3)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="expected two"):
        image_metrics(torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 9, 3))
    with pytest.raises(ValueError, match="expected two"):
        per_image_psnr(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))


def test_selection_score():
    errors = torch.tensor([[1.0, 4.0, 2.0, 3.0], [2.0, 0.0, 2.0, 7.0]])  # best: 0, 1, either, 0
    assert selection_score(errors, torch.tensor([0, 1, 0, 0])) == pytest.approx(1.0)
    assert selection_score(errors, torch.tensor([1, 0, 1, 1])) == pytest.approx(0.0)
    # Right on pixel 0 (matters 1) and 3 (matters 4), wrong on pixel 1 (matters 4): 1 - 4 / 9.
    assert selection_score(errors, torch.tensor([0, 0, 1, 0])) == pytest.approx(5 / 9)
    # Three NeRFs: the middle one costs half the span.
    assert selection_score(torch.tensor([[0.0], [1.0], [2.0]]), torch.tensor([1])) == pytest.approx(0.5)
    assert math.isnan(selection_score(torch.ones(2, 3), torch.zeros(3, dtype=torch.long)))
    with pytest.raises(ValueError, match="does not match"):
        selection_score(errors, torch.zeros(3, dtype=torch.long))
