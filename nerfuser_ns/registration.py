"""NeRF registration from re-rendering (NeRFuser, ICCV 2023, Sec. 3.2), for N >= 2 NeRFs.

Pipeline: sample camera poses in each NeRF's own frame (the paper's hemisphere, the run's training poses, or both)
-> render them (cached in a work folder keyed by the inputs) -> one SfM over the union of the renders with pycolmap
(SIFT, one shared PINHOLE camera with the exactly known intrinsics, kept fixed) -> per NeRF, recover the SIM(3)
NeRF -> SfM frame from the same cameras known in both frames (:mod:`nerfuser_ns.sim3`) -> express everything in a
reference NeRF's frame -> refine the SIM(3)s by bundle adjustment over each NeRF's rigid camera set
(:mod:`nerfuser_ns.bundle`) -> self-check by cross-rendering (SfM can merge unrelated content into one confident, wrong
model) -> one JSON registration file, written atomically.

Anything a renderer of the :class:`nerfuser_ns.renderers.Renderer` protocol can render registers: trained nerfstudio
runs (:class:`~nerfuser_ns.renderers.NerfstudioRenderer`) or ground-truth scenes for tests.

Conventions: SIM(3) ``T_AB`` maps points of A into B (``p_B = T_AB p_A``); poses are camera-to-world, OpenGL camera
axes (nerfstudio). Bad inputs raise :class:`RegistrationError` with a one-line message naming the NeRF.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

import numpy as np
from jaxtyping import Float
from PIL import Image
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from nerfuser_ns import bundle, sim3
from nerfuser_ns.cameras import Intrinsics, intrinsics_from_fov
from nerfuser_ns.files import atomic_path, write_text_atomic
from nerfuser_ns.renderers import Renderer
from nerfuser_ns.sampling import sample_hemisphere_poses

FORMAT_VERSION = 1
CONSOLE = Console(width=120)
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse
SUGGESTION = (
    "render more poses (--sampling.num-poses), a larger radius (--sampling.radius) or the run's training poses "
    "(--sampling.source training|both)"
)
DEFAULT_RENDER_SIZE = (400, 300, 60.0)
"""Render width, height and horizontal field of view when the reference run's training cameras are unknown."""


class RegistrationError(ValueError):
    """Registration cannot produce a trustworthy result; the one-line message names the NeRF and what to change."""


class RegistrationFailed(RegistrationError):
    """The self-check rejected the solution; ``record`` holds it (with the scores) for inspection."""

    def __init__(self, message: str, record: dict):
        super().__init__(message)
        self.record = record


# ---------------------------------------------------------------------------------------------------------------------
# Settings


@dataclass
class PoseSamplingConfig:
    """Which views of each NeRF to render, in the NeRF's own frame."""

    source: Literal["auto", "hemisphere", "training", "both"] = "auto"
    """Poses to render: the paper's hemisphere, the run's own training poses, or both. ``auto``: the training poses
    when every run's dataset is readable, then training + hemisphere, then the hemisphere alone if a choice does not
    register; the hemisphere when a dataset is gone. What was chosen, and why, is printed and recorded."""
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
        """The render intrinsics; unset values are :data:`DEFAULT_RENDER_SIZE`'s (:func:`resolve_sampling` sets them
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
class RegistrationConfig:
    """Registration from re-rendering: pose sampling, SfM, estimator and self-check settings."""

    sampling: PoseSamplingConfig = field(default_factory=PoseSamplingConfig)
    """Which views of each NeRF to render."""
    sfm: SfMConfig = field(default_factory=SfMConfig)
    """SfM settings."""
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


# ---------------------------------------------------------------------------------------------------------------------
# Small helpers


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.nan_to_num(rgb, nan=0.0).clip(0, 1) * 255.0).astype(np.uint8)


def _mat(T: np.ndarray) -> list:
    return np.round(np.asarray(T, dtype=np.float64), 12).tolist()


def _f(x) -> float | None:
    """JSON-safe float (NaN / inf become null)."""
    x = float(x)
    return x if math.isfinite(x) else None


def _progress(console: Console) -> Progress:
    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    return Progress(*cols, console=console, transient=True)


# ---------------------------------------------------------------------------------------------------------------------
# Pose sampling and rendering (cached)


def sample_poses(renderer: Renderer, cfg: PoseSamplingConfig) -> tuple[Float[np.ndarray, "n 4 4"], list[str]]:
    """Poses to render for one NeRF, in its own frame, and where each came from ("hemisphere" / "training")."""
    poses, sources = [], []
    if cfg.source in ("hemisphere", "both"):
        try:
            hemi = sample_hemisphere_poses(
                cfg.num_poses, cfg.radius, cfg.elevation_range_deg, cfg.center, jitter_deg=cfg.jitter_deg,
                seed=cfg.seed,
            )
        except ValueError as e:
            raise RegistrationError(f"bad pose sampling settings: {e}") from None
        poses.append(hemi)
        sources += ["hemisphere"] * len(hemi)
    if cfg.source in ("training", "both"):
        train = renderer.training_poses()
        if train is None or len(train) == 0:
            raise RegistrationError(f"{renderer.name}: has no training poses; use --sampling.source hemisphere")
        train = np.asarray(train, dtype=np.float64)
        if not np.isfinite(train).all():
            raise RegistrationError(f"{renderer.name}: its training poses contain NaN or inf")
        if len(train) > cfg.max_training_poses:
            if cfg.seed == 0:
                pick = np.round(np.linspace(0, len(train) - 1, cfg.max_training_poses)).astype(int)
            else:
                rng = np.random.default_rng(cfg.seed)
                pick = np.sort(rng.choice(len(train), cfg.max_training_poses, replace=False))
            train = train[pick]
        poses.append(train)
        sources += ["training"] * len(train)
    if cfg.source not in ("hemisphere", "training", "both"):
        raise RegistrationError(f"unknown pose source {cfg.source!r}; use hemisphere, training or both")
    return np.concatenate(poses), sources


@dataclass
class ViewSet:
    """One NeRF's rendered views, as stored in its render folder."""

    name: str
    folder: Path
    """``<work_dir>/renders/<key>``: images/*.png, accumulation.npz, poses.json."""
    c2w: Float[np.ndarray, "n 4 4"]
    """Poses in the NeRF's own frame."""
    sources: list[str]
    mean_accumulation: Float[np.ndarray, " n"]
    kept: np.ndarray
    """Views that go into the SfM (enough accumulation)."""
    reused: bool = False
    """Whether the renders came from the cache."""
    render_seconds: float | None = 0.0
    """Seconds the renders took when they were made (None for cache folders written before this was stored)."""

    @property
    def image_names(self) -> list[str]:
        """Names relative to ``<work_dir>/renders`` (what the SfM database stores)."""
        return [f"{self.folder.name}/images/{k:05d}.png" for k in range(len(self.c2w))]

    def load_rgb(self, k: int) -> np.ndarray:
        return np.asarray(Image.open(self.folder / "images" / f"{k:05d}.png").convert("RGB"), dtype=np.float32) / 255

    def load_accumulation(self) -> np.ndarray:
        with np.load(self.folder / "accumulation.npz") as z:
            return z["accumulation"].astype(np.float32)


