"""Evaluation on generated scenes with exact ground truth: scene/run bookkeeping, blending quality, render cost.

The building blocks of ``scripts/bench_blending.py`` and ``scripts/evaluate.py``: a :class:`SceneRuns` ties a
generated scene (``scripts/make_scene.py``) to the runs trained on its captures (``scripts/build_demo.py``) and
derives every ground-truth transform from files on disk; :func:`blend_metrics` scores every blend method in one
rendering pass; :func:`measure_render_cost` times the fused model against its sub-models on the same rays.
"""

from __future__ import annotations

import ctypes
import json
import statistics
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models.base_model import Model
from PIL import Image
from rich.progress import track
from torch import Tensor

from nerfuser_ns import runs, runtime, sim3
from nerfuser_ns.bench import metrics
from nerfuser_ns.blending import COVERAGE_METHODS, PAPER_BLEND_METHODS, PAPER_MISSION_BAY, PAPER_OBJECT_CENTRIC
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.model import NerfuserModel, fuse_models, map_rays
from nerfuser_ns.registration.record import TrainingCameras
from nerfuser_ns.spec import read_registered_nerfs

"""Every blend method, in the paper's table order."""

PAPER_SETTINGS = {"object-centric": PAPER_OBJECT_CENTRIC, "street": PAPER_MISSION_BAY, "drive": PAPER_MISSION_BAY}
"""(gamma, tau) the paper uses per scene layout: its object-centric scenes, and Mission Bay for the streets."""

RUN_SUBDIR = Path("nerfacto-cpu/demo")
"""Where ``scripts/build_demo.py`` puts a capture's run below ``<runs dir>/<capture>/``."""


class EvaluationError(ValueError):
    """Bad evaluation input (one line, naming the file or value)."""


