"""Ground-truth synthetic scenes: textured geometry, a vectorised CPU ray-caster, capture layouts, dataset writer.

The scenes stand in for real multi-capture data sets (NeRFuser's indoor object-centric scenes and its Mission Bay
street split) with one thing real data lacks: the exact SIM(3) between every capture and the world. One more layout,
``room``, is a deliberately repetitive room (opposite walls alike) that can fool a free SfM.

Conventions used everywhere in the project:

* World frame: +z up, metres.
* Cameras follow nerfstudio: camera-to-world 4x4 matrices with OpenGL camera axes (the camera looks along -z,
  +y is up in the image, +x right); pinhole intrinsics ``fx, fy, cx, cy, width, height``; the ray of pixel
  ``(row, col)`` goes through ``(col + 0.5, row + 0.5)``.
* SIM(3): ``T = [[s R, t], [0, 0, 0, 1]]`` maps ``p_world = T @ [p_capture, 1]``. A camera pose ``[R_c | t_c]`` in
  the capture frame becomes ``[R_T R_c | s R_T t_c + t_T]`` in the world (:func:`transform_poses`): the rotation
  stays orthonormal and the camera's metric size scales with the frame.
* Capture frames are prepared as in the paper: the world camera centres of one capture are centred (their mean
  goes to the origin), rotated by a random yaw about +z (so +z stays up) and scaled so that the mean camera
  distance to the origin is 1. Hence ``capture_to_world`` has ``s`` = mean camera distance to the centre (metres),
  ``R`` = yaw rotation, ``t`` = mean camera centre.
* ``render`` returns depth as the distance along the (unit) ray. Depth PNGs on disk follow nerfstudio's
  ``depth_file_path`` convention instead: z-depth (along the camera's -z axis), in capture-frame units, times
  1000, as 16-bit PNG (``depth_unit_scale_factor: 0.001``); nerfstudio multiplies z-depth by the ray direction
  norm to get ray distance.

Textures are collages of real photographs shipped inside scikit-image (no network), modulated by multi-scale noise
so that every surface carries unique, non-repeating texture for SIFT (the room layout repeats textures on purpose).
Shading is Lambertian and view-independent (a directional light fixed per scene plus ambient, no shadows), so a NeRF
can represent it exactly.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import torch
from jaxtyping import Bool, Float, Int
from PIL import Image
from torch import Tensor

from nerfuser_ns.appearance import linear_to_srgb, srgb_to_linear
from nerfuser_ns.cameras import ArrayOrTensor, Intrinsics, camera_rays, check_positive_int, supersample_offsets
from nerfuser_ns.sampling import look_at
from nerfuser_ns.sim3 import decompose_sim3, invert_sim3, make_sim3, transform_poses

FORMAT_VERSION = 1
_NO_BOTTOM = ("-y", "+x", "+y", "-x", "top")
LayoutName = Literal["object-centric", "street", "drive", "room", "row-houses"]
LAYOUT_NAMES: tuple[str, ...] = ("object-centric", "street", "drive", "room", "row-houses")

# Photographs stored inside the scikit-image package (checked to load with the network blocked, skimage 0.26).
# Images that skimage fetches with pooch (e.g. "eagle", "kidney", "lily", "skin") are deliberately absent, and so
# are near-textureless ones (horse silhouette, mostly black hubble_deep_field / retina).
PHOTO_NAMES: tuple[str, ...] = (
    "astronaut",
    "brick",
    "camera",
    "cell",
    "chelsea",
    "clock",
    "coffee",
    "coins",
    "grass",
    "gravel",
    "immunohistochemistry",
    "moon",
    "page",
    "rocket",
    "text",
)

_EPS = 1e-6  # minimum hit distance (metres): avoids self-intersection at the ray origin
_LIGHT_DIR = (0.35, 0.25, 0.9)  # default directional light (normalised at use)
_AMBIENT = 0.45
_DIFFUSE = 0.55

def yaw_rotation(yaw: float) -> np.ndarray:
    """Rotation by ``yaw`` radians about +z (float64 [3, 3])."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------------------------
# Scene description
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class Scene:
    """Textured primitives ready for ray casting (all geometry float64, world metres).

    Every primitive owns one *surface* (one texture); ``surface_object`` groups surfaces into named objects
    (``object_names``), which the renderer reports per pixel (``object_id``).
    Quads are parallelograms ``corner + a * edge_u + b * edge_v``, a, b in [0, 1], with texture coordinates (a, b)
    (``edge_v`` is "up" in the texture). Cylinders are vertical (axis +z) and open; their caps are disks.
    Disks are horizontal.
    """

    quad_corner: Float[Tensor, "q 3"]
    quad_u: Float[Tensor, "q 3"]
    quad_v: Float[Tensor, "q 3"]
    quad_surface: Int[Tensor, " q"]
    sphere_center: Float[Tensor, "s 3"]
    sphere_radius: Float[Tensor, " s"]
    sphere_surface: Int[Tensor, " s"]
    cylinder_base: Float[Tensor, "c 3"]
    """Centre of the bottom circle."""
    cylinder_radius: Float[Tensor, " c"]
    cylinder_height: Float[Tensor, " c"]
    cylinder_surface: Int[Tensor, " c"]
    disk_center: Float[Tensor, "d 3"]
    disk_radius: Float[Tensor, " d"]
    disk_surface: Int[Tensor, " d"]
    texture_atlas: Float[Tensor, "texels 3"]
    """All surface textures, flattened row-major one after the other (float32, linear RGB in [0, 1])."""
    surface_texture_offset: Int[Tensor, " p"]
    surface_texture_height: Int[Tensor, " p"]
    surface_texture_width: Int[Tensor, " p"]
    surface_object: Int[Tensor, " p"]
    object_names: list[str]
    bbox_min: Float[np.ndarray, "3"]
    bbox_max: Float[np.ndarray, "3"]
    """Axis-aligned bounds of everything (the enclosure)."""
    object_bounds: dict[str, tuple[list[float], list[float]]] = field(default_factory=dict)
    """Per named object: axis-aligned (min, max) corners in world metres."""
    part_bounds: list[tuple[str, list[float], list[float]]] = field(default_factory=list)
    """Per solid part (box, sphere, cylinder, stand-alone quad): (object name, min, max), for free-space tests."""
    light_dir: tuple[float, float, float] = _LIGHT_DIR
    """Direction towards the directional light (normalised at use)."""

    @property
    def num_surfaces(self) -> int:
        return int(self.surface_object.shape[0])

    def object_index(self, name: str) -> int:
        return self.object_names.index(name)