def render_key(renderer: Renderer, cfg: PoseSamplingConfig) -> str:
    """Hash of everything the renders depend on: the renderer's own key (weights, mtime) and the sampling settings."""
    return _hash({"renderer": renderer.cache_key(), "sampling": asdict(cfg), "version": FORMAT_VERSION})[:16]


def _damage(views: ViewSet) -> str | None:
    """What is wrong with a cached render folder (a missing or truncated image, unreadable accumulation), or None."""
    try:
        if views.load_accumulation().shape[0] != len(views.c2w):
            return "accumulation.npz does not match poses.json"
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        return f"accumulation.npz: {type(e).__name__}"
    for k in range(len(views.c2w)):
        try:
            with Image.open(views.folder / "images" / f"{k:05d}.png") as image:
                image.load()  # decodes: a truncated file fails here
        except (OSError, ValueError) as e:
            return f"images/{k:05d}.png: {type(e).__name__}"
    return None


def render_views_cached(
    renderer: Renderer, cfg: PoseSamplingConfig, renders_root: Path, console: Console = CONSOLE
) -> ViewSet:
    """Sample poses and render them into ``renders_root/<key>``, or reuse the folder a previous run left there."""
    key = render_key(renderer, cfg)
    folder = renders_root / key
    meta_path = folder / "poses.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            views = meta["views"]
            cached = ViewSet(
                renderer.name, folder, np.array([v["c2w"] for v in views], dtype=np.float64),
                [v["source"] for v in views], np.array([v["mean_accumulation"] for v in views]),
                np.array([v["kept"] for v in views], dtype=bool), reused=True,
                render_seconds=meta.get("render_seconds"),
            )
            damage = _damage(cached)
        except (KeyError, ValueError, TypeError) as e:
            damage = f"unreadable poses.json ({type(e).__name__})"
        if damage is None:
            return cached
        console.print(f"[yellow]{renderer.name}: cached renders in {folder} are damaged ({damage}); rendering again[/]")
        shutil.rmtree(folder, ignore_errors=True)

    c2w, sources = sample_poses(renderer, cfg)
    intr = cfg.intrinsics()
    renders_root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{key}.tmp-", dir=renders_root))
    start = time.perf_counter()
    try:
        (tmp / "images").mkdir()
        accs = np.zeros((len(c2w), intr.height, intr.width), dtype=np.float16)
        bad = []
        with _progress(console) as bar:
            task = bar.add_task(f"rendering {renderer.name}", total=len(c2w))
            for k in range(len(c2w)):
                out = renderer.render(c2w[k : k + 1], intr)
                rgb = np.asarray(out.rgb[0], dtype=np.float32)
                if rgb.shape != (intr.height, intr.width, 3):
                    raise RegistrationError(
                        f"{renderer.name}: rendered an image of shape {rgb.shape}, expected "
                        f"{(intr.height, intr.width, 3)}"
                    )
                acc = np.ones(rgb.shape[:2], np.float32) if out.accumulation is None else out.accumulation[0]
                if not (np.isfinite(rgb).all() and np.isfinite(acc).all()):
                    bad.append(k)
                Image.fromarray(_to_uint8(rgb)).save(tmp / "images" / f"{k:05d}.png", compress_level=1)
                accs[k] = np.nan_to_num(acc, nan=0.0).clip(0, 1)
                bar.advance(task)
        if bad:
            raise RegistrationError(
                f"{renderer.name}: rendered NaN or inf in {len(bad)} of {len(c2w)} views (a diverged run?); "
                "check the run or pass another checkpoint"
            )
        np.savez_compressed(tmp / "accumulation.npz", accumulation=accs)
        mean_acc = accs.astype(np.float32).mean(axis=(1, 2))
        kept = mean_acc >= cfg.min_view_accumulation
        meta = {
            "renderer": renderer.name,
            "render_seconds": time.perf_counter() - start,
            "cache_key": renderer.cache_key(),
            "sampling": asdict(cfg),
            "intrinsics": asdict(intr),
            "views": [
                {"file": f"images/{k:05d}.png", "c2w": _mat(c2w[k]), "source": sources[k],
                 "mean_accumulation": float(mean_acc[k]), "kept": bool(kept[k])}
                for k in range(len(c2w))
            ],
        }
        (tmp / "poses.json").write_text(json.dumps(meta, indent=1) + "\n")
        os.chmod(tmp, 0o755)
        if folder.exists():  # a damaged entry
            shutil.rmtree(folder)
        os.rename(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    # The poses as stored, so a first run and a rerun on the cache compute from identical numbers.
    stored = np.array([v["c2w"] for v in meta["views"]], dtype=np.float64)
    return ViewSet(renderer.name, folder, stored, sources, mean_acc, kept, False, meta["render_seconds"])


# ---------------------------------------------------------------------------------------------------------------------
# SfM


@dataclass
class SfMResult:
    """What registration needs from the SfM run (JSON-cached beside its database)."""

    c2w: dict[str, list]
    """Per registered image of the largest model: camera-to-world in the SfM frame C, OpenGL axes."""
    model_counts: list[list[int]]
    """Per model (largest first): registered views per NeRF."""
    covisible: dict[str, list[int]]
    """Per registered image: number of its 3D points also observed by each NeRF's images."""
    num_points3D: int
    mean_reprojection_error: float
    num_images: int
    matching: str
    timings: dict[str, float] = field(default_factory=dict)
    reused: bool = False
    folder: str = ""
    """The SfM's work folder (database, ``sparse/`` models, ``observations.npz``)."""


def _cheap_pairs(views: Sequence[ViewSet], names: list[list[str]], cfg: SfMConfig) -> list[tuple[str, str]]:
    """Image pairs linear in the number of images: own-NeRF nearest views (by known pose) + a spread cross subset."""
    pairs = set()
    for i, vs in enumerate(views):
        idx = np.flatnonzero(vs.kept)
        c = vs.c2w[idx, :3, 3]
        d = vs.c2w[idx, :3, 2]  # viewing axis (back): close in position and direction = likely overlap
        dist = np.linalg.norm(c[:, None] - c[None], axis=-1) / max(np.linalg.norm(c - c.mean(0), axis=-1).mean(), 1e-9)
        dist = dist + (1 - d @ d.T)
        for a in range(len(idx)):
            for b in np.argsort(dist[a])[1 : cfg.own_neighbors + 1]:
                pairs.add(tuple(sorted((names[i][idx[a]], names[i][idx[b]]))))
        for j, vj in enumerate(views):
            if j == i:
                continue
            jdx = np.flatnonzero(vj.kept)
            sub = jdx[np.unique(np.round(np.linspace(0, len(jdx) - 1, min(cfg.cross_views, len(jdx)))).astype(int))]
            for a in idx:
                for b in sub:
                    pairs.add(tuple(sorted((names[i][a], names[j][b]))))
    return sorted(pairs)


def run_sfm(
    views: Sequence[ViewSet], intrinsics: Intrinsics, cfg: SfMConfig, work_dir: Path, console: Console = CONSOLE
) -> SfMResult:
    """SIFT + matching + incremental mapping over the kept views of all NeRFs, intrinsics known and fixed.

    Cached: a second call with the same renders and settings reads ``result.json`` back.
    """
    import pycolmap  # lazy: heavy

    renders_root = views[0].folder.parent
    names = [vs.image_names for vs in views]
    used = [n for vs, ns in zip(views, names, strict=True) for n, k in zip(ns, vs.kept, strict=True) if k]
    nerf_of = {n: i for i, ns in enumerate(names) for n in ns}
    key = _hash({"images": used, "sfm": asdict(cfg), "intrinsics": asdict(intrinsics), "colmap": pycolmap.__version__})
    folder = work_dir / "sfm" / key[:16]
    result_path = folder / "result.json"
    if result_path.is_file():
        try:
            return SfMResult(**{**json.loads(result_path.read_text()), "reused": True, "folder": str(folder)})
        except (TypeError, ValueError):
            pass
    if folder.exists():
        shutil.rmtree(folder)
    (folder / "sparse").mkdir(parents=True)
    db = folder / "database.db"
    timings = {}
    device = pycolmap.Device.cpu
    pycolmap.logging.minloglevel = 0 if cfg.verbose else 2  # glog: 0 INFO, 1 WARNING, 2 ERROR

    with console.status(f"SfM: extracting SIFT features from {len(used)} renders"):
        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        k = intrinsics
        reader.camera_params = f"{k.fx!r},{k.fy!r},{k.cx!r},{k.cy!r}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = cfg.num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = cfg.max_num_features
        pycolmap.extract_features(
            db, renders_root, image_names=used, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
            extraction_options=extraction, device=device,
        )
        timings["features"] = time.perf_counter() - t0

    matching_opts = pycolmap.FeatureMatchingOptions()
    matching_opts.num_threads = cfg.num_threads
    matching_opts.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed
    verification.min_num_inliers = cfg.min_num_inliers
    exhaustive = len(used) <= cfg.exhaustive_max_images
    with console.status(f"SfM: matching {len(used)} renders ({'exhaustive' if exhaustive else 'pose-guided pairs'})"):
        t0 = time.perf_counter()
        if exhaustive:
            pycolmap.match_exhaustive(db, matching_options=matching_opts, verification_options=verification,
                                      device=device)
        else:
            pair_file = folder / "pairs.txt"
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in _cheap_pairs(views, names, cfg)))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(db, matching_options=matching_opts, pairing_options=pairing,
                                       verification_options=verification, device=device)
        timings["matching"] = time.perf_counter() - t0

    with console.status("SfM: incremental mapping (intrinsics fixed)"):
        t0 = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        # The renders' intrinsics are exact: never refine them.
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
        options.min_model_size = cfg.min_model_size
        options.min_num_matches = cfg.min_num_matches
        options.mapper.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
        options.mapper.abs_pose_min_inlier_ratio = cfg.abs_pose_min_inlier_ratio
        options.num_threads = cfg.num_threads
        options.random_seed = cfg.seed
        models = pycolmap.incremental_mapping(db, renders_root, folder / "sparse", options)
        timings["mapping"] = time.perf_counter() - t0

    recons = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    model_counts = []
    for rec in recons:
        counts = [0] * len(views)
        for image_id in rec.reg_image_ids():
            counts[nerf_of[rec.image(image_id).name]] += 1
        model_counts.append(counts)
    c2w, covisible, num_points, reproj = {}, {}, 0, float("nan")
    if recons:
        rec = recons[0]
        id_to_nerf = {}
        for image_id in rec.reg_image_ids():
            image = rec.image(image_id)
            cam_from_world = sim3.to_homogeneous(np.asarray(image.cam_from_world().matrix(), dtype=np.float64))
            # COLMAP cameras use OpenCV axes (looking +z, y down); nerfstudio's are OpenGL: flip y and z.
            c2w[image.name] = _mat(sim3.invert_sim3(cam_from_world) @ OPENGL_FROM_OPENCV)
            id_to_nerf[image_id] = nerf_of[image.name]
            covisible[image.name] = [0] * len(views)
        # Per image, how many of its 3D points the other NeRFs' images see too (overlap, for the self-check).
        for point in rec.points3D.values():
            ids = [el.image_id for el in point.track.elements]
            nerfs = {id_to_nerf[i] for i in ids if i in id_to_nerf}
            if len(nerfs) < 2:
                continue
            for i in set(ids):
                if i in id_to_nerf:
                    row = covisible[rec.image(i).name]
                    for j in nerfs:
                        row[j] += 1
        num_points = rec.num_points3D()
        reproj = float(rec.compute_mean_reprojection_error())
    result = SfMResult(c2w, model_counts, covisible, num_points, reproj, len(used),
                       "exhaustive" if exhaustive else "pose-guided pairs", timings, folder=str(folder))
    if recons:
        _save_observations(recons[0], folder / "observations.npz")
    write_text_atomic(result_path, json.dumps(asdict(result)) + "\n")
    return result