@dataclass
class SceneRuns:
    """A generated scene and the runs trained on its captures (one run per capture, same order)."""

    name: str
    """Short name used in reports."""
    scene_dir: Path
    """The scene folder (with ``ground_truth.json``)."""
    configs: list[Path]
    """config.yml of each capture's run, in the ground truth's capture order."""
    ground_truth: dict = field(repr=False)
    """The parsed ``ground_truth.json``."""

    @property
    def captures(self) -> list[str]:
        return [c["name"] for c in self.ground_truth["captures"]]

    @classmethod
    def from_dirs(cls, name: str, scene_dir: Path | str, runs_dir: Path | str) -> SceneRuns:
        """Reads ``<scene_dir>/ground_truth.json`` and finds ``<runs_dir>/<capture>/nerfacto-cpu/demo/config.yml``."""
        scene_dir, runs_dir = Path(scene_dir), Path(runs_dir)
        gt_path = scene_dir / "ground_truth.json"
        if not gt_path.is_file():
            raise EvaluationError(f"{gt_path}: no ground truth; generate the scene with scripts/make_scene.py")
        gt = json.loads(gt_path.read_text())
        configs = [runs_dir / c["name"] / RUN_SUBDIR / "config.yml" for c in gt["captures"]]
        missing = [str(p) for p in configs if not p.is_file()]
        if missing:
            raise EvaluationError(
                f"{missing[0]}: no trained run for this capture; train it with scripts/build_demo.py "
                f"--scene-dir {scene_dir} --runs-dir {runs_dir}"
            )
        return cls(name=name, scene_dir=scene_dir, configs=configs, ground_truth=gt)

    @classmethod
    def parse(cls, spec: str) -> SceneRuns:
        """``NAME=SCENE_DIR:RUNS_DIR`` (the ``--scenes`` syntax of the benchmark scripts)."""
        name, _, dirs = spec.partition("=")
        scene_dir, _, runs_dir = dirs.partition(":")
        if not name or not scene_dir or not runs_dir:
            raise EvaluationError(f"scene {spec!r}: expected NAME=SCENE_DIR:RUNS_DIR")
        return cls.from_dirs(name, scene_dir, runs_dir)

    def capture_dirs(self) -> list[Path]:
        """Each run's dataset (the capture folder): where its training poses are read when the path recorded in the
        run's config.yml (relative to where it was trained) does not resolve."""
        return [self.scene_dir / c for c in self.captures]

    def nerf_to_world(self) -> list[Float[np.ndarray, "4 4"]]:
        """Ground truth: each run's NeRF frame -> the scene's world frame (capture_to_world after the inverse of the
        run's dataparser transform; the run's dataset is the scene's capture folder when it has one, else the path its
        config.yml records)."""
        return [
            np.asarray(c["capture_to_world"], dtype=np.float64)
            @ sim3.invert_sim3(runs.read_dataparser_transform(p, data_override=d if d.is_dir() else None))
            for c, p, d in zip(self.ground_truth["captures"], self.configs, self.capture_dirs(), strict=True)
        ]

    def nerf_to_common(self, reference: int = 0) -> list[Float[np.ndarray, "4 4"]]:
        """Ground truth: each run's NeRF frame -> the reference run's NeRF frame (the common frame)."""
        to_world = self.nerf_to_world()
        world_to_common = sim3.invert_sim3(to_world[reference])
        return [world_to_common @ T for T in to_world]

    def _test_capture(
        self, reference: int, max_views: int | None
    ) -> tuple[Path, dict, list[dict], Float[np.ndarray, "n 4 4"], Float[np.ndarray, "4 4"]]:
        """The test capture's folder, transforms.json, its first ``max_views`` frames, their world-frame poses
        [n, 4, 4], and the world -> common SIM(3)."""
        test_dir = self.scene_dir / self.ground_truth["test"]["path"]
        meta = json.loads((test_dir / "transforms.json").read_text())
        frames = meta["frames"][:max_views]
        c2w_world = np.stack([np.asarray(f["transform_matrix"], dtype=np.float64) for f in frames])
        return test_dir, meta, frames, c2w_world, sim3.invert_sim3(self.nerf_to_world()[reference])

    def test_views(self, reference: int = 0, max_views: int | None = None) -> tuple[Cameras, Float[Tensor, "n h w 3"]]:
        """The world-frame test capture, posed in the common frame, and its ground-truth images."""
        test_dir, meta, frames, c2w_world, world_to_common = self._test_capture(reference, max_views)
        c2w = sim3.transform_poses(world_to_common, c2w_world)
        intrinsics = Intrinsics(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"])
        cams = runs.make_cameras(c2w[:, :3], intrinsics)
        images = [np.asarray(Image.open(test_dir / f["file_path"]).convert("RGB"), np.float32) / 255 for f in frames]
        return cams, torch.from_numpy(np.stack(images))

    def test_surface_points(self, reference: int = 0, max_views: int | None = None) -> Float[Tensor, "n h w 3"]:
        """The ground-truth surface point seen by every test pixel (its pixel-centre ray at the depth file's z-depth),
        in the common frame; NaN where the ray hits nothing or the depth saturates."""
        test_dir, meta, frames, c2w_world, world_to_common = self._test_capture(reference, max_views)
        if any("depth_file_path" not in f for f in frames):
            raise EvaluationError(f"{test_dir / 'transforms.json'}: test frames without depth_file_path; "
                                  "regenerate the scene with scripts/make_scene.py")  # fmt: skip
        w, h = int(meta["w"]), int(meta["h"])
        cols = (np.arange(w) + 0.5 - meta["cx"]) / meta["fl_x"]
        rows = -(np.arange(h) + 0.5 - meta["cy"]) / meta["fl_y"]
        # camera-space points at z-depth 1 (nerfstudio cameras look along -z)
        d_cam = np.stack(np.broadcast_arrays(cols[None, :], rows[:, None], -np.ones((h, w))), axis=-1)
        points = []
        for f, c2w in zip(frames, c2w_world, strict=True):
            raw = np.asarray(Image.open(test_dir / f["depth_file_path"]), dtype=np.float64)
            z = np.where((raw > 0) & (raw < 65535), raw * float(meta["depth_unit_scale_factor"]), np.nan)
            p_world = (d_cam * z[..., None]) @ c2w[:3, :3].T + c2w[:3, 3]
            points.append(p_world @ world_to_common[:3, :3].T + world_to_common[:3, 3])
        return torch.from_numpy(np.stack(points)).float()


def registered_transforms(registration_file: Path | str, scene: SceneRuns) -> list[Float[np.ndarray, "4 4"]]:
    """Estimated NeRF -> common transforms from a registration file, in the scene's capture order."""
    by_name = {e.name: e.nerf_to_common for e in read_registered_nerfs(registration_file, check_runs=False)}
    missing = [c for c in scene.captures if c not in by_name]
    if missing:
        raise EvaluationError(f"{registration_file}: no NeRF named {missing[0]!r} (it has {sorted(by_name)})")
    return [by_name[c] for c in scene.captures]


def training_cameras(scene: SceneRuns, models: Sequence[tuple[str, Model]]) -> list[TrainingCameras]:
    """Each run's training cameras in its NeRF frame, as the run finally saw them (camera-optimiser corrections
    applied): what a registration records for the ``coverage`` blend method (ours)."""
    out = []
    for config, capture, (_, model) in zip(scene.configs, scene.capture_dirs(), models, strict=True):
        cams = runs.training_cameras(config, data_override=capture)
        c2w = runs.optimized_poses(model, cams.camera_to_worlds).detach().cpu().numpy()
        full = np.tile(np.eye(4), (len(c2w), 1, 1))
        full[:, :3, :4] = c2w
        intr = torch.cat([x.reshape(-1, 1).float() for x in (cams.fx, cams.fy, cams.cx, cams.cy, cams.width,
                                                             cams.height)], dim=1)  # fmt: skip
        out.append(TrainingCameras(full, intr.numpy().astype(np.float64)))
    return out


def fused(  # noqa: ANN201 - NerfuserModel
    models: Sequence[tuple[str, Model]],
    transforms: Sequence[np.ndarray],
    cameras: Sequence[TrainingCameras] | None = None,
    colour_maps: Sequence[np.ndarray | None] | None = None,
    **overrides,
):
    """A fused model of loaded sub-models under the given NeRF -> common transforms (``cameras``: their training
    cameras, for ``coverage``; ``colour_maps``: their maps to the reference's colours, applied with
    ``appearance_matching=True``; ``overrides``: config fields)."""
    if len(models) != len(transforms):
        raise EvaluationError(f"{len(models)} models but {len(transforms)} transforms")
    cams = [None] * len(models) if cameras is None else list(cameras)
    maps = [None] * len(models) if colour_maps is None else list(colour_maps)
    return fuse_models([(n, m, T, c, k) for (n, m), T, c, k in zip(models, transforms, cams, maps, strict=True)],
                       **overrides)  # fmt: skip


def blend_metrics(
    models: Sequence[tuple[str, Model]],
    transforms: Sequence[np.ndarray],
    cameras: Cameras,
    target: Float[Tensor, "n h w 3"],
    gamma: float = 5.0,
    tau: float | None = PAPER_OBJECT_CENTRIC[1],
    methods: Sequence[str] = PAPER_BLEND_METHODS,
    reference_nerf: int = 0,
    description: str = "blending",
    nerf_cameras: Sequence[TrainingCameras] | None = None,
    colour_maps: Sequence[np.ndarray | None] | None = None,
) -> dict[str, dict[str, float]]:
    """PSNR/SSIM/LPIPS of every blend method on the given views, rendered in one pass (shared sub-model queries);
    ``coverage`` and ``coverage-3d`` (ours) need the runs' ``nerf_cameras``; ``colour_maps`` (each NeRF's map to the
    reference's colours) turn appearance matching (ours) on."""
    needs_cameras = [m for m in methods if m in COVERAGE_METHODS]
    if needs_cameras and nerf_cameras is None:
        raise EvaluationError(f"blend method {needs_cameras[0]!r} needs the runs' training cameras (nerf_cameras)")
    model = fused(
        models, transforms, nerf_cameras, colour_maps, gamma=gamma, tau=tau, reference_nerf=reference_nerf,
        render_all_methods=True, share_outputs=False, appearance_matching=colour_maps is not None,
    )  # fmt: skip
    keys = tuple(f"rgb_{m.replace('-', '_')}" for m in methods)
    with torch.no_grad():
        out = runs.render_views(model, cameras, outputs=keys, description=description)
    return {m: metrics.image_metrics(out[k].clamp(0, 1), target) for m, k in zip(methods, keys, strict=True)}


def _return_freed_memory_to_os() -> None:
    """glibc keeps freed blocks (its mmap threshold grows with use), hiding later allocations from the resident size;
    a fixed 64 KiB threshold makes every large tensor its own mapping, returned on free, and ``malloc_trim`` hands
    back the free pages inside the heap (what earlier work left there), so RSS follows live memory."""
    runtime.install()  # its allocator setting, applied once, must not override this one later in the measured block
    if runtime.set_malloc_thresholds(1 << 16, 1 << 16):
        ctypes.CDLL(None).malloc_trim(0)
    # not glibc: peaks then only show growth beyond the allocator's cache


class _PeakRSS:
    """Samples the process's resident memory in a thread; ``peak - baseline`` is what the block added at most."""

    def __init__(self, interval_s: float = 0.002):
        _return_freed_memory_to_os()

        self._proc = psutil.Process()
        self._interval = interval_s
        self._stop = threading.Event()
        self.baseline = self.peak = 0

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._proc.memory_info().rss)
            time.sleep(self._interval)

    def __enter__(self) -> _PeakRSS:
        self.baseline = self.peak = self._proc.memory_info().rss
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:  # noqa: ANN002
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._proc.memory_info().rss)

    @property
    def added_mib(self) -> float:
        return (self.peak - self.baseline) / 2**20


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _PeakMemory:
    """What a block added at most to the memory it runs in: the process's resident memory (sampled, :class:`_PeakRSS`)
    on the CPU, the allocator's peak on a GPU."""

    def __init__(self, device: torch.device):
        self._device = device
        self._rss = _PeakRSS() if device.type != "cuda" else None
        self._baseline = 0

    def __enter__(self) -> _PeakMemory:
        if self._rss is not None:
            self._rss.__enter__()
        else:
            torch.cuda.synchronize(self._device)
            self._baseline = torch.cuda.memory_allocated(self._device)
            torch.cuda.reset_peak_memory_stats(self._device)
        return self

    def __exit__(self, *exc) -> None:  # noqa: ANN002
        if self._rss is not None:
            self._rss.__exit__(*exc)
        else:
            torch.cuda.synchronize(self._device)
            self._peak = torch.cuda.max_memory_allocated(self._device)

    @property
    def added_mib(self) -> float:
        return self._rss.added_mib if self._rss is not None else (self._peak - self._baseline) / 2**20


