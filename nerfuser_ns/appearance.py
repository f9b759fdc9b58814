"""Appearance matching (ours, beyond the paper): one colour map per NeRF, to the reference NeRF's colours.

Captures filmed at different times differ in exposure and white balance; blending two NeRFs of them shows seams.
Both are per-channel gains on LINEAR RGB (the camera's exposure times its white-balance gains). Per NeRF ``i`` a map
``M_i = [A_i | b_i]`` (3x4, the file's general affine form) acts in linear RGB:

    c_ref_lin ≈ A_i c_i_lin + b_i,    c_lin = srgb_to_linear(c)   (nerfstudio NeRFs output sRGB-encoded colours)

and the estimate is the gain model, ``A_i = diag(g_i)``, ``b_i = 0``.

Estimation (registration, :mod:`nerfuser_ns.registration.self_check`): for each checked pair (i, j) and each
direction, NeRF ``j`` is rendered at views of NeRF ``i``'s mapped through the solution (and the other way round);
where both renders are opaque (accumulation >= 0.95) and no channel is clipped, one direction's pixel pairs give
per-channel gains as the ratio of the two renders' summed linear colours, and the pair's gains are the geometric mean
of the two directions' (:func:`fit_colour_map_directions`).

Why ratios of sums: the two renders of a pixel never show exactly the same point (registration error, each NeRF's
blur), and a least-squares fit of one on the other shrinks its slopes towards 0 by that misalignment (errors in
variables; on two stock nerfacto runs of one object with no colour difference it gave gains of 0.52-0.80). Sums over
thousands of pixels average the misalignment out. Why two directions, and many views: each NeRF renders its own
training views brighter than the other NeRF renders them (measured on a validation pair of CPU-trained nerfacto
runs with ground-truth transforms, 24 views each way: 16-27% per channel for one NeRF, 9-20% for the other), so one
direction alone is biased by its NeRF's advantage; the geometric mean cancels the part the two NeRFs share (left:
0-5%). That advantage varies from view to view, so the fit takes ``colour_views`` views per direction evenly spread
over the run's views (the same pair, every evenly spread subset: worst channel 6% off on average and up to 11% with
4 views, 5% and up to 7% with 12). The pairs' maps are chained along the self-check's spanning tree to the reference
(:func:`chain_to_reference`). Last, the reference NeRF's own map to its training images
(:mod:`nerfuser_ns.registration.reference_colour`) is composed onto every map, so the matched scene takes the
reference capture's colours rather than those of nerfacto's average appearance embedding.

Application (:class:`nerfuser_ns.model.NerfuserModel`): every sample colour and background colour of NeRF ``i`` becomes
``linear_to_srgb(clip(A_i srgb_to_linear(c) + b_i, 0, 1))`` before blending; the identity map leaves colours
untouched (exactly: it is skipped).

Pure math: torch for the model's colours (device-clean), numpy/float64 for the estimate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

IDENTITY: Float[np.ndarray, "3 4"] = np.hstack([np.eye(3), np.zeros((3, 1))])
"""The identity colour map."""
OPAQUE = 0.95
"""Accumulation both renders need at a pixel for it to enter the fit."""
CLIPPED = 254.5 / 255.0
"""sRGB values at or above this (in either render) are saturated: their pixel is left out of the fit."""
MIN_PIXELS = 64
"""Fewer pixel pairs than this: no map (None)."""
MAX_GAIN = 16.0
"""Gains beyond ``[1 / MAX_GAIN, MAX_GAIN]`` (4 stops) are no exposure difference but a failed match: no map."""
LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
"""Rec. 601 luma weights."""


def luma(rgb: Float[np.ndarray, "*bs 3"]) -> Float[np.ndarray, "*bs"]:
    """Rec. 601 luma of RGB colours (float32)."""
    return rgb[..., :3].astype(np.float32) @ LUMA


def srgb_to_linear(x: Tensor) -> Tensor:
    """The sRGB transfer function inverted (IEC 61966-2-1), elementwise."""
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.0) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Tensor) -> Tensor:
    """The sRGB transfer function (IEC 61966-2-1), elementwise."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1.0 / 2.4) - 0.055)