def _save_observations(rec, path: Path) -> None:
    """The feature tracks of an SfM model as flat arrays (what the rigid-set bundle adjustment needs)."""
    reg = list(rec.reg_image_ids())
    row = {image_id: n for n, image_id in enumerate(reg)}
    names = [rec.image(i).name for i in reg]
    xyz, cam, point, xy = [], [], [], []
    for p_idx, p in enumerate(rec.points3D.values()):
        xyz.append(p.xyz)
        for el in p.track.elements:
            cam.append(row[el.image_id])
            point.append(p_idx)
            xy.append(rec.image(el.image_id).points2D[el.point2D_idx].xy)
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp, names=np.array(names), points=np.asarray(xyz, np.float64).reshape(-1, 3),
            obs_cam=np.asarray(cam, np.int32), obs_point=np.asarray(point, np.int32),
            obs_xy=np.asarray(xy, np.float64).reshape(-1, 2),
        )


def load_observations(sfm: SfMResult) -> dict[str, np.ndarray]:
    """Feature tracks of the largest SfM model (SfM frame): ``names``, ``points``, ``obs_cam``, ``obs_point``,
    ``obs_xy``. Work folders written before these were stored get them from their ``sparse/`` models."""
    folder = Path(sfm.folder)
    path = folder / "observations.npz"
    if not path.is_file():
        import pycolmap

        models = [pycolmap.Reconstruction(str(d)) for d in sorted((folder / "sparse").glob("*")) if d.is_dir()]
        if not models:
            raise RegistrationError(f"{folder}: no SfM model to refine on; delete the folder to rerun the SfM")
        _save_observations(max(models, key=lambda r: r.num_reg_images()), path)
    try:
        with np.load(path) as z:
            return {key: z[key] for key in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise RegistrationError(
            f"{path}: damaged SfM cache ({type(e).__name__}); delete {folder} and run again (the SfM is redone)"
        ) from None


def refine_transforms(
    views: Sequence[ViewSet], sfm: SfMResult, T_to_C: Float[np.ndarray, "k 4 4"], ref: int, intr: Intrinsics,
    loss_scale_px: float,
) -> tuple[np.ndarray, dict]:
    """Rigid-set bundle adjustment (:func:`nerfuser_ns.bundle.refine_sim3_bundle`) from the estimator's transforms.

    Returns the refined NeRF -> reference transforms and a summary; keeps the initial ones (``used`` False) when the
    refinement does not lower the reprojection error or no point is seen by two NeRFs.
    """
    T0 = sim3.to_reference_frame(T_to_C, ref)
    obs = load_observations(sfm)
    pose = {n: (i, vs.c2w[k]) for i, vs in enumerate(views) for k, n in enumerate(vs.image_names)}
    names = [str(n) for n in obs["names"]]
    if any(n not in pose for n in names):
        raise RegistrationError(f"{sfm.folder}: SfM model images do not match the renders; delete the folder")
    cam_nerf = np.array([pose[n][0] for n in names], dtype=int)
    cam_c2w = np.stack([pose[n][1] for n in names])
    # Only points seen by two NeRFs tie the transforms together.
    pairs = np.unique(np.stack([obs["obs_point"], cam_nerf[obs["obs_cam"]]], 1), axis=0)
    linked = np.bincount(pairs[:, 0], minlength=len(obs["points"])) >= 2
    keep = linked[obs["obs_point"]]
    summary = {"used": False, "points": int(linked.sum()), "observations": int(keep.sum())}
    if keep.sum() == 0:
        return T0, {**summary, "reason": "no 3D point is seen by two NeRFs"}
    new_id = np.cumsum(linked) - 1
    points = sim3.transform_points(sim3.invert_sim3(T_to_C[ref]), obs["points"][linked])
    res = bundle.refine_sim3_bundle(
        T0, cam_c2w, cam_nerf, (intr.fx, intr.fy, intr.cx, intr.cy), points, obs["obs_cam"][keep],
        new_id[obs["obs_point"][keep]], obs["obs_xy"][keep], ref=ref, loss_scale_px=loss_scale_px,
    )
    summary.update({
        "rms_px_before": _f(res.rms_px_before), "rms_px_after": _f(res.rms_px_after),
        "median_px_after": _f(res.median_px_after), "inlier_fraction": _f(res.inlier_fraction),
        "iterations": res.iterations, "solver": res.message,
    })
    if not (np.isfinite(res.T_to_ref).all() and res.rms_px_after <= res.rms_px_before):
        return T0, {**summary, "reason": "the refinement did not lower the reprojection error"}
    change = sim3.sim3_errors(res.T_to_ref, T0)
    summary["used"] = True
    summary["change"] = [{"r_deg": _f(change.r_err_deg[i]), "t": _f(change.t_err[i]), "s": _f(change.s_err[i])}
                         for i in range(len(T0))]
    return res.T_to_ref, summary


# ---------------------------------------------------------------------------------------------------------------------
# Self-check by cross-rendering


def _gray_blocks(rgb: np.ndarray, factor: int) -> np.ndarray:
    gray = rgb[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32) if rgb.ndim == 3 else rgb
    return _blocks(gray, factor)


def _blocks(x: np.ndarray, factor: int) -> np.ndarray:
    if factor <= 1:
        return x.astype(np.float64)
    h, w = (x.shape[0] // factor) * factor, (x.shape[1] // factor) * factor
    return x[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3), dtype=np.float64)


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
    ga, gb = _gray_blocks(a, downsample), _gray_blocks(b, downsample)
    m = np.ones(ga.shape, bool) if mask is None else _blocks(mask.astype(np.float32), downsample) > 0.5
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

    @property
    def score(self) -> float:
        """The worse direction (NaN if either saw nothing in common)."""
        return float(min(self.ncc_i_in_j, self.ncc_j_in_i)) if np.isfinite([self.ncc_i_in_j, self.ncc_j_in_i]).all() \
            else float("nan")


def _cross_direction(
    src: ViewSet, dst: Renderer, T_src_to_dst: np.ndarray, order: Sequence[int], intrinsics: Intrinsics,
    cfg: RegistrationConfig, acc_src: np.ndarray,
) -> float:
    order = list(order)[: cfg.self_check_views]
    if not order:
        return float("nan")
    poses = sim3.transform_poses(T_src_to_dst, src.c2w[order])
    scores = []
    for k, pose in zip(order, poses, strict=True):
        out = dst.render(pose[None], intrinsics)
        rgb = np.nan_to_num(np.asarray(out.rgb[0], dtype=np.float32))
        # Compare what the PNG stored, as the SfM saw it.
        rgb = _to_uint8(rgb).astype(np.float32) / 255
        mask = acc_src[k] >= 0.5
        if out.accumulation is not None:
            mask &= np.nan_to_num(out.accumulation[0]) >= 0.5
        scores.append(ncc(src.load_rgb(k), rgb, mask, cfg.ncc_downsample))
    scores = np.array(scores)
    return float(np.median(scores[np.isfinite(scores)])) if np.isfinite(scores).any() else float("nan")


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

    ``view_order[(i, j)]`` lists i's views to use, best first (default: i's kept views, evenly spread).
    """
    checks = []
    accs = [vs.load_accumulation() for vs in views]
    for i, j in pairs:
        T_ij = sim3.relative_sim3(T_to_ref[j], T_to_ref[i])  # i -> j
        T_ji = sim3.invert_sim3(T_ij)

        def order(a, b):
            if view_order is not None and (a, b) in view_order:
                return view_order[(a, b)]
            idx = np.flatnonzero(views[a].kept)
            return idx[np.round(np.linspace(0, len(idx) - 1, min(cfg.self_check_views, len(idx)))).astype(int)]

        s_ij = _cross_direction(views[i], renderers[j], T_ij, order(i, j), intrinsics, cfg, accs[i])
        s_ji = _cross_direction(views[j], renderers[i], T_ji, order(j, i), intrinsics, cfg, accs[j])
        checks.append(CrossRenderCheck(i, j, s_ij, s_ji, cfg.self_check_views))
    return checks


def _spanning_pairs(overlap: np.ndarray) -> list[tuple[int, int]]:
    """Maximum spanning tree (Prim) of the NeRF overlap graph: every NeRF checked against its best neighbour."""
    k = len(overlap)
    in_tree, pairs = {0}, []
    while len(in_tree) < k:
        best = max(((a, b) for a in in_tree for b in range(k) if b not in in_tree), key=lambda p: overlap[p])
        pairs.append(tuple(sorted(best)))
        in_tree.add(best[1])
    return pairs


# ---------------------------------------------------------------------------------------------------------------------
# The whole registration


def _validate_settings(config: RegistrationConfig) -> Intrinsics:
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
        (config.ncc_downsample >= 1, "--ncc-downsample must be >= 1"),
        (config.min_registered_views >= 2, "--min-registered-views must be >= 2"),
        (config.umeyama_max_error > 0, "--umeyama-max-error must be > 0"),
        (config.sfm.exhaustive_max_images >= 2 and config.sfm.own_neighbors >= 1 and config.sfm.cross_views >= 1,
         "--sfm.exhaustive-max-images, --sfm.own-neighbors and --sfm.cross-views must be positive"),
    ]
    for ok, message in checks:
        if not ok:
            raise RegistrationError(message)
    return intr


@dataclass
class SamplingChoice:
    """One pose-sampling setting to try, and why it was chosen."""

    config: RegistrationConfig
    """The registration settings with a concrete pose source and render camera."""
    reason: str
    """Why this source and camera (printed and recorded)."""


def _training_cameras_available(renderer: Renderer) -> str | None:
    """None when the renderer's training poses can be read, else the reason why not (one line)."""
    try:
        poses = renderer.training_poses()
    except (RegistrationError, ValueError, OSError) as e:  # runs.RunLoadError is a ValueError
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    return None if poses is not None and len(poses) > 0 else "it has no training poses"


