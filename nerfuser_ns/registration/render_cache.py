"""Registration step 1: sample camera poses in each NeRF's own frame and render them, cached in the work folder.

Each NeRF's renders go to ``<work_dir>/renders/<key>`` (``images/*.png``, ``accumulation.npz``, ``poses.json``, and
``depth.npz`` when depth is asked for), the key a hash of the renderer's own cache key, the sampling settings and
whether depth is stored: a later run with the same inputs reuses them, and a damaged folder is rendered again.
A new folder also takes the views the same run already rendered at the same poses and intrinsics in another folder
(:class:`EarlierViews`), so the automatic choice's ``both`` after ``training`` renders only the hemisphere it adds.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float
from PIL import Image
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.config import (
    CONSOLE,
    FORMAT_VERSION,
    SUGGESTION,
    PoseSamplingConfig,
    RegistrationConfig,
    RegistrationError,
    content_hash,
    json_matrix,
    validate_settings,
)
from nerfuser_ns.renderers import Renderer
from nerfuser_ns.sampling import sample_hemisphere_poses

POSES_FILE = "poses.json"
"""The render folder's index: per view its pose, source, mean accumulation and whether the SfM uses it."""


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """An RGB render in [0, 1] as the 8-bit image stored (and seen by the SfM)."""
    return np.round(np.nan_to_num(rgb, nan=0.0).clip(0, 1) * 255.0).astype(np.uint8)


def _progress(console: Console) -> Progress:
    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    return Progress(*cols, console=console, transient=True)


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
    has_depth: bool = False
    """Whether ``depth.npz`` holds each view's rendered ray distance."""

    @property
    def image_names(self) -> list[str]:
        """Names relative to ``<work_dir>/renders`` (what the SfM database stores)."""
        return [f"{self.folder.name}/images/{k:05d}.png" for k in range(len(self.c2w))]

    def load_rgb(self, k: int) -> np.ndarray:
        return np.asarray(Image.open(self.folder / "images" / f"{k:05d}.png").convert("RGB"), dtype=np.float32) / 255

    def load_accumulation(self) -> np.ndarray:
        return _read_array(self.folder, "accumulation").astype(np.float32)

    def load_depth(self) -> Float[np.ndarray, "n h w"]:
        """Ray distance per pixel (unit-direction rays, this NeRF's units; 0 where nothing is hit)."""
        return _read_array(self.folder, "depth").astype(np.float32)

    @classmethod
    def from_folder(cls, folder: Path | str, name: str | None = None, has_depth: bool | None = None) -> ViewSet:
        """A render folder as :func:`render_views_cached` wrote it (``name`` default: the renderer it records;
        ``has_depth`` default: whether it holds ``depth.npz``). Raises ``OSError``, ``KeyError``, ``ValueError`` or
        ``TypeError`` when its ``poses.json`` is missing or unreadable."""
        folder = Path(folder)
        meta = load_render_meta(folder)
        views = meta["views"]
        return cls(
            name if name is not None else meta["renderer"], folder,
            np.array([v["c2w"] for v in views], dtype=np.float64), [v["source"] for v in views],
            np.array([v["mean_accumulation"] for v in views]), np.array([v["kept"] for v in views], dtype=bool),
            reused=True, render_seconds=meta.get("render_seconds"),
            has_depth=(folder / "depth.npz").is_file() if has_depth is None else has_depth,
        )


# What a damaged or truncated cache file raises when read.
_ARRAY_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def _read_array(folder: Path, name: str) -> np.ndarray:
    """``<folder>/<name>.npz``'s array ``name``, as stored (raises one of ``_ARRAY_ERRORS`` when damaged)."""
    with np.load(folder / f"{name}.npz") as z:
        return z[name]


def _decode_error(image: Path) -> str | None:
    """Why ``image`` cannot be decoded (a missing or truncated file), or None."""
    try:
        with Image.open(image) as im:
            im.load()  # decodes: a truncated file fails here
    except (OSError, ValueError) as e:
        return type(e).__name__
    return None


def render_key(renderer: Renderer, cfg: PoseSamplingConfig, depth: bool = False) -> str:
    """Hash of everything the renders depend on: the renderer's own key (weights, mtime), the sampling settings and
    whether depth is stored (keys without depth are those of folders written before depth could be)."""
    key = {"renderer": renderer.cache_key(), "sampling": asdict(cfg), "version": FORMAT_VERSION}
    return content_hash({**key, "depth": True} if depth else key)[:16]


def load_render_meta(folder: Path | str) -> dict[str, Any]:
    """A render folder's ``poses.json`` as written by :func:`render_views_cached` (raises ``OSError`` or
    ``ValueError`` when it is missing or not JSON)."""
    return json.loads((Path(folder) / POSES_FILE).read_text())


def load_render_intrinsics(folder: Path | str) -> Intrinsics:
    """The camera a render folder's views were rendered with (its ``poses.json``)."""
    return Intrinsics(**load_render_meta(folder)["intrinsics"])


