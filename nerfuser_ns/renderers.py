"""Things that render images from camera poses, for registration from re-rendering.

Registration only needs "something that renders RGB from a camera-to-world pose in its own frame": the
:class:`Renderer` protocol. :class:`NerfstudioRenderer` adapts a trained nerfstudio run, loaded lazily from its own
config.yml (see :mod:`nerfuser_ns.runs`); the benchmark kit adds a ground-truth scene renderer
(``nerfuser_ns.bench.scene_renderer``).

Poses are camera-to-world 4x4 in nerfstudio's OpenGL camera convention, intrinsics a :class:`cameras.Intrinsics`.
"""

from __future__ import annotations

import copy
import functools
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from jaxtyping import Float

from nerfuser_ns import runs
from nerfuser_ns.cameras import Intrinsics


@dataclass
class RenderBatch:
    """Rendered views."""

    rgb: Float[np.ndarray, "n h w 3"]
    """Colour, float32 in [0, 1]."""
    accumulation: Float[np.ndarray, "n h w"] | None = None
    """Opacity along each pixel's ray in [0, 1] (None if the renderer has no notion of it: everything is seen)."""
    depth: Float[np.ndarray, "n h w"] | None = None
    """Distance along each pixel-centre ray (unit direction; ray distance, not z-depth, as nerfstudio's ``depth``) in
    the renderer's frame units, 0 where nothing is hit; only when asked for (``render(..., depth=True)``)."""


@runtime_checkable
class Renderer(Protocol):
    """Renders RGB (and accumulation) from camera poses expressed in the renderer's own frame."""

    name: str
    """Human-readable name, used in messages and the registration file."""

    def cache_key(self) -> str:
        """A string that changes whenever the renders would (weights file, its mtime...): keys the render cache."""
        ...

    def render(self, c2w: Float[np.ndarray, "n 4 4"], intrinsics: Intrinsics) -> RenderBatch:
        """Render the views ``c2w`` (own frame, OpenGL axes) with shared pinhole ``intrinsics``.

        Renderers that can also render depth take a keyword ``depth: bool = False`` and then fill
        :attr:`RenderBatch.depth` (both adapters below do).
        """
        ...

    def training_poses(self) -> Float[np.ndarray, "n 4 4"] | None:
        """Camera-to-world poses the renderer was trained from, in its own frame (None if unknown).

        Renderers may also have ``training_intrinsics() -> Intrinsics | None``, the typical pinhole intrinsics of
        their training cameras: registration's default render camera (both adapters below do).
        """
        ...


def gives_depth(renderer: Renderer) -> bool:
    """Whether the renderer can render depth beside the images (its ``render`` takes ``depth``)."""
    return "depth" in inspect.signature(renderer.render).parameters