class SceneBuilder:
    """Accumulates primitives and their procedurally generated textures, then freezes them into a :class:`Scene`."""

    def __init__(
        self,
        rng: np.random.Generator,
        texels_per_metre: float = 128.0,
        max_texture_size: int = 2048,
        light_dir: tuple[float, float, float] = _LIGHT_DIR,
    ):
        self.rng = rng
        self.light_dir = light_dir
        self.texels_per_metre = texels_per_metre
        self.max_texture_size = max_texture_size
        self.quads: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.spheres: list[tuple[np.ndarray, float, int]] = []
        self.cylinders: list[tuple[np.ndarray, float, float, int]] = []
        self.disks: list[tuple[np.ndarray, float, int]] = []
        self.textures: list[np.ndarray] = []
        self.surface_object: list[int] = []
        self.object_names: list[str] = []
        self.object_bounds: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.part_bounds: list[tuple[str, list[float], list[float]]] = []

    # -- textures ---------------------------------------------------------------------------------------------
    def _texture(
        self, size_u_m: float, size_v_m: float, density: float | None = None, half_turn: bool = False, **kwargs
    ) -> np.ndarray:
        """Collage texture for a surface of the given size; ``density`` (texels per metre) overrides the default;
        ``half_turn`` makes it equal to itself turned by 180 degrees (:func:`half_turn_symmetric`)."""
        density = min(density or self.texels_per_metre, self.texels_per_metre)
        density = min(density, self.max_texture_size / max(size_u_m, size_v_m))
        w = max(8, int(round(size_u_m * density)))
        h = max(8, int(round(size_v_m * density)))
        texture = make_collage_texture(self.rng, h, w, texels_per_metre=density, **kwargs)
        return half_turn_symmetric(texture) if half_turn else texture

    def _surface(self, obj: str, texture: np.ndarray) -> int:
        if obj not in self.object_names:
            self.object_names.append(obj)
        self.textures.append(texture.astype(np.float32))
        self.surface_object.append(self.object_names.index(obj))
        return len(self.textures) - 1

    def _part(self, obj: str, lo, hi) -> None:
        self.part_bounds.append((obj, np.asarray(lo, dtype=float).tolist(), np.asarray(hi, dtype=float).tolist()))

    def _grow_bounds(self, obj: str, lo: np.ndarray, hi: np.ndarray) -> None:
        if obj in self.object_bounds:
            old_lo, old_hi = self.object_bounds[obj]
            lo, hi = np.minimum(old_lo, lo), np.maximum(old_hi, hi)
        self.object_bounds[obj] = (np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))

    # -- primitives -------------------------------------------------------------------------------------------
    def add_quad(
        self, obj: str, corner, edge_u, edge_v, part: bool = True, texture: np.ndarray | None = None, **texture_kwargs
    ) -> np.ndarray:
        """Adds a quad and returns its texture; ``texture`` (float [h, w, 3]) paints it with a given image, e.g. one an
        earlier call returned, instead of a new collage."""
        corner, edge_u, edge_v = (np.asarray(a, dtype=np.float64) for a in (corner, edge_u, edge_v))
        if texture is None:
            texture = self._texture(float(np.linalg.norm(edge_u)), float(np.linalg.norm(edge_v)), **texture_kwargs)
        self.quads.append((corner, edge_u, edge_v, self._surface(obj, texture)))
        pts = corner + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) @ np.stack([edge_u, edge_v])
        self._grow_bounds(obj, pts.min(0), pts.max(0))
        if part:
            self._part(obj, pts.min(0), pts.max(0))
        return texture

    def add_box(
        self,
        obj: str,
        center,
        size,
        yaw: float = 0.0,
        inward: bool = False,
        faces: Sequence[str] = ("-y", "+x", "+y", "-x", "top", "bottom"),
        textures: dict[str, np.ndarray] | None = None,
        **texture_kwargs,
    ) -> dict[str, np.ndarray]:
        """Box with centre ``center``, extents ``size`` (x, y, z before yaw), rotated by ``yaw`` about +z.

        ``inward`` only matters for texture orientation (rooms are seen from inside); ``faces`` (box-local
        -y, +x, +y, -x, top, bottom) drops faces never seen, e.g. the bottom of a box standing on the floor.
        Returns the faces' textures by face name; ``textures`` (such a dict) paints the faces it names with the
        given images instead of new collages, e.g. to repeat a box exactly.
        """
        textures = textures or {}
        c = np.asarray(center, dtype=np.float64)
        h = 0.5 * np.asarray(size, dtype=np.float64)
        R = yaw_rotation(yaw)
        ex, ey, ez = R[:, 0] * h[0], R[:, 1] * h[1], R[:, 2] * h[2]
        # Side faces: edge_u horizontal, edge_v up, so photographs stand upright; order picks the viewing side.
        sides = [(-ex - ey, 2 * ex), (ex - ey, 2 * ey), (ex + ey, -2 * ex), (-ex + ey, -2 * ey)]
        quads = {}
        for face, (start, along) in zip(("-y", "+x", "+y", "-x"), sides, strict=True):
            if inward:
                start, along = start + along, -along
            quads[face] = (c + start - ez, along, 2 * ez)
        quads["top"] = (c - ex - ey + ez, 2 * ex, 2 * ey)
        quads["bottom"] = (c - ex - ey - ez, 2 * ex, 2 * ey)
        drawn = {}
        for face, quad in quads.items():
            if face in faces:
                drawn[face] = self.add_quad(obj, *quad, part=False, texture=textures.get(face), **texture_kwargs)
        corners = c + np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) @ np.stack([ex, ey, ez])
        self._part(obj, corners.min(0), corners.max(0))
        return drawn

    def add_sphere(self, obj: str, center, radius: float, **texture_kwargs) -> None:
        center = np.asarray(center, dtype=np.float64)
        tex = self._texture(2 * math.pi * radius, math.pi * radius, **texture_kwargs)
        self.spheres.append((center, float(radius), self._surface(obj, tex)))
        self._grow_bounds(obj, center - radius, center + radius)
        self._part(obj, center - radius, center + radius)

    def add_cylinder(self, obj: str, base, radius: float, height: float, caps: bool = True, **texture_kwargs) -> None:
        base = np.asarray(base, dtype=np.float64)
        tex = self._texture(2 * math.pi * radius, height, **texture_kwargs)
        self.cylinders.append((base, float(radius), float(height), self._surface(obj, tex)))
        if caps:
            self.add_disk(obj, base + np.array([0.0, 0.0, height]), radius, **texture_kwargs)
        self._grow_bounds(obj, base - [radius, radius, 0], base + [radius, radius, height])
        self._part(obj, base - [radius, radius, 0], base + [radius, radius, height])

    def add_disk(self, obj: str, center, radius: float, **texture_kwargs) -> None:
        center = np.asarray(center, dtype=np.float64)
        tex = self._texture(2 * radius, 2 * radius, **texture_kwargs)
        self.disks.append((center, float(radius), self._surface(obj, tex)))
        self._grow_bounds(obj, center - [radius, radius, 0], center + [radius, radius, 0])

    def build(self) -> Scene:
        def vec(items, i, dim=3):
            arr = np.array([it[i] for it in items], dtype=np.float64).reshape(len(items), *([dim] if dim else []))
            return torch.from_numpy(arr)

        def ids(items):
            return torch.tensor([it[-1] for it in items], dtype=torch.long)

        sizes = [t.shape[0] * t.shape[1] for t in self.textures]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        atlas = np.concatenate([t.reshape(-1, 3) for t in self.textures], axis=0)
        all_lo = np.min([b[0] for b in self.object_bounds.values()], axis=0)
        all_hi = np.max([b[1] for b in self.object_bounds.values()], axis=0)
        return Scene(
            quad_corner=vec(self.quads, 0),
            quad_u=vec(self.quads, 1),
            quad_v=vec(self.quads, 2),
            quad_surface=ids(self.quads),
            sphere_center=vec(self.spheres, 0),
            sphere_radius=vec(self.spheres, 1, None),
            sphere_surface=ids(self.spheres),
            cylinder_base=vec(self.cylinders, 0),
            cylinder_radius=vec(self.cylinders, 1, None),
            cylinder_height=vec(self.cylinders, 2, None),
            cylinder_surface=ids(self.cylinders),
            disk_center=vec(self.disks, 0),
            disk_radius=vec(self.disks, 1, None),
            disk_surface=ids(self.disks),
            texture_atlas=torch.from_numpy(np.ascontiguousarray(atlas, dtype=np.float32)),
            surface_texture_offset=torch.from_numpy(offsets),
            surface_texture_height=torch.tensor([t.shape[0] for t in self.textures], dtype=torch.long),
            surface_texture_width=torch.tensor([t.shape[1] for t in self.textures], dtype=torch.long),
            surface_object=torch.tensor(self.surface_object, dtype=torch.long),
            object_names=list(self.object_names),
            bbox_min=all_lo,
            bbox_max=all_hi,
            object_bounds={k: (v[0].tolist(), v[1].tolist()) for k, v in self.object_bounds.items()},
            part_bounds=list(self.part_bounds),
            light_dir=tuple(float(v) for v in self.light_dir),
        )


# ----------------------------------------------------------------------------------------------------------------
# Textures
# ----------------------------------------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def load_photos() -> tuple[np.ndarray, ...]:
    """The photographs of :data:`PHOTO_NAMES` as float32 RGB [h, w, 3] in [0, 1] (grey images get 3 channels).

    Only images bundled inside the scikit-image package are used: this never downloads anything.
    """
    import skimage.data  # here, not at the top: its import loads the whole package; only textures need it

    photos = []
    for name in PHOTO_NAMES:
        img = np.asarray(getattr(skimage.data, name)())
        if img.dtype == np.bool_:
            img = img.astype(np.float32)
        img = img.astype(np.float32)
        img = img / 255.0 if img.max() > 1.0 else img
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=-1)
        photos.append(np.ascontiguousarray(img[..., :3]))
    return tuple(photos)


def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Anti-aliased bilinear resize (deterministic) via PIL, per channel in float32."""
    chans = [np.asarray(Image.fromarray(img[..., c]).resize((w, h), Image.Resampling.BILINEAR, reducing_gap=None))
             for c in range(img.shape[-1])]
    return np.stack(chans, axis=-1)


def _value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """Smooth random field in [-1, 1] with feature size ``cell`` texels (bicubic upsampled random grid)."""
    gh, gw = max(2, int(math.ceil(h / cell)) + 1), max(2, int(math.ceil(w / cell)) + 1)
    grid = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    up = np.asarray(Image.fromarray(grid).resize((int(gw * cell), int(gh * cell)), Image.Resampling.BICUBIC))
    return np.clip(up[:h, :w], -1.0, 1.0)


def make_collage_texture(
    rng: np.random.Generator,
    height: int,
    width: int,
    texels_per_metre: float,
    patch_size_m: tuple[float, float] = (0.25, 0.9),
    patches_per_m2: float = 4.0,
    tint: Sequence[float] | None = None,
    noise_amplitude: float = 0.25,
    photo_names: Sequence[str] | None = None,
) -> Float[np.ndarray, "h w 3"]:
    """A unique (non-repeating) texture: a random photograph crop overlaid with many smaller photo patches.

    Patches get random crops, flips, quarter turns and colour gains, so no two surfaces (or parts of one surface)
    look alike; a multi-scale noise modulation keeps flat photo regions (skies, dark backgrounds) textured.
    """
    photos = load_photos()
    if photo_names is not None:
        photos = tuple(photos[PHOTO_NAMES.index(name)] for name in photo_names)

    def crop(h: int, w: int) -> np.ndarray:
        img = photos[int(rng.integers(len(photos)))]
        if rng.random() < 0.5:
            img = np.ascontiguousarray(np.rot90(img))
        ih, iw = img.shape[:2]
        # Crop the largest window of the target aspect, at a random zoom, then resize.
        aspect = w / h
        ch = min(ih, iw / aspect) * rng.uniform(0.4, 1.0)
        cw = ch * aspect
        y0 = int(rng.uniform(0, ih - ch + 1e-9))
        x0 = int(rng.uniform(0, iw - cw + 1e-9))
        patch = img[y0 : y0 + max(1, int(ch)), x0 : x0 + max(1, int(cw))]
        patch = _resize(np.ascontiguousarray(patch), h, w)
        if rng.random() < 0.5:
            patch = patch[:, ::-1]
        gain = rng.uniform(0.75, 1.3, size=3).astype(np.float32)
        return patch * gain

    canvas = crop(height, width)
    area = height * width / texels_per_metre**2
    num_patches = int(rng.poisson(patches_per_m2 * area)) + 1
    for _ in range(num_patches):
        ph = int(np.clip(rng.uniform(*patch_size_m) * texels_per_metre, 4, height))
        pw = int(np.clip(ph * rng.uniform(0.6, 1.6), 4, width))
        y0, x0 = int(rng.integers(0, height - ph + 1)), int(rng.integers(0, width - pw + 1))
        canvas[y0 : y0 + ph, x0 : x0 + pw] = crop(ph, pw)
    # Multi-scale brightness modulation: feature sizes ~40 cm, ~12 cm and ~4 cm (at least 3 texels).
    mod = np.zeros((height, width), dtype=np.float32)
    for cell_m, weight in ((0.4, 0.5), (0.12, 0.3), (0.04, 0.2)):
        mod += weight * _value_noise(rng, height, width, max(3.0, cell_m * texels_per_metre))
    canvas = canvas * (1.0 + noise_amplitude * mod[..., None])
    if tint is not None:
        canvas = canvas * np.asarray(tint, dtype=np.float32)
    return np.clip(canvas, 0.0, 1.0).astype(np.float32)


def half_turn_symmetric(texture: Float[np.ndarray, "h w c"]) -> Float[np.ndarray, "h w c"]:
    """``texture`` with its second half (in row-major order) replaced by its first half turned by 180 degrees, so
    that the result equals itself turned by 180 degrees (``out == out[::-1, ::-1]``).

    A quad ``corner + a * edge_u + b * edge_v`` centred on a vertical axis (a floor, a ceiling) painted with it looks
    the same after a half turn about that axis: the turn maps texture coordinates (a, b) to (1 - a, 1 - b).
    """
    flat = texture.reshape(-1, texture.shape[-1]).copy()  # row-major: turning by 180 degrees reverses the order
    n = flat.shape[0]
    flat[n - n // 2 :] = flat[: n // 2][::-1]
    return flat.reshape(texture.shape)


# ----------------------------------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------------------------------


class RayHits(NamedTuple):
    """Result of :func:`render_rays` (leading dims as the input rays)."""

    rgb: Float[Tensor, "*bs 3"]
    """Shaded colour (float32 in [0, 1]; 0 where the ray misses)."""
    depth: Float[Tensor, "*bs"]
    """Distance along the ray to the hit in the rays' units (``inf`` on a miss); for unit directions: ray distance."""
    mask: Bool[Tensor, "*bs"]
    """Whether the ray hit anything."""
    object_id: Int[Tensor, "*bs"]
    """Index into ``scene.object_names`` (-1 on a miss)."""