def _damage(views: ViewSet) -> str | None:
    """What is wrong with a cached render folder (a missing or truncated image, unreadable accumulation), or None."""
    try:
        if views.load_accumulation().shape[0] != len(views.c2w):
            return "accumulation.npz does not match poses.json"
        if views.has_depth and views.load_depth().shape[0] != len(views.c2w):
            return "depth.npz does not match poses.json"
    except _ARRAY_ERRORS as e:
        return f"accumulation.npz or depth.npz: {type(e).__name__}"
    for k in range(len(views.c2w)):
        if error := _decode_error(views.folder / "images" / f"{k:05d}.png"):
            return f"images/{k:05d}.png: {error}"
    return None


def _pose_key(c2w: np.ndarray) -> tuple[float, ...]:
    """A pose as stored in ``poses.json`` (rounded as :func:`json_matrix` rounds), for exact look-ups."""
    return tuple(np.asarray(json_matrix(c2w), dtype=np.float64).ravel().tolist())


class EarlierViews:
    """Views the same run already rendered at the same intrinsics, in other folders of ``renders_root``: a pose
    source tried after another (``both`` after ``training``) renders only the poses it adds. Folders that cannot be
    read are passed over (their views are rendered)."""

    def __init__(self, renders_root: Path, renderer: Renderer, intrinsics: Intrinsics, depth: bool):
        self.depth, self.reused = depth, 0
        self._index: dict[tuple[float, ...], tuple[Path, int]] = {}
        self._arrays: dict[Path, tuple[np.ndarray, np.ndarray | None] | None] = {}
        key, intr = json.loads(json.dumps(renderer.cache_key())), json.loads(json.dumps(asdict(intrinsics)))
        folders = sorted(renders_root.iterdir()) if renders_root.is_dir() else []
        for folder in folders:
            if folder.name.startswith(".") or (depth and not (folder / "depth.npz").is_file()):
                continue
            try:
                meta = load_render_meta(folder)
                if meta.get("cache_key") != key or meta.get("intrinsics") != intr:
                    continue
                for j, view in enumerate(meta["views"]):
                    self._index.setdefault(_pose_key(np.asarray(view["c2w"])), (folder, j))
            except (OSError, ValueError, KeyError, TypeError):
                continue

    def _load(self, folder: Path) -> tuple[np.ndarray, np.ndarray | None] | None:
        if folder not in self._arrays:
            try:
                self._arrays[folder] = (_read_array(folder, "accumulation"),
                                        _read_array(folder, "depth") if self.depth else None)  # fmt: skip
            except _ARRAY_ERRORS:
                self._arrays[folder] = None
        return self._arrays[folder]

    def copy(
        self, c2w: np.ndarray, image: Path, accs: np.ndarray, depths: np.ndarray | None, k: int
    ) -> bool:
        """Fill view ``k`` (its image file, accumulation and depth) from an earlier render of ``c2w``; False when
        there is none to take."""
        found = self._index.get(_pose_key(c2w))
        arrays = None if found is None else self._load(found[0])
        if found is None or arrays is None or found[1] >= len(arrays[0]):
            return False
        folder, j = found
        source = folder / "images" / f"{j:05d}.png"
        if _decode_error(source):  # a truncated image is rendered again, not copied
            return False
        shutil.copyfile(source, image)
        accs[k] = arrays[0][j]
        if depths is not None and arrays[1] is not None:
            depths[k] = arrays[1][j]
        self.reused += 1
        return True


