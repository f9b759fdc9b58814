"""Things that render images from camera poses, for registration from re-rendering.

Registration only needs "something that renders RGB from a camera-to-world pose in its own frame". Two adapters:

* :class:`NerfstudioRenderer`: a trained nerfstudio run, loaded lazily from its own config.yml (see
  :mod:`nerfuser_ns.runs`).
* :class:`SceneFrameRenderer`: a ground-truth generated scene (:mod:`nerfuser_ns.scenes`) seen through a frame's
  SIM(3), i.e. a perfect "NeRF" whose frame is, e.g., a capture frame. It makes end-to-end tests fast and exact.

Poses are camera-to-world 4x4 in nerfstudio's OpenGL camera convention, intrinsics a :class:`scenes.Intrinsics`.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from jaxtyping import Float

from nerfuser_ns.scenes import Intrinsics


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


def _as_4x4(c2w: np.ndarray) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim == 2:
        c2w = c2w[None]
    if c2w.shape[-2:] == (3, 4):
        c2w = np.concatenate([c2w, np.broadcast_to([0.0, 0.0, 0.0, 1.0], c2w.shape[:-2] + (1, 4))], axis=-2)
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f"poses must be [N, 3|4, 4], got {c2w.shape}")
    return c2w


class SceneFrameRenderer:
    """A ground-truth scene seen through ``frame_to_world`` (SIM(3)): a perfect NeRF living in that frame.

    A pose ``G`` in the frame is rendered from the world pose ``transform_poses(frame_to_world, G)``; the pinhole
    intrinsics are unchanged (a similarity does not change what a camera sees). Accumulation is the hit mask; depth
    is the ray-caster's world ray distance divided by the frame's scale (frame units).
    """

    def __init__(
        self,
        scene,
        frame_to_world: Float[np.ndarray, "4 4"],
        name: str,
        training_c2w: Float[np.ndarray, "n 4 4"] | None = None,
        supersample: int = 1,
        key: str = "",
    ):
        self.scene = scene
        self.frame_to_world = np.asarray(frame_to_world, dtype=np.float64)
        self.name = name
        self._training = None if training_c2w is None else _as_4x4(training_c2w)
        self.supersample = supersample
        self._key = key
        self._training_intrinsics: Intrinsics | None = None

    @classmethod
    def from_layout(
        cls, layout, capture: str, frame_to_capture: np.ndarray | None = None, supersample: int = 1
    ) -> SceneFrameRenderer:
        """The capture ``capture`` of a :class:`scenes.SceneLayout`, in the capture's frame.

        ``frame_to_capture`` (SIM(3)) puts the renderer in another frame, e.g. ``inv(data_to_nerf)`` to mimic the
        frame a nerfstudio run trained on that capture lives in. Training poses are the capture's, in that frame.
        """
        from nerfuser_ns.sim3 import compose, invert_sim3, transform_poses

        caps = {c.name: c for c in layout.captures}
        if capture not in caps:
            raise ValueError(f"no capture {capture!r} in the layout; it has {sorted(caps)}")
        cap = caps[capture]
        frame_to_capture = np.eye(4) if frame_to_capture is None else np.asarray(frame_to_capture, dtype=np.float64)
        frame_to_world = compose(cap.capture_to_world, frame_to_capture)
        training = transform_poses(invert_sim3(frame_to_capture), cap.c2w_capture)
        key = json.dumps({"layout": layout.layout, "params": layout.params}, sort_keys=True, default=str)
        renderer = cls(layout.scene, frame_to_world, capture, training, supersample, key=key)
        renderer._training_intrinsics = cap.intrinsics
        return renderer

    def cache_key(self) -> str:
        h = hashlib.sha256(self._key.encode())
        h.update(np.round(self.frame_to_world, 12).tobytes())
        h.update(f"{self.name}|{self.supersample}".encode())
        return "scene:" + h.hexdigest()

    def render(self, c2w: Float[np.ndarray, "n 4 4"], intrinsics: Intrinsics, depth: bool = False) -> RenderBatch:
        from nerfuser_ns.scenes import render
        from nerfuser_ns.sim3 import decompose_sim3, transform_poses

        world = transform_poses(self.frame_to_world, _as_4x4(c2w))
        scale = float(decompose_sim3(self.frame_to_world)[2])  # world units per frame unit
        k = intrinsics
        rgbs, accs, depths = [], [], []
        for pose in world:
            out = render(self.scene, pose, k.fx, k.fy, k.cx, k.cy, k.width, k.height, supersample=self.supersample)
            rgbs.append(out.rgb.numpy())
            accs.append(out.mask.numpy().astype(np.float32))
            depths.append(out.depth.numpy() / scale)
        return RenderBatch(
            np.stack(rgbs).astype(np.float32), np.stack(accs), np.stack(depths).astype(np.float32) if depth else None
        )

    def training_poses(self) -> Float[np.ndarray, "n 4 4"] | None:
        return None if self._training is None else self._training.copy()

    def training_intrinsics(self) -> Intrinsics | None:
        return self._training_intrinsics


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
        from nerfuser_ns import runs

        self.config_path = runs.resolve_config_path(config_path)
        config = runs.read_config(self.config_path)
        self.checkpoint_path, self.step = runs.find_checkpoint(self.config_path, config)
        self.name = name or str(config_path)
        self.device = device
        self.data_override = data_override
        self.eval_num_rays_per_chunk = eval_num_rays_per_chunk
        self._loaded = None
        self._training_cameras = None

    @functools.cached_property
    def data_to_nerf(self) -> np.ndarray | None:
        """SIM(3) from the run's stored dataset frame to its NeRF frame (reads the dataset: see runs)."""
        from nerfuser_ns import runs

        return runs.read_dataparser_transform(self.config_path, self.data_override)

    def _load(self):
        from nerfuser_ns import runs

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
        from nerfuser_ns import runs

        if self._training_cameras is None:
            self._training_cameras = runs.training_cameras(self.config_path, self.data_override)
        return self._training_cameras

    def checkpoint_identity(self) -> dict:
        """The checkpoint rendered (file, step, SHA-256): recorded by the registration."""
        from nerfuser_ns import runs

        return runs.checkpoint_identity(self.config_path)

    def cache_key(self) -> str:
        stat = self.checkpoint_path.stat()
        ckpt = self.checkpoint_path.resolve()
        return f"nerfstudio:{self.config_path.resolve()}|{ckpt}|{stat.st_mtime_ns}|{stat.st_size}"

    def render(self, c2w: Float[np.ndarray, "n 4 4"], intrinsics: Intrinsics, depth: bool = False) -> RenderBatch:
        """Render the views; ``depth=True`` adds the model's ``depth`` output (nerfacto: the median sample distance
        along the unit-direction ray, i.e. ray distance in the NeRF frame's units)."""
        from nerfuser_ns import runs

        loaded = self._load()
        k = intrinsics
        cameras = runs.make_cameras(_as_4x4(c2w)[:, :3, :], k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        names = ("rgb", "accumulation", "depth") if depth else ("rgb", "accumulation")
        out = runs.render_views(loaded.model, cameras, outputs=names, progress=False)
        rgb = out["rgb"].clamp(0, 1).numpy().astype(np.float32)
        acc = out["accumulation"][..., 0].clamp(0, 1).numpy().astype(np.float32)
        return RenderBatch(rgb, acc, out["depth"][..., 0].numpy().astype(np.float32) if depth else None)

    def training_poses(self) -> Float[np.ndarray, "n 4 4"] | None:
        """The training poses as the run finally saw them: with its camera optimiser's learned corrections (stock
        nerfacto optimises poses), so the renders show what the run learned best."""
        from nerfuser_ns import runs

        c2w = self.training_cameras().camera_to_worlds
        return _as_4x4(runs.optimized_poses(self._load().model, c2w).detach().cpu().numpy())

    def training_intrinsics(self) -> Intrinsics | None:
        cams = self.training_cameras()
        med = [float(x.float().median()) for x in (cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height)]
        return Intrinsics(med[0], med[1], med[2], med[3], int(round(med[4])), int(round(med[5])))
