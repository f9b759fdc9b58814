"""Registration step 5: check the solution by cross-rendering (SfM can merge unrelated content into one confident,
wrong model).

For a spanning tree of NeRF pairs (i, j) chosen by their SfM overlap: views of i are mapped through the solution
into j's frame, rendered by j, and compared with i's own renders by normalised cross-correlation (and back), and, where
both give depth, j's depth there with i's own (:func:`depth_log_ratio`: a link wrong in scale, which the NCC barely
sees, puts j's surfaces nearer or farther than i's). The depth is compared at i's views nearest j's views under the
solution (:func:`depth_views`: among training views where the renders hold any), not at the views sharing the most SfM
points that the NCC uses: those are the content the link was fitted to, where a link wrong elsewhere still agrees.
Before it, and before the direct alignment's renders, each NeRF's SfM cameras are checked against its transform
(:func:`camera_failure`), and the SfM's other models that link the same NeRFs against the registration's link
(:func:`model_disagreements`; a disagreement refuses the registration unless the other model's link cross-renders
clearly worse, :func:`model_contest`); the cameras again against the final transform.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from jaxtyping import Float

from nerfuser_ns import appearance, sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import RegistrationConfig, RegistrationError, suggestion
from nerfuser_ns.registration.estimate import NerfEstimate, estimate_transform
from nerfuser_ns.registration.render_cache import ViewSet, to_uint8
from nerfuser_ns.registration.sfm import SfMResult, other_models
from nerfuser_ns.renderers import Renderer, gives_depth

COLOUR_REDUCE = 2
"""The colour fit renders its views at 1/COLOUR_REDUCE of the size: its sums need views, not pixels (measured on the
validation pair: the same gains within 0.3% from every pixel, every 2nd or every 4th)."""


def _gray_block_mean(rgb: np.ndarray, factor: int) -> np.ndarray:
    """Luma (Rec. 601) of an RGB(A) image, or a grey image as it is, averaged over ``factor`` blocks."""
    gray = appearance.luma(rgb) if rgb.ndim == 3 else rgb
    return block_mean(gray, factor)


def block_mean(x: np.ndarray, factor: int) -> np.ndarray:
    """``x`` (``[h, w, ...]``) cropped to a multiple of ``factor`` and averaged over ``factor`` x ``factor`` blocks, in
    float64 (trailing axes, e.g. colour channels, kept)."""
    if factor <= 1:
        return x.astype(np.float64)
    h, w = (x.shape[0] // factor) * factor, (x.shape[1] // factor) * factor
    blocks = x[:h, :w].reshape(h // factor, factor, w // factor, factor, *x.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64)


def ncc(
    a: Float[np.ndarray, "h w 3"],
    b: Float[np.ndarray, "h w 3"],
    mask: np.ndarray | None = None,
    downsample: int = 1,
    min_fraction: float = 0.1,
) -> float:
    """Normalised cross-correlation of two images in grayscale over ``mask`` (after block-averaging).

    NaN when fewer than ``min_fraction`` of the (downsampled) pixels are usable or either image is flat there.
    """
    ga, gb = _gray_block_mean(a, downsample), _gray_block_mean(b, downsample)
    m = np.ones(ga.shape, bool) if mask is None else block_mean(mask.astype(np.float32), downsample) > 0.5
    if m.sum() < max(4, min_fraction * m.size):
        return float("nan")
    x, y = ga[m] - ga[m].mean(), gb[m] - gb[m].mean()
    denom = math.sqrt(float((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / denom) if denom > 1e-12 else float("nan")


@dataclass
class CrossRenderCheck:
    """Cross-render self-check of one NeRF pair: NCC of i's renders against j rendered at i's poses (and back)."""

    i: int
    j: int
    ncc_i_in_j: float
    """Median NCC: views of i mapped into j's frame, rendered by j, against i's own renders."""
    ncc_j_in_i: float
    """The same the other way round."""
    views: int
    """Views per direction."""
    colour_j_to_i: Float[np.ndarray, "3 4"] | None = None
    """Colour map (linear-RGB gains, :mod:`nerfuser_ns.appearance`) from j's renders to i's at the same pixels (None:
    too few opaque, unclipped pixels)."""
    colour_i_to_j: Float[np.ndarray, "3 4"] | None = None
    """The same from i's to j's."""
    colour_pixels: int = 0
    """Pixel pairs the colour maps were fitted on."""
    depth_i_in_j: float = float("nan")
    """Median log depth ratio (:func:`depth_log_ratio`) of j rendered at i's views mapped into j's frame against i's
    own depth (NaN: no depth, from either renderer or the stored views)."""
    depth_j_in_i: float = float("nan")
    """The same the other way round."""

    @property
    def depth_disagreement(self) -> float:
        """The direction whose log depth ratio lies farther from 0, signed (NaN when neither was measured)."""
        values = [v for v in (self.depth_i_in_j, self.depth_j_in_i) if np.isfinite(v)]
        return float(max(values, key=abs)) if values else float("nan")

    @property
    def score(self) -> float:
        """The worse direction (NaN if either saw nothing in common)."""
        return float(min(self.ncc_i_in_j, self.ncc_j_in_i)) if np.isfinite([self.ncc_i_in_j, self.ncc_j_in_i]).all() \
            else float("nan")


def _finite_median(x: np.ndarray) -> float:
    return float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")


def _cross_direction(
    src: ViewSet, dst: Renderer, T_src_to_dst: np.ndarray, order: Sequence[int], depth_order: Sequence[int],
    intrinsics: Intrinsics, cfg: RegistrationConfig, acc_src: np.ndarray,
) -> tuple[float, float]:
    """(median NCC over ``src``'s first ``cfg.self_check_views`` views of ``order``, median log depth ratio over the
    first as many of ``depth_order``); one set of renders when both name the same views."""
    views = list(order)[: cfg.self_check_views]
    at_depth = list(depth_order)[: cfg.self_check_views]
    depths: list[float] = []
    same = views == at_depth
    scores = view_nccs(src, dst, T_src_to_dst, views, intrinsics, cfg, acc_src, depths=depths if same else None)
    if not same:
        view_nccs(src, dst, T_src_to_dst, at_depth, intrinsics, cfg, acc_src, depths=depths)
    return _finite_median(scores), _finite_median(np.array(depths, dtype=np.float64))


def nearest_views(
    views: ViewSet, T_to_other: Float[np.ndarray, "4 4"], other: ViewSet, training_only: bool = False
) -> list[int]:
    """``views``' kept views, those whose centres mapped by ``T_to_other`` lie nearest ``other``'s view centres first
    (where the other NeRF renders from nearby if the link is right; chosen by the cameras alone, not by the content
    a link was fitted to).

    ``training_only``: among ``views``' views rendered at its training cameras and nearest ``other``'s, each side
    falling back to all its views when it has none (the depth check's views: :func:`depth_views`)."""
    own, targets = views.kept, other.c2w[:, :3, 3]
    if training_only:
        own_training, other_training = views.kept & training_views(views), training_views(other)
        own = own_training if own_training.any() else own
        targets = targets[other_training] if other_training.any() else targets
    centres = sim3.transform_poses(T_to_other, views.c2w)[:, :3, 3]
    d = np.linalg.norm(centres[:, None] - targets[None], axis=-1).min(axis=1)
    return [int(k) for k in np.argsort(d, kind="stable") if own[k]]


def training_views(views: ViewSet) -> np.ndarray:
    """Which of ``views`` were rendered at the NeRF's training cameras (none when the sources are not recorded)."""
    flags = np.array([s == "training" for s in views.sources], dtype=bool)
    return flags if len(flags) == len(views.c2w) else np.zeros(len(views.c2w), dtype=bool)


def depth_views(views: ViewSet, T_to_other: Float[np.ndarray, "4 4"], other: ViewSet) -> list[int]:
    """The views the depth check compares at: :func:`nearest_views` among training views where there are any.

    At its training cameras a NeRF's depth is what its capture showed; at views it was not trained on (the
    hemisphere's) both NeRFs extrapolate: under street-21's true link the median log ratio at the nearest views of
    all was +0.084 (one hemisphere view +0.23), at the nearest training views +0.014, while a scale error of 0.1 still
    gave 0.10-0.17 there (reports/depth_check_training_views.md). ``depth_threshold`` was fixed at training views."""
    return nearest_views(views, T_to_other, other, training_only=True)


def depth_log_ratio(
    own: Float[np.ndarray, "h w"],
    other: Float[np.ndarray, "h w"],
    scale: float,
    mask: np.ndarray,
    min_fraction: float = 0.1,
) -> float:
    """Median over ``mask`` of ``log(other / (scale * own))``: ``own`` one NeRF's ray distance at its view, ``other``
    the other NeRF's at the same view mapped through a link of scale ``scale`` (its units per the first's).

    0 where the link puts the other NeRF's surfaces where the first has them; a link whose scale is off by ``e`` in
    log scale about the camera gives ``-e``. NaN when fewer than ``min_fraction`` of the pixels are usable.
    """
    ok = mask & np.isfinite(own) & np.isfinite(other) & (own > 0) & (other > 0)
    if ok.sum() < max(4, min_fraction * ok.size):
        return float("nan")
    return float(np.median(np.log(other[ok].astype(np.float64) / (scale * own[ok].astype(np.float64)))))


def spread_views(views: ViewSet, count: int) -> Float[np.ndarray, " m"]:
    """``count`` of the kept views, evenly spread over them (all when there are fewer)."""
    idx = np.flatnonzero(views.kept)
    return idx[np.round(np.linspace(0, len(idx) - 1, min(count, len(idx)))).astype(int)]


def _colour_pairs(
    src: ViewSet, dst: Renderer, T_src_to_dst: np.ndarray, intrinsics: Intrinsics, cfg: RegistrationConfig,
    acc_src: np.ndarray,
) -> tuple[Float[np.ndarray, "n 3"], Float[np.ndarray, "n 3"]]:
    """(src's colours, dst's colours) at the pixels both render opaque, over ``cfg.colour_views`` of src's views
    rendered at 1/:data:`COLOUR_REDUCE` size: the appearance matching's samples for one direction."""
    colours: list = []
    view_nccs(src, dst, T_src_to_dst, spread_views(src, cfg.colour_views), intrinsics, cfg, acc_src,
              reduce=COLOUR_REDUCE, colours=colours)  # fmt: skip
    empty = np.zeros((0, 3))
    return (np.concatenate([empty] + [a.reshape(-1, 3) for a, _ in colours]),
            np.concatenate([empty] + [b.reshape(-1, 3) for _, b in colours]))  # fmt: skip


def view_nccs(
    src: ViewSet, dst: Renderer, T_src_to_dst: np.ndarray, order: Sequence[int], intrinsics: Intrinsics,
    cfg: RegistrationConfig, acc_src: np.ndarray | None = None, reduce: int = 1, colours: list | None = None,
    depths: list | None = None,
) -> Float[np.ndarray, " n"]:
    """NCC of each of ``src``'s views ``order`` against ``dst`` rendered at that view mapped by ``T_src_to_dst``
    (NaN where they see too little in common).

    ``reduce`` > 1 renders ``dst`` at 1/reduce of the size (reduce^2 times fewer rays) and compares it with ``src``'s
    renders block-averaged by that factor: the NCC block-averages by ``cfg.ncc_downsample`` anyway.

    ``colours``, when given, receives per view ``(src's colours, dst's colours)`` at the pixels both render opaque
    (accumulation >= :data:`nerfuser_ns.appearance.OPAQUE`): the appearance matching's samples.

    ``depths``, when given and both ``src``'s stored views and ``dst`` give depth, receives per view
    :func:`depth_log_ratio` of ``dst``'s depth against ``src``'s on the pixels both render opaque.
    """
    order = list(order)
    if not order:
        return np.zeros(0)
    acc_src = src.load_accumulation() if acc_src is None else acc_src
    with_depth = depths is not None and src.has_depth and gives_depth(dst)
    depth_src = src.load_depth() if with_depth else None
    scale = float(sim3.decompose_sim3(T_src_to_dst)[2]) if with_depth else 1.0
    poses = sim3.transform_poses(T_src_to_dst, src.c2w[order])
    big = intrinsics
    small = big if reduce <= 1 else Intrinsics(big.fx / reduce, big.fy / reduce, big.cx / reduce, big.cy / reduce,
                                               big.width // reduce, big.height // reduce)  # fmt: skip
    scores = []
    for k, pose in zip(order, poses, strict=True):
        out = dst.render(pose[None], small, **({"depth": True} if with_depth else {}))
        rgb = np.nan_to_num(np.asarray(out.rgb[0], dtype=np.float32))
        # Compare what the PNG stored, as the SfM saw it.
        rgb = to_uint8(rgb).astype(np.float32) / 255
        mask = block_mean(acc_src[k], reduce) >= 0.5
        if out.accumulation is not None:
            mask &= np.nan_to_num(out.accumulation[0]) >= 0.5
        own = block_mean(src.load_rgb(k), reduce)
        if colours is not None or with_depth:  # the pixels both render opaque
            opaque = block_mean(acc_src[k], reduce) >= appearance.OPAQUE
            if out.accumulation is not None:
                opaque &= np.nan_to_num(out.accumulation[0]) >= appearance.OPAQUE
        if colours is not None:
            colours.append((own[opaque], rgb[opaque]))
        if with_depth and out.depth is not None:
            depths.append(depth_log_ratio(block_mean(depth_src[k], reduce), np.asarray(out.depth[0]), scale, opaque))
        scores.append(ncc(own, rgb, mask, max(1, cfg.ncc_downsample // reduce)))
    return np.array(scores)


def cross_render_check(
    renderers: Sequence[Renderer],
    views: Sequence[ViewSet],
    T_to_ref: Float[np.ndarray, "k 4 4"],
    pairs: Sequence[tuple[int, int]],
    intrinsics: Intrinsics,
    cfg: RegistrationConfig,
    view_order: dict[tuple[int, int], Sequence[int]] | None = None,
) -> list[CrossRenderCheck]:
    """For each pair (i, j): map views of i through the estimate into j, render j there, NCC against i's renders.

    ``view_order[(i, j)]`` lists i's views to use for the NCC, best first (default: i's kept views, evenly spread);
    the depth is compared at i's :func:`depth_views` under the estimate, whatever the order. The pair's
    colour maps come from ``cfg.colour_views`` views per direction, evenly spread and rendered small, the two
    directions' gains averaged (:func:`nerfuser_ns.appearance.fit_colour_map_directions`: why).
    """
    checks = []
    accs = [vs.load_accumulation() for vs in views]
    for i, j in pairs:
        T_ij = sim3.relative_sim3(T_to_ref[j], T_to_ref[i])  # i -> j
        T_ji = sim3.invert_sim3(T_ij)

        def order(a, b):
            if view_order is not None and (a, b) in view_order:
                return view_order[(a, b)]
            return spread_views(views[a], cfg.self_check_views)

        near_ij, near_ji = depth_views(views[i], T_ij, views[j]), depth_views(views[j], T_ji, views[i])
        s_ij, d_ij = _cross_direction(views[i], renderers[j], T_ij, order(i, j), near_ij, intrinsics, cfg, accs[i])
        s_ji, d_ji = _cross_direction(views[j], renderers[i], T_ji, order(j, i), near_ji, intrinsics, cfg, accs[j])
        colour_j_to_i = colour_i_to_j = None
        pixels = 0
        if cfg.colour_views > 0:
            i_own, j_there = _colour_pairs(views[i], renderers[j], T_ij, intrinsics, cfg, accs[i])
            j_own, i_there = _colour_pairs(views[j], renderers[i], T_ji, intrinsics, cfg, accs[j])
            colour_j_to_i = appearance.fit_colour_map_directions([(j_there, i_own), (j_own, i_there)])
            colour_i_to_j = appearance.fit_colour_map_directions([(i_own, j_there), (i_there, j_own)])
            pixels = len(i_own) + len(j_own)
        checks.append(CrossRenderCheck(i, j, s_ij, s_ji, cfg.self_check_views, colour_j_to_i, colour_i_to_j, pixels,
                                       d_ij, d_ji))  # fmt: skip
    return checks


def covisibility(views: Sequence[ViewSet], sfm: SfMResult) -> np.ndarray:
    """``[k, k]`` overlap between NeRFs: 3D points of the SfM model seen by both (symmetric: the smaller count)."""
    overlap = np.zeros((len(views), len(views)), dtype=int)
    for i, vs in enumerate(views):
        for name in vs.image_names:
            if name in sfm.covisible:
                overlap[i] += np.asarray(sfm.covisible[name])
    return np.minimum(overlap, overlap.T)


def spanning_pairs(overlap: np.ndarray) -> list[tuple[int, int]]:
    """Maximum spanning tree (Prim) of the NeRF overlap graph: every NeRF checked against its best neighbour."""
    k = len(overlap)
    in_tree, pairs = {0}, []
    while len(in_tree) < k:
        best = max(((a, b) for a in in_tree for b in range(k) if b not in in_tree), key=lambda p: overlap[p])
        pairs.append(tuple(sorted(best)))
        in_tree.add(best[1])
    return pairs


def tree_edges(pairs: Sequence[tuple[int, int]], ref: int) -> list[tuple[int, int]]:
    """The spanning tree's pairs as (parent, child), parents nearer the reference first (breadth-first)."""
    edges, seen, frontier = [], {ref}, [ref]
    while frontier:
        nxt = []
        for a in frontier:
            for i, j in pairs:
                b = j if i == a else i if j == a else None
                if b is not None and b not in seen:
                    seen.add(b)
                    edges.append((a, b))
                    nxt.append(b)
        frontier = nxt
    return edges


def best_views(
    views: Sequence[ViewSet], sfm: SfMResult, pairs: Sequence[tuple[int, int]]
) -> dict[tuple[int, int], list[int]]:
    """Per checked pair and direction (a, b): a's kept views, those that share the most SfM points with b first."""
    k = len(views)
    view_order = {}
    for i, j in pairs:
        for a, b in ((i, j), (j, i)):
            names_a = views[a].image_names
            cov = np.array([sfm.covisible.get(n, [0] * k)[b] if views[a].kept[n_i] else -1
                            for n_i, n in enumerate(names_a)])  # fmt: skip
            view_order[(a, b)] = [int(v) for v in np.argsort(-cov, kind="stable") if cov[v] >= 0]
    return view_order


def pair_failure(check: CrossRenderCheck, config: RegistrationConfig) -> str | None:
    """What failed in a pair's cross-render check, in words, or None: its NCC below the threshold (a pair that saw
    nothing in common fails), else its depth disagreement beyond ``config.depth_threshold`` (where measured)."""
    if not (np.isfinite(check.score) and check.score >= config.ncc_threshold):
        what = "saw nothing in common" if not np.isfinite(check.score) else f"NCC {check.score:.2f}"
        return f"cross-render self-check failed ({what} < {config.ncc_threshold})"
    d = check.depth_disagreement
    if config.depth_threshold > 0 and np.isfinite(d) and abs(d) > config.depth_threshold:
        return (f"cross-render depth check failed (through the link, the other NeRF renders the surfaces "
                f"{math.exp(d):.2f}x as deep as each NeRF's own depth at its views: median log ratio {d:+.3f}, beyond "
                f"{config.depth_threshold}; the link's scale or place is wrong)")  # fmt: skip
    return None


def passed(check: CrossRenderCheck, config: RegistrationConfig) -> bool:
    """Whether a pair's cross-render check passed (:func:`pair_failure`)."""
    return pair_failure(check, config) is None


def camera_residuals(
    views: Sequence[ViewSet], estimates: Sequence[NerfEstimate], T_to_C: Float[np.ndarray, "k 4 4"]
) -> list[tuple[Float[np.ndarray, " m"], Float[np.ndarray, " m"]]]:
    """Per NeRF, its SfM cameras against its transform into the SfM frame: the rotation (deg) and centre (its units)
    residual of each camera its estimate used."""
    return [sim3.pose_residuals(T_to_C[i], vs.c2w[ne.estimate.used], ne.G_sfm[ne.estimate.used])
            for i, (vs, ne) in enumerate(zip(views, estimates, strict=True))]  # fmt: skip


def camera_failure(
    names: Sequence[str],
    scales: Sequence[float],
    rotation_deg: Sequence[float | None],
    centre: Sequence[float | None],
    config: RegistrationConfig,
    fitted: Sequence[tuple[float, float] | None] | None = None,
) -> str | None:
    """The one-line error for the first NeRF whose SfM cameras disagree with its transform beyond the paper's failure
    rule (:func:`sim3.is_failure` on the medians over its cameras, ``rotation_deg`` and ``centre`` per NeRF, centres in
    its units and ``scales`` its scale to the reference), else None.

    The estimate follows the cameras, so only a refinement that followed points seen across NeRFs against them, or
    cameras that disagree among themselves, gets here: one of the two links unrelated content. ``fitted`` (per NeRF,
    the same medians against the estimator's own transform) tells the two apart: where the cameras fail the rule
    against their own best fit, the SfM reconstructed the NeRF's views distorted or merged unrelated content into them
    (measured on a drive: 11.2 deg from their own fit, the registration 18 deg wrong). Modes without SfM cameras have
    no residuals (None) and pass.
    """
    fitted = fitted if fitted is not None else [None] * len(names)
    for name, scale, rot, cen, fit in zip(names, scales, rotation_deg, centre, fitted, strict=True):
        if rot is None or cen is None:
            continue
        centre_ref = cen * scale
        if sim3.is_failure(rot, centre_ref, 0.0):
            why = "its cameras disagree among themselves, so the SfM probably merged unrelated content"
            if fit is not None and sim3.is_failure(fit[0], fit[1] * scale, 0.0):
                why = (f"they fit no one SIM(3) of its known poses ({fit[0]:.1f} deg and {fit[1] * scale:.3f} from "
                       f"their own best fit), so the SfM reconstructed its views distorted or merged unrelated "
                       f"content into them")
            elif config.refine:
                why = ("the bundle adjustment followed points seen across NeRFs that its cameras contradict, so the "
                       "SfM probably merged unrelated content")
            return (
                f"{name}: its SfM cameras disagree with its registered transform by {rot:.1f} deg and "
                f"{centre_ref:.3f} reference units (median; the paper's failure rule: 5 deg, 0.2): {why}; "
                f"{suggestion(config.sampling.source)} (or --no-camera-check to keep it)"
            )
    return None


MODEL_CHECK_MIN_VIEWS = 4
"""Views a NeRF needs in another SfM model for that model's link to count in :func:`model_disagreements` (fixed
before the check was first measured)."""


@dataclass
class ModelLinks:
    """What one other SfM model says: each NeRF's SIM(3) into that model's frame, where it holds enough of its views."""

    num_views: int
    """Views the model registered (of every NeRF)."""
    views_per_nerf: list[int]
    """Per NeRF: its kept views the model registered."""
    T_to_model: dict[int, Float[np.ndarray, "4 4"]]
    """Per NeRF index with at least :data:`MODEL_CHECK_MIN_VIEWS` (and ``min_registered_views``) kept views in the
    model and a non-degenerate estimate: ``T_nerf->model``."""


def model_links(
    views: Sequence[ViewSet], sfm: SfMResult, config: RegistrationConfig,
    models: Sequence[dict[str, np.ndarray]] | None = None,
) -> list[ModelLinks]:
    """Per SfM model of ``models``, in their order: the NeRFs it links on its own, each by ``config.estimator`` as the
    largest model's are. ``models``: each model's poses (default: the SfM's other models, largest first, read from its
    folder by :func:`~nerfuser_ns.registration.sfm.other_models`)."""
    models = other_models(sfm) if models is None else models
    out = []
    for poses in models:
        counts = [sum(kept and n in poses for n, kept in zip(vs.image_names, vs.kept, strict=True)) for vs in views]
        linked = {}
        for i, vs in enumerate(views):
            if counts[i] < max(MODEL_CHECK_MIN_VIEWS, config.min_registered_views):
                continue
            try:
                linked[i] = estimate_transform(vs, replace(sfm, c2w=poses), config).estimate.T
            except RegistrationError:  # a degenerate small model says nothing
                continue
        out.append(ModelLinks(len(poses), counts, linked))
    return out


@dataclass
class ModelDisagreement:
    """Another SfM model's link of two NeRFs beyond the paper's failure rule from the registration's."""

    num_views: int
    """Views the other model registered."""
    a: int
    """The NeRF the other model's link is anchored at (its smallest index)."""
    j: int
    """The NeRF it links to ``a`` otherwise."""
    r_err_deg: float
    t_ref: float
    """Translation difference in reference units."""
    s_err: float
    T_to_ref: Float[np.ndarray, "k 4 4"]
    """The registration's transforms with ``j``'s replaced by the other model's link to ``a``: what
    :func:`cross_render_check` scores the other model's link by."""


def model_disagreements(
    views: Sequence[ViewSet],
    sfm: SfMResult,
    T_to_ref: Float[np.ndarray, "k 4 4"],
    config: RegistrationConfig,
    models: Sequence[dict[str, np.ndarray]] | None = None,
) -> list[ModelDisagreement]:
    """Every link of another SfM model that differs from the registration's beyond the paper's failure rule
    (translations in reference units), the largest model first.

    The SfM splits views it cannot join; a smaller model that still holds :data:`MODEL_CHECK_MIN_VIEWS` views of two
    NeRFs links them on its own (:func:`model_links`). Views of one consistent overlap link them alike, so models that
    disagree mean the SfM linked content that is not the same, in one of the models (measured: a drive pair whose three
    models linked the NeRFs 5.8, 14 and 23 deg from the truth, the largest passing the self-check at NCC 0.63 and the
    camera check). ``models``: as :func:`model_links`'s.
    """
    out = []
    for model in model_links(views, sfm, config, models):
        if len(model.T_to_model) < 2:
            continue
        a, *others = sorted(model.T_to_model)
        T_a = model.T_to_model[a]
        scale_a = float(sim3.decompose_sim3(T_to_ref[a])[2])
        for j in others:
            link = sim3.invert_sim3(T_a) @ model.T_to_model[j]  # j -> a, as the other model links them
            e = sim3.sim3_errors(link, sim3.invert_sim3(T_to_ref[a]) @ T_to_ref[j])
            t_ref = float(e.t_err) * scale_a
            if sim3.is_failure(e.r_err_deg, t_ref, e.s_err):
                T_other = np.array(T_to_ref, dtype=np.float64, copy=True)
                T_other[j] = T_to_ref[a] @ link
                out.append(ModelDisagreement(model.num_views, a, j, float(e.r_err_deg), t_ref, float(e.s_err),
                                             T_other))  # fmt: skip
    return out


def model_contest(registration: CrossRenderCheck, model: CrossRenderCheck, config: RegistrationConfig) -> bool:
    """Whether another model's link, cross-rendered beside the registration's on the same views, refuses the
    registration: unless it fails the self-check (:func:`passed`) or the registration's link scores better by more than
    ``known_geometry.ambiguity_margin`` (the rule known geometry chooses between its hypotheses by), the two links are
    at best ambiguous. A model that linked unrelated content renders unrelated content; a registration that did renders
    no better than a model that did not."""
    if not passed(model, config):
        return False
    return not (np.isfinite(registration.score)
                and registration.score - model.score > config.known_geometry.ambiguity_margin)  # fmt: skip


def model_failure_line(
    d: ModelDisagreement, names: Sequence[str], config: RegistrationConfig,
    nccs: tuple[float, float] | None = None,
) -> str:
    """The one-line error of a disagreement that refuses the registration; ``nccs``: the registration's and the other
    model's cross-render scores (:func:`model_contest`), where they were rendered."""
    scored = ""
    if nccs is not None:
        within = "" if not nccs[1] < nccs[0] else f", within {config.known_geometry.ambiguity_margin} of it"
        scored = (f"; cross-rendered on the same views its link scores NCC {nccs[1]:.2f} against the registration's "
                  f"{nccs[0]:.2f}{within}")
    return (
        f"{names[d.j]}: another SfM model ({d.num_views} views) links it to {names[d.a]} "
        f"{d.r_err_deg:.1f} deg, {d.t_ref:.3f} reference units and {d.s_err:.3f} in log scale "
        f"away from the registration's link (the paper's failure rule: 5 deg, 0.2, 0.1){scored}: views the SfM "
        f"could not join disagree, so it probably merged unrelated content; "
        f"{suggestion(config.sampling.source)} (or --no-model-check to keep it)"
    )


LIKELY_CAUSE = {
    "sfm": "the SfM probably merged unrelated content",
    "known-geometry": "the matches probably linked unrelated content (repeated structure)",
    "graph": "an edge of the pose graph probably linked unrelated content",
}
"""Per registration mode, the usual cause of a failed self-check (its error names it)."""


def failure_message(checks: Sequence[CrossRenderCheck], names: Sequence[str], config: RegistrationConfig) -> str | None:
    """The one-line error for the first failed pair, or None when every checked pair passed."""
    for c in checks:
        if (what := pair_failure(c, config)) is not None:
            escape = ("calibrate --ncc-threshold for blurry renders" if what.startswith("cross-render self-check")
                      else "--depth-threshold 0 to skip the depth check")  # fmt: skip
            return (f"{names[c.i]} and {names[c.j]}: {what}; {LIKELY_CAUSE[config.mode]}; "
                    f"{suggestion(config.sampling.source, config.mode)} (or {escape})")  # fmt: skip
    return None