def apply_colour_map(rgb: Float[Tensor, "*bs 3"], colour_map: Float[Tensor, "3 4"]) -> Float[Tensor, "*bs 3"]:
    """``linear_to_srgb(clip(A srgb_to_linear(rgb) + b, 0, 1))``."""
    m = colour_map.to(rgb)
    lin = srgb_to_linear(rgb) @ m[:, :3].T + m[:, 3]
    return linear_to_srgb(lin.clamp(0.0, 1.0))


def _channel_sums(
    source: Float[np.ndarray, "n 3"], target: Float[np.ndarray, "n 3"]
) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"], int]:
    """Summed linear colours of the pixels saturated in neither (non-finite ones left out), and their count."""
    src = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    ok = (src < CLIPPED).all(-1) & (dst < CLIPPED).all(-1) & np.isfinite(src).all(-1) & np.isfinite(dst).all(-1)
    s_sum = srgb_to_linear(torch.from_numpy(src[ok])).numpy().sum(0)
    d_sum = srgb_to_linear(torch.from_numpy(dst[ok])).numpy().sum(0)
    return s_sum, d_sum, int(ok.sum())


def fit_colour_map_directions(
    directions: Sequence[tuple[Float[np.ndarray, "n 3"], Float[np.ndarray, "n 3"]]], min_pixels: int = MIN_PIXELS
) -> Float[np.ndarray, "3 4"] | None:
    """The per-channel linear-RGB gains taking ``source`` sRGB colours to ``target`` ones, as a 3x4 map
    ``[diag(g) | 0]``, from one or more directions of a cross-render, each a ``(source, target)`` pair of colours at
    the same pixels: per direction ``g_c = sum(target_lin_c) / sum(source_lin_c)`` over the pixels saturated in
    neither, then the geometric mean over the directions with at least ``min_pixels`` such pixels. None when no
    direction has them or a gain is not plausible (:data:`MAX_GAIN`)."""
    logs = []
    for source, target in directions:
        s_sum, d_sum, n = _channel_sums(source, target)
        if n < min_pixels:
            continue
        if not ((s_sum > 0).all() and (d_sum > 0).all()):
            return None
        logs.append(np.log(d_sum / s_sum))
    if not logs:
        return None
    gains = np.exp(np.mean(logs, axis=0))
    if not (np.isfinite(gains).all() and (gains >= 1 / MAX_GAIN).all() and (gains <= MAX_GAIN).all()):
        return None
    return np.hstack([np.diag(gains), np.zeros((3, 1))])


def fit_colour_map(
    source: Float[np.ndarray, "n 3"], target: Float[np.ndarray, "n 3"], min_pixels: int = MIN_PIXELS
) -> Float[np.ndarray, "3 4"] | None:
    """:func:`fit_colour_map_directions` of one direction."""
    return fit_colour_map_directions([(source, target)], min_pixels)


def compose(outer: Float[np.ndarray, "3 4"], inner: Float[np.ndarray, "3 4"]) -> Float[np.ndarray, "3 4"]:
    """The map ``outer(inner(c))`` (both affine in linear RGB; the clip in between is dropped)."""
    A = outer[:, :3] @ inner[:, :3]
    return np.hstack([A, (outer[:, :3] @ inner[:, 3] + outer[:, 3])[:, None]])


def invert(colour_map: Float[np.ndarray, "3 4"]) -> Float[np.ndarray, "3 4"]:
    """The map undoing ``colour_map`` (its linear part must be invertible)."""
    A_inv = np.linalg.inv(colour_map[:, :3])
    return np.hstack([A_inv, (-A_inv @ colour_map[:, 3])[:, None]])


def chain_to_reference(
    num_nerfs: int, reference: int, pair_maps: Mapping[tuple[int, int], Float[np.ndarray, "3 4"] | None]
) -> list[Float[np.ndarray, "3 4"] | None]:
    """Per NeRF its map to the reference's colours, composed along the pairs: ``pair_maps[(a, b)]`` maps b's colours
    to a's. The reference gets the identity; a NeRF no chain of known maps reaches gets None."""
    out: list[np.ndarray | None] = [None] * num_nerfs
    out[reference] = IDENTITY.copy()
    frontier = [reference]
    while frontier:
        a = frontier.pop(0)
        for (x, y), m in pair_maps.items():
            if x == a and m is not None and out[y] is None:
                out[y] = compose(out[a], m)  # type: ignore[arg-type]
                frontier.append(y)
    return out
