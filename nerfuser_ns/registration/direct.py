"""Registration step 4b (ours): direct photometric alignment of each linked NeRF pair, after the bundle adjustment.

The SfM and its bundle adjustment see a NeRF pair only through SIFT keypoints on blurry renders. Direct alignment
uses every textured pixel the two NeRFs both render. For a pair (parent ``p``, child ``c``, transform ``T: c -> p``)
and a view of ``s`` (one of the two) at its pose ``P`` in ``s``'s frame, the other NeRF ``d`` is rendered at the same
view mapped into its frame, with depth, and each of its opaque pixels ``u`` becomes a surface point ``X = c_d + z r(u)``
of ``d``. Moved into ``s``'s frame by the current transform and by a small correction ``E``, the point must show in
``s``'s own render where ``d`` showed it:

    r_u(E) = I_s(pi_P(E X_s)) - (a I_d(u) + b),

``I`` the renders' luma, ``pi_P`` the projection into the view, ``(a, b)`` a gain and bias per view fitted once at
``E = I`` (each NeRF renders its own views brighter than the other does). The correction is one SIM(3) ``D`` in the
parent's frame, about the points' median (``T' = D T``): ``E = D`` for the parent's views and ``E = T^-1 D^-1 T`` for
the child's. Seven unknowns per pair, soft-L1 least squares (scipy), the loss scale the initial residuals' robust
spread (no constant to tune). Because both renders share the camera, an error in ``d``'s depth moves ``X`` along the
ray that projects to ``u``: it enters only through the correction itself, not as a bias.

Pixels: ``d``'s opaque pixels that land on opaque, textured pixels of ``s`` (luma gradient above the view's median),
at most ``max_pixels_per_view`` per view (seeded). The pair's transform is kept only when the fit lowers the robust
cost and moves it less than the caps (a move larger than an SfM error is not trusted). It refines, it does not
search: from a transform turned 9 degrees it moved 0.2 (the checks after it judge such a link).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from jaxtyping import Float
from rich.console import Console
from scipy.optimize import least_squares

from nerfuser_ns import sim3
from nerfuser_ns.appearance import OPAQUE, luma
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import DirectConfig
from nerfuser_ns.registration.known_geometry import bilinear, pixel_index, pixel_rays, project
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.self_check import tree_edges
from nerfuser_ns.renderers import Renderer, gives_depth

NO_CHANGE = {"r_deg": 0.0, "t": 0.0, "s": 0.0}

# ---------------------------------------------------------------------------------------------------------------------
# Pure geometry (the tests check these directly)


def correction(
    params: Float[np.ndarray, " 7"], centre: Float[np.ndarray, " 3"], focal: float, distance: float
) -> Float[np.ndarray, "4 4"]:
    """The SIM(3) ``D(y) = centre + exp(s) R (y - centre) + t`` of the parameters in pixel-like units: rotation
    vector ``params[:3] / focal``, translation ``params[3:6] * distance / focal``, log scale ``params[6] / focal``
    (one unit moves a point at ``distance`` by about one pixel, which conditions the solve)."""
    R = sim3.so3_exp(np.asarray(params[:3], dtype=np.float64) / focal)
    s = float(np.exp(params[6] / focal))
    t = np.asarray(params[3:6], dtype=np.float64) * distance / focal
    centre = np.asarray(centre, dtype=np.float64)
    return sim3.make_sim3(s * R, centre - s * R @ centre + t)


def surface_points(
    c2w: Float[np.ndarray, "4 4"], depth: Float[np.ndarray, "h w"], intrinsics: Intrinsics
) -> tuple[Float[np.ndarray, "h w 3"], Float[np.ndarray, "h w 2"]]:
    """Each pixel centre's surface point ``c + depth * r`` in the frame of ``c2w`` (depth is ray distance) and the
    pixel centre itself."""
    h, w = depth.shape
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = np.stack([xs.ravel(), ys.ravel()], axis=-1)
    rays = pixel_rays(c2w, xy, intrinsics)
    points = np.asarray(c2w, dtype=np.float64)[:3, 3] + depth.reshape(-1, 1).astype(np.float64) * rays
    return points.reshape(h, w, 3), xy.reshape(h, w, 2)


def subsampled(intrinsics: Intrinsics, factor: int) -> Intrinsics:
    """Every ``factor``-th pixel of ``intrinsics``: pixel ``i`` of the result is pixel ``factor * i`` of the full
    image, ray for ray (a plain 1/factor resize would put its pixel centres between the full image's)."""
    k, f = intrinsics, max(1, int(factor))
    return Intrinsics(k.fx / f, k.fy / f, (k.cx - 0.5) / f + 0.5, (k.cy - 0.5) / f + 0.5, max(1, k.width // f),
                      max(1, k.height // f))  # fmt: skip


def gradient_magnitude(image: Float[np.ndarray, "h w"]) -> Float[np.ndarray, "h w"]:
    """Central-difference gradient magnitude (per pixel, edges one-sided)."""
    gy, gx = np.gradient(image.astype(np.float64))
    return np.hypot(gx, gy)


@dataclass
class Samples:
    """One view's pixels of the other NeRF ``d``, in the frame of the NeRF ``s`` whose render they are compared with."""

    c2w: Float[np.ndarray, "4 4"]
    """The view in ``s``'s frame."""
    image: Float[np.ndarray, "h w"]
    """``s``'s own render of it (luma)."""
    points: Float[np.ndarray, "m 3"]
    """``d``'s surface points, mapped into ``s``'s frame by the current transform."""
    values: Float[np.ndarray, " m"]
    """``d``'s luma at those points, mapped by the view's gain and bias onto ``s``'s."""
    parent_side: bool
    """Whether ``s`` is the pair's parent (the correction then applies as it is, else conjugated)."""


def view_samples(
    c2w: Float[np.ndarray, "4 4"], own_rgb: Float[np.ndarray, "h w 3"], own_acc: Float[np.ndarray, "h w"],
    other: Float[np.ndarray, "m 3"], other_rgb: Float[np.ndarray, "m 3"], intrinsics: Intrinsics,
    max_pixels: int, rng: np.random.Generator, parent_side: bool,
) -> Samples | None:
    """The samples of one view: ``other`` are the other NeRF's opaque surface points (already in this NeRF's frame)
    and their colours; kept where they project onto this NeRF's opaque, textured pixels. None below 100 pixels."""
    image = luma(own_rgb)
    xy, _, inside = project(c2w, other, intrinsics)
    rows, cols = pixel_index(xy, image.shape)
    keep = inside & (own_acc[rows, cols] >= OPAQUE)
    grad = gradient_magnitude(image)[rows, cols]
    if keep.sum() < 100:
        return None
    keep &= grad > np.median(grad[keep])
    idx = np.flatnonzero(keep)
    if len(idx) < 100:
        return None
    if len(idx) > max_pixels:
        idx = np.sort(rng.choice(idx, size=max_pixels, replace=False))
    values = luma(other_rgb[idx])
    own = bilinear(image, xy[idx])
    gain, bias = np.linalg.lstsq(np.stack([values, np.ones_like(values)], axis=-1), own, rcond=None)[0]
    return Samples(np.asarray(c2w, np.float64), image, other[idx], gain * values + bias, parent_side)


def residuals(
    D: Float[np.ndarray, "4 4"], T: Float[np.ndarray, "4 4"], samples: Sequence[Samples], intrinsics: Intrinsics
) -> Float[np.ndarray, " m"]:
    """Photometric residuals of every sample under the correction ``D`` of the pair's transform ``T: c -> p`` (in
    the parent's frame; ``T' = D T``)."""
    conj = sim3.compose(sim3.invert_sim3(T), sim3.invert_sim3(D), T)
    out = []
    for s in samples:
        moved = sim3.transform_points(D if s.parent_side else conj, s.points)
        xy, _, _ = project(s.c2w, moved, intrinsics)
        out.append(bilinear(s.image, xy) - s.values)
    return np.concatenate(out) if out else np.zeros(0)


# ---------------------------------------------------------------------------------------------------------------------
# One pair, then every linked pair


@dataclass
class PairAlignment:
    """What the direct alignment did to one NeRF pair."""

    parent: int
    child: int
    used: bool
    reason: str
    """Why it was or was not kept, in words."""
    views: int
    pixels: int
    cost_before: float | None
    cost_after: float | None
    """Mean soft-L1 cost of the residuals (in units of the loss scale) before and after (None: not fitted)."""
    loss_scale: float | None
    change: dict
    """How far the child's transform moved (r_deg, t in the parent's units, s), whether kept or not."""

    def to_record(self) -> dict:
        return asdict(self)


def _pair_samples(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], T: np.ndarray, parent: int, child: int,
    order: dict[tuple[int, int], Sequence[int]], intr: Intrinsics, cfg: DirectConfig, accs: Sequence[np.ndarray],
) -> list[Samples]:
    """Render each NeRF of the pair at ``cfg.views`` of the other's views (mapped by ``T: c -> p``), with depth, at
    1/``cfg.render_factor`` of the size, and build the samples of both directions."""
    rng = np.random.default_rng(cfg.seed)
    small = subsampled(intr, cfg.render_factor)
    out = []
    for s, d in ((parent, child), (child, parent)):
        T_sd = sim3.invert_sim3(T) if s == parent else T
        picked = list(order.get((s, d), np.flatnonzero(views[s].kept)))[: cfg.views]
        if not picked:
            continue
        P = views[s].c2w[picked]
        mapped, T_ds = sim3.transform_poses(T_sd, P), sim3.invert_sim3(T_sd)
        batch = renderers[d].render(mapped, small, depth=True)
        for n, k in enumerate(picked):
            acc = batch.accumulation[n] if batch.accumulation is not None else np.ones(batch.depth[n].shape)
            ok = (acc >= OPAQUE) & (batch.depth[n] > 0)
            pts, _ = surface_points(mapped[n], batch.depth[n], small)
            pts_s = sim3.transform_points(T_ds, pts[ok])
            sample = view_samples(P[n], views[s].load_rgb(k), accs[s][k], pts_s, batch.rgb[n][ok], intr,
                                  cfg.max_pixels_per_view, rng, s == parent)  # fmt: skip
            if sample is not None:
                out.append(sample)
    return out


def align_pair(
    samples: Sequence[Samples], T: Float[np.ndarray, "4 4"], intr: Intrinsics, cfg: DirectConfig, parent: int,
    child: int,
) -> tuple[np.ndarray, PairAlignment]:
    """Fit the correction of one pair's transform ``T: c -> p`` to its samples; returns the transform to use (``T``
    itself unless the fit is kept) and what happened."""
    pixels = int(sum(len(s.values) for s in samples))
    if pixels < cfg.min_pixels:
        return T, PairAlignment(parent, child, False, f"{pixels} pixels (< {cfg.min_pixels})", len(samples), pixels,
                                None, None, None, dict(NO_CHANGE))  # fmt: skip
    # the correction's centre and length unit, in the parent's frame (child-side points mapped there by T)
    in_parent = [(s.points, s.c2w[:3, 3]) if s.parent_side else
                 (sim3.transform_points(T, s.points), sim3.transform_points(T, s.c2w[:3, 3])) for s in samples]
    centre = np.median(np.concatenate([p for p, _ in in_parent]), axis=0)
    distance = float(np.median(np.concatenate([np.linalg.norm(p - c, axis=-1) for p, c in in_parent])))
    focal = float(intr.fx)

    def fun(p):
        return residuals(correction(p, centre, focal, distance), T, samples, intr)

    r0 = fun(np.zeros(7))
    scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-4)
    fit = least_squares(fun, np.zeros(7), loss="soft_l1", f_scale=scale, diff_step=1e-2, max_nfev=cfg.max_evaluations)

    def cost(r):  # scipy's soft-L1, in units of the loss scale
        return float(np.mean(2 * (np.sqrt(1 + (r / scale) ** 2) - 1)))

    before, after = cost(r0), cost(fit.fun)
    T_new = sim3.compose(correction(fit.x, centre, focal, distance), T)
    e = sim3.sim3_errors(T_new, T)
    change = {"r_deg": float(e.r_err_deg), "t": float(e.t_err), "s": float(e.s_err)}
    if not after < before:
        used, reason = False, "the fit did not lower the cost"
    elif (e.r_err_deg > cfg.max_change_deg or e.t_err > cfg.max_change_distance * distance
          or e.s_err > cfg.max_change_log_scale):
        used, reason = False, (f"it moved the transform by {e.r_err_deg:.3f} deg / {e.t_err:.4f} / {e.s_err:.4f} in "
                               f"log scale, beyond the caps")
    else:
        used, reason = True, f"cost {before:.4f} -> {after:.4f}"
    result = PairAlignment(parent, child, used, reason, len(samples), pixels, before, after, scale, change)
    return (T_new if used else T), result


def align_direct(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], T_to_ref: Float[np.ndarray, "k 4 4"],
    pairs: Sequence[tuple[int, int]], ref: int, intr: Intrinsics, cfg: DirectConfig,
    order: dict[tuple[int, int], Sequence[int]], console: Console,
) -> tuple[np.ndarray, dict]:
    """Direct alignment of every pair of the spanning tree ``pairs``, from the reference outwards (each child's
    transform composed with its parent's refined one). Returns the NeRFs' transforms to the reference and the
    summary the record stores (``direct``)."""
    T_to_ref = np.array(T_to_ref, dtype=np.float64)
    accs = [vs.load_accumulation() for vs in views]
    results = []
    for parent, child in tree_edges(pairs, ref):
        T = sim3.relative_sim3(T_to_ref[parent], T_to_ref[child])  # child -> parent
        no_depth = [renderers[i].name for i in (parent, child) if not gives_depth(renderers[i])]
        if no_depth:
            console.print(f"direct alignment {views[parent].name} / {views[child].name}: skipped ({no_depth[0]}'s "
                          "renderer gives no depth)")  # fmt: skip
            results.append(PairAlignment(parent, child, False, f"{no_depth[0]}'s renderer gives no depth", 0, 0,
                                         None, None, None, dict(NO_CHANGE)))  # fmt: skip
            continue
        for _ in range(cfg.iterations):
            with console.status(f"direct alignment: rendering {views[parent].name} / {views[child].name} at each "
                                f"other's views ({cfg.views} per direction, with depth)"):  # fmt: skip
                samples = _pair_samples(renderers, views, T, parent, child, order, intr, cfg, accs)
            T, result = align_pair(samples, T, intr, cfg, parent, child)
            results.append(result)
            c = result.change
            console.print(f"direct alignment {views[parent].name} / {views[child].name}: {result.pixels} pixels in "
                          f"{result.views} views; {'kept' if result.used else 'not kept'} ({result.reason}); change "
                          f"{c['r_deg']:.4f} deg, {c['t']:.5f}, {c['s']:.5f}")  # fmt: skip
            if not result.used:
                break
        T_to_ref[child] = T_to_ref[parent] @ T
    return T_to_ref, {"pairs": [r.to_record() for r in results], "settings": asdict(cfg)}