def render_views_cached(
    renderer: Renderer, cfg: PoseSamplingConfig, renders_root: Path, console: Console = CONSOLE, depth: bool = False
) -> ViewSet:
    """Sample poses and render them into ``renders_root/<key>``, or reuse the folder a previous run left there;
    ``depth`` also stores each view's rendered depth (the renderer must take ``depth=True``)."""
    key = render_key(renderer, cfg, depth)
    folder = renders_root / key
    if (folder / POSES_FILE).is_file():
        try:
            cached = ViewSet.from_folder(folder, renderer.name, has_depth=depth)
            damage = _damage(cached)
        except (KeyError, ValueError, TypeError) as e:
            damage = f"unreadable poses.json ({type(e).__name__})"
        if damage is None:
            return cached
        console.print(f"[yellow]{renderer.name}: cached renders in {folder} are damaged ({damage}); rendering again[/]")
        shutil.rmtree(folder, ignore_errors=True)

    c2w, sources = sample_poses(renderer, cfg)
    intr = cfg.intrinsics()
    earlier = EarlierViews(renders_root, renderer, intr, depth)
    renders_root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{key}.tmp-", dir=renders_root))
    start = time.perf_counter()
    try:
        (tmp / "images").mkdir()
        accs = np.zeros((len(c2w), intr.height, intr.width), dtype=np.float16)
        depths = np.zeros((len(c2w), intr.height, intr.width), dtype=np.float32) if depth else None
        bad = []
        with _progress(console) as bar:
            task = bar.add_task(f"rendering {renderer.name}", total=len(c2w))
            for k in range(len(c2w)):
                if earlier.copy(c2w[k], tmp / "images" / f"{k:05d}.png", accs, depths, k):
                    bar.advance(task)
                    continue
                # renderers without depth need not take the keyword
                out = renderer.render(c2w[k : k + 1], intr, **({"depth": True} if depth else {}))
                rgb = np.asarray(out.rgb[0], dtype=np.float32)
                if rgb.shape != (intr.height, intr.width, 3):
                    raise RegistrationError(
                        f"{renderer.name}: rendered an image of shape {rgb.shape}, expected "
                        f"{(intr.height, intr.width, 3)}"
                    )
                acc = np.ones(rgb.shape[:2], np.float32) if out.accumulation is None else out.accumulation[0]
                if not (np.isfinite(rgb).all() and np.isfinite(acc).all()):
                    bad.append(k)
                if depth:
                    if out.depth is None:
                        raise RegistrationError(f"{renderer.name}: its renderer gives no depth; use --mode sfm")
                    depths[k] = np.where(np.isfinite(out.depth[0]), out.depth[0], 0.0)
                Image.fromarray(to_uint8(rgb)).save(tmp / "images" / f"{k:05d}.png", compress_level=1)
                accs[k] = np.nan_to_num(acc, nan=0.0).clip(0, 1)
                bar.advance(task)
        if earlier.reused:
            console.print(f"{renderer.name}: {earlier.reused} of {len(c2w)} views taken from earlier renders of the "
                          f"same run in {renders_root}")  # fmt: skip
        if bad:
            raise RegistrationError(
                f"{renderer.name}: rendered NaN or inf in {len(bad)} of {len(c2w)} views (a diverged run?); "
                "check the run or pass another checkpoint"
            )
        np.savez_compressed(tmp / "accumulation.npz", accumulation=accs)
        if depth:
            np.savez_compressed(tmp / "depth.npz", depth=depths)
        mean_acc = accs.astype(np.float32).mean(axis=(1, 2))
        kept = mean_acc >= cfg.min_view_accumulation
        meta = {
            "renderer": renderer.name,
            "render_seconds": time.perf_counter() - start,
            "cache_key": renderer.cache_key(),
            "sampling": asdict(cfg),
            "intrinsics": asdict(intr),
            "reused_views": earlier.reused,
            "views": [
                {"file": f"images/{k:05d}.png", "c2w": json_matrix(c2w[k]), "source": sources[k],
                 "mean_accumulation": float(mean_acc[k]), "kept": bool(kept[k])}
                for k in range(len(c2w))
            ],
        }
        (tmp / POSES_FILE).write_text(json.dumps(meta, indent=1) + "\n")
        os.chmod(tmp, 0o755)
        if folder.exists():  # a damaged entry
            shutil.rmtree(folder)
        os.rename(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    # The poses as stored, so a first run and a rerun on the cache compute from identical numbers.
    stored = np.array([v["c2w"] for v in meta["views"]], dtype=np.float64)
    return ViewSet(renderer.name, folder, stored, sources, mean_acc, kept, False, meta["render_seconds"], depth)


def check_kept_views(views: Sequence[ViewSet], min_views: int, cfg: PoseSamplingConfig) -> None:
    """Every NeRF needs ``min_views`` views that see enough for the SfM."""
    for vs in views:
        if vs.kept.sum() < min_views:
            raise RegistrationError(
                f"{vs.name}: only {int(vs.kept.sum())} of {len(vs.c2w)} rendered views see enough (mean accumulation "
                f">= {cfg.min_view_accumulation}); aim the views at the content: {SUGGESTION}"
            )


def check_inputs(renderers: Sequence[Renderer], config: RegistrationConfig) -> tuple[int, int, Intrinsics]:
    """Before anything is rendered: the NeRFs and settings make sense. Returns the reference index, the views each
    NeRF needs in the SfM model, and the render intrinsics."""
    k = len(renderers)
    names = [r.name for r in renderers]
    if k < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {k}")
    if not -k <= config.reference < k:
        raise RegistrationError(f"reference index {config.reference} out of range for {k} NeRFs")
    if config.estimator not in ("nerfuser", "nerfuser-median", "umeyama-ransac"):
        raise RegistrationError(f"unknown estimator {config.estimator!r}")
    keys = [render_key(r, config.sampling) for r in renderers]
    for a in range(k):
        for b in range(a):
            if keys[a] == keys[b]:
                raise RegistrationError(f"{names[a]}: passed twice (same run as {names[b]}); pass distinct runs")
    min_views = max(config.min_registered_views, 3 if config.estimator == "umeyama-ransac" else 2)
    return config.reference % k, min_views, validate_settings(config)