@dataclass
class RenderCost:
    """Fused render time against the sum of the sub-models' own render times for the same rays."""

    num_rays: int
    """Rays per chunk (one forward pass)."""
    fused_s: float
    """Median seconds of one fused forward pass over the chunk."""
    sub_s: list[float]
    """Median seconds of each sub-model's own forward pass over the chunk, mapped into its frame."""
    ratio: float
    """Median over repeats of ``fused / sum(subs)`` within each repeat. Paired: the passes of one repeat run back to
    back (in a shuffled order), so a slow spell of a shared machine slows both sides of one ratio alike; ratios of
    separate medians or minima mix moments (and a sum of N minima is biased low)."""
    ratio_quartiles: tuple[float, float]
    """Lower and upper quartile of the per-repeat ratios: the measurement's spread."""
    fused_peak_mib: float
    """Peak memory added by one fused pass over the chunk (MiB, in a pass after the timing): resident memory, sampled,
    on the CPU; the CUDA allocator's peak on a GPU."""
    sub_peak_mib: list[float]
    """Peak memory added by each sub-model's own pass (MiB, as ``fused_peak_mib``)."""
    method: str
    repeats: int
    used_rays: list[int]
    """Rays of the chunk the fused model queries each sub-model on (the others fail every distance test there)."""
    sub_used_s: list[float]
    """Median seconds of each sub-model's own pass over just those rays (0 for none)."""
    ratio_used: float
    """Median over repeats of ``fused / sum(sub_used)``: the fused model's overhead over the sub-model work it does
    (``ratio`` credits it with skipping the NeRFs the distance test leaves out)."""
    ratio_used_quartiles: tuple[float, float]
    fused_min_s: float
    """Seconds of the fastest fused pass: the repeat least disturbed by other work on a shared machine (a median of a
    few repeats of passes this short can swing by several times under load)."""
    sub_used_min_s: list[float]
    """Seconds of each sub-model's fastest pass over the rays the fused model queries it on (0 for none)."""

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def measure_render_cost(
    models: Sequence[tuple[str, Model]],
    transforms: Sequence[np.ndarray],
    cameras: Cameras,
    num_rays: int = 4096,
    repeats: int = 15,
    method: str = "idw-sample",
    seed: int = 0,
    gamma: float = 5.0,
    tau: float | None = PAPER_OBJECT_CENTRIC[1],
    nerf_cameras: Sequence[TrainingCameras] | None = None,
) -> RenderCost:
    """Times one chunk of ``num_rays`` random test rays through the fused model (``method``, no extra outputs) and
    through each sub-model's own forward pass (collider, sampler, field, renderers) on the same rays mapped into its
    frame, and through each sub-model on just the rays the fused model queries it on. Each repeat runs every pass
    once, in a shuffled order (seeded); the ratios are medians of the per-repeat ratios. The first (warm-up,
    compilation) pass is not counted. Memory is measured in one more pass per full-chunk path, after the timing.
    ``nerf_cameras``: the runs' training cameras (``coverage`` and ``coverage-3d`` need them)."""
    # The allocator setting the memory sampler needs, from the start: every pass, timed or sampled, and every call
    # in a process then runs under the same one (set lazily, the first call's memory hid in glibc's cache).
    _return_freed_memory_to_os()
    model = fused(models, transforms, nerf_cameras, blend_method=method, gamma=gamma, tau=tau, share_outputs=False)
    cameras = cameras.to(model.device)
    bundle = cameras.generate_rays(torch.arange(len(cameras), device=model.device)[:, None], keep_shape=False)
    gen = torch.Generator().manual_seed(seed)  # on the CPU: the same rays on every device
    pick = torch.randperm(len(bundle), generator=gen)[:num_rays].to(model.device)
    rays = bundle[pick]
    mapped = [map_rays(rays, model.common_to_nerf[i], m.num_train_data)[0] for i, (_, m) in enumerate(models)]
    used = model.used_nerfs(rays)
    used_mapped = [r[u] if bool(u.any()) else None for r, u in zip(mapped, used, strict=True)]

    n = len(models)
    passes = [lambda: model(rays)] + [lambda r=r, m=m: m(r) for r, (_, m) in zip(mapped, models, strict=True)]
    passes += [lambda r=r, m=m: None if r is None else m(r) for r, (_, m) in zip(used_mapped, models, strict=True)]
    times: list[list[float]] = [[] for _ in passes]
    peaks: list[float] = []
    order_rng = np.random.default_rng(seed)
    with torch.no_grad():
        for p in passes:
            p()  # warm-up
        for _ in range(repeats):
            for i in order_rng.permutation(len(passes)):
                _synchronize(model.device)  # CUDA runs asynchronously: time the work, not its launch
                t = time.perf_counter()
                passes[i]()
                _synchronize(model.device)
                times[i].append(time.perf_counter() - t)
        # memory after the timing: the sampler thread would slow the timed passes
        for p in passes[: n + 1]:
            with _PeakMemory(model.device) as mem:
                p()
            peaks.append(mem.added_mib)
    med = [statistics.median(t) for t in times]
    fused_t, sub_t, used_t = times[0], times[1 : n + 1], times[n + 1 :]
    ratios = [f / sum(subs) for f, *subs in zip(fused_t, *sub_t, strict=True)]
    ratios_used = [f / sum(subs) for f, *subs in zip(fused_t, *used_t, strict=True)]

    def quartiles(x: list[float]) -> tuple[float, float]:
        q1, _, q3 = statistics.quantiles(x, n=4, method="inclusive") if len(x) > 1 else (x[0],) * 3
        return q1, q3

    return RenderCost(
        num_rays=len(rays), fused_s=med[0], sub_s=med[1 : n + 1], ratio=statistics.median(ratios),
        ratio_quartiles=quartiles(ratios), fused_peak_mib=peaks[0], sub_peak_mib=peaks[1:], method=method,
        repeats=repeats, used_rays=[int(u.sum()) for u in used], sub_used_s=med[n + 1 :],
        ratio_used=statistics.median(ratios_used), ratio_used_quartiles=quartiles(ratios_used),
        fused_min_s=min(fused_t), sub_used_min_s=[min(t) for t in used_t],
    )  # fmt: skip