def _first_positive(t: Tensor, valid: Tensor) -> Tensor:
    return torch.where(valid & (t > _EPS), t, torch.full_like(t, math.inf))


def _intersect(scene: Scene, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Nearest hit of each ray: (t [n], surface [n], normal [n, 3], uv [n, 2]); t = inf on a miss."""
    n = o.shape[0]
    cand_t, cand_kind, cand_idx = [], [], []

    # Quads: plane hit then parallelogram coordinates (a, b) via the dual basis of (edge_u, edge_v).
    qc, qu, qv = scene.quad_corner, scene.quad_u, scene.quad_v
    qn = torch.cross(qu, qv, dim=-1)
    uu, uv_, vv = (qu * qu).sum(-1), (qu * qv).sum(-1), (qv * qv).sum(-1)
    det = uu * vv - uv_**2
    du = (vv[:, None] * qu - uv_[:, None] * qv) / det[:, None]  # dual vectors: a = du . (p - c)
    dv = (uu[:, None] * qv - uv_[:, None] * qu) / det[:, None]
    denom = d @ qn.T
    safe = torch.where(denom.abs() > 1e-12, denom, torch.full_like(denom, 1e-12))
    tq = ((qc * qn).sum(-1) - o @ qn.T) / safe
    a = o @ du.T - (qc * du).sum(-1) + tq * (d @ du.T)
    b = o @ dv.T - (qc * dv).sum(-1) + tq * (d @ dv.T)
    tq = _first_positive(tq, (denom.abs() > 1e-12) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1))
    cand_t.append(tq)

    # Spheres: nearest positive root of |o + t d - c|^2 = r^2 (d is unit length).
    oc = o[:, None, :] - scene.sphere_center[None]
    bh = (oc * d[:, None, :]).sum(-1)
    disc = bh**2 - ((oc * oc).sum(-1) - scene.sphere_radius**2)
    sq = torch.sqrt(disc.clamp_min(0))
    t0, t1 = -bh - sq, -bh + sq
    ts = torch.where(t0 > _EPS, t0, t1)
    cand_t.append(_first_positive(ts, disc >= 0))

    # Open vertical cylinders: quadratic in xy, then the z range.
    ocx = o[:, None, :2] - scene.cylinder_base[None, :, :2]
    dxy = d[:, None, :2]
    qa = (dxy * dxy).sum(-1)
    qb = (ocx * dxy).sum(-1)
    qc_ = (ocx * ocx).sum(-1) - scene.cylinder_radius**2
    disc = qb**2 - qa * qc_
    sq = torch.sqrt(disc.clamp_min(0))
    qa_safe = torch.where(qa > 1e-12, qa, torch.ones_like(qa))
    best = torch.full_like(qa, math.inf)
    for tc in ((-qb + sq) / qa_safe, (-qb - sq) / qa_safe):  # far root first so the near one wins
        z = o[:, None, 2] + tc * d[:, None, 2] - scene.cylinder_base[None, :, 2]
        ok = (disc >= 0) & (qa > 1e-12) & (z >= 0) & (z <= scene.cylinder_height) & (tc > _EPS)
        best = torch.where(ok & (tc < best), tc, best)
    cand_t.append(best)

    # Horizontal disks.
    dz = d[:, None, 2]
    dz_safe = torch.where(dz.abs() > 1e-12, dz, torch.full_like(dz, 1e-12))
    td = (scene.disk_center[None, :, 2] - o[:, None, 2]) / dz_safe
    pxy = o[:, None, :2] + td[..., None] * d[:, None, :2] - scene.disk_center[None, :, :2]
    inside = ((pxy * pxy).sum(-1) <= scene.disk_radius**2) & (dz.abs() > 1e-12)
    cand_t.append(_first_positive(td, inside))

    counts = [t.shape[1] for t in cand_t]
    for kind, c in enumerate(counts):
        cand_kind.append(torch.full((c,), kind, dtype=torch.long))
        cand_idx.append(torch.arange(c))
    all_t = torch.cat(cand_t, dim=1)
    kinds, idxs = torch.cat(cand_kind), torch.cat(cand_idx)
    if all_t.shape[1] == 0:
        return (torch.full((n,), math.inf, dtype=o.dtype), torch.full((n,), -1, dtype=torch.long),
                torch.zeros_like(o), torch.zeros(n, 2, dtype=o.dtype))
    t, arg = all_t.min(dim=1)
    kind, idx = kinds[arg], idxs[arg]
    hit = torch.isfinite(t)
    p = o + torch.where(hit, t, torch.zeros_like(t))[:, None] * d

    surface = torch.full((n,), -1, dtype=torch.long)
    normal = torch.zeros_like(o)
    uv = torch.zeros(n, 2, dtype=o.dtype)
    two_pi = 2 * math.pi

    m = hit & (kind == 0)
    if m.any():
        k = idx[m]
        rel = p[m] - qc[k]
        uv[m] = torch.stack([(rel * du[k]).sum(-1), (rel * dv[k]).sum(-1)], -1)
        normal[m] = qn[k] / torch.linalg.norm(qn[k], dim=-1, keepdim=True)
        surface[m] = scene.quad_surface[k]
    m = hit & (kind == 1)
    if m.any():
        k = idx[m]
        nrm = (p[m] - scene.sphere_center[k]) / scene.sphere_radius[k, None]
        u = torch.atan2(nrm[:, 1], nrm[:, 0]) / two_pi + 0.5
        v = 1.0 - torch.arccos(nrm[:, 2].clamp(-1, 1)) / math.pi
        uv[m], normal[m], surface[m] = torch.stack([u, v], -1), nrm, scene.sphere_surface[k]
    m = hit & (kind == 2)
    if m.any():
        k = idx[m]
        rel = p[m] - scene.cylinder_base[k]
        nrm = torch.cat([rel[:, :2] / scene.cylinder_radius[k, None], torch.zeros_like(rel[:, :1])], -1)
        u = torch.atan2(nrm[:, 1], nrm[:, 0]) / two_pi + 0.5
        v = rel[:, 2] / scene.cylinder_height[k]
        uv[m], normal[m], surface[m] = torch.stack([u, v], -1), nrm, scene.cylinder_surface[k]
    m = hit & (kind == 3)
    if m.any():
        k = idx[m]
        rel = (p[m, :2] - scene.disk_center[k, :2]) / (2 * scene.disk_radius[k, None]) + 0.5
        nrm = torch.zeros_like(p[m])
        nrm[:, 2] = 1.0
        uv[m], normal[m], surface[m] = rel, nrm, scene.disk_surface[k]
    return t, surface, normal, uv


def _sample_texture(scene: Scene, surface: Tensor, uv: Tensor) -> Tensor:
    """Bilinear texture lookup (clamped at the edges) in the flat atlas; ``v`` points up in the image."""
    h = scene.surface_texture_height[surface].to(uv.dtype)
    w = scene.surface_texture_width[surface].to(uv.dtype)
    x = (uv[:, 0] * w - 0.5).clamp(min=torch.zeros_like(w), max=w - 1)
    y = ((1.0 - uv[:, 1]) * h - 0.5).clamp(min=torch.zeros_like(h), max=h - 1)
    x0, y0 = x.floor(), y.floor()
    fx, fy = (x - x0)[:, None].float(), (y - y0)[:, None].float()
    x0, y0 = x0.long(), y0.long()
    x1 = torch.minimum(x0 + 1, w.long() - 1)
    y1 = torch.minimum(y0 + 1, h.long() - 1)
    base, wl = scene.surface_texture_offset[surface], w.long()
    atlas = scene.texture_atlas

    def at(yy, xx):
        return atlas[base + yy * wl + xx]

    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x1) * fx * (1 - fy)
            + at(y1, x0) * (1 - fx) * fy + at(y1, x1) * fx * fy)


def render_rays(
    scene: Scene,
    origins: Float[ArrayOrTensor, "*bs 3"],
    directions: Float[ArrayOrTensor, "*bs 3"],
    chunk_size: int = 1 << 15,
) -> RayHits:
    """Casts arbitrary rays against the scene (vectorised, chunked to bound memory).

    Directions need not be unit length; ``depth`` is then the ray parameter t (hit = o + t d), so unit directions
    give metric ray distance. Shading is Lambertian and view-independent: albedo * (ambient + diffuse max(0, n.l))
    with the normal flipped towards the viewer (every surface is two-sided).
    """
    o = torch.as_tensor(origins).to(torch.float64)
    d = torch.as_tensor(directions).to(torch.float64)
    o, d = torch.broadcast_tensors(o, d)
    batch_shape = o.shape[:-1]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    norm = torch.linalg.norm(d, dim=-1)
    if torch.any(norm <= 0):
        raise ValueError("render_rays: zero-length ray direction")
    d_unit = d / norm[:, None]
    light = torch.tensor(scene.light_dir, dtype=torch.float64)
    light = light / torch.linalg.norm(light)
    rgb_out, t_out, sid_out = [], [], []
    for i in range(0, o.shape[0], chunk_size):
        oc, dc = o[i : i + chunk_size], d_unit[i : i + chunk_size]
        t, surface, normal, uv = _intersect(scene, oc, dc)
        hit = surface >= 0
        rgb = torch.zeros(oc.shape[0], 3, dtype=torch.float32)
        if hit.any():
            albedo = _sample_texture(scene, surface[hit], uv[hit])
            nrm = normal[hit]
            nrm = torch.where(((nrm * dc[hit]).sum(-1) > 0)[:, None], -nrm, nrm)  # face the viewer
            shade = _AMBIENT + _DIFFUSE * (nrm @ light).clamp_min(0)
            rgb[hit] = (albedo * shade[:, None].float()).clamp(0, 1)
        rgb_out.append(rgb)
        t_out.append(t)
        sid_out.append(surface)
    rgb, t, surface = torch.cat(rgb_out), torch.cat(t_out), torch.cat(sid_out)
    t = t / norm  # back to the caller's direction scale
    mask = surface >= 0
    object_id = torch.where(mask, scene.surface_object[surface.clamp_min(0)], torch.full_like(surface, -1))
    return RayHits(
        rgb=rgb.reshape(*batch_shape, 3),
        depth=t.reshape(batch_shape),
        mask=mask.reshape(batch_shape),
        object_id=object_id.reshape(batch_shape),
    )


class RenderOutput(NamedTuple):
    """Result of :func:`render`. Unpack as ``rgb, depth, mask, object_id = render(...)``."""

    rgb: Float[Tensor, "h w 3"]
    """Anti-aliased colour, float32 in [0, 1] (mean of the supersample rays)."""
    depth: Float[Tensor, "h w"]
    """Ray distance (not z) of the pixel-centre ray, float64, world units; 0 where nothing is hit."""
    mask: Bool[Tensor, "h w"]
    """Whether the pixel-centre ray hit anything."""
    object_id: Int[Tensor, "h w"]
    """Object hit by the pixel-centre ray (index into ``scene.object_names``; -1 on a miss)."""


def render(
    scene: Scene, c2w: Float[ArrayOrTensor, "3|4 4"], intrinsics: Intrinsics, supersample: int = 2
) -> RenderOutput:
    """Renders one pinhole camera (OpenGL axes, nerfstudio convention) posed by camera-to-world ``c2w`` (world frame).

    Colour averages a ``supersample`` x ``supersample`` grid of rays per pixel (anti-aliasing); depth, mask and
    object id come from the pixel-centre ray, the ray nerfstudio casts for that pixel.
    """
    check_positive_int("width", intrinsics.width)
    check_positive_int("height", intrinsics.height)
    offsets = supersample_offsets(supersample)
    centre_in_grid = supersample % 2 == 1  # odd grids contain the pixel centre already
    if not centre_in_grid:
        offsets = offsets + [(0.5, 0.5)]
    origins, directions = camera_rays(c2w, intrinsics, offsets)
    hits = render_rays(scene, origins, directions)
    k = supersample * supersample
    centre = k // 2 if centre_in_grid else k
    rgb = hits.rgb[:, :, :k].mean(dim=2)
    depth = torch.where(hits.mask[:, :, centre], hits.depth[:, :, centre], torch.zeros_like(hits.depth[:, :, centre]))
    return RenderOutput(rgb=rgb, depth=depth, mask=hits.mask[:, :, centre], object_id=hits.object_id[:, :, centre])


def ray_to_z_depth(depth: Float[Tensor, "h w"], intrinsics: Intrinsics) -> Float[Tensor, "h w"]:
    """Converts ray-distance depth of pixel-centre rays into z-depth (along the camera's viewing axis)."""
    k = intrinsics
    rows = torch.arange(k.height, dtype=torch.float64)[:, None]
    cols = torch.arange(k.width, dtype=torch.float64)[None, :]
    norm = torch.sqrt(((cols + 0.5 - k.cx) / k.fx) ** 2 + ((rows + 0.5 - k.cy) / k.fy) ** 2 + 1.0)
    return depth.to(torch.float64) / norm


def visibility(
    scene: Scene, points: Float[ArrayOrTensor, "n 3"], c2w: Float[np.ndarray, "m 4 4"], intrinsics: Intrinsics,
    tolerance: float = 1e-3,
) -> Bool[Tensor, "n m"]:
    """Whether each world point is seen by each camera: inside the image and not occluded (relative tolerance)."""
    pts = torch.as_tensor(np.asarray(points, dtype=np.float64))
    c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float64))
    centres = c2w_t[:, :3, 3]
    rel = pts[:, None, :] - centres[None]  # [n, m, 3]
    cam = torch.einsum("nmj,mji->nmi", rel, c2w_t[:, :3, :3])  # world -> camera axes (R^T rel)
    z = -cam[..., 2]
    k = intrinsics
    col = k.fx * cam[..., 0] / z.clamp_min(1e-9) + k.cx
    row = -k.fy * cam[..., 1] / z.clamp_min(1e-9) + k.cy
    in_image = (z > 0) & (col >= 0) & (col < k.width) & (row >= 0) & (row < k.height)
    dist = torch.linalg.norm(rel, dim=-1)
    hits = render_rays(scene, centres[None].expand_as(rel), rel / dist[..., None])
    unoccluded = hits.depth >= dist * (1 - tolerance)
    return in_image & unoccluded