def as_4x4(c2w: np.ndarray) -> np.ndarray:
    """Poses as float64 [N, 4, 4] from [4, 4], [3, 4], [N, 3, 4] or [N, 4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim == 2:
        c2w = c2w[None]
    if c2w.shape[-2:] == (3, 4):
        c2w = np.concatenate([c2w, np.broadcast_to([0.0, 0.0, 0.0, 1.0], c2w.shape[:-2] + (1, 4))], axis=-2)
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f"poses must be [N, 3|4, 4], got {c2w.shape}")
    return c2w


class NerfstudioRenderer:
    """A trained nerfstudio run, rebuilt from its own config.yml on first use.

    Construction checks the config and that a checkpoint exists (``runs.RunLoadError`` otherwise) without loading
    any weights, so bad inputs fail before anything is rendered.
    """

    def __init__(
        self,
        config_path: Path | str,
        device: str = "cpu",
        data_override: Path | None = None,
        eval_num_rays_per_chunk: int | None = None,
        name: str | None = None,
    ):
        self.config_path = runs.resolve_config_path(config_path)
        config = runs.read_config(self.config_path)
        self.checkpoint_path, self.step = runs.find_checkpoint(self.config_path, config)
        self.camera_optimizer_mode = runs.camera_optimizer_mode(config)
        """The run's camera optimiser as trained (None: its model has none)."""
        self.name = name or str(config_path)
        self.device = device
        self.data_override = data_override
        self._dataset_path = runs.dataset_path(config, data_override)
        self.eval_num_rays_per_chunk = eval_num_rays_per_chunk
        self._loaded = None
        self._training_views = None

    def __getstate__(self) -> dict:
        # a copy sent to another process (a Ray task) loads the run there, lazily, instead of carrying the model
        return {**self.__dict__, "_loaded": None}

    @functools.cached_property
    def data_to_nerf(self) -> np.ndarray | None:
        """SIM(3) from the run's stored dataset frame to its NeRF frame (reads the dataset: see runs)."""
        return runs.read_dataparser_transform(self.config_path, self.data_override)

    def _load(self):
        if self._loaded is None:
            self._loaded = runs.load_run(
                self.config_path,
                device=self.device,
                data_override=self.data_override,
                eval_num_rays_per_chunk=self.eval_num_rays_per_chunk,
            )
        return self._loaded

    def training_cameras(self):  # noqa: ANN201 - nerfstudio Cameras (imported lazily)
        """The run's training cameras in its NeRF frame, parsed from its dataset (``runs.RunLoadError`` when the
        dataset cannot be read)."""
        return self._views().cameras

    def _views(self):  # noqa: ANN202 - nerfstudio DataparserOutputs (imported lazily)
        # the dataset is parsed once: cameras and image files come from the same parse
        if self._training_views is None:
            self._training_views = runs.training_views(self.config_path, self.data_override)
        return self._training_views

    def checkpoint_identity(self) -> dict:
        """The checkpoint rendered (file, step, SHA-256): recorded by the registration."""
        return runs.checkpoint_identity(self.config_path)

    def cache_key(self) -> str:
        stat = self.checkpoint_path.stat()
        ckpt = self.checkpoint_path.resolve()
        return f"nerfstudio:{self.config_path.resolve()}|{ckpt}|{stat.st_mtime_ns}|{stat.st_size}"

    def render(self, c2w: Float[np.ndarray, "n 4 4"], intrinsics: Intrinsics, depth: bool = False) -> RenderBatch:
        """Render the views; ``depth=True`` adds the model's ``depth`` output (nerfacto: the median sample distance
        along the unit-direction ray, i.e. ray distance in the NeRF frame's units)."""
        loaded = self._load()
        k = intrinsics
        cameras = runs.make_cameras(as_4x4(c2w)[:, :3, :], k)
        names = ("rgb", "accumulation", "depth") if depth else ("rgb", "accumulation")
        out = runs.render_views(loaded.model, cameras, outputs=names, progress=False)
        rgb = out["rgb"].clamp(0, 1).numpy().astype(np.float32)
        acc = out["accumulation"][..., 0].clamp(0, 1).numpy().astype(np.float32)
        return RenderBatch(rgb, acc, out["depth"][..., 0].numpy().astype(np.float32) if depth else None)

    def training_poses(self) -> Float[np.ndarray, "n 4 4"] | None:
        """The training poses as the run finally saw them: with its camera optimiser's learned corrections (stock
        nerfacto optimises poses), so the renders show what the run learned best."""
        c2w = self.training_cameras().camera_to_worlds
        return as_4x4(runs.optimized_poses(self._load().model, c2w).detach().cpu().numpy())

    def dataset_path(self) -> Path | None:
        """The run's dataset as it was given (``--data`` override or config.yml's, anchored as nerfstudio resolves it):
        a folder, or the transforms file the run trained on (``transforms_larger_side.json``); None when it records
        none or it is gone."""
        path = self._dataset_path
        if path is None:
            return None
        return path if (path.is_file() if path.suffix == ".json" else path.is_dir()) else None

    def training_image_files(self) -> list[Path]:
        """The training images, in the order of :meth:`training_cameras` (``runs.RunLoadError`` without a dataset)."""
        return [Path(f) for f in self._views().image_filenames]

    def render_training_views(self, indices: list[int], factor: int) -> list[RenderBatch]:
        """The training cameras ``indices`` rendered at 1/``factor`` of their size (each camera's own intrinsics and
        lens distortion, the camera optimiser's poses), one batch per view: what the run renders where it was shown
        the training image (with nerfacto's average appearance embedding, as for every view it did not train on)."""
        model = self._load().model
        cams = self.training_cameras()
        c2w = torch.as_tensor(self.training_poses()[:, :3, :], dtype=torch.float32)
        out = []
        for i in indices:
            cam = copy.deepcopy(cams[i : i + 1])
            width, height = int(cam.width[0, 0]) // factor, int(cam.height[0, 0]) // factor
            cam.camera_to_worlds = c2w[i : i + 1]
            cam.rescale_output_resolution(1.0 / factor)
            # set the size exactly: the image is cropped to a multiple of factor and block-averaged to this size
            cam.width, cam.height = torch.full_like(cam.width, width), torch.full_like(cam.height, height)
            views = runs.render_views(model, cam, outputs=("rgb", "accumulation"), progress=False)
            out.append(RenderBatch(views["rgb"].clamp(0, 1).numpy().astype(np.float32),
                                   views["accumulation"][..., 0].clamp(0, 1).numpy().astype(np.float32)))  # fmt: skip
        return out

    def training_intrinsics(self) -> Intrinsics | None:
        cams = self.training_cameras()
        med = [float(x.float().median()) for x in (cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height)]
        return Intrinsics(med[0], med[1], med[2], med[3], int(round(med[4])), int(round(med[5])))
