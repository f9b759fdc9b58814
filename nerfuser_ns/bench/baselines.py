"""Point-cloud registration baselines for NeRF registration (NeRFuser, ICCV 2023, "NeRF Registration", Table 1).

The paper compares its registration from re-rendering with three Open3D point-cloud registration (PCR) methods, run
on point clouds extracted from the NeRFs and on point clouds fused from ground-truth posed RGB-D images:

* ``icp``: point-to-plane ICP (Rusinkiewicz & Levoy), a local method. The paper does not say how it is initialised;
  with no prior it can only start from the identity (the two NeRF frames taken as equal), which is what we do.
* ``fgr``: Fast Global Registration (Zhou et al.) on FPFH feature matches.
* ``ransac``: FPFH (Rusu et al.) feature matches + RANSAC (the paper's "FPFH" row).

Those methods solve SE(3) only, so, as in the paper, the source cloud is first brought into the target's units with
the ground-truth relative scale ``s`` (``S = diag(s, s, s, 1)``); the method then solves the rigid ``G`` with
``target ~ G S source`` and the SIM(3) estimate is ``T = G S``. Its errors against ground truth come from
:func:`nerfuser_ns.sim3.sim3_errors` (``s_err`` is then 0 by construction: the paper's "N/A").

Point clouds come from depth renders: any :class:`~nerfuser_ns.renderers.Renderer` whose ``render`` takes
``depth=True`` (both project adapters do) renders RGB, accumulation and depth at poses in its own frame; pixels with
enough accumulation and a finite positive depth are back-projected along their pixel-centre rays. Depth is the
distance along the unit-length ray (nerfstudio 1.1.5's ``depth`` output: for nerfacto the median sample distance
of ``RaySamples`` whose directions are normalised; the scene ray-caster's depth likewise), not z-depth; z-depth
input (e.g. dataset depth PNGs) is accepted with ``depth_kind="z"``.

Determinism: RANSAC and FGR draw their samples from Open3D's global random generator, which
:meth:`PCRBaseline.register` seeds with ``PCRConfig.seed`` (``o3d.utility.random.seed``) before every call. Open3D
parallelises RANSAC with OpenMP; the draws are serialised, so repeated calls on the same clouds give identical
results (checked with OMP_NUM_THREADS=1 and 2, which also agree with each other). The methods are discontinuous in
their input, though: a relative change of 1e-15 in the scale can move FGR's answer by ~0.1 deg on the demo clouds.

Conventions as in :mod:`nerfuser_ns.sim3`: ``T_AB`` maps points of A into B; poses are camera-to-world with OpenGL
camera axes. Bad input raises :class:`BaselineError` with a one-line message.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
from jaxtyping import Float
from nerfstudio.configs.base_config import InstantiateConfig

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics, camera_rays

if TYPE_CHECKING:  # open3d is imported lazily: it is heavy and only these baselines need it
    import open3d as o3d

    from nerfuser_ns.renderers import RenderBatch, Renderer

Method = Literal["icp", "fgr", "ransac"]
METHODS: tuple[str, ...] = ("icp", "fgr", "ransac")
"""The baselines, in the paper's row order (ICP, FGR, FPFH + RANSAC)."""


class BaselineError(ValueError):
    """Input a point-cloud baseline cannot use (empty cloud, bad scale, missing depth...); one-line message."""


OPEN3D_MISSING = 'the point-cloud baselines need Open3D: pip install "nerfuser_ns[baselines]"'


def _o3d():
    """Open3D, imported here, not at the top: it is the optional ``baselines`` extra (:class:`BaselineError` with
    :data:`OPEN3D_MISSING` where it is not installed)."""
    try:
        import open3d as o3d
    except ImportError:
        raise BaselineError(OPEN3D_MISSING) from None
    return o3d


def open3d_version() -> str:
    """The installed Open3D's version, checked before long work that needs it."""
    return _o3d().__version__


# ---------------------------------------------------------------------------------------------------------------------
# Settings