def resolve_sampling(renderers: Sequence[Renderer], config: RegistrationConfig) -> list[SamplingChoice]:
    """The pose-sampling settings to try, in order: the user's choice, or for ``source="auto"`` the training poses
    (then training + hemisphere, then the hemisphere) when every run's dataset is readable, else the hemisphere.

    The render camera defaults to the reference run's training cameras' horizontal field of view and aspect, with
    ``size`` pixels along the longer side; :data:`DEFAULT_RENDER_SIZE` when they are unknown.
    """
    sc = config.sampling
    k = len(renderers)
    missing = {}
    if sc.source == "auto" or sc.width is None or sc.height is None or sc.fov_deg is None:
        for i, r in enumerate(renderers):
            why = _training_cameras_available(r)
            if why is not None:
                missing[i] = why
    width, height, fov = sc.width, sc.height, sc.fov_deg
    camera_note = "render size and field of view as given"
    if width is None or height is None or fov is None:
        ref = config.reference % k if -k <= config.reference < k else 0
        intr = None if ref in missing else getattr(renderers[ref], "training_intrinsics", lambda: None)()
        if intr is not None:
            factor = sc.size / max(intr.width, intr.height)
            auto_w, auto_h = max(8, round(intr.width * factor)), max(8, round(intr.height * factor))
            auto_fov = math.degrees(2 * math.atan2(intr.width / 2, intr.fx))
            camera_note = f"render camera from {renderers[ref].name}'s training cameras"
        else:
            auto_w, auto_h, auto_fov = DEFAULT_RENDER_SIZE
            camera_note = "render camera {}x{} at {:g} deg (the reference run's training cameras are unknown)".format(
                *DEFAULT_RENDER_SIZE)
        width = auto_w if width is None else width
        height = auto_h if height is None else height
        fov = auto_fov if fov is None else fov
    if sc.source != "auto":
        sources = [(sc.source, "as given")]
    elif missing:
        i, why = next(iter(missing.items()))
        sources = [("hemisphere", f"training poses unavailable ({renderers[i].name}: {why})")]
    else:
        sources = [("training", "every run's dataset is readable"),
                   ("both", "the training poses alone did not register"),
                   ("hemisphere", "neither the training poses nor training + hemisphere registered")]  # fmt: skip
    out = []
    for source, why in sources:
        sampling = replace(sc, source=source, width=int(width), height=int(height), fov_deg=float(fov))
        out.append(SamplingChoice(replace(config, sampling=sampling), f"{why}; {camera_note}"))
    return out


