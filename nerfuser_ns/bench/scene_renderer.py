"""A ground-truth generated scene as a :class:`~nerfuser_ns.renderers.Renderer`: a perfect NeRF in a known frame.

It makes end-to-end registration tests and benchmarks fast and exact: the frame's SIM(3) to the world is known.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
from jaxtyping import Float

from nerfuser_ns.bench.scenes import render
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.renderers import RenderBatch, as_4x4
from nerfuser_ns.sim3 import compose, decompose_sim3, invert_sim3, transform_poses


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
        self._training = None if training_c2w is None else as_4x4(training_c2w)
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
        world = transform_poses(self.frame_to_world, as_4x4(c2w))
        scale = float(decompose_sim3(self.frame_to_world)[2])  # world units per frame unit
        k = intrinsics
        rgbs, accs, depths = [], [], []
        for pose in world:
            out = render(self.scene, pose, k, supersample=self.supersample)
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