@dataclass
class PointCloudConfig:
    """How depth renders become a point cloud in the renderer's frame."""

    min_accumulation: float = 0.5
    """Pixels whose accumulation (opacity) is below this are background and dropped (nerfstudio's exporter: 0.5)."""
    max_depth: float | None = None
    """Drop pixels farther than this along the ray, in the frame's units (None: no limit)."""
    crop_half_size: float | None = None
    """Keep only points inside the cube ``[-c, c]^3`` of the frame (None: no crop). nerfacto models its scene box
    ``[-1, 1]^3`` at full resolution and contracts everything beyond it; its depth out there is poor (demo NeRF
    ``capture_b``: 85% of pixels within 5% of the true depth inside the box, 42% outside), and far floaters would
    set the extent (hence the voxel size) of an uncropped cloud."""
    voxel_size: float | None = None
    """Voxel size of the downsampling, in the frame's units (None: ``voxel_fraction`` times the cloud's extent)."""
    voxel_fraction: float = 0.005
    """Default voxel size as a fraction of the cloud's robust extent (see ``extent_quantile``)."""
    extent_quantile: float = 0.02
    """The extent is the diagonal of the box between the ``q`` and ``1 - q`` quantiles of the coordinates (robust to
    NeRF floaters)."""
    normal_radius_factor: float = 2.0
    """Normals are fitted to the neighbours within this many voxels (at most ``normal_max_nn`` of them)."""
    normal_max_nn: int = 30
    """Most neighbours used for a normal."""
    remove_outliers: bool = True
    """Statistical outlier removal after downsampling (as nerfstudio's point-cloud exporter does)."""
    outlier_neighbors: int = 20
    """Neighbours of the statistical outlier test."""
    outlier_std_ratio: float = 10.0
    """Points whose mean neighbour distance is more than this many standard deviations above the mean are dropped
    (nerfstudio's exporter default)."""
    min_points: int = 100
    """Fewer valid pixels than this is an error (nothing to register)."""

    def validate(self) -> None:
        """One-line :class:`BaselineError` for settings that cannot work."""
        positive_or_none = {"max_depth": self.max_depth, "crop_half_size": self.crop_half_size,
                            "voxel_size": self.voxel_size}  # fmt: skip
        for name, value in positive_or_none.items():
            if value is not None and not (np.isfinite(value) and value > 0):
                raise BaselineError(f"{name} must be positive (or None), got {value}")
        checks = [
            (0 <= self.min_accumulation <= 1, f"min_accumulation must be in [0, 1], got {self.min_accumulation}"),
            (0 < self.voxel_fraction < 1, f"voxel_fraction must be in (0, 1), got {self.voxel_fraction}"),
            (0 <= self.extent_quantile < 0.5, f"extent_quantile must be in [0, 0.5), got {self.extent_quantile}"),
            (self.normal_radius_factor > 0 and self.outlier_std_ratio > 0, "radius factor and std ratio must be > 0"),
            (min(self.normal_max_nn, self.outlier_neighbors, self.min_points) >= 1, "counts must be >= 1"),
        ]
        for ok, message in checks:
            if not ok:
                raise BaselineError(message)