def register(
    renderers: Sequence[Renderer],
    config: RegistrationConfig | None = None,
    work_dir: Path | str = Path("nerfuser_register_work"),
    console: Console = CONSOLE,
) -> dict:
    """Register N >= 2 renderers; returns the registration record (what :func:`write_registration` stores).

    With ``sampling.source="auto"`` (the default) the pose sources of :func:`resolve_sampling` are tried in order until
    one registers; each choice and each fallback is printed. Raises :class:`RegistrationError` (one line, naming the
    NeRF) when the result cannot be trusted.
    """
    config = config or RegistrationConfig()
    if len(renderers) < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {len(renderers)}")
    choices = resolve_sampling(renderers, config)
    for choice in choices:
        _validate_settings(choice.config)
    tried = []
    for n, choice in enumerate(choices):
        sc = choice.config.sampling
        console.print(f"pose sampling: [bold]{sc.source}[/] ({choice.reason}), renders {sc.width}x{sc.height} at "
                      f"{sc.fov_deg:.1f} deg")  # fmt: skip
        try:
            record = _register_once(renderers, choice.config, work_dir, console)
        except RegistrationError as e:
            if n + 1 == len(choices):
                raise
            reason = str(e).splitlines()[0]
            tried.append({"source": sc.source, "error": reason})
            console.print(f"[yellow]{sc.source} poses did not register: {reason}[/]")
            continue
        record["sampling_choice"] = {"requested": config.sampling.source, "source": sc.source,
                                     "reason": choice.reason, "tried_before": tried}  # fmt: skip
        return record
    raise AssertionError("unreachable")  # pragma: no cover