# ----------------------------------------------------------------------------------------------------------------
# Captures and layouts
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class Capture:
    """A set of cameras with shared intrinsics; ``c2w_world`` are the world-frame poses (float64 [n, 4, 4])."""

    name: str
    c2w_world: Float[np.ndarray, "n 4 4"]
    intrinsics: Intrinsics
    capture_to_world: Float[np.ndarray, "4 4"]
    """SIM(3) from this capture's own frame to the world (identity for the test capture, posed in the world)."""
    focus: str = ""
    """What the capture is about (an object name or a street segment), for humans."""
    exposure: float = 1.0
    """Gain on linear RGB of every image of this capture (``LayoutParams.appearance_jitter``; the test capture: 1)."""
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Per-channel gains on linear RGB (green 1)."""

    @property
    def appearance_gains(self) -> np.ndarray | None:
        """Linear-RGB gains ``exposure * white_balance``; None when neutral (images as rendered)."""
        gains = self.exposure * np.asarray(self.white_balance, dtype=np.float64)
        return None if np.array_equal(gains, np.ones(3)) else gains

    @property
    def num_views(self) -> int:
        return int(self.c2w_world.shape[0])

    @property
    def c2w_capture(self) -> np.ndarray:
        """Poses in the capture's own frame (what transforms.json stores)."""
        return transform_poses(invert_sim3(self.capture_to_world), self.c2w_world)


@dataclass
class SceneLayout:
    """A generated scene with its training captures (each in its own frame) and a world-frame test capture."""

    layout: str
    seed: int
    params: dict[str, object]
    scene: Scene
    captures: list[Capture]
    test: Capture


def normalising_sim3(positions: Float[np.ndarray, "n 3"], yaw: float) -> np.ndarray:
    """capture->world SIM(3) of the paper's capture frame: centred on the mean camera centre, yawed, unit mean radius.

    ``s`` = mean distance of the cameras to their mean (metres per capture unit), ``R`` = yaw about +z,
    ``t`` = mean camera centre; so camera centres in the capture frame have mean norm exactly 1.
    """
    positions = np.asarray(positions, dtype=np.float64)
    centre = positions.mean(axis=0)
    scale = float(np.linalg.norm(positions - centre, axis=-1).mean())
    if scale <= 0:
        raise ValueError("capture cameras must not all coincide")
    return make_sim3(yaw_rotation(yaw), centre, scale)