@dataclass
class PCRConfig(InstantiateConfig):
    """One point-cloud registration baseline and its settings (``config.setup()`` builds a :class:`PCRBaseline`).

    Distances are in the target cloud's units (the source is pre-scaled by the known relative scale), most of them
    as multiples of the voxel size, as in Open3D's registration tutorials.
    """

    _target: type = field(default_factory=lambda: PCRBaseline)
    """The class :meth:`setup` instantiates."""
    method: Method = "ransac"
    """icp: point-to-plane ICP from the identity; fgr: Fast Global Registration on FPFH matches; ransac: FPFH matches
    with RANSAC."""
    voxel_size: float | None = None
    """Voxel size both clouds are downsampled to before normals and features (None: ``voxel_fraction`` times the
    target cloud's robust extent)."""
    voxel_fraction: float = 0.02
    """Default voxel size as a fraction of the target cloud's robust extent."""
    extent_quantile: float = 0.02
    """Quantile of the robust extent (see :attr:`PointCloudConfig.extent_quantile`)."""
    normal_radius_factor: float = 2.0
    """Normal estimation radius, in voxels."""
    normal_max_nn: int = 30
    """Most neighbours for a normal."""
    feature_radius_factor: float = 5.0
    """FPFH radius, in voxels."""
    feature_max_nn: int = 100
    """Most neighbours for an FPFH feature."""
    icp_distance_factor: float = 2.0
    """ICP: maximum correspondence distance, in voxels."""
    icp_max_iterations: int = 100
    """ICP: iterations."""
    fgr_distance_factor: float = 0.5
    """FGR: maximum correspondence distance, in voxels (absolute scale)."""
    fgr_iterations: int = 64
    """FGR: iterations."""
    fgr_max_tuples: int = 1000
    """FGR: most tuples kept by the tuple test."""
    ransac_distance_factor: float = 1.5
    """RANSAC: inlier distance, in voxels."""
    ransac_n: int = 3
    """RANSAC: correspondences per hypothesis."""
    ransac_edge_length: float = 0.9
    """RANSAC: edge-length checker similarity (0 disables the checker)."""
    ransac_mutual_filter: bool = False
    """RANSAC: keep only mutual nearest feature matches."""
    ransac_max_iterations: int = 100_000
    """RANSAC: most hypotheses."""
    ransac_confidence: float = 0.999
    """RANSAC: stop when a solution is found with this confidence."""
    refine_with_icp: bool = False
    """fgr / ransac: refine the global estimate with point-to-plane ICP (Open3D's tutorial pipeline). Off by default:
    the paper lists the methods alone (it does not mention a refinement)."""
    refine_distance_factor: float = 1.0
    """Refinement ICP: maximum correspondence distance, in voxels (iterations: ``icp_max_iterations``)."""
    eval_distance_factor: float = 1.5
    """Fitness / inlier RMSE of the result are measured with this correspondence distance, in voxels."""
    seed: int = 0
    """Seed of Open3D's random generator (RANSAC, FGR), set before each registration."""
    min_points: int = 10
    """Each downsampled cloud needs at least this many points."""

    def validate(self) -> None:
        """One-line :class:`BaselineError` for settings that cannot work."""
        checks = [
            (self.method in METHODS, f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}"),
            (self.voxel_size is None or (np.isfinite(self.voxel_size) and self.voxel_size > 0),
             f"voxel_size must be positive, got {self.voxel_size}"),
            (0 < self.voxel_fraction < 1, f"voxel_fraction must be in (0, 1), got {self.voxel_fraction}"),
            (0 <= self.extent_quantile < 0.5, f"extent_quantile must be in [0, 0.5), got {self.extent_quantile}"),
            (min(self.normal_radius_factor, self.feature_radius_factor, self.icp_distance_factor,
                 self.fgr_distance_factor, self.ransac_distance_factor, self.eval_distance_factor,
                 self.refine_distance_factor) > 0,
             "radius and distance factors must be positive"),
            (min(self.normal_max_nn, self.feature_max_nn, self.icp_max_iterations, self.fgr_iterations,
                 self.fgr_max_tuples, self.ransac_max_iterations) >= 1, "neighbour and iteration counts must be >= 1"),
            (self.ransac_n >= 3, f"ransac_n must be >= 3, got {self.ransac_n}"),
            (0 < self.ransac_confidence < 1, f"ransac_confidence must be in (0, 1), got {self.ransac_confidence}"),
            (0 <= self.ransac_edge_length < 1, f"ransac_edge_length must be in [0, 1), got {self.ransac_edge_length}"),
            (self.min_points >= 3, f"min_points must be >= 3, got {self.min_points}"),
        ]  # fmt: skip
        for ok, message in checks:
            if not ok:
                raise BaselineError(message)


# ---------------------------------------------------------------------------------------------------------------------
# Point clouds from depth renders