def _register_once(
    renderers: Sequence[Renderer],
    config: RegistrationConfig,
    work_dir: Path | str,
    console: Console,
) -> dict:
    """One registration with concrete pose-sampling settings (see :func:`register`)."""
    work_dir = Path(work_dir)
    k = len(renderers)
    names = [r.name for r in renderers]
    if k < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {k}")
    if not -k <= config.reference < k:
        raise RegistrationError(f"reference index {config.reference} out of range for {k} NeRFs")
    ref = config.reference % k
    if config.estimator not in ("nerfuser", "nerfuser-median", "umeyama-ransac"):
        raise RegistrationError(f"unknown estimator {config.estimator!r}")
    keys = [render_key(r, config.sampling) for r in renderers]
    for a in range(k):
        for b in range(a):
            if keys[a] == keys[b]:
                raise RegistrationError(f"{names[a]}: passed twice (same run as {names[b]}); pass distinct runs")
    min_views = max(config.min_registered_views, 3 if config.estimator == "umeyama-ransac" else 2)
    intr = _validate_settings(config)
    timings: dict[str, float] = {}

    # 1. Render (or reuse the renders of a previous run).
    t0 = time.perf_counter()
    views = [render_views_cached(r, config.sampling, work_dir / "renders", console) for r in renderers]
    timings["render"] = time.perf_counter() - t0
    for vs in views:
        if vs.kept.sum() < min_views:
            raise RegistrationError(
                f"{vs.name}: only {int(vs.kept.sum())} of {len(vs.c2w)} rendered views see enough (mean accumulation "
                f">= {config.sampling.min_view_accumulation}); aim the views at the content: {SUGGESTION}"
            )

    # 2. One SfM over the union.
    sfm = run_sfm(views, intr, config.sfm, work_dir, console)
    for step in ("features", "matching", "mapping"):
        timings[step] = 0.0 if sfm.reused else sfm.timings.get(step, 0.0)
    # What each step costs without the work folder (reused renders and SfM report the time they took when made).
    render_s = [vs.render_seconds for vs in views]
    compute = {"render": None if None in render_s else float(sum(render_s))}
    compute.update({step: sfm.timings.get(step) for step in ("features", "matching", "mapping")})
    if not sfm.model_counts:
        raise RegistrationError(
            f"SfM reconstructed nothing from the renders of {', '.join(names)} (too few matches); {SUGGESTION}"
        )
    largest = sfm.model_counts[0]
    for i in range(k):
        if largest[i] >= min_views:
            continue
        elsewhere = [m for m in sfm.model_counts[1:] if m[i] >= min_views]
        if elsewhere:
            together = [names[j] for j in range(k) if largest[j] >= min_views]
            raise RegistrationError(
                f"{names[i]}: its views form a separate SfM model from {', '.join(together) or 'the others'} "
                f"(no overlap found between the NeRFs); {SUGGESTION}"
            )
        raise RegistrationError(
            f"{names[i]}: only {largest[i]} of {int(views[i].kept.sum())} views registered in the SfM model "
            f"(need {min_views}); {SUGGESTION}"
        )

    # 3. Per NeRF: its SIM(3) into the SfM frame C, then into the reference frame.
    t0 = time.perf_counter()
    estimates, G_sfms = [], []
    for vs in views:
        G_sfm = np.full((len(vs.c2w), 4, 4), np.nan)
        for n, (name, kept) in enumerate(zip(vs.image_names, vs.kept, strict=True)):
            if kept and name in sfm.c2w:
                G_sfm[n] = sfm.c2w[name]
        try:
            if config.estimator == "umeyama-ransac":
                est = sim3.estimate_sim3_umeyama(vs.c2w, G_sfm, robust=True, max_error=config.umeyama_max_error,
                                                 seed=config.sfm.seed)
            else:
                method = "weiszfeld" if config.estimator == "nerfuser" else "median"
                est = sim3.estimate_sim3_from_poses(vs.c2w, G_sfm, method=method)
        except (ValueError, RuntimeError) as e:
            raise RegistrationError(f"{vs.name}: the SIM(3) estimate failed ({e}); {SUGGESTION}") from None
        if not (np.isfinite(est.T).all() and est.scale > 0):
            raise RegistrationError(f"{vs.name}: the SIM(3) estimate is NaN or degenerate; {SUGGESTION}")
        estimates.append(est)
        G_sfms.append(G_sfm)
    T_to_C = np.stack([e.T for e in estimates])
    T_to_ref = sim3.to_reference_frame(T_to_C, ref)
    refinement = None
    if config.refine:
        with console.status("refining the transforms (rigid-set bundle adjustment)"):
            T_to_ref, refinement = refine_transforms(views, sfm, T_to_C, ref, intr, config.refine_loss_scale_px)
        T_to_C = T_to_C[ref] @ T_to_ref
    timings["solve"] = time.perf_counter() - t0

    # 4. Overlap between NeRFs (3D points seen by both) and the cross-render self-check.
    overlap = np.zeros((k, k), dtype=int)
    for i, vs in enumerate(views):
        for name in vs.image_names:
            if name in sfm.covisible:
                overlap[i] += np.asarray(sfm.covisible[name])
    overlap = np.minimum(overlap, overlap.T)
    checked_pairs = _spanning_pairs(overlap) if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    view_order = {}
    for i, j in checked_pairs:
        for a, b in ((i, j), (j, i)):
            names_a = views[a].image_names
            cov = np.array([sfm.covisible.get(n, [0] * k)[b] if views[a].kept[n_i] else -1
                            for n_i, n in enumerate(names_a)])
            view_order[(a, b)] = [int(v) for v in np.argsort(-cov, kind="stable") if cov[v] >= 0]
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config, view_order)
    timings["self_check"] = time.perf_counter() - t0

    # 5. The record.
    check_of = {(c.i, c.j): c for c in checks}
    pairs = []
    for i in range(k):
        for j in range(i + 1, k):
            c = check_of.get((i, j))
            pairs.append({
                "i": i, "j": j, "names": [names[i], names[j]],
                "T_j_to_i": _mat(sim3.relative_sim3(T_to_ref[i], T_to_ref[j])),
                "covisible_points": int(overlap[i, j]),
                "self_check": None if c is None else {
                    "ncc": _f(c.score), "ncc_i_in_j": _f(c.ncc_i_in_j), "ncc_j_in_i": _f(c.ncc_j_in_i),
                    "views_per_direction": c.views, "threshold": config.ncc_threshold,
                    "passed": bool(np.isfinite(c.score) and c.score >= config.ncc_threshold),
                },
            })
    nerfs = []
    for i, (r, vs, est) in enumerate(zip(renderers, views, estimates, strict=True)):
        registered = sum(1 for n, kept in zip(vs.image_names, vs.kept, strict=True) if kept and n in sfm.c2w)
        # SfM cameras against the final transform (the refined one, when refined).
        rot, cen = sim3.pose_residuals(T_to_C[i], vs.c2w[est.used], G_sfms[i][est.used])
        config_path = getattr(r, "config_path", None)
        nerfs.append({
            "name": r.name,
            "config": None if config_path is None else str(Path(config_path).absolute()),
            # which weights were registered: fusing them after a retraining is refused (nerfuser_ns.data)
            "checkpoint": r.checkpoint_identity() if hasattr(r, "checkpoint_identity") else None,
            "T_to_reference": _mat(T_to_ref[i]),
            "transform": _mat(T_to_ref[i]),  # alias read by nerfuser_ns.data (p_reference = T @ [p_nerf, 1])
            "scale_to_reference": float(sim3.decompose_sim3(T_to_ref[i])[2]),
            "T_to_sfm": _mat(T_to_C[i]),
            "views": {"rendered": len(vs.c2w), "kept": int(vs.kept.sum()), "registered": registered,
                      "sources": {s: vs.sources.count(s) for s in sorted(set(vs.sources))}},
            "render_folder": str(vs.folder),
            "renders_reused": vs.reused,
            "estimator": est.method,
            "refinement_change": refinement["change"][i] if refinement and refinement["used"] else None,
            "cameras_used": est.num_cameras,
            "scale_to_sfm": est.scale,
            "scale_spread": est.scale_spread,
            "scale_outlier_fraction": est.scale_outlier_fraction,
            "residuals": {
                "rotation_deg_median": _f(np.median(rot)), "rotation_deg_max": _f(np.max(rot)),
                "centre_median": _f(np.median(cen)), "centre_max": _f(np.max(cen)),
                "centre_units": "this NeRF's units", "of": "the SfM's cameras against the final transform",
            },
        })
    record = {
        "format_version": FORMAT_VERSION,
        "kind": "nerfuser_registration",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "reference": {"index": ref, "name": names[ref]},
        "conventions": {
            "sim3": "T = [[s R, t], [0, 0, 0, 1]]; T_to_reference maps points of the NeRF's frame into the "
                    "reference NeRF's frame: p_ref = T @ [p, 1]",
            "poses": "camera-to-world, OpenGL camera axes (nerfstudio)",
            "pairs": "T_j_to_i maps NeRF j's points into NeRF i's frame",
        },
        "nerfs": nerfs,
        "pairs": pairs,
        "sfm": {
            "images": sfm.num_images, "registered": len(sfm.c2w), "matching": sfm.matching,
            "models": sfm.model_counts, "points3D": sfm.num_points3D,
            "mean_reprojection_error_px": _f(sfm.mean_reprojection_error), "reused": sfm.reused,
            "intrinsics": asdict(intr),
        },
        "refinement": refinement,
        "settings": asdict(config),
        "timings_s": {k_: round(v, 3) for k_, v in timings.items()},
        "compute_timings_s": {
            k_: None if v is None else round(v, 3)
            for k_, v in {**compute, "solve": timings["solve"], "self_check": timings["self_check"]}.items()
        },
        "reused": {"renders": [vs.reused for vs in views], "sfm": sfm.reused},
    }

    # 6. Fail clearly when the self-check says the SfM merged the wrong things.
    for c in checks:
        if not (np.isfinite(c.score) and c.score >= config.ncc_threshold):
            what = "saw nothing in common" if not np.isfinite(c.score) else f"NCC {c.score:.2f}"
            raise RegistrationFailed(
                f"{names[c.i]} and {names[c.j]}: cross-render self-check failed ({what} < {config.ncc_threshold}); "
                f"the SfM probably merged unrelated content; {SUGGESTION} (or calibrate --ncc-threshold for blurry "
                "renders)",
                record,
            )
    return record