def geometric_gammas(low: float = 1e-2, high: float = 1e3, num: int = 11) -> list[float]:
    """Gamma values spaced geometrically over ``[low, high]`` (the paper's ablation range)."""
    return [float(g) for g in np.geomspace(low, high, num)]


__all__ = [
    "EvaluationError",
    "PAPER_SETTINGS",
    "RenderCost",
    "SceneRuns",
    "blend_metrics",
    "blend_sweep",
    "fused",
    "gamma_sweep",
    "geometric_gammas",
    "measure_render_cost",
    "registered_transforms",
]


def gamma_sweep(
    models: Sequence[tuple[str, Model]],
    transforms: Sequence[np.ndarray],
    cameras: Cameras,
    target: Float[Tensor, "n h w 3"],
    gammas: Sequence[float],
    tau: float | None = PAPER_OBJECT_CENTRIC[1],
    methods: Sequence[str] = PAPER_BLEND_METHODS,
) -> dict[float, dict[str, dict[str, float]]]:
    """Metrics of every method for every gamma (:func:`blend_sweep` over ``{"gamma": g}``)."""
    model = fused(models, transforms, tau=tau, render_all_methods=True, share_outputs=False)
    results = blend_sweep(model, cameras, target, [{"gamma": float(g)} for g in gammas], methods, "gamma sweep")
    return {float(g): r for g, r in zip(gammas, results, strict=True)}