@dataclass
class LayoutParams:
    """Parameters shared by all layouts (recorded in ground_truth.json)."""

    seed: int = 0
    num_views: int = 64
    """Views per training capture."""
    num_test_views: int = 12
    width: int = 192
    height: int = 144
    hfov_deg: float = 65.0
    """Horizontal field of view of every camera."""
    num_captures: int = 3
    """Number of training captures (street, drive and row houses; object-centric and room always have 2)."""
    texels_per_metre: float = 128.0
    """Texture resolution (capped at 2048 texels per surface side)."""
    symmetric: bool = False
    """Room layout only (the others ignore it): leave out the room's one asymmetric element, its door, so that the
    room is exactly symmetric under a half turn about its vertical axis (the registration becomes ambiguous)."""
    appearance_jitter: float = 0.0
    """Per training capture its own exposure and white balance, as captures filmed at different times have: exposure
    ``2^u`` stops with ``u ~ U(-j, j)``, red and blue gains ``2^v``, ``v ~ U(-j/2, j/2)`` (green 1), on linear RGB.
    0: every capture as rendered (the test capture always is)."""
    appearance_bracket: bool = False
    """Spread the captures' appearances over the jitter's range instead of drawing them: capture ``i`` of ``n`` gets
    ``u_i = j (2 i / (n - 1) - 1)`` stops of exposure, red ``2^(u_i / 2)`` and blue ``2^(-u_i / 2)`` (the largest
    exposure and white-balance differences the jitter allows, between the first and the last capture)."""

    def validate(self) -> None:
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        check_positive_int("num_views", self.num_views, minimum=4)
        check_positive_int("num_test_views", self.num_test_views, minimum=1)
        check_positive_int("width", self.width, minimum=8)
        check_positive_int("height", self.height, minimum=8)
        check_positive_int("num_captures", self.num_captures, minimum=2)
        if not 10.0 <= self.hfov_deg <= 120.0:
            raise ValueError(f"hfov_deg must be in [10, 120], got {self.hfov_deg}")
        if not 4.0 <= self.texels_per_metre <= 1024.0:
            raise ValueError(f"texels_per_metre must be in [4, 1024], got {self.texels_per_metre}")
        if not isinstance(self.symmetric, (bool, np.bool_)):
            raise ValueError(f"symmetric must be a boolean, got {self.symmetric!r}")
        if not 0.0 <= self.appearance_jitter <= 2.0:
            raise ValueError(f"appearance_jitter must be in [0, 2] stops, got {self.appearance_jitter}")
        if self.appearance_bracket and self.appearance_jitter <= 0:
            raise ValueError("appearance_bracket spreads the appearance_jitter range: set appearance_jitter > 0")


def _rng(seed: int, stream: int) -> np.random.Generator:
    """Independent, reproducible random streams (geometry, textures, cameras...) for one seed."""
    return np.random.default_rng([int(seed), stream])


def _inside_any(scene: Scene, p: np.ndarray, margin: float, ignore: Sequence[str] = ()) -> bool:
    for name, lo, hi in scene.part_bounds:
        if name in ignore:
            continue
        if np.all(p >= np.asarray(lo) - margin) and np.all(p <= np.asarray(hi) + margin):
            return True
    return False


def _valid_position(scene: Scene, p: np.ndarray, enclosure: str, margin: float = 0.25) -> bool:
    lo, hi = (np.asarray(a) for a in scene.object_bounds[enclosure])
    in_enclosure = bool(np.all(p >= lo + margin) and np.all(p <= hi - margin))
    return in_enclosure and not _inside_any(scene, p, margin, ignore=(enclosure,))


def _capture_from_world(name: str, c2w: np.ndarray, intr: Intrinsics, rng: np.random.Generator, focus: str) -> Capture:
    yaw = float(rng.uniform(-math.pi, math.pi))
    return Capture(name, c2w, intr, normalising_sim3(c2w[:, :3, 3], yaw), focus=focus)


def _line_of_sight(scene: Scene, position: np.ndarray, target: np.ndarray) -> float:
    """Distance (metres) the ray from ``position`` towards ``target`` runs before it hits the scene."""
    d = np.asarray(target, dtype=np.float64) - position
    return float(render_rays(scene, position, d / np.linalg.norm(d)).depth)


def _sample_cameras(
    scene: Scene,
    enclosure: str,
    n: int,
    propose: Callable[[int, int], tuple[np.ndarray, np.ndarray]],
    min_clearance: float = 0.0,
) -> np.ndarray:
    """Draws ``propose(i, attempt) -> (position, target)`` until the position is free space (rejection sampling)
    and, with ``min_clearance`` (metres), the camera's line of sight runs that far before it hits anything."""
    positions, targets = [], []
    for i in range(n):
        for attempt in range(200):
            pos, tgt = propose(i, attempt)
            if _valid_position(scene, pos, enclosure) and (
                min_clearance <= 0 or _line_of_sight(scene, pos, tgt) >= min_clearance
            ):
                break
        else:
            raise RuntimeError(f"could not place camera {i} in free space")
        positions.append(pos)
        targets.append(tgt)
    return look_at(np.array(positions), np.array(targets))