def register_runs(
    config_paths: Sequence[Path | str],
    output: Path | str,
    config: RegistrationConfig | None = None,
    work_dir: Path | str | None = None,
    names: Sequence[str] | None = None,
    device: str = "cpu",
    console: Console = CONSOLE,
    data_overrides: Sequence[Path | None] | None = None,
) -> dict:
    """Register trained nerfstudio runs from their config.yml files and write the registration file at ``output``.

    ``work_dir`` defaults to ``<output>_work`` (renders and SfM files, reused by later calls). ``data_overrides[i]``
    is run i's dataset folder where its config's path no longer holds it (training poses are read from it). Raises
    :class:`RegistrationError` or ``runs.RunLoadError`` (one line) on bad input; nothing is written then.
    """
    from nerfuser_ns.renderers import NerfstudioRenderer

    output = Path(output)
    if names is not None and len(names) != len(config_paths):
        raise RegistrationError(f"{len(names)} names for {len(config_paths)} runs")
    if data_overrides is not None and len(data_overrides) != len(config_paths):
        raise RegistrationError(f"{len(data_overrides)} dataset folders for {len(config_paths)} runs")
    renderers = [
        NerfstudioRenderer(
            c, device=device, name=None if names is None else names[i],
            data_override=None if data_overrides is None else data_overrides[i],
        )
        for i, c in enumerate(config_paths)
    ]  # fmt: skip
    work_dir = Path(work_dir) if work_dir is not None else output.with_name(output.stem + "_work")
    record = register(renderers, config, work_dir, console=console)
    write_registration(record, output)
    return record


def write_registration(record: dict, path: Path | str) -> Path:
    """Write the registration record as JSON, atomically (temp file + rename)."""
    path = Path(path)
    write_text_atomic(path, json.dumps(record, indent=2) + "\n")
    return path


def read_registration(path: Path | str) -> dict:
    """Read a registration file; ``T_to_reference`` of each NeRF comes back as a [4, 4] array."""
    path = Path(path)
    try:
        record = json.loads(path.read_text())
        if record.get("kind") != "nerfuser_registration":
            raise ValueError("not a registration file")
        for n in record["nerfs"]:
            n["T_to_reference"] = np.asarray(n["T_to_reference"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise RegistrationError(f"{path}: not a readable registration file ({type(e).__name__}: {e})") from None
    return record