def blend_sweep(
    model: NerfuserModel,
    cameras: Cameras,
    target: Float[Tensor, "n h w 3"],
    settings: Sequence[dict[str, Any]],
    methods: Sequence[str] = PAPER_BLEND_METHODS,
    description: str = "blend sweep",
) -> list[dict[str, dict[str, float]]]:
    """PSNR / SSIM of every method under every blend setting (``settings[j]``: changes for
    ``NerfuserModel.set_blend``, e.g. ``{"gamma": 2.0}`` or ``{"coverage": CoverageParams(sigma_deg=10)}``).

    The sub-models are queried once per ray chunk and the samples re-blended per setting
    (``NerfuserModel.blend_samples``): a gamma sweep costs little more than one render, while other coverage
    constants score every sample again per setting. ``model`` must render every method (``render_all_methods``); its
    settings are restored afterwards."""
    keys = [f"rgb_{m.replace('-', '_')}" for m in methods]
    cameras = cameras.to(model.device)
    before = model.blend_settings
    images: list[dict[str, list[Tensor]]] = [{k: [] for k in keys} for _ in settings]
    chunk = model.config.eval_num_rays_per_chunk
    try:
        with torch.no_grad():
            for c in track(range(len(cameras)), description=description, transient=True):
                bundle = cameras.generate_rays(camera_indices=c, keep_shape=True)
                h, w = bundle.origins.shape[:2]
                flat = bundle.flatten()
                parts: list[dict[str, list[Tensor]]] = [{k: [] for k in keys} for _ in settings]
                for start in range(0, len(flat), chunk):
                    rays = flat[start : start + chunk]
                    per_nerf = model.nerf_samples(rays)
                    for j, changes in enumerate(settings):
                        model.blend_settings = before.replace(model.num_nerfs, **changes)
                        out = model.blend_samples(rays, per_nerf)
                        for k in keys:
                            parts[j][k].append(out[k])
                for j in range(len(settings)):
                    for k in keys:
                        images[j][k].append(torch.cat(parts[j][k]).reshape(h, w, -1).cpu())
    finally:
        model.blend_settings = before
    return [
        {m: metrics.image_metrics(torch.stack(images[j][k]).clamp(0, 1), target, lpips=False)
         for m, k in zip(methods, keys, strict=True)}  # fmt: skip
        for j in range(len(settings))
    ]