def make_object_centric(params: LayoutParams) -> SceneLayout:
    """Indoor room (8 x 6 x 3 m) with two distinct objects ~2.6 m apart and some furniture.

    ``object1`` is a box standing on a table-like block (left, x ~ -1.3 m); ``object2`` is a sphere on a cylindrical
    pedestal (right, x ~ +1.3 m). Capture A rings object 1 and capture B rings object 2 (three elevations,
    radius 1.7-2.3 m, looking at the object): views from the far side of one object see the other, so the captures
    overlap. Test views stand on an ellipse around both objects looking at the space between them.
    """
    params.validate()
    geo = _rng(params.seed, 0)
    b = SceneBuilder(_rng(params.seed, 1), texels_per_metre=params.texels_per_metre)
    room = (8.0, 6.0, 3.0)
    # Floor: ground-like photographs; walls and ceiling: large photo patches (recognisable, unique everywhere).
    b.add_quad("room", (-room[0] / 2, -room[1] / 2, 0.0), (room[0], 0, 0), (0, room[1], 0), patch_size_m=(0.4, 1.2),
               patches_per_m2=1.5, photo_names=("brick", "grass", "gravel", "coins", "coffee", "page"))
    b.add_box("room", (0, 0, room[2] / 2), room, inward=True, faces=_NO_BOTTOM, patch_size_m=(0.5, 1.5),
              patches_per_m2=1.0)
    o1 = np.array([-1.3, 0.0]) + geo.uniform(-0.15, 0.15, 2)
    o2 = np.array([1.3, 0.15]) + geo.uniform(-0.15, 0.15, 2)
    table_h = 0.6 * geo.uniform(0.9, 1.1)
    b.add_box("object1", (*o1, table_h / 2), (0.9, 0.7, table_h), yaw=geo.uniform(-0.3, 0.3), faces=_NO_BOTTOM)
    box_size = np.array([0.45, 0.32, 0.38]) * geo.uniform(0.9, 1.1, 3)
    b.add_box("object1", (*(o1 + geo.uniform(-0.1, 0.1, 2)), table_h + box_size[2] / 2), box_size,
              yaw=geo.uniform(0, math.pi), patch_size_m=(0.1, 0.3), patches_per_m2=8)
    ped_h, sph_r = 0.55 * geo.uniform(0.9, 1.1), 0.38 * geo.uniform(0.9, 1.1)
    b.add_cylinder("object2", (*o2, 0.0), 0.25, ped_h)
    b.add_sphere("object2", (*o2, ped_h + sph_r - 0.03), sph_r, patch_size_m=(0.15, 0.4), patches_per_m2=6)
    # Furniture along the walls: parallax and texture for the room, never in the middle.
    b.add_box("cabinet", (-3.5, 2.45, 0.9), (0.8, 0.9, 1.8), yaw=geo.uniform(-0.1, 0.1), faces=_NO_BOTTOM)
    b.add_box("bench", (0.5, -2.6, 0.25), (1.6, 0.5, 0.5), yaw=geo.uniform(-0.1, 0.1), faces=_NO_BOTTOM)
    b.add_cylinder("column", (3.45, 2.45, 0.0), 0.25, 2.2)
    b.add_box("crate", (3.3, -2.3, 0.3), (0.6, 0.6, 0.6), yaw=geo.uniform(0, 1.5), faces=_NO_BOTTOM)
    scene = b.build()

    intr = Intrinsics.from_fov(params.width, params.height, params.hfov_deg)
    cams_rng = _rng(params.seed, 2)
    centres = {"object1": scene.object_bounds["object1"], "object2": scene.object_bounds["object2"]}

    def ring_sampler(obj: str):
        lo, hi = (np.asarray(a) for a in centres[obj])
        focus = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.55 * hi[2]])
        elevations = (8.0, 22.0, 38.0)
        phase = cams_rng.uniform(0, 2 * math.pi, len(elevations))

        def propose(i: int, attempt: int):
            ring = i % len(elevations)
            per_ring = math.ceil(params.num_views / len(elevations))
            # Azimuth jitter grows with failed attempts so blocked slots move to free space.
            az = phase[ring] + 2 * math.pi * (i // len(elevations)) / per_ring
            az += cams_rng.normal(0, 0.05 + 0.05 * attempt)
            el = math.radians(elevations[ring] + cams_rng.uniform(-4, 4))
            r = cams_rng.uniform(1.7, 2.3)
            pos = focus + r * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            return pos, focus + cams_rng.normal(0, 0.08, 3)

        return propose

    captures = []
    for name, obj in (("capture_a", "object1"), ("capture_b", "object2")):
        c2w = _sample_cameras(scene, "room", params.num_views, ring_sampler(obj))
        captures.append(_capture_from_world(name, c2w, intr, cams_rng, obj))

    mid = np.array([(o1[0] + o2[0]) / 2, (o1[1] + o2[1]) / 2, 0.5])
    test_phase = cams_rng.uniform(0, 2 * math.pi)

    def test_propose(i: int, attempt: int):
        az = test_phase + 2 * math.pi * i / params.num_test_views + cams_rng.normal(0, 0.1)
        pos = np.array([mid[0] + 3.0 * math.cos(az), mid[1] + 2.1 * math.sin(az), cams_rng.uniform(1.1, 1.9)])
        return pos, mid + cams_rng.normal(0, [0.4, 0.25, 0.1])

    test_c2w = _sample_cameras(scene, "room", params.num_test_views, test_propose)
    test = Capture("test", test_c2w, intr, np.eye(4), focus="whole scene")
    return SceneLayout("object-centric", params.seed, asdict(params), scene, captures, test)


ROW_HOUSE_PERIOD_M = 3.5
"""Spacing of the row-houses layout's identical houses: the street layout's captures stand 7 m (two houses) apart, so
every capture's facades repeat in its neighbours' at a whole number of periods."""


def _street_world(params: LayoutParams, x_caps: np.ndarray, row_houses: bool = False) -> tuple[Scene, float]:
    """The street scene shared by the street and drive layouts: road along +x, buildings and furniture both sides.

    ``row_houses``: the buildings are one house repeated every :data:`ROW_HOUSE_PERIOD_M` on both sides (same size,
    same facade and side textures); only the road, the backdrop and the street furniture differ along the street.
    Returns the scene and the half width of the road (facades start there). Draws from the geometry and texture
    streams only, so the cameras of either layout do not change the world.
    """
    geo = _rng(params.seed, 0)
    b = SceneBuilder(_rng(params.seed, 1), texels_per_metre=min(params.texels_per_metre, 48.0))
    half_road = 4.0
    x_lo, x_hi = x_caps[0] - 12.0, x_caps[-1] + 12.0
    # Far backdrop (coarse texture: only seen far away) with its floor a hair below the finely textured road.
    enclosure = (x_hi - x_lo + 30.0, 44.0, 24.0)
    b.add_box("world", (0, 0, enclosure[2] / 2 - 0.01), enclosure, inward=True, patch_size_m=(2.0, 6.0),
              patches_per_m2=0.08, density=8.0)
    b.add_quad("world", (x_lo - 6.0, -half_road - 2.5, 0.0), (x_hi - x_lo + 12.0, 0, 0), (0, 2 * half_road + 5.0, 0),
               part=False, patch_size_m=(0.4, 1.5), patches_per_m2=1.0,
               photo_names=("brick", "grass", "gravel", "coins", "page", "text", "moon"))
    house: dict[str, np.ndarray] = {}
    for side in (-1.0, 1.0):
        x = x_lo
        facade = "-y" if side > 0 else "+y"  # the face towards the street
        if row_houses:
            x = math.floor(x_lo / ROW_HOUSE_PERIOD_M) * ROW_HOUSE_PERIOD_M
            while x < x_hi:
                w, depth, height = ROW_HOUSE_PERIOD_M - 0.3, 5.0, 7.0
                centre = (x + w / 2, side * (half_road + 0.3 + depth / 2), height / 2)
                # Both sides show the house's street face: the texture drawn for the first facade, on every facade.
                front = b.add_box("buildings", centre, (w, depth, height), faces=(facade,),
                                  textures={facade: house["front"]} if house else None,
                                  patch_size_m=(0.4, 1.6), patches_per_m2=2.0)
                house.setdefault("front", front[facade])
                ends = b.add_box("buildings", centre, (w, depth, height), faces=("+x", "-x"),
                                 textures={"+x": house["end"], "-x": house["end"]} if "end" in house else None,
                                 patch_size_m=(0.6, 2.0), patches_per_m2=1.0, density=24.0)
                house.setdefault("end", ends["+x"])
                x += ROW_HOUSE_PERIOD_M
        else:
            while x < x_hi:
                w = geo.uniform(3.0, 6.0)
                depth, height = geo.uniform(4.0, 7.0), geo.uniform(3.5, 9.0)
                y = side * (half_road + geo.uniform(0.0, 0.6) + depth / 2)
                b.add_box("buildings", (x + w / 2, y, height / 2), (w, depth, height), faces=(facade,),
                          patch_size_m=(0.4, 1.6), patches_per_m2=2.0)
                b.add_box("buildings", (x + w / 2, y, height / 2), (w, depth, height), faces=("+x", "-x"),
                          patch_size_m=(0.6, 2.0), patches_per_m2=1.0, density=24.0)
                x += w + geo.uniform(0.0, 1.2)
        for xp in np.arange(x_lo + 2.0, x_hi - 2.0, 5.0) + geo.uniform(-1, 1):
            if geo.random() < 0.5:
                b.add_cylinder("street_furniture", (xp, side * (half_road - 0.6), 0.0), 0.12, 3.0)
            else:
                b.add_box("street_furniture", (xp, side * (half_road - 0.9), 0.6), (1.4, 0.9, 1.2), faces=_NO_BOTTOM,
                          patch_size_m=(0.15, 0.5), patches_per_m2=10)
    return b.build(), half_road


def make_street(params: LayoutParams, row_houses: bool = False) -> SceneLayout:
    """A straight street along +x lined by textured buildings on both sides, with posts and kiosks on the pavement.

    Capture k covers the segment centred at x_k = (k - (N - 1) / 2) * 7 m: cameras at 1.4-2.2 m height within
    +-3.5 m of x_k, looking at the facades or along the street; neighbouring segments overlap by their views. Test
    views stand between consecutive capture centres. ``row_houses``: the :func:`make_row_houses` layout.
    """
    params.validate()
    spacing = 7.0
    n = params.num_captures
    x_caps = (np.arange(n) - (n - 1) / 2) * spacing
    scene, half_road = _street_world(params, x_caps, row_houses=row_houses)

    intr = Intrinsics.from_fov(params.width, params.height, params.hfov_deg)
    cams_rng = _rng(params.seed, 2)

    def segment_sampler(xc: float, half_len: float):
        def propose(i: int, attempt: int):
            pos = np.array([xc + cams_rng.uniform(-half_len, half_len), cams_rng.uniform(-2.2, 2.2),
                            cams_rng.uniform(1.4, 2.2)])
            if i % 5 == 4:  # look along the street
                tgt = np.array([pos[0] + cams_rng.choice([-1, 1]) * 12.0, cams_rng.uniform(-2, 2), 2.0])
            else:  # look at a facade (alternate sides)
                side = 1.0 if i % 2 == 0 else -1.0
                tgt = np.array([pos[0] + cams_rng.uniform(-4, 4), side * (half_road + 1.0), cams_rng.uniform(1.5, 4.5)])
            return pos, tgt

        return propose

    captures = []
    for k, xc in enumerate(x_caps):
        c2w = _sample_cameras(scene, "world", params.num_views, segment_sampler(xc, 3.5))
        captures.append(_capture_from_world(f"capture_{k}", c2w, intr, cams_rng, f"segment x={xc:+.1f} m"))

    gaps = (x_caps[:-1] + x_caps[1:]) / 2

    def test_propose(i: int, attempt: int):
        return segment_sampler(gaps[i % len(gaps)], 1.0)(i // len(gaps), attempt)

    test_c2w = _sample_cameras(scene, "world", params.num_test_views, test_propose)
    test = Capture("test", test_c2w, intr, np.eye(4), focus="between capture centres")
    return SceneLayout("row-houses" if row_houses else "street", params.seed, asdict(params), scene, captures, test)


def make_row_houses(params: LayoutParams) -> SceneLayout:
    """The street layout with repeated structure: both sides lined by one house repeated every
    :data:`ROW_HOUSE_PERIOD_M` (the same size, facade and side walls), so every capture's facades reappear in its
    neighbours' two houses along. Only the road, the backdrop and the randomly placed posts and kiosks tell one stretch
    of the street from another: a free SfM can link two captures a whole number of houses apart."""
    return make_street(params, row_houses=True)


DRIVE_RIG_CAMERAS = 8
"""Cameras of the drive layout's roof rig, one every 45 deg of yaw (with the default 65 deg field of view
neighbours overlap), like Mission Bay's surround rig of 12."""
DRIVE_STEP_M = 0.5
"""Distance the drive layout's car moves between two rig exposures."""


def make_drive(params: LayoutParams) -> SceneLayout:
    """The street of :func:`make_street` captured the way the paper's Mission Bay data is: from a car.

    A roof rig of :data:`DRIVE_RIG_CAMERAS` level cameras looking all around (1.9 m up, in the lane at y = -1.2 m)
    fires every :data:`DRIVE_STEP_M` while the car drives along +x. As in the paper's split of Mission Bay (of every
    30 frames the first 25 train a block, the next 5 are held out), each capture is a block of ``num_views / rig``
    consecutive stops, the next ``stops / 5`` stops are left out, and the test views are the rig's side cameras
    (looking at the left or right facades) at those left-out stops, between every two neighbouring blocks.
    """
    params.validate()
    rig = DRIVE_RIG_CAMERAS
    if params.num_views % rig:
        raise ValueError(f"num_views must be a multiple of {rig} for the drive layout (one exposure of the "
                         f"{rig}-camera rig per stop), got {params.num_views}")
    stops = params.num_views // rig
    gap = max(1, round(stops / 5))
    n = params.num_captures
    period = (stops + gap) * DRIVE_STEP_M
    x_caps = (np.arange(n) - (n - 1) / 2) * period
    scene, _ = _street_world(params, x_caps)

    intr = Intrinsics.from_fov(params.width, params.height, params.hfov_deg)
    cams_rng = _rng(params.seed, 2)
    lane_y, rig_z, pitch = -1.2, 1.9, math.radians(4.0)

    def rig_poses(xs: np.ndarray, yaw_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera centres and viewing targets, stop-major, of one exposure per stop (``yaw_offsets``: the cameras'
        yaws relative to the car, [cameras] or [stops, cameras]), with odometry-like jitter of the car."""
        pos = np.stack([xs + cams_rng.normal(0, 0.03, len(xs)), lane_y + cams_rng.normal(0, 0.05, len(xs)),
                        rig_z + cams_rng.normal(0, 0.02, len(xs))], axis=-1)
        heading = cams_rng.normal(0, math.radians(1.5), len(xs))
        yaw = heading[:, None] + np.broadcast_to(yaw_offsets, (len(xs), np.shape(yaw_offsets)[-1]))
        d = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.full_like(yaw, np.sin(pitch))], -1)
        pos = np.broadcast_to(pos[:, None], d.shape)
        return pos.reshape(-1, 3), (pos + d).reshape(-1, 3)

    def fixed(positions: np.ndarray, targets: np.ndarray):
        return lambda i, attempt: (positions[i], targets[i])

    surround = 2 * math.pi * np.arange(rig) / rig
    captures, last_stops = [], []
    for k, xc in enumerate(x_caps):
        xs = xc + (np.arange(stops) - (stops - 1) / 2) * DRIVE_STEP_M
        last_stops.append(xs[-1])
        pos, tgt = rig_poses(xs, surround)
        c2w = _sample_cameras(scene, "world", params.num_views, fixed(pos, tgt))
        captures.append(_capture_from_world(f"capture_{k}", c2w, intr, cams_rng, f"drive block x={xc:+.1f} m"))

    # Test stops spread over the left-out stops of every gap; the side camera alternates left / right.
    i = np.arange(params.num_test_views)
    g, j = i % (n - 1), i // (n - 1)
    per_gap = math.ceil(params.num_test_views / (n - 1))
    first = np.array(last_stops[:-1])[g] + DRIVE_STEP_M
    xs = first + (gap - 1) * DRIVE_STEP_M * (j + 0.5) / per_gap
    side = np.where(j % 2 == 0, math.pi / 2, -math.pi / 2)
    pos, tgt = rig_poses(xs, side[:, None])
    test_c2w = _sample_cameras(scene, "world", params.num_test_views, fixed(pos, tgt))
    test = Capture("test", test_c2w, intr, np.eye(4), focus="side cameras between neighbouring blocks")
    return SceneLayout("drive", params.seed, asdict(params), scene, captures, test)


def make_room(params: LayoutParams) -> SceneLayout:
    """Indoor room (8 x 6 x 3 m) of repeated structure that can fool a free SfM: it maps onto itself under the half
    turn ``(x, y, z) -> (-x, -y, z)`` about its vertical axis, all but one element.

    Opposite walls carry the same image (a feature on the north wall has an exact twin on the south wall, likewise
    east and west), floor and ceiling textures equal themselves turned by 180 degrees (:func:`half_turn_symmetric`),
    and the furnishing comes in identical pairs, a box and its image under the half turn: shelves against the long
    walls, square floor-to-ceiling pillars, crates in the corners. The light shines from straight above (walls get
    ambient light only), so that shading keeps the symmetry too. The one asymmetric element, a uniquely textured door
    on the east wall off its centre (y ~ 0.9 m), makes the true registration decidable; ``params.symmetric`` leaves
    it out (nothing else changes: the geometry, the other textures and the cameras stay the same).

    Capture A stands in the west half (x in [-2.4, -0.5] m) and capture B in the east half (x in [0.5, 2.4] m), each
    looking all around at the walls and furniture, so each sees its own half close up and the other one from afar.
    Test views stand in the middle (|x| < 0.6 m), looking all around.
    """
    params.validate()
    geo = _rng(params.seed, 0)
    b = SceneBuilder(_rng(params.seed, 1), texels_per_metre=params.texels_per_metre, light_dir=(0.0, 0.0, 1.0))
    room = (8.0, 6.0, 3.0)
    hx, hy = room[0] / 2, room[1] / 2
    b.add_quad("room", (-hx, -hy, 0.0), (room[0], 0, 0), (0, room[1], 0), half_turn=True, patch_size_m=(0.4, 1.2),
               patches_per_m2=1.5, photo_names=("brick", "grass", "gravel", "coins", "coffee", "page"))
    walls = b.add_box("room", (0, 0, room[2] / 2), room, inward=True, faces=("-y", "+x"), patch_size_m=(0.5, 1.5),
                      patches_per_m2=1.0)
    b.add_box("room", (0, 0, room[2] / 2), room, inward=True, faces=("+y", "-x"),
              textures={"+y": walls["-y"], "-x": walls["+x"]})
    b.add_quad("room", (-hx, -hy, room[2]), (room[0], 0, 0), (0, room[1], 0), part=False, half_turn=True,
               patch_size_m=(0.5, 1.5), patches_per_m2=1.0)

    def twins(obj: str, center, size, yaw: float, faces: Sequence[str] = _NO_BOTTOM) -> None:
        """A box and its image under the half turn, with the same textures."""
        looks = b.add_box(obj, center, size, yaw=yaw, faces=faces)
        b.add_box(obj, np.multiply(center, (-1, -1, 1)), size, yaw=yaw + math.pi, faces=faces, textures=looks)

    shelf = (1.6, 0.45, 2.0)
    twins("shelves", (-1.8 + geo.uniform(-0.3, 0.3), hy - shelf[1] / 2 - 0.02, shelf[2] / 2), shelf, 0.0,
          faces=("-y", "+x", "-x", "top"))
    twins("pillars", (-1.3 + geo.uniform(-0.15, 0.15), -1.0 + geo.uniform(-0.15, 0.15), room[2] / 2),
          (0.4, 0.4, room[2]), geo.uniform(0, math.pi / 2), faces=("-y", "+x", "+y", "-x"))
    twins("crates", (-3.2 + geo.uniform(-0.1, 0.1), -2.2 + geo.uniform(-0.1, 0.1), 0.35), (0.7, 0.7, 0.7),
          geo.uniform(-0.3, 0.3))
    if not params.symmetric:  # drawn last: leaving it out changes nothing else
        b.add_box("door", (hx - 0.04, 0.9 + geo.uniform(-0.2, 0.2), 1.05), (0.08, 1.0, 2.1),
                  faces=("-y", "+y", "-x", "top"), patch_size_m=(0.15, 0.4), patches_per_m2=10.0,
                  photo_names=("astronaut", "chelsea", "coffee", "rocket"))
    scene = b.build()

    intr = Intrinsics.from_fov(params.width, params.height, params.hfov_deg)
    cams_rng = _rng(params.seed, 2)

    def look_around(x_range: tuple[float, float], n: int):
        phase = cams_rng.uniform(0, 2 * math.pi)

        def propose(i: int, attempt: int):
            pos = np.array([cams_rng.uniform(*x_range), cams_rng.uniform(-1.8, 1.8), cams_rng.uniform(1.2, 1.9)])
            # Azimuth jitter grows with failed attempts so views blocked close by turn away.
            az = phase + 2 * math.pi * i / n + cams_rng.normal(0, 0.15 + 0.1 * attempt)
            el = math.radians(cams_rng.uniform(-20.0, 5.0))
            return pos, pos + np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

        return propose

    # Cameras stay more than the clearance (1.5 m) away from the door, so it never changes where they go.
    captures = []
    for name, x_range, half in (("capture_a", (-2.4, -0.5), "west"), ("capture_b", (0.5, 2.4), "east")):
        c2w = _sample_cameras(scene, "room", params.num_views, look_around(x_range, params.num_views), 1.5)
        captures.append(_capture_from_world(name, c2w, intr, cams_rng, f"{half} half of the room"))
    test_c2w = _sample_cameras(scene, "room", params.num_test_views,
                               look_around((-0.6, 0.6), params.num_test_views), 1.5)
    test = Capture("test", test_c2w, intr, np.eye(4), focus="middle of the room, looking around")
    return SceneLayout("room", params.seed, asdict(params), scene, captures, test)


LAYOUTS: dict[str, Callable[[LayoutParams], SceneLayout]] = {
    "object-centric": make_object_centric,
    "street": make_street,
    "drive": make_drive,
    "room": make_room,
    "row-houses": make_row_houses,
}


def benchmark_params(layout: str, seed: int) -> dict:
    """The layout parameters our benchmarks' scenes use (``build_demo.py``, ``evaluate.py``): 192 x 144 images, 64
    views per capture and 12 test views; three captures on a street; the drive's 12 rig stops per block (96 views)
    and 24 test views, 12 per gap; the room with its door (not ``symmetric``); the row houses as the street."""
    params = dict(seed=seed, num_views=64, num_test_views=12, width=192, height=144)
    if layout in ("street", "drive", "row-houses"):
        params["num_captures"] = 3
    if layout == "drive":
        params.update(num_views=12 * DRIVE_RIG_CAMERAS, num_test_views=24)
    return params


def make_layout(layout: str, **params) -> SceneLayout:
    """Builds a layout by name (``"object-centric"``, ``"street"``, ``"drive"``, ``"room"`` or ``"row-houses"``);
    keyword arguments are :class:`LayoutParams`."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    unknown = set(params) - set(LayoutParams.__dataclass_fields__)
    if unknown:
        raise ValueError(f"unknown layout parameters: {sorted(unknown)}")
    lp = LayoutParams(**params)
    built = LAYOUTS[layout](lp)
    if lp.appearance_jitter > 0:
        _draw_appearance(built, lp.appearance_jitter, lp.appearance_bracket)
    else:  # the parameter's default leaves ground_truth.json as it was before the parameter existed
        built.params.pop("appearance_jitter", None)
    if not lp.appearance_bracket:
        built.params.pop("appearance_bracket", None)
    return built


APPEARANCE_STREAM = 97
"""Random stream of the per-capture appearance (independent of geometry, textures and cameras)."""


def _draw_appearance(layout: SceneLayout, jitter: float, bracket: bool = False) -> None:
    """Gives each training capture its own exposure and white balance (see ``LayoutParams.appearance_jitter`` and
    ``appearance_bracket``)."""
    if bracket:
        for u, cap in zip(np.linspace(-jitter, jitter, len(layout.captures)), layout.captures, strict=True):
            cap.exposure = float(2.0**u)
            cap.white_balance = (float(2.0 ** (u / 2)), 1.0, float(2.0 ** (-u / 2)))
        return
    rng = _rng(layout.seed, APPEARANCE_STREAM)
    for cap in layout.captures:
        cap.exposure = float(2.0 ** rng.uniform(-jitter, jitter))
        red, blue = 2.0 ** rng.uniform(-jitter / 2, jitter / 2, size=2)
        cap.white_balance = (float(red), 1.0, float(blue))


def apply_appearance(rgb: Float[Tensor, "*bs 3"], gains: np.ndarray | None) -> Float[Tensor, "*bs 3"]:
    """Rendered sRGB colours as a capture with these linear-RGB gains records them (clipped to [0, 1])."""
    if gains is None:
        return rgb
    lin = srgb_to_linear(rgb.clamp(0.0, 1.0)) * torch.as_tensor(gains, dtype=rgb.dtype, device=rgb.device)
    return linear_to_srgb(lin.clamp(0.0, 1.0))


def layout_from_ground_truth(path: str | Path) -> SceneLayout:
    """Regenerates the exact layout (geometry, textures, cameras) recorded in a scene's ``ground_truth.json``."""
    path = Path(path)
    gt = json.loads((path / "ground_truth.json" if path.is_dir() else path).read_text())
    if gt.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"unsupported ground_truth.json format_version {gt.get('format_version')!r}")
    return make_layout(gt["layout"], **gt["params"])


# ----------------------------------------------------------------------------------------------------------------
# Dataset writer
# ----------------------------------------------------------------------------------------------------------------

DEPTH_UNIT_SCALE = 0.001  # nerfstudio's depth_unit_scale_factor: stored uint16 * 0.001 = capture units


def _rounded(a: np.ndarray, digits: int = 12) -> list:
    """JSON-friendly nested lists; rounding hides float noise so identical inputs give identical files."""
    return np.round(np.asarray(a, dtype=np.float64), digits).tolist()


def _save_png(path: Path, array: np.ndarray) -> None:
    Image.fromarray(array).save(path, format="PNG", optimize=False, compress_level=6)


def to_uint8(rgb: Float[Tensor, "h w 3"]) -> np.ndarray:
    """float [0, 1] -> uint8 with rounding (what the PNGs store)."""
    return np.round(rgb.detach().cpu().numpy().clip(0, 1) * 255.0).astype(np.uint8)


def write_capture(
    layout: SceneLayout,
    capture: Capture,
    folder: Path,
    world_frame: bool = False,
    supersample: int = 2,
    progress: Callable[[], None] | None = None,
) -> None:
    """Renders ``capture`` into a nerfstudio dataset folder (transforms.json, images/, depths/).

    Poses are stored in the capture's own frame, or in the world frame if ``world_frame`` (the test capture).
    Depth PNGs: z-depth in the stored frame's units x 1000 (uint16, 0 = no hit, saturates at 65.535 units).
    """
    k = capture.intrinsics
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    (folder / "depths").mkdir(exist_ok=True)
    T = np.eye(4) if world_frame else capture.capture_to_world
    scale = float(decompose_sim3(T)[2])
    poses = capture.c2w_world if world_frame else capture.c2w_capture
    frames = []
    for i in range(capture.num_views):
        out = render(layout.scene, capture.c2w_world[i], k, supersample=supersample)
        z = ray_to_z_depth(out.depth, k).numpy() / scale
        depth_u16 = np.where(out.mask.numpy(), np.clip(np.round(z / DEPTH_UNIT_SCALE), 1, 65535), 0).astype(np.uint16)
        image_name, depth_name = f"images/frame_{i:05d}.png", f"depths/frame_{i:05d}.png"
        _save_png(folder / image_name, to_uint8(apply_appearance(out.rgb, capture.appearance_gains)))
        _save_png(folder / depth_name, depth_u16)
        frames.append({"file_path": image_name, "depth_file_path": depth_name, "transform_matrix": _rounded(poses[i])})
        if progress is not None:
            progress()
    transforms = {
        "camera_model": "OPENCV",
        "fl_x": k.fx,
        "fl_y": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "w": k.width,
        "h": k.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "depth_unit_scale_factor": DEPTH_UNIT_SCALE,
        "frames": frames,
    }
    (folder / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")


def ground_truth_dict(layout: SceneLayout, supersample: int) -> dict:
    """The content of ``ground_truth.json`` (see :func:`write_scene`)."""
    captures = []
    for cap in layout.captures:
        R, t, s = decompose_sim3(cap.capture_to_world)
        captures.append({
            "name": cap.name,
            "path": cap.name,
            "num_views": cap.num_views,
            "focus": cap.focus,
            "capture_to_world": _rounded(cap.capture_to_world),
            "scale": round(float(s), 12),
            "rotation": _rounded(R),
            "translation": _rounded(t),
            # only for captures with their own appearance: other scenes' files stay as they were
            **({} if cap.appearance_gains is None else {"appearance": {
                "exposure": round(cap.exposure, 12), "white_balance": [round(g, 12) for g in cap.white_balance],
                "applied": "linear RGB gains exposure * white_balance on the rendered images"}}),
        })  # fmt: skip
    scene = layout.scene
    return {
        "format_version": FORMAT_VERSION,
        "layout": layout.layout,
        "seed": layout.seed,
        "params": dict(layout.params),
        "render": {"supersample": supersample, "ambient": _AMBIENT, "diffuse": _DIFFUSE, "light_dir": scene.light_dir},
        "conventions": {
            "world": "+z up, metres",
            "camera": "nerfstudio / OpenGL camera-to-world (camera looks along -z, +y up, +x right)",
            "sim3": "p_world = capture_to_world @ [p_capture, 1], capture_to_world = [[s R, t], [0, 0, 0, 1]]",
            "capture_frame": "origin = mean camera centre, yaw about +z, scale = mean camera distance to centre = 1",
            "depth_files": "16-bit PNG, z-depth (not ray distance) in the dataset's frame units / 0.001, 0 = no hit",
        },
        "captures": captures,
        "test": {"name": layout.test.name, "path": layout.test.name, "num_views": layout.test.num_views,
                 "frame": "world"},
        "objects": {name: {"min": _rounded(lo), "max": _rounded(hi)} for name, (lo, hi) in scene.object_bounds.items()},
    }


def write_scene(
    layout: SceneLayout,
    output_dir: str | Path,
    supersample: int = 2,
    progress: Callable[[], None] | None = None,
) -> Path:
    """Writes every capture, the world-frame test capture and ``ground_truth.json`` under ``output_dir``.

    Layout on disk: ``<output_dir>/<capture name>/{transforms.json, images/, depths/}``, ``<output_dir>/test/...``,
    ``<output_dir>/ground_truth.json``. Atomic: everything is written into a sibling temporary folder first and
    swapped in by rename, so an interrupted run never leaves a half-written scene. An existing ``output_dir`` is
    replaced only if it is empty or holds a previous scene (has ground_truth.json). ``progress`` is called once per
    rendered frame. Same layout and arguments give byte-identical files.
    """
    check_positive_int("supersample", supersample)
    output_dir = Path(output_dir).absolute()
    if output_dir.exists():
        if not output_dir.is_dir():
            raise ValueError(f"output path {output_dir} exists and is not a folder")
        if any(output_dir.iterdir()) and not (output_dir / "ground_truth.json").exists():
            raise ValueError(f"refusing to replace {output_dir}: not empty and not a generated scene")
    output_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{output_dir.name}.tmp-", dir=output_dir.parent))
    try:
        for cap in layout.captures:
            write_capture(layout, cap, tmp / cap.name, world_frame=False, supersample=supersample, progress=progress)
        write_capture(layout, layout.test, tmp / layout.test.name, world_frame=True, supersample=supersample,
                      progress=progress)
        gt = ground_truth_dict(layout, supersample)
        (tmp / "ground_truth.json").write_text(json.dumps(gt, indent=2) + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp makes 0700 folders
        if output_dir.exists():
            old = output_dir.parent / f".{output_dir.name}.old-{os.getpid()}"
            os.rename(output_dir, old)
            os.rename(tmp, output_dir)
            shutil.rmtree(old)
        else:
            os.rename(tmp, output_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return output_dir


def generate_scene(output_dir: str | Path, layout: str, supersample: int = 2, **params) -> SceneLayout:
    """:func:`make_layout` + :func:`write_scene`, skipped when ``output_dir`` already holds this exact scene (its
    recorded ``ground_truth.json`` equals the one these arguments give). Returns the layout."""
    built = make_layout(layout, **params)
    gt_path = Path(output_dir) / "ground_truth.json"
    expected = json.loads(json.dumps(ground_truth_dict(built, supersample=supersample)))
    if not gt_path.is_file() or json.loads(gt_path.read_text()) != expected:
        write_scene(built, output_dir, supersample=supersample)
    return built
