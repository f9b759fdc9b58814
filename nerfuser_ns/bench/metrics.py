"""Image metrics as the paper reports them: PSNR, SSIM, and LPIPS when its weights are available locally.

Scores are computed per image and averaged over images (as ``ns-eval`` does). LPIPS goes through
:class:`nerfuser_ns.runtime.LazyLPIPS`, so it is NaN, with one warning, on a machine without the AlexNet weights.
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float, Int
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from nerfuser_ns import runtime


def _channels_first(
    pred: Float[Tensor, "num_images height width 3"], target: Float[Tensor, "num_images height width 3"]
) -> tuple[Float[Tensor, "num_images 3 height width"], Float[Tensor, "num_images 3 height width"]]:
    """Both stacks checked, as float in [0, 1], channels first (torchmetrics' layout)."""
    if pred.shape != target.shape or pred.ndim != 4 or pred.shape[-1] != 3:
        raise ValueError(
            f"expected two [N, H, W, 3] image stacks of one shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
        )
    return pred.float().clamp(0, 1).permute(0, 3, 1, 2), target.float().clamp(0, 1).permute(0, 3, 1, 2)


def _psnr_each(pred: Float[Tensor, "n 3 h w"], target: Float[Tensor, "n 3 h w"]) -> Float[Tensor, " n"]:
    return torch.stack(
        [peak_signal_noise_ratio(p[None], t[None], data_range=1.0) for p, t in zip(pred, target, strict=True)]
    )


def per_image_psnr(
    pred: Float[Tensor, "num_images height width 3"], target: Float[Tensor, "num_images height width 3"]
) -> Float[Tensor, " num_images"]:
    """PSNR (dB) of each image of ``pred`` against ``target`` in [0, 1] (``pred`` clamped to [0, 1] first)."""
    return _psnr_each(*_channels_first(pred, target))


def image_metrics(
    pred: Float[Tensor, "num_images height width 3"],
    target: Float[Tensor, "num_images height width 3"],
    lpips: bool = True,
) -> dict[str, float]:
    """Mean per-image PSNR (dB), SSIM and LPIPS (NaN when unavailable) of ``pred`` against ``target`` in [0, 1]."""
    pred, target = _channels_first(pred, target)
    psnr = _psnr_each(pred, target)
    ssim = torch.stack(
        [
            structural_similarity_index_measure(p[None], t[None], data_range=1.0)
            for p, t in zip(pred, target, strict=True)
        ]
    )
    out = {"psnr": round(float(psnr.mean()), 4), "ssim": round(float(ssim.mean()), 5), "lpips": math.nan}
    if lpips:
        runtime.install()
        if runtime.lpips_weights_available():
            # here, not at the top: LPIPS is optional and its module is reached only when its weights are on disk
            from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

            metric = LearnedPerceptualImagePatchSimilarity(normalize=True)
            out["lpips"] = round(
                float(torch.stack([metric(p[None], t[None]) for p, t in zip(pred, target, strict=True)]).mean()), 5
            )
    return out


def selection_score(errors: Float[Tensor, " num_nerfs *bs"], choice: Int[Tensor, " *bs"]) -> float:
    """How well a per-pixel choice of NeRF picks the better rendering: ``1 - regret / worst regret``.

    ``regret = sum (e_choice - e_best)`` over pixels, ``worst regret = sum (e_worst - e_best)``: 1 always picks the
    lowest-error NeRF, 0 always the highest; for two NeRFs it is the share of pixels picked right, each pixel counted
    by how much the choice matters there (a coin flip scores 0.5). NaN where no choice matters (all errors equal).

    Args:
        errors: per-NeRF error of each pixel (e.g. squared error, averaged over channels).
        choice: the NeRF index a cue picks per pixel.
    """
    if choice.shape != errors.shape[1:]:
        raise ValueError(f"choice {tuple(choice.shape)} does not match errors {tuple(errors.shape)} past the NeRF axis")
    best, worst = errors.min(dim=0).values, errors.max(dim=0).values
    picked = errors.gather(0, choice.unsqueeze(0).long())[0]
    span = float((worst - best).sum())
    return math.nan if span <= 0 else 1.0 - float((picked - best).sum()) / span