def render_rgbd(renderer: Renderer, c2w: Float[np.ndarray, "n 4 4"], intrinsics: Intrinsics) -> RenderBatch:
    """Render colour, accumulation and depth at ``c2w`` (the renderer's own frame) through its ``depth=True`` option."""
    if "depth" not in inspect.signature(renderer.render).parameters:
        raise BaselineError(f"{renderer.name}: its render() has no depth option, so no point cloud can be extracted")
    batch = renderer.render(c2w, intrinsics, depth=True)
    if batch.depth is None:
        raise BaselineError(f"{renderer.name}: rendered no depth")
    n, h, w = len(c2w), intrinsics.height, intrinsics.width
    if batch.depth.shape != (n, h, w) or batch.rgb.shape != (n, h, w, 3):
        raise BaselineError(
            f"{renderer.name}: rendered rgb {batch.rgb.shape} and depth {batch.depth.shape}, expected {(n, h, w)}"
        )
    return batch


def pixel_rays(
    c2w: Float[np.ndarray, "n r 4"], intrinsics: Intrinsics
) -> tuple[Float[np.ndarray, "n h w 3"], Float[np.ndarray, "n h w 3"]]:
    """Origins and unit directions of every pixel-centre ray (nerfstudio's convention, :func:`cameras.camera_rays`)."""
    c2w = sim3.to_homogeneous(np.asarray(c2w, dtype=np.float64))
    if c2w.ndim == 2:
        c2w = c2w[None]
    k = intrinsics
    origins, directions = [], []
    for pose in c2w:
        o, d = camera_rays(pose, k)
        origins.append(o[:, :, 0].numpy())
        directions.append(d[:, :, 0].numpy())
    return np.stack(origins), np.stack(directions)


def backproject(
    depth: Float[np.ndarray, "n h w"],
    c2w: Float[np.ndarray, "n r 4"],
    intrinsics: Intrinsics,
    depth_kind: Literal["ray", "z"] = "ray",
) -> tuple[Float[np.ndarray, "n h w 3"], Float[np.ndarray, "n h w 3"]]:
    """3D points ``o + depth * d`` of every pixel (frame of ``c2w``) and the unit ray directions ``d``.

    ``depth_kind="ray"``: distance along the unit ray (nerfstudio's ``depth``); ``"z"``: distance along the camera's
    viewing axis (-z), converted with the cosine between each ray and that axis.
    """
    depth = np.asarray(depth, dtype=np.float64)
    c2w = sim3.to_homogeneous(np.asarray(c2w, dtype=np.float64))
    if c2w.ndim == 2:
        c2w = c2w[None]
    if depth.ndim == 2:
        depth = depth[None]
    if depth.shape != (len(c2w), intrinsics.height, intrinsics.width):
        raise BaselineError(
            f"depth of shape {depth.shape} does not match {len(c2w)} poses at {intrinsics.width}x{intrinsics.height}"
        )
    if depth_kind not in ("ray", "z"):
        raise BaselineError(f"unknown depth_kind {depth_kind!r}; use 'ray' or 'z'")
    origins, directions = pixel_rays(c2w, intrinsics)
    if depth_kind == "z":
        forward = -c2w[:, None, None, :3, 2]  # the camera looks along its -z axis
        depth = depth / np.sum(directions * forward, axis=-1)
    return origins + depth[..., None] * directions, directions


def robust_extent(points: Float[np.ndarray, "m 3"], quantile: float = 0.02) -> float:
    """Diagonal of the box between the ``quantile`` and ``1 - quantile`` coordinate quantiles."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        raise BaselineError("the point cloud is empty: its extent is undefined")
    lo, hi = np.quantile(points, [quantile, 1.0 - quantile], axis=0)
    return float(np.linalg.norm(hi - lo))


def _estimate_normals(cloud: o3d.geometry.PointCloud, radius: float, max_nn: int) -> None:
    """Fit normals; when the cloud has normals already, the new ones are oriented like them (Open3D's rule)."""
    o3d = _o3d()
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))


