"""Registration step 3: each NeRF's SIM(3) into the SfM frame, from its cameras known in both frames.

A NeRF's rendered views have known poses in its own frame; those the SfM registered have poses in the SfM frame C
too. :mod:`nerfuser_ns.sim3` recovers ``T_nerf->C`` from these pairs: the paper's estimator (median pairwise scale,
robust L1 average of the per-camera bridges), its element-wise median variant, or Umeyama with LO-RANSAC.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float

from nerfuser_ns import sim3
from nerfuser_ns.registration.config import RegistrationConfig, RegistrationError, suggestion
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.sfm import SfMResult


@dataclass(frozen=True)
class NerfEstimate:
    """One NeRF's estimate and the SfM poses it was fitted to."""

    estimate: sim3.Sim3Estimate
    """``T_nerf->C`` with the estimator's diagnostics (``used``: the cameras that entered it)."""
    G_sfm: Float[np.ndarray, "n 4 4"]
    """Per rendered view: its camera-to-world in the SfM frame (NaN where the SfM did not register it or the view was
    left out)."""


def sfm_poses(views: ViewSet, sfm: SfMResult) -> Float[np.ndarray, "n 4 4"]:
    """The SfM's poses of one NeRF's views, in view order (NaN for views not in the largest model)."""
    G_sfm = np.full((len(views.c2w), 4, 4), np.nan)
    for n, (name, kept) in enumerate(zip(views.image_names, views.kept, strict=True)):
        if kept and name in sfm.c2w:
            G_sfm[n] = sfm.c2w[name]
    return G_sfm


def estimate_transform(views: ViewSet, sfm: SfMResult, config: RegistrationConfig) -> NerfEstimate:
    """``T_nerf->C`` of one NeRF with ``config.estimator``; a failed or degenerate estimate is an error naming it."""
    G_sfm = sfm_poses(views, sfm)
    try:
        if config.estimator == "umeyama-ransac":
            est = sim3.estimate_sim3_umeyama(views.c2w, G_sfm, robust=True, max_error=config.umeyama_max_error,
                                             seed=config.sfm.seed)
        else:
            method = "weiszfeld" if config.estimator == "nerfuser" else "median"
            est = sim3.estimate_sim3_from_poses(views.c2w, G_sfm, method=method)
    except (ValueError, RuntimeError) as e:
        raise RegistrationError(
            f"{views.name}: the SIM(3) estimate failed ({e}); {suggestion(config.sampling.source)}") from None
    if not (np.isfinite(est.T).all() and est.scale > 0):
        raise RegistrationError(
            f"{views.name}: the SIM(3) estimate is NaN or degenerate; {suggestion(config.sampling.source)}")
    return NerfEstimate(est, G_sfm)


def estimate_transforms(
    views: Sequence[ViewSet], sfm: SfMResult, config: RegistrationConfig
) -> list[NerfEstimate]:
    """:func:`estimate_transform` of every NeRF, in order."""
    return [estimate_transform(vs, sfm, config) for vs in views]
