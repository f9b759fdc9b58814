"""Registration settings, errors and constants, shared by every step of :mod:`nerfuser_ns.registration`.

Also the small conventions the steps share: content hashes of cache keys and JSON-safe numbers (matrices rounded to
12 digits, NaN / inf stored as null).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
from rich.console import Console

from nerfuser_ns.cameras import Intrinsics, intrinsics_from_fov
from nerfuser_ns.registration.pose_graph import CYCLE_MAX_LOG_SCALE, CYCLE_MAX_ROTATION_DEG, CYCLE_MAX_TRANSLATION
from nerfuser_ns.sampling import sample_hemisphere_poses

if TYPE_CHECKING:  # record.py imports this module
    from nerfuser_ns.registration.record import RegistrationResult

FORMAT_VERSION = 1
CONSOLE = Console(width=120)
SUGGESTION = (
    "render more poses (--sampling.num-poses), a larger radius (--sampling.radius) or the run's training poses "
    "(--sampling.source training|both)"
)
"""What to try when the hemisphere poses do not register (:func:`suggestion` per pose source)."""
ADVICE = {
    "training": ("render more training poses (--sampling.max-training-poses)",
                 "add hemisphere poses (--sampling.source both)"),
    "both": ("render more poses (--sampling.max-training-poses, --sampling.num-poses)",),
}  # fmt: skip
"""Per pose source other than the hemisphere, what to try when its renders did not register (:func:`suggestion`)."""


def suggestion(source: str, mode: str = "sfm") -> str:
    """What to try when renders from pose source ``source`` did not register in registration mode ``mode`` (the
    hemisphere's advice by default); known geometry is offered to the SfM mode only."""
    if source not in ADVICE:
        return SUGGESTION
    options = [*ADVICE[source], *(["register on known geometry (--mode known-geometry)"] if mode == "sfm" else [])]
    return options[0] if len(options) == 1 else f"{', '.join(options[:-1])} or {options[-1]}"


DEFAULT_RENDER_SIZE = (400, 300, 60.0)
"""Render width, height and horizontal field of view when the reference run's training cameras are unknown."""


class RegistrationError(ValueError):
    """Registration cannot produce a trustworthy result; the one-line message names the NeRF and what to change."""


class RegistrationFailed(RegistrationError):
    """The self-check rejected the solution; ``result`` holds it (with the scores) for inspection."""

    def __init__(self, message: str, result: RegistrationResult):
        super().__init__(message)
        self.result = result

    @property
    def record(self) -> dict:
        """The rejected solution as a registration record (what ``write_registration`` stores)."""
        return self.result.to_record()


class TwinLinked(RegistrationFailed):
    """The twin check refused the SfM's link: another transform that the rendered depth supports renders better
    (repeated structure). The automatic choice registers on known geometry next."""


# ---------------------------------------------------------------------------------------------------------------------
# Settings


@dataclass
class PoseSamplingConfig:
    """Which views of each NeRF to render, in the NeRF's own frame."""

    source: Literal["auto", "hemisphere", "training", "both"] = "auto"
    """Poses to render: the paper's hemisphere, the run's own training poses, or both. ``auto``: the training poses
    when every run's dataset is readable, then training + hemisphere, then the hemisphere alone if a choice does not
    register; the hemisphere when a dataset is gone; in mode sfm, known geometry on the most views last. What was
    chosen, and why, is printed and recorded."""
    num_poses: int = 32
    """Hemisphere poses per NeRF (the paper uses 32 on object scenes, 60 on ScanNet)."""
    radius: float = 1.0
    """Hemisphere radius, in the NeRF's units."""
    elevation_range_deg: tuple[float, float] = (0.0, 30.0)
    """(min, max) elevation of the hemisphere rings above the NeRF's xy plane (+z up)."""
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Centre of the hemisphere (the cameras look at it)."""
    jitter_deg: float = 0.0
    """Random perturbation of azimuth / elevation (0: the deterministic ring layout)."""
    seed: int = 0
    """Seed of the jitter and of the training-pose subset (0: evenly spaced through the run's list; any other seed: a
    random subset, for benchmarks over pose draws)."""
    max_training_poses: int = 32
    """At most this many training poses per NeRF."""
    width: int | None = None
    """Rendered image width in pixels (default: ``size`` along the longer side of the reference run's training
    cameras, their aspect kept; 400 when its dataset is gone)."""
    height: int | None = None
    """Rendered image height in pixels (default: as ``width``; 300 when the reference run's dataset is gone)."""
    fov_deg: float | None = None
    """Horizontal field of view of the renders (square pixels, centred principal point). Default: that of the reference
    run's training cameras (median focal length over width); 60 when its dataset is gone."""
    size: int = 400
    """With the default width and height: the longer side of the renders, in pixels, whatever the training images'
    size (a NeRF renders at any resolution; SIFT needs texture at this size: 200x150 renders of a room gave too few
    features, and larger renders cost time on a CPU)."""
    min_view_accumulation: float = 0.5
    """Views whose mean accumulation (opacity) is below this see mostly nothing and are left out of the SfM."""

    def intrinsics(self) -> Intrinsics:
        """The render intrinsics; unset values are :data:`DEFAULT_RENDER_SIZE`'s (``resolve_sampling`` sets them
        from the runs' training cameras first)."""
        width, height, fov = (d if v is None else v for v, d in zip((self.width, self.height, self.fov_deg),
                                                                     DEFAULT_RENDER_SIZE, strict=True))  # fmt: skip
        fx, fy, cx, cy = intrinsics_from_fov(width, height, fov)
        return Intrinsics(fx, fy, cx, cy, width, height)


@dataclass
class SfMConfig:
    """pycolmap settings for the one SfM over all renders."""

    exhaustive_max_images: int = 100
    """Match every pair up to this many images; above, match each image to its nearest views of its own NeRF
    (known poses) and to a spread subset of every other NeRF's views (linear in the number of images)."""
    own_neighbors: int = 10
    """Cheap scheme: nearest views of the same NeRF each image is matched to."""
    cross_views: int = 24
    """Cheap scheme: views of each other NeRF each image is matched to."""
    max_num_features: int = 8192
    """SIFT features per image."""
    min_model_size: int = 3
    """Smaller SfM models are discarded (pycolmap's default, 10, would hide small separate models)."""
    min_num_inliers: int = 10
    """Geometric verification: inlier matches an image pair needs (COLMAP: 15). Renders of different NeRFs share
    fewer features than photos of one capture; the cross-render self-check guards against wrong links."""
    min_num_matches: int = 10
    """Mapping: verified matches a pair needs to be used (COLMAP: 15)."""
    abs_pose_min_num_inliers: int = 15
    """Mapping: 2D-3D inliers an image needs to register (COLMAP: 30)."""
    abs_pose_min_inlier_ratio: float = 0.15
    """Mapping: inlier ratio an image needs to register (COLMAP: 0.25)."""
    num_threads: int = -1
    """Threads for extraction, matching and mapping (-1: all cores)."""
    seed: int = 0
    """pycolmap's random seed (mapping and RANSAC), for reproducible runs."""
    verbose: bool = False
    """Show COLMAP's own log (INFO level)."""


@dataclass
class KnownGeometryConfig:
    """Registration on known geometry: SIFT keypoints of the renders lifted to 3D with the rendered depth at the known
    poses, matched across NeRFs, and SIM(3) hypotheses by RANSAC on the 3D-3D matches (no SfM)."""

    max_num_features: int = 4096
    """SIFT features per render."""
    min_accumulation: float = 0.95
    """A keypoint's depth is trusted only where the render is this opaque (in its 3x3 neighbourhood)."""
    max_depth_step: float = 0.05
    """... and where the depth varies by at most this fraction of itself over the 3x3 neighbourhood (no edge)."""
    consistency_tolerance: float = 0.02
    """A lifted point agrees with another view of its NeRF when that view's rendered depth at the point's projection
    is within this fraction of the point's distance from that camera."""
    min_consistent_views: int = 1
    """Other views of the same NeRF a lifted point must agree with (0: no multi-view check)."""
    vocabulary_words: int = 256
    """Visual words of the vocabulary built from the renders' own descriptors (for candidate view pairs)."""
    candidate_views: int = 5
    """Candidate pairs: each view is matched to this many most similar views of each other NeRF."""
    exhaustive_max_pairs: int = 256
    """Match every cross-NeRF view pair while there are at most this many (per NeRF pair)."""
    ratio: float = 0.8
    """Lowe's ratio test on descriptor distances (with mutual nearest neighbours)."""
    ransac_max_error: float = 0.02
    """RANSAC inlier threshold on 3D matches, as a fraction of the target NeRF's median rendered depth."""
    min_inliers: int = 30
    """A SIM(3) hypothesis needs this many inlier 3D matches."""
    max_hypotheses: int = 16
    """Distinct hypotheses kept per NeRF pair (sequential RANSAC: the next one from the matches left over). Ordinary
    overlaps give one or two; repeated structure gives one per symmetry it has: on the row-houses validation scene
    (seed 0: one house repeated every 3.5 m on both sides) the true link ranked 6th to 8th by inliers behind twins
    shifted by whole houses or turned by half a turn, and a cap of 3 never saw it."""
    min_hypothesis_fraction: float = 0.05
    """Hypotheses with fewer inliers than this fraction of the best one's are dropped before the self-check scores
    them (each scored hypothesis costs cross-renders). Small on purpose: under repeated structure the wrong link can
    have the most inliers (in the room of seed 1 the true one had 21% of its twin's; 0.25 dropped it)."""
    hypothesis_views: int = 16
    """Competing hypotheses are cross-rendered on this many views per direction (the same views for each: those
    where their inlier counts differ most first) and scored by their worst view's NCC."""
    ambiguity_margin: float = 0.05
    """When the runner-up passes the self-check's threshold and scores within this NCC of the best, the registration
    is ambiguous: it fails and names both scores instead of picking one."""
    loss_scale: float = 0.01
    """Joint solve: soft-L1 scale of 3D residuals, relative to the points' distance from their cameras."""


@dataclass
class DirectConfig:
    """Direct photometric alignment of each linked NeRF pair after the bundle adjustment (ours; mode sfm): every
    textured pixel the two NeRFs both render, instead of the SfM's keypoints (:mod:`.direct`)."""

    enabled: bool = True
    """Run it (--direct.no-enabled: the SfM, the paper's estimator and the bundle adjustment only). Chosen on the
    validation case object-centric-11 (stock nerfacto on COLMAP-posed captures): IDW-Sample 22.35 -> 22.60 dB on test
    views placed by the runs' content frames, 19.27 -> 19.51 dB by the stored truth; +62 s of a 15-minute registration
    on a CPU."""
    views: int = 8
    """Views per direction and pair: each NeRF's views that share the most SfM points with the other first; the other
    NeRF is rendered there with depth."""
    render_factor: int = 2
    """Those renders at 1/render_factor of the registration's render size (their pixels are compared with the full-size
    renders the SfM used, so this thins the samples, not the images they are read from)."""
    max_pixels_per_view: int = 20000
    """Samples per view at most (drawn with ``seed``)."""
    min_pixels: int = 2000
    """A pair with fewer samples keeps its transform."""
    iterations: int = 1
    """Render-and-fit rounds per pair (each round renders again at the refined transform)."""
    max_evaluations: int = 60
    """Residual evaluations per fit (scipy least_squares ``max_nfev``; a numeric Jacobian takes 8 per step)."""
    max_change_deg: float = 1.0
    """A fit that turns the transform by more than this keeps the bundle adjustment's transform."""
    max_change_distance: float = 0.02
    """... or moves it by more than this fraction of the views' median depth ..."""
    max_change_log_scale: float = 0.02
    """... or changes its scale by more than this in log scale."""
    seed: int = 0
    """Seed of the pixel draw."""


@dataclass
class ColocatedConfig:
    """Re-render refinement of each linked NeRF pair (ours): each NeRF rendered with depth at the other's views mapped
    through the link, the co-located renders' optical-flow correspondences lifted with each NeRF's own depth, the link
    re-fitted by RANSAC on them (:mod:`.colocated`)."""

    enabled: bool = True
    """Run it in mode known-geometry (the automatic choice's last step, after every SfM was refused), after the joint
    solve and its refinement, before the self-check (--colocated.no-enabled: off)."""
    sfm: bool = False
    """Also run it in mode sfm, after the checks that need no renders and before the direct alignment (off by
    default: on our streets and objects the SfM's links are good to 0.1-0.2 deg, finer than this refinement was
    measured)."""
    views: int = 6
    """Views per direction and pair: each NeRF's views whose centres lie nearest the other's under the link."""
    iterations: int = 1
    """Render-and-fit rounds at most (each round renders at the link the previous one found). One: on the development
    drive (drive-10, stock nerfacto on COLMAP-posed captures, one of them bent 3.7 deg by COLMAP) the first round took
    the refused known-geometry link from 5.6 to 1.7 deg off the runs' content frames (5.9 to 0.9 off the stored
    truth); a second round (of a first version that chose its views again each round) moved it 2.4 deg, away from
    both truths."""
    stride: int = 4
    """Flow correspondences are read every this many pixels."""
    max_flow_error_px: float = 1.0
    """... and kept where the backward flow returns within this many pixels of the start."""
    min_accumulation: float = 0.95
    """A correspondence's depth is trusted only where the render is this opaque (in its 3x3 neighbourhood) ..."""
    max_depth_step: float = 0.05
    """... and where the depth varies by at most this fraction of itself over the neighbourhood (no edge)."""
    ransac_max_error: float = 0.05
    """RANSAC inlier threshold (gross flow errors only: the bundle adjustment fits the rest), as a fraction of the
    matches' median distance from their cameras."""
    min_inliers: int = 30
    """A round with fewer inlier matches keeps the link it started from (and ends the refinement)."""
    loss_scale_px: float = 1.0
    """The bundle adjustment's soft-L1 loss scale (pixels), as the other refinements'."""
    min_change_deg: float = 0.05
    """Stop when a round turns the link by less than this ..."""
    min_change: float = 0.002
    """... and moves the inliers' median point by less than this fraction of the matches' median camera distance."""
    seed: int = 0
    """RANSAC seed."""


@dataclass
class GraphConfig:
    """Registration of many NeRFs as a SIM(3) pose graph: candidate NeRF pairs from the renders' visual words (or the
    neighbours given), each pair registered on known geometry (the known-geometry settings apply), the pairwise
    SIM(3)s checked around cycles and solved together (:mod:`nerfuser_ns.registration.pose_graph`, GTSAM)."""

    neighbours: tuple[str, ...] = ()
    """NeRF pairs to register, as ``a:b`` with NeRF names or indices (e.g. ``--graph.neighbours 0:1 1:2``); when
    given, only these pairs are registered and the retrieval below is skipped."""
    score_views: int = 5
    """A NeRF pair's retrieval score: the mean of its this-many most similar view pairs (tf-idf cosine)."""
    verify_views: int = 24
    """Geometric verification of retrieval: every NeRF pair's this-many most similar view pairs are matched in 3D
    and one LO-RANSAC SIM(3) is fitted; its inlier count ranks each NeRF's partners (about 0.17 s per NeRF pair on
    two CPU cores, so quadratic in the NeRFs: 83 s at 32). Where the captures share textures (generated scenes,
    repeated facades) the tf-idf score ranks true neighbours anywhere; the inliers count only content that lies the
    same way in 3D. 0: rank by the tf-idf score alone."""
    min_similarity: float = 0.8
    """Without verification (``verify_views`` 0): NeRF pairs whose tf-idf score is at least this are candidates. Not
    calibrated on real captures: on generated drives unrelated blocks score up to 0.93."""
    top_k: int = 3
    """Each NeRF's this-many best partners (most verified inliers; the tf-idf score without verification) are
    candidates whatever their score (every NeRF gets a chance; bounds the pairs registered to about ``top_k`` per
    NeRF)."""
    bridge_rounds: int = 8
    """When the registered pairs leave the NeRFs in pieces: rounds in which every piece registers its next
    ``bridge_pairs`` best pairs (as ``top_k`` ranks them) to NeRFs outside it (retrieval only; 0: never)."""
    bridge_pairs: int = 2
    """... pairs per piece and round."""
    max_cycle_rotation_deg: float = CYCLE_MAX_ROTATION_DEG
    """A cycle of three pairwise SIM(3)s whose composition rotates by more than this fails (longer cycles get
    sqrt(length / 3) times each limit); the edge in most failing cycles is dropped."""
    max_cycle_translation: float = CYCLE_MAX_TRANSLATION
    """... or translates by more than this fraction of the first NeRF's length scale (the median distance of its
    lifted keypoints from their cameras)."""
    max_cycle_log_scale: float = CYCLE_MAX_LOG_SCALE
    """... or scales by more than this in ``|log s|``."""
    robust: Literal["huber", "cauchy"] = "huber"
    """Robust loss of the pose-graph solve."""
    executor: Literal["serial", "ray"] = "serial"
    """Where each NeRF's renders and keypoints and each pair's registration run: in this process, or as Ray tasks
    (the city extra; the same results). The render cache on disk is what the tasks share."""
    ray_address: str | None = None
    """With ``executor ray``: the Ray cluster to join (e.g. ``auto``, ``ray://head:10001``; every worker must see the
    work folder); default: start Ray on this machine."""
    ray_gpus_per_task: float | None = None
    """With ``executor ray``: GPUs each rendering task (a NeRF's renders, a pair's cross-renders) asks Ray for
    (fractions share a GPU); default: 1 when the cluster has GPUs, else 0."""


@dataclass
class RegistrationConfig:
    """Registration from re-rendering: pose sampling, SfM, estimator and self-check settings."""

    sampling: PoseSamplingConfig = field(default_factory=PoseSamplingConfig)
    """Which views of each NeRF to render."""
    mode: Literal["sfm", "known-geometry", "graph"] = "sfm"
    """sfm: the paper's one SfM over all renders, then a SIM(3) per NeRF from its cameras; known-geometry: no SfM, the
    renders' keypoints lifted to 3D with the rendered depth at the known poses and matched across NeRFs (ours);
    graph: known geometry on candidate NeRF pairs only, joined by a SIM(3) pose graph (ours, for many NeRFs; needs
    the city extra)."""
    sfm: SfMConfig = field(default_factory=SfMConfig)
    """SfM settings (mode sfm)."""
    known_geometry: KnownGeometryConfig = field(default_factory=KnownGeometryConfig)
    """Known-geometry settings (modes known-geometry and graph)."""
    graph: GraphConfig = field(default_factory=GraphConfig)
    """Pose-graph settings (mode graph)."""
    estimator: Literal["nerfuser", "nerfuser-median", "umeyama-ransac"] = "nerfuser"
    """nerfuser: the paper's median pairwise scale and robust (L1) bridge average; nerfuser-median: the bridges'
    element-wise median as in the paper's code; umeyama-ransac: Umeyama on camera centres with LO-RANSAC (pycolmap)."""
    umeyama_max_error: float = 0.05
    """umeyama-ransac: inlier threshold on camera centres, in the NeRF's units."""
    refine: bool = True
    """Refine the estimator's SIM(3)s by bundle adjustment in which each NeRF's cameras move together (their poses
    are known in the NeRF's frame): 7 unknowns per NeRF fitted to every feature seen by two NeRFs, instead of one pose
    per camera (measured: median rotation error 2-3x lower on CPU-trained nerfacto NeRFs)."""
    refine_loss_scale_px: float = 1.0
    """Refinement: soft-L1 loss scale in pixels (reprojection errors well above it barely pull)."""
    direct: DirectConfig = field(default_factory=DirectConfig)
    """Direct photometric alignment after the refinement (mode sfm, ours)."""
    colocated: ColocatedConfig = field(default_factory=ColocatedConfig)
    """Re-render refinement at co-located views (ours; mode known-geometry by default)."""
    camera_check: bool = True
    """Fail when a NeRF's SfM cameras disagree with its final transform beyond the paper's failure rule (their
    median: 5 deg or 0.2 reference units): the refinement then followed points seen across NeRFs that the cameras
    contradict, and one of the two links unrelated content (measured: a pair linked 13 deg wrong, which the
    self-check passed at NCC 0.41, at 9.2 deg; correct registrations 0.2-0.4 deg)."""
    model_check: bool = True
    """Fail when another model of the SfM (views it could not join to the largest) links two NeRFs differently from
    the registration beyond the paper's failure rule (5 deg, 0.2 reference units, 0.1 in log scale) and its link,
    cross-rendered beside the registration's on the same views, passes the self-check and scores no worse than the
    registration's by more than ``known_geometry.ambiguity_margin``: the SfM then linked content that is not the same,
    in one model or the other (measured: a drive pair linked 5.8 deg and 18% in scale wrong, which the self-check
    passed at NCC 0.63, where the other two models were 14 and 23 deg off). A model whose link renders clearly worse
    merged unrelated content itself, and the registration is kept (measured: the rule of refusing on any disagreement
    refused right links on drive-21 and street-21, whose other models' links score -0.02 and 0.18 against 0.79 and
    0.76; reports/check_refusals_model_contest.md)."""
    twin_check: bool = False
    """Mode sfm (ours, off by default): before the direct alignment, cross-render the SfM's link of each checked NeRF
    pair against the other SIM(3)s the renders' depth supports (known geometry's hypotheses and each NeRF's own
    symmetries, on the same renders) and fail when one scores better in its worst view by
    ``known_geometry.ambiguity_margin``: the SfM linked repeated structure by the wrong copy; the automatic choice then
    registers on known geometry from the same renders. Needs depth from every renderer (skipped otherwise). Off by
    default: on exact renders it refuses the half-turn twin of the generated room, but on stock nerfacto runs of that
    room the twin renders better than the truth at every view (worst 0.76 against -0.17; reports/twin_check_room4.md),
    so there it passes the twin, and what it costs and refuses on other scenes is not measured."""
    reference: int = 0
    """Index of the NeRF whose frame is the common frame."""
    min_registered_views: int = 2
    """Each NeRF needs at least this many views registered in the SfM model (umeyama-ransac needs 3)."""
    self_check_views: int = 4
    """Cross-render check: views per direction and NeRF pair (0 disables the check)."""
    ncc_threshold: float = 0.4
    """Fail when a checked pair's cross-render NCC is below this. Calibrated on CPU-trained nerfacto renders
    (scripts/calibrate_ncc.py, demo and street scenes): exact transforms 0.64-0.80, errors within 1 deg / 0.05
    units >= 0.53, rotations >= 10 deg or translations >= 0.4 <= 0.20; scale errors alone barely move it."""
    ncc_downsample: int = 4
    """Block-average both images by this factor before the NCC (tolerates blur and sub-pixel misalignment)."""
    depth_threshold: float = 0.07
    """Cross-render check (ours): fail when a checked pair's other NeRF, rendered at a NeRF's views through the link,
    puts its surfaces farther or nearer than that NeRF's own depth by more than this median log ratio (either
    direction; where both give depth; 0 disables). The NCC barely sees scale errors: a drive link 13% off in scale
    passed at NCC 0.62. Fixed on that drive's true link and its perturbations
    (reports/depth_check_calibration_drive6.md): the exact link 0.007, links within 1 deg / 0.05 units / 0.05 in log
    scale <= 0.049, scale errors of 0.1 0.103, the wrong link 0.207; on the demo pair, checked after, 0.008, <= 0.027
    and 0.113 (reports/depth_check_calibration_demo.md). Compared at each NeRF's views nearest the other's, among
    those rendered at training cameras where there are any (``self_check.depth_views``), as it was calibrated."""
    colour_views: int = 16
    """Appearance matching: views per checked pair and direction the colour maps are fitted on, evenly spread over
    each NeRF's views and rendered at half size (each NeRF renders its own views brighter than the other does, by a
    share that varies from view to view: more views average it out; 0: no colour maps)."""
    reference_colour: bool = True
    """Appearance matching (ours): also map the reference NeRF's colours to its own training images, fitted on
    ``colour_views`` of its training cameras (needs its dataset), so the matched fused scene takes the reference
    capture's colours instead of those of nerfacto's average appearance embedding (2-37% brighter than the capture on
    our runs); --no-reference-colour keeps the reference NeRF's colours."""


def validate_settings(config: RegistrationConfig) -> Intrinsics:
    """Check the settings before anything is rendered; returns the render intrinsics."""
    sc = config.sampling
    numbers = {"--sampling.center": sc.center, "--sampling.radius": sc.radius, "--sampling.jitter-deg": sc.jitter_deg,
               "--sampling.elevation-range-deg": sc.elevation_range_deg}  # fmt: skip
    for option, value in numbers.items():
        if not np.isfinite(np.asarray(value, dtype=np.float64)).all():
            raise RegistrationError(f"{option} {value}: must be finite")
    try:
        intr = sc.intrinsics()
        if sc.source in ("hemisphere", "both"):
            sample_hemisphere_poses(
                sc.num_poses, sc.radius, sc.elevation_range_deg, sc.center, jitter_deg=sc.jitter_deg, seed=sc.seed
            )
    except ValueError as e:
        raise RegistrationError(f"bad pose sampling settings: {e}") from None
    checks = [
        (sc.source in ("hemisphere", "training", "both"), f"unknown pose source {sc.source!r}"),
        (sc.max_training_poses >= 2, "--sampling.max-training-poses must be >= 2"),
        (sc.size >= 16, "--sampling.size must be >= 16"),
        (0.0 <= sc.min_view_accumulation <= 1.0, "--sampling.min-view-accumulation must be in [0, 1]"),
        (config.self_check_views >= 0, "--self-check-views must be >= 0"),
        (config.colour_views >= 0, "--colour-views must be >= 0"),
        (config.ncc_downsample >= 1, "--ncc-downsample must be >= 1"),
        (math.isfinite(config.depth_threshold) and config.depth_threshold >= 0,
         "--depth-threshold must be >= 0 (0 disables the depth check)"),
        (config.min_registered_views >= 2, "--min-registered-views must be >= 2"),
        (config.umeyama_max_error > 0, "--umeyama-max-error must be > 0"),
        (config.sfm.exhaustive_max_images >= 2 and config.sfm.own_neighbors >= 1 and config.sfm.cross_views >= 1,
         "--sfm.exhaustive-max-images, --sfm.own-neighbors and --sfm.cross-views must be positive"),
        (config.mode in ("sfm", "known-geometry", "graph"),
         f"unknown --mode {config.mode!r}; use sfm, known-geometry or graph"),
    ]
    kg = config.known_geometry
    checks += [
        (kg.max_num_features >= 16, "--known-geometry.max-num-features must be >= 16"),
        (0.0 <= kg.min_accumulation <= 1.0, "--known-geometry.min-accumulation must be in [0, 1]"),
        (kg.max_depth_step > 0 and kg.consistency_tolerance > 0 and kg.ransac_max_error > 0 and kg.loss_scale > 0,
         "--known-geometry.max-depth-step, consistency-tolerance, ransac-max-error and loss-scale must be > 0"),
        (kg.min_consistent_views >= 0, "--known-geometry.min-consistent-views must be >= 0"),
        (kg.vocabulary_words >= 2 and kg.candidate_views >= 1 and kg.exhaustive_max_pairs >= 0,
         "--known-geometry.vocabulary-words must be >= 2 and --known-geometry.candidate-views >= 1"),
        (0.0 < kg.ratio <= 1.0, "--known-geometry.ratio must be in (0, 1]"),
        (kg.min_inliers >= 3 and kg.max_hypotheses >= 1 and kg.hypothesis_views >= 1,
         "--known-geometry.min-inliers must be >= 3, --known-geometry.max-hypotheses and hypothesis-views >= 1"),
        (0.0 <= kg.min_hypothesis_fraction <= 1.0 and kg.ambiguity_margin >= 0,
         "--known-geometry.min-hypothesis-fraction must be in [0, 1] and --known-geometry.ambiguity-margin >= 0"),
    ]
    dc = config.direct
    checks += [
        (dc.views >= 1 and dc.render_factor >= 1 and dc.max_pixels_per_view >= 100 and dc.min_pixels >= 0,
         "--direct.views and --direct.render-factor must be >= 1, --direct.max-pixels-per-view >= 100"),
        (dc.iterations >= 1 and dc.max_evaluations >= 8, "--direct.iterations must be >= 1, max-evaluations >= 8"),
        (dc.max_change_deg > 0 and dc.max_change_distance > 0 and dc.max_change_log_scale > 0,
         "--direct.max-change-deg, max-change-distance and max-change-log-scale must be > 0"),
    ]
    gc = config.graph
    checks += [
        (gc.score_views >= 1 and gc.top_k >= 0 and gc.verify_views >= 0,
         "--graph.score-views must be >= 1, --graph.top-k and --graph.verify-views >= 0"),
        (math.isfinite(gc.min_similarity), "--graph.min-similarity must be finite"),
        (gc.bridge_rounds >= 0 and gc.bridge_pairs >= 1,
         "--graph.bridge-rounds must be >= 0 and --graph.bridge-pairs >= 1"),
        (gc.max_cycle_rotation_deg > 0 and gc.max_cycle_translation > 0 and gc.max_cycle_log_scale > 0,
         "--graph.max-cycle-rotation-deg, max-cycle-translation and max-cycle-log-scale must be > 0"),
        (gc.robust in ("huber", "cauchy"), f"unknown --graph.robust {gc.robust!r}; use huber or cauchy"),
        (gc.executor in ("serial", "ray"), f"unknown --graph.executor {gc.executor!r}; use serial or ray"),
        (gc.ray_address is None or gc.executor == "ray",
         f"--graph.ray-address {gc.ray_address} is for --graph.executor ray; pass both or neither"),
        (gc.ray_gpus_per_task is None or gc.ray_gpus_per_task >= 0,
         f"--graph.ray-gpus-per-task must be >= 0, got {gc.ray_gpus_per_task}"),
    ]
    for item in gc.neighbours:
        a, sep, b = str(item).partition(":")
        checks.append((bool(sep and a and b and ":" not in b),
                       f"--graph.neighbours {item!r}: expected a:b with two NeRF names or indices"))
    for ok, message in checks:
        if not ok:
            raise RegistrationError(message)
    return intr


# ---------------------------------------------------------------------------------------------------------------------
# Conventions shared by the steps' files


def content_hash(obj) -> str:
    """SHA-256 of ``obj`` as sorted JSON (cache keys of renders and SfM runs)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def json_matrix(T: np.ndarray) -> list:
    """A matrix as stored in JSON: float64, rounded to 12 digits, nested lists."""
    return np.round(np.asarray(T, dtype=np.float64), 12).tolist()


def json_float(x) -> float | None:
    """JSON-safe float (NaN / inf become null)."""
    x = float(x)
    return x if math.isfinite(x) else None