def point_cloud_from_rgbd(
    rgb: Float[np.ndarray, "n h w 3"],
    depth: Float[np.ndarray, "n h w"],
    c2w: Float[np.ndarray, "n r 4"],
    intrinsics: Intrinsics,
    accumulation: Float[np.ndarray, "n h w"] | None = None,
    config: PointCloudConfig | None = None,
    depth_kind: Literal["ray", "z"] = "ray",
) -> o3d.geometry.PointCloud:
    """Fuse RGB-D views into one coloured, voxel-downsampled point cloud with normals, in the frame of ``c2w``.

    Pixels are kept where the depth is finite, positive (at most ``config.max_depth``, the point inside
    ``config.crop_half_size``) and the accumulation is at least ``config.min_accumulation``. Normals are fitted to
    the downsampled cloud and oriented towards the cameras that saw the points (each point starts with the direction
    back to its camera; voxels average them).
    """
    o3d = _o3d()
    config = config or PointCloudConfig()
    config.validate()
    rgb = np.asarray(rgb, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    if rgb.shape[:-1] != depth.shape or rgb.shape[-1] != 3:
        raise BaselineError(f"rgb of shape {rgb.shape} does not match depth of shape {depth.shape}")
    points, directions = backproject(depth, c2w, intrinsics, depth_kind)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0) & np.isfinite(points).all(axis=-1)
        if config.max_depth is not None:
            valid &= depth <= config.max_depth
        if config.crop_half_size is not None:
            valid &= np.abs(points).max(axis=-1) <= config.crop_half_size
        if accumulation is not None:
            acc = np.asarray(accumulation, dtype=np.float64)
            if acc.shape != depth.shape:
                raise BaselineError(f"accumulation of shape {acc.shape} does not match depth of shape {depth.shape}")
            valid &= acc >= config.min_accumulation
    num_valid = int(valid.sum())
    if num_valid < config.min_points:
        raise BaselineError(
            f"only {num_valid} pixels have a valid depth (need {config.min_points}): the views see nothing; aim them "
            "at the content or lower min_accumulation"
        )
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[valid]))
    cloud.colors = o3d.utility.Vector3dVector(np.nan_to_num(rgb[valid]).clip(0.0, 1.0))
    cloud.normals = o3d.utility.Vector3dVector(-directions[valid])  # towards the camera: orients the fitted normals
    voxel = config.voxel_size or config.voxel_fraction * robust_extent(points[valid], config.extent_quantile)
    if not (np.isfinite(voxel) and voxel > 0):
        raise BaselineError("all valid points coincide: the point cloud has no extent")
    cloud = cloud.voxel_down_sample(voxel)
    if config.remove_outliers and len(cloud.points) > config.outlier_neighbors:
        cloud, _ = cloud.remove_statistical_outlier(config.outlier_neighbors, config.outlier_std_ratio)
    _estimate_normals(cloud, config.normal_radius_factor * voxel, config.normal_max_nn)
    return cloud


def extract_point_cloud(
    renderer: Renderer,
    c2w: Float[np.ndarray, "n 4 4"],
    intrinsics: Intrinsics,
    config: PointCloudConfig | None = None,
    batch_size: int = 8,
) -> o3d.geometry.PointCloud:
    """Render ``c2w`` (in the renderer's frame) with depth and fuse the views (:func:`point_cloud_from_rgbd`).

    The cloud is in the renderer's frame: for a nerfstudio run, the NeRF frame (``data_to_nerf`` of its dataset).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or len(c2w) == 0 or not np.isfinite(c2w).all():
        raise BaselineError(f"{renderer.name}: need a non-empty stack of finite poses [N, 4, 4], got {c2w.shape}")
    batches = [render_rgbd(renderer, c2w[i : i + batch_size], intrinsics) for i in range(0, len(c2w), batch_size)]
    rgb = np.concatenate([b.rgb for b in batches])
    depth = np.concatenate([b.depth for b in batches])
    accs = [b.accumulation for b in batches]
    accumulation = None if any(a is None for a in accs) else np.concatenate(accs)
    try:
        return point_cloud_from_rgbd(rgb, depth, c2w, intrinsics, accumulation, config)
    except BaselineError as e:
        raise BaselineError(f"{renderer.name}: {e}") from None


def cloud_points(cloud: o3d.geometry.PointCloud) -> Float[np.ndarray, "m 3"]:
    """The points of a cloud as a float64 array."""
    return np.asarray(cloud.points, dtype=np.float64)


# ---------------------------------------------------------------------------------------------------------------------
# Registration


@dataclass(frozen=True)
class PCRResult:
    """A point-cloud baseline's SIM(3) estimate source -> target, with diagnostics."""

    T: Float[np.ndarray, "4 4"]
    """``T_source->target = G @ S``: the rigid solution composed with the given scale."""
    method: str
    """``icp``, ``fgr`` or ``ransac``, with ``+icp`` when refined by ICP."""
    scale: float
    """The given (ground-truth) relative scale: one source unit is ``scale`` target units."""
    voxel_size: float
    """Voxel size used, in target units."""
    fitness: float
    """Fraction of downsampled source points with a target point within ``eval_distance_factor`` voxels."""
    inlier_rmse: float
    """RMS distance of those points, in target units."""
    num_source_points: int
    """Downsampled source points."""
    num_target_points: int
    """Downsampled target points."""
    seconds: float
    """Time of downsampling, features and registration."""

    def errors(self, T_true: Float[np.ndarray, "4 4"]) -> sim3.Sim3Errors:
        """The paper's errors against the ground-truth ``T_source->target`` (:func:`nerfuser_ns.sim3.sim3_errors`)."""
        return sim3.sim3_errors(self.T, T_true)


def _check_cloud(cloud, what: str, min_points: int) -> None:
    o3d = _o3d()
    if not isinstance(cloud, o3d.geometry.PointCloud):
        raise BaselineError(f"the {what} must be an open3d.geometry.PointCloud, got {type(cloud).__name__}")
    n = len(cloud.points)
    if n == 0:
        raise BaselineError(f"the {what} point cloud is empty")
    if n < min_points:
        raise BaselineError(f"the {what} point cloud has {n} points, need at least {min_points}")
    if not np.isfinite(cloud_points(cloud)).all():
        raise BaselineError(f"the {what} point cloud contains NaN or inf coordinates")


class PCRBaseline:
    """A point-cloud registration baseline (see :class:`PCRConfig`)."""

    def __init__(self, config: PCRConfig):
        config.validate()
        self.config = config

    def voxel_size_for(self, target: o3d.geometry.PointCloud) -> float:
        """``config.voxel_size``, or ``voxel_fraction`` times the target's robust extent."""
        c = self.config
        if c.voxel_size is not None:
            return float(c.voxel_size)
        voxel = c.voxel_fraction * robust_extent(cloud_points(target), c.extent_quantile)
        if not voxel > 0:
            raise BaselineError("the target point cloud has no extent (all points coincide)")
        return voxel

    def _prepare(self, cloud: o3d.geometry.PointCloud, voxel: float, what: str):
        """Downsample, fit normals (kept oriented like the input's, if any) and compute FPFH features."""
        o3d = _o3d()
        c = self.config
        down = cloud.voxel_down_sample(voxel)
        if len(down.points) < c.min_points:
            raise BaselineError(
                f"the {what} point cloud has {len(down.points)} points after downsampling to voxels of {voxel:.4g} "
                f"(need {c.min_points}); pass a smaller voxel size"
            )
        _estimate_normals(down, c.normal_radius_factor * voxel, c.normal_max_nn)
        if c.method == "icp":
            return down, None
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=c.feature_radius_factor * voxel, max_nn=c.feature_max_nn)
        )
        return down, fpfh

    def register(
        self, source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, scale: float = 1.0
    ) -> PCRResult:
        """Estimate ``T_source->target`` given the relative ``scale`` (source units -> target units).

        The source is scaled about its frame's origin by ``scale``, the method solves the rigid ``G`` on the
        downsampled clouds, and the result is ``T = G @ diag(scale, scale, scale, 1)``.
        """
        o3d = _o3d()
        reg = o3d.pipelines.registration
        c = self.config
        if not (np.isfinite(scale) and scale > 0):
            raise BaselineError(f"the relative scale must be positive and finite, got {scale}")
        _check_cloud(source, "source", c.min_points)
        _check_cloud(target, "target", c.min_points)
        start = time.perf_counter()
        S = sim3.scale_matrix(float(scale))
        scaled = o3d.geometry.PointCloud(source)  # a copy: the caller's cloud is left alone
        scaled.transform(S)  # scales points; normals keep their direction
        voxel = self.voxel_size_for(target)
        src, src_fpfh = self._prepare(scaled, voxel, "source")
        tgt, tgt_fpfh = self._prepare(target, voxel, "target")

        o3d.utility.random.seed(c.seed)
        if c.method == "icp":
            result = reg.registration_icp(
                src, tgt, c.icp_distance_factor * voxel, np.eye(4), reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=c.icp_max_iterations),
            )  # fmt: skip
        elif c.method == "fgr":
            option = reg.FastGlobalRegistrationOption(
                maximum_correspondence_distance=c.fgr_distance_factor * voxel, use_absolute_scale=True,
                iteration_number=c.fgr_iterations, maximum_tuple_count=c.fgr_max_tuples,
            )  # fmt: skip
            result = reg.registration_fgr_based_on_feature_matching(src, tgt, src_fpfh, tgt_fpfh, option)
        else:
            distance = c.ransac_distance_factor * voxel
            checkers = [reg.CorrespondenceCheckerBasedOnDistance(distance)]
            if c.ransac_edge_length > 0:
                checkers.insert(0, reg.CorrespondenceCheckerBasedOnEdgeLength(c.ransac_edge_length))
            result = reg.registration_ransac_based_on_feature_matching(
                src, tgt, src_fpfh, tgt_fpfh, c.ransac_mutual_filter, distance,
                reg.TransformationEstimationPointToPoint(False), c.ransac_n, checkers,
                reg.RANSACConvergenceCriteria(c.ransac_max_iterations, c.ransac_confidence),
            )  # fmt: skip
        G = np.asarray(result.transformation, dtype=np.float64)
        refined = c.refine_with_icp and c.method != "icp"
        if refined and np.isfinite(G).all():
            G = reg.registration_icp(
                src, tgt, c.refine_distance_factor * voxel, G, reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=c.icp_max_iterations),
            ).transformation  # fmt: skip
            G = np.asarray(G, dtype=np.float64)
        seconds = time.perf_counter() - start
        if np.isfinite(G).all():
            G = sim3.make_sim3(sim3.project_to_so3(G[:3, :3]), G[:3, 3])  # exact SE(3) (Open3D works in float64)
            quality = reg.evaluate_registration(src, tgt, c.eval_distance_factor * voxel, G)
            fitness, rmse = float(quality.fitness), float(quality.inlier_rmse)
        else:
            G, fitness, rmse = np.full((4, 4), np.nan), 0.0, float("nan")
        return PCRResult(
            T=G @ S, method=c.method + ("+icp" if refined else ""), scale=float(scale), voxel_size=float(voxel),
            fitness=fitness, inlier_rmse=rmse,
            num_source_points=len(src.points), num_target_points=len(tgt.points), seconds=seconds,
        )  # fmt: skip


def register_point_clouds(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    scale: float = 1.0,
    method: Method = "ransac",
    config: PCRConfig | None = None,
) -> PCRResult:
    """Run one baseline: ``T_source->target`` given the relative ``scale`` (``config``'s method is overridden)."""
    config = replace(config or PCRConfig(), method=method)
    return config.setup().register(source, target, scale)


def register_icp(source, target, scale: float = 1.0, config: PCRConfig | None = None) -> PCRResult:
    """Point-to-plane ICP from the identity (after scaling): see :func:`register_point_clouds`."""
    return register_point_clouds(source, target, scale, "icp", config)


def register_fgr(source, target, scale: float = 1.0, config: PCRConfig | None = None) -> PCRResult:
    """Fast Global Registration on FPFH matches: see :func:`register_point_clouds`."""
    return register_point_clouds(source, target, scale, "fgr", config)


def register_ransac(source, target, scale: float = 1.0, config: PCRConfig | None = None) -> PCRResult:
    """FPFH matches + RANSAC: see :func:`register_point_clouds`."""
    return register_point_clouds(source, target, scale, "ransac", config)
