"""The ``nerfuser`` model: several frozen, registered NeRFs rendered as one scene (NeRFuser, Sec. 3.3).

Per ray batch (rays in the COMMON frame):

0. the NeRFs each ray can use are found (:meth:`NerfuserModel.used_nerfs`: the distance test's survivors, the nearest
   or the reference NeRF, by method); a NeRF is queried only on its rays, and a ray's result depends on its own
   NeRFs alone;
1. each ray is mapped into each NeRF's own frame through ``T_common->nerf`` (origins, re-normalised directions,
   near/far), so every NeRF sees the ray it would see itself, and goes through that NeRF's own collider, proposal
   sampler and field (:class:`NerfactoAdapter`);
2. each NeRF's sample intervals are converted back to common-frame ray distances (a NeRF with scale ``s`` in its
   SIM(3) has ``t_common = s * t_nerf`` for unit directions);
3. the NeRFs are blended with the selected method (``nerf``, ``nearest``, ``idw-2d``, ``idw-3d``, ``idw-sample``; ours:
   ``coverage``, IDW-Sample weighted by each NeRF's training-camera coverage, :mod:`nerfuser_ns.coverage`, and
   ``coverage-3d``, each NeRF's own rendering weighted by that coverage at its surface point), every NeRF keeping its
   own background term (nerfacto "last_sample"). ``auto`` (ours, the default) is ``idw-sample``, ``idw-2d`` or
   ``coverage``, chosen once from the training cameras (:mod:`nerfuser_ns.blend_choice`).

Appearance matching (ours, :mod:`nerfuser_ns.appearance`): each NeRF's sample and background colours go through its
colour map to the reference capture's colours (from the registration file; identity when absent) before blending, when
``appearance_matching`` is on (the default; the viewer has a checkbox for it). Training cameras (for ``coverage`` and
``coverage-3d``) come from the registration file too, mapped once into the common frame; rendering never reads a
dataset. Without them ``coverage`` is IDW-Sample and ``coverage-3d`` IDW-2D (one warning).

Frames: the sub-models never move; only rays do. ``pixel_area`` (the pixel footprint at unit ray distance, a solid
angle) is invariant under a similarity: at distance ``t_nerf = t / s`` the footprint is ``pixel_area * t^2 / s^2``,
exactly the common-frame footprint ``pixel_area * t^2`` in NeRF units. So it is passed on unchanged.

The blend method, gamma, tau and appearance matching can be changed at render time: set
:attr:`NerfuserModel.blend_method` (and ``gamma``/``tau``/``appearance_matching``), use the viewer's "NeRFuser"
controls, or set the environment variables ``NERFUSER_BLEND_METHOD``, ``NERFUSER_GAMMA``, ``NERFUSER_TAU`` (``none``
disables the test), ``NERFUSER_APPEARANCE_MATCHING`` (``0``/``1``) before ``ns-render``/``ns-eval`` start.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import Bool, Float
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.base_model import Model, ModelConfig
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerCheckbox, ViewerDropdown, ViewerNumber
from torch import Tensor
from torch.nn import Parameter
from torchmetrics.functional import structural_similarity_index_measure
from torchmetrics.image import PeakSignalNoiseRatio

from nerfuser_ns import blending, runtime
from nerfuser_ns.adapters import (
    ADAPTERS,
    FrozenModels,
    ModelCache,
    NerfactoAdapter,
    NerfAdapter,
    NerfSamples,
    QueriedSamples,
    check_model_class,
    make_adapter,
)
from nerfuser_ns.appearance import IDENTITY, apply_colour_map
from nerfuser_ns.blend_choice import AUTO, BLEND_CHOICES, BlendChoice, choose_blend_method
from nerfuser_ns.blend_settings import SHARE_PALETTE, BlendSettings
from nerfuser_ns.blending import BLEND_METHODS, COVERAGE_METHODS, PAPER_OBJECT_CENTRIC
from nerfuser_ns.coverage import CameraIndex, CoverageParams
from nerfuser_ns.registration.record import TrainingCameras
from nerfuser_ns.runs import load_run, read_config
from nerfuser_ns.spec import FusionSpec, read_fusion_spec
from nerfuser_ns.viewer import NerfuserSceneControl

# ----------------------------------------------------------------------------------------------------------------------
# Ray mapping


def _camera_indices(ray_bundle: RayBundle, num_train_data: int) -> Tensor:
    """Camera indices valid for a sub-model (nerfacto's field needs them; in eval it uses the mean embedding)."""
    if ray_bundle.camera_indices is not None:
        return ray_bundle.camera_indices.clamp(0, max(num_train_data - 1, 0))
    return torch.zeros_like(ray_bundle.origins[..., :1], dtype=torch.long)


def map_rays(
    ray_bundle: RayBundle, common_to_nerf: Float[Tensor, "4 4"], num_train_data: int
) -> tuple[RayBundle, Float[Tensor, "num_rays 1"]]:
    """The common-frame rays as seen in one NeRF's frame, and the factor ``k`` with ``t_nerf = k * t_common``.

    ``k = |A d|`` for the linear part ``A`` of ``T_common->nerf`` (``1 / s`` for unit directions); directions are
    re-normalised, nears/fars (if set) scaled by ``k``. Camera indices are clamped into the sub-model's range (in eval
    nerfacto uses its average appearance embedding anyway).
    """
    A, b = common_to_nerf[:3, :3], common_to_nerf[:3, 3]
    origins = ray_bundle.origins @ A.T + b
    directions = ray_bundle.directions @ A.T
    k = torch.linalg.vector_norm(directions, dim=-1, keepdim=True)
    directions = directions / k
    mapped = RayBundle(
        origins=origins,
        directions=directions,
        pixel_area=ray_bundle.pixel_area,
        camera_indices=_camera_indices(ray_bundle, num_train_data),
        nears=None if ray_bundle.nears is None else ray_bundle.nears * k,
        fars=None if ray_bundle.fars is None else ray_bundle.fars * k,
        metadata=dict(ray_bundle.metadata),
        times=ray_bundle.times,
    )
    return mapped, k


def _pad_samples(x: Tensor, k: int, value: Tensor | float, dim: int) -> Tensor:
    """Pads the samples axis to ``k`` (zero-length, zero-weight samples at the last end keep bins contiguous)."""
    missing = k - x.shape[dim]
    if missing == 0:
        return x
    shape = list(x.shape)
    shape[dim] = missing
    if isinstance(value, Tensor):
        pad = value.unsqueeze(dim).expand(shape)
    else:
        pad = torch.full(shape, value, dtype=x.dtype, device=x.device)
    return torch.cat([x, pad], dim=dim)


# ----------------------------------------------------------------------------------------------------------------------
# Model


@dataclass
class NerfuserModelConfig(ModelConfig):
    """Fused NeRFs (NeRFuser). The sub-models come from the fusion spec (see nerfuser_ns.data), never from here."""

    _target: type = field(default_factory=lambda: NerfuserModel)
    enable_collider: bool = False
    """Off: each sub-model applies its own collider in its own frame (what it would do itself). If the incoming
    rays already carry nears/fars, they are mapped into each NeRF's frame instead."""
    blend_method: BlendChoice = "auto"
    """``auto`` (ours, the default: ``idw-sample`` when every NeRF's training cameras look at a centre, as around
    objects, ``idw-2d`` when every NeRF was filmed by a camera rig, ``coverage`` otherwise, as along a street; see
    nerfuser_ns.blend_choice), ``nerf`` (one NeRF),
    ``nearest``, ``idw-2d``, ``idw-3d``, ``idw-sample`` (NeRFuser), ``coverage`` (ours: IDW-Sample weighted by each
    NeRF's training-camera coverage; IDW-Sample when a NeRF's cameras are unknown) or ``coverage-3d`` (ours: each
    NeRF's own rendering weighted by that coverage at its surface point; IDW-2D without the cameras)."""
    gamma: float = PAPER_OBJECT_CENTRIC[0]
    """IDW blending rate (w ~ d^-gamma); 0: mean, inf: nearest. The paper uses 5 (objects), 10 (street)."""
    tau: float | None = PAPER_OBJECT_CENTRIC[1]
    """Distance test (IDW methods): NeRFs whose origin is more than tau times as far from the camera as the nearest
    one's are left out (two NeRFs: the nearest alone past that ratio). None or 0 disables it (as in the viewer). The
    paper uses 1.8 (objects), 1.2 (street)."""
    reference_nerf: int = 0
    """The NeRF rendered by the ``nerf`` method."""
    coverage: CoverageParams = field(default_factory=CoverageParams)
    """Constants of the ``coverage`` and ``coverage-3d`` methods: angular width, cameras per score, candidate cameras
    per ray."""
    appearance_matching: bool = True
    """Map each NeRF's colours to the reference capture's with its colour map from the registration file (ours; the
    identity where the file has none; False renders every NeRF as it is). Captures filmed at different exposure or
    white balance need it (+2.4 to +3.7 dB on our bracketed pairs, stock nerfacto included); without differences it
    moved the blends by +0.05 to +0.08 dB on a stock nerfacto pair and by -0.14 to +0.37 dB on our nerfacto-cpu pairs
    (docs/blending.md)."""
    share_outputs: bool = True
    """Also output ``share_<i>`` (each NeRF's share of the pixel weight) and a colour-coded ``nerf_share`` map."""
    render_all_methods: bool = False
    """Also output ``rgb_<method>`` for every method (``-`` as ``_``) and report their metrics in ns-eval."""
    eval_num_rays_per_chunk: int = 4096
    """Rays per forward pass when rendering images."""
    fusion_spec: Path | None = None
    """The fusion spec, read when the datamanager passes none (e.g. the model loaded alone by runs.load_run);
    ns-train nerfuser records --data here."""
    max_resident_nerfs: int | None = None
    """Ours: at most this many sub-models in memory. None (the default): all are loaded at setup and stay resident.
    A number >= 1: each is loaded from its run on the model's device the first time a ray batch needs it (the
    distance test decides), and the least recently used are dropped to make room, so many NeRFs render in the memory
    of a few; a batch needing more is queried one NeRF at a time. The price: a dropped NeRF is reloaded from its
    checkpoint when needed again. Sub-models passed already loaded (``metadata["nerfuser_models"]``) always stay
    resident: there is nothing to reload them from. See docs/many_nerfs.md."""


class NerfuserModel(Model):
    """Renders N frozen, registered sub-models as one scene in the common frame.

    Sub-models come from ``metadata["nerfuser"]`` (a :class:`nerfuser_ns.data.FusionSpec`, set by the datamanager):
    each is rebuilt from its own run with :func:`nerfuser_ns.runs.load_run`. ``metadata["nerfuser_models"]``, a list of
    ``(name, Model, nerf_to_common[, training_cameras[, colour_to_reference]])`` (cameras as
    :class:`~nerfuser_ns.registration.record.TrainingCameras` or :class:`~nerfuser_ns.coverage.CameraIndex` in the
    NeRF's frame, the colour map 3x4), passes already loaded models instead (tests, scripts).

    With ``max_resident_nerfs`` set, sub-models from the spec are not loaded at setup but by :attr:`nerf_cache`
    (a :class:`~nerfuser_ns.adapters.ModelCache`) when a ray batch first needs them; :attr:`nerfs` and
    :attr:`adapters` are then None.
    """

    config: NerfuserModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        runtime.install()
        metadata = self.kwargs.get("metadata") or {}
        limit = self.config.max_resident_nerfs
        self.nerf_cache: ModelCache | None = None
        if metadata.get("nerfuser_models") is not None:
            entries = list(metadata["nerfuser_models"])
        elif metadata.get("nerfuser") is not None or self.config.fusion_spec is not None:
            spec = metadata.get("nerfuser") or read_fusion_spec(self.config.fusion_spec, register=False)
            check_mergeable(spec)  # before any run is loaded
            # With a limit, nothing is loaded here: all the setup needs (transforms, cameras, colour maps) is in the
            # spec, and the camera-index range is read from the model once it is loaded.
            entries = [(n.name, None if limit is not None else load_run(n.config_path, device="cpu").model,
                        n.nerf_to_common, n.training_cameras, n.colour_to_reference) for n in spec.nerfs]  # fmt: skip
            if limit is not None:
                paths = [n.config_path for n in spec.nerfs]
                self.nerf_cache = ModelCache(len(paths), lambda i: load_run(paths[i], device=self.device).model,
                                             limit, names=[n.name for n in spec.nerfs])  # fmt: skip
        else:
            raise ValueError("nerfuser: no sub-models; pass the fusion spec (--data, or --pipeline.model.fusion-spec)")
        if not entries:
            raise ValueError("nerfuser: no sub-models to fuse")
        self.nerf_names = [str(e[0]) for e in entries]
        self.nerfs: FrozenModels | None = None
        self.adapters: list[NerfAdapter] | None = None
        if self.nerf_cache is None:
            self.nerfs = FrozenModels([e[1] for e in entries])
            self.adapters = [make_adapter(m, name) for name, m in zip(self.nerf_names, self.nerfs.models, strict=True)]
        T = torch.tensor(np.stack([np.asarray(e[2], dtype=np.float64) for e in entries]), dtype=torch.float64)
        scales = torch.linalg.det(T[:, :3, :3]).pow(1.0 / 3.0)
        T_inv = torch.linalg.inv(T)
        # Not persistent: the registration comes from the spec, not from the fused checkpoint.
        self.register_buffer("nerf_to_common", T.float(), persistent=False)
        self.register_buffer("common_to_nerf", T_inv.float(), persistent=False)
        self.register_buffer("nerf_origins", T[:, :3, 3].float(), persistent=False)
        self.register_buffer("nerf_scales", scales.float(), persistent=False)
        self._identity = [bool(torch.equal(t, torch.eye(4, dtype=t.dtype))) for t in T]
        # Training cameras, mapped once into the common frame (per device on first use; a few KB per NeRF).
        self.nerf_cameras = [_camera_index(e[3] if len(e) > 3 else None, t) for e, t in zip(entries, T, strict=True)]
        self._cameras_on: dict[torch.device, list[CameraIndex | None]] = {}
        self._coverage_warned = False
        # What ``auto`` renders with: decided once, from the cameras alone.
        self.auto_method, self.auto_reason = choose_blend_method(self.nerf_cameras, self.nerf_names)
        maps = [None if len(e) < 5 or e[4] is None else np.asarray(e[4], dtype=np.float64) for e in entries]
        for name, m in zip(self.nerf_names, maps, strict=True):
            if m is not None and (m.shape != (3, 4) or not np.isfinite(m).all()):
                raise ValueError(f"nerfuser: run {name!r}: its colour map must be a finite 3x4 matrix")
        self._colour_mapped = [m is not None and not np.array_equal(m, IDENTITY) for m in maps]
        colour_maps = np.stack([IDENTITY if m is None else m for m in maps])
        self.register_buffer("colour_maps", torch.tensor(colour_maps, dtype=torch.float32), persistent=False)

        # Render-time settings: one checked value, changed only through set_blend (viewer, sweeps, attributes).
        self.blend_settings = BlendSettings.from_config(self.config).checked(self.num_nerfs)
        if self.blend_settings.method == AUTO:
            CONSOLE.print(f"nerfuser: blend method auto -> {self.auto_reason}")
        self._add_viewer_controls()

        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity  # lazy/offline after runtime.install

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = structural_similarity_index_measure
        self.lpips = LearnedPerceptualImagePatchSimilarity(normalize=True)

    @property
    def num_nerfs(self) -> int:
        return len(self.nerf_names)

    def adapter(self, i: int) -> NerfAdapter:
        """Sub-model ``i``'s adapter; with ``max_resident_nerfs``, loaded now if it is not resident."""
        if self.nerf_cache is not None:
            return self.nerf_cache.get(i)
        return self.adapters[i]  # type: ignore[index]

    def set_blend(self, **changes: Any) -> BlendSettings:
        """Change blend settings (``method``, ``gamma``, ``tau``, ``reference_nerf``, ``appearance_matching``): checked
        here, once; ValueError (one line) leaves the settings as they were."""
        self.blend_settings = self.blend_settings.replace(self.num_nerfs, **changes)
        return self.blend_settings

    # The settings as attributes (nerfstudio style); assigning one goes through set_blend.
    blend_method = property(lambda self: self.blend_settings.method, lambda self, v: self.set_blend(method=v))
    gamma = property(lambda self: self.blend_settings.gamma, lambda self, v: self.set_blend(gamma=v))
    tau = property(lambda self: self.blend_settings.tau, lambda self, v: self.set_blend(tau=v))
    reference_nerf = property(lambda self: self.blend_settings.reference_nerf,
                              lambda self, v: self.set_blend(reference_nerf=v))  # fmt: skip
    appearance_matching = property(lambda self: self.blend_settings.appearance_matching,
                                   lambda self, v: self.set_blend(appearance_matching=v))  # fmt: skip

    @property
    def active_method(self) -> str:
        """The blend method rendered now: the setting, with ``auto`` resolved (:attr:`auto_method`)."""
        return self.auto_method if self.blend_method == AUTO else self.blend_method

    def _reference_options(self) -> list[str]:
        """The reference NeRF control's choices: "index: name", so equal names stay distinct."""
        return [f"{i}: {name}" for i, name in enumerate(self.nerf_names)]

    def blend_control_values(self) -> dict[str, Any]:
        """The viewer controls' values for the current settings (tau off shows as 0)."""
        return {"blend_method": self.blend_method, "gamma": float(self.gamma), "tau": float(self.tau or 0.0),
                "reference_nerf": self._reference_options()[self.reference_nerf % self.num_nerfs],
                "appearance_matching": self.appearance_matching}  # fmt: skip

    def _add_viewer_controls(self) -> None:
        def set_method(element) -> None:  # noqa: ANN001
            self.set_blend(method=element.value)

        def set_gamma(element) -> None:  # noqa: ANN001
            self.set_blend(gamma=max(float(element.value), 0.0))

        def set_tau(element) -> None:  # noqa: ANN001
            self.set_blend(tau=None if float(element.value) <= 0 else max(float(element.value), 1.0))

        reference_options = self._reference_options()

        def set_reference(element) -> None:  # noqa: ANN001
            self.set_blend(reference_nerf=reference_options.index(element.value))

        def set_matching(element) -> None:  # noqa: ANN001
            self.set_blend(appearance_matching=bool(element.value))

        values = self.blend_control_values()
        controls = {
            "blend_method": ViewerDropdown(
                "NeRFuser blend method", values["blend_method"], list(BLEND_CHOICES), cb_hook=set_method,
                hint=f"auto: {self.auto_reason}",
            ),
            "reference_nerf": ViewerDropdown(
                "NeRFuser reference NeRF", values["reference_nerf"], reference_options, cb_hook=set_reference
            ),
            "gamma": ViewerNumber("NeRFuser gamma", values["gamma"], cb_hook=set_gamma),
            "tau": ViewerNumber("NeRFuser tau (0: off)", values["tau"], cb_hook=set_tau),
            "appearance_matching": ViewerCheckbox(
                "NeRFuser appearance matching", values["appearance_matching"], cb_hook=set_matching,
                hint="Each NeRF's colours mapped to the reference capture's (the registration's colour maps)",
            ),
        }

        # The controls at the top of the viewer's panel, scene groups (NeRF frames, registration and test cameras), CPU
        # defaults: set up by the viewer, if any. The control holds the elements (see NerfuserSceneControl).
        self.viewer_scene = NerfuserSceneControl(self, controls)

    # --- nerfstudio Model API ---------------------------------------------------------------------------------------

    def get_param_groups(self) -> dict[str, list[Parameter]]:
        return {}  # frozen: nothing to optimise

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> dict[str, Tensor]:  # noqa: ANN001
        return {}

    def get_metrics_dict(self, outputs, batch) -> dict[str, Tensor]:  # noqa: ANN001
        if "image" not in batch:
            return {}
        gt = batch["image"][..., :3].to(self.device)
        return {"psnr": self.psnr(outputs["rgb"], gt)}

    @torch.no_grad()
    def nerf_samples(
        self, ray_bundle: RayBundle, used: Bool[Tensor, "num_nerfs num_rays"] | None = None
    ) -> list[QueriedSamples | None]:
        """Every NeRF's samples for the (flat) common-frame rays.

        ``used`` (e.g. :meth:`used_nerfs`) limits each NeRF to the rays it is used on: a NeRF used on none is not
        queried at all (None), one used on some rays only on those. None queries every NeRF on every ray.
        """
        out: list[QueriedSamples | None] = []
        # One NeRF at a time, its samples plain tensors: with a cache, a NeRF may be dropped once it has answered.
        for i in range(self.num_nerfs):
            rows, rays = None, ray_bundle
            if used is not None:
                if not bool(used[i].any()):
                    out.append(None)
                    continue
                if not bool(used[i].all()):
                    rows = used[i].nonzero()[:, 0]
                    rays = ray_bundle[rows]
            adapter = self.adapter(i)  # loaded only here, for a NeRF some ray uses
            if self._identity[i]:  # exactly the rays the NeRF would see itself, no float round trip
                bundle = RayBundle(
                    origins=rays.origins,
                    directions=rays.directions,
                    pixel_area=rays.pixel_area,
                    camera_indices=_camera_indices(rays, adapter.model.num_train_data),
                    nears=rays.nears,
                    fars=rays.fars,
                    metadata=dict(rays.metadata),
                    times=rays.times,
                )
                k = torch.ones_like(rays.origins[..., :1])
            else:
                bundle, k = map_rays(rays, self.common_to_nerf[i], adapter.model.num_train_data)
            bundle = adapter.collide(bundle)
            out.append(QueriedSamples(adapter.samples(bundle), k, rows))
        return out

    def _methods(self) -> list[str]:
        methods = list(BLEND_METHODS) if self.config.render_all_methods else [self.active_method]
        if self.active_method not in methods:
            methods.append(self.active_method)
        return methods

    def _usage(
        self, camera_d: Float[Tensor, "num_nerfs num_rays"]
    ) -> tuple[Bool[Tensor, "num_nerfs num_rays"], Bool[Tensor, "num_nerfs num_rays"]]:
        """The IDW methods' distance mask, and the NeRFs any method being rendered can weight, per ray."""
        n = camera_d.shape[0]
        mask = blending.distance_mask(camera_d, self.tau if n > 1 else None)
        used = torch.zeros_like(mask)
        for method in self._methods():
            if method == "nerf":
                used[self.reference_nerf % n] = True
            elif method == "nearest":
                used |= blending.nearest_weights(camera_d) > 0
            else:
                used |= mask
        return mask, used

    def used_nerfs(self, ray_bundle: RayBundle) -> Bool[Tensor, "num_nerfs num_rays"]:
        """Per (flat) ray, the NeRFs the current settings can give weight to: the reference NeRF (``nerf``), the
        nearest (``nearest``), those passing the distance test (IDW methods). The others cannot change the ray's
        colour, so they are not queried for it."""
        camera_d = blending.camera_to_origin_distances(ray_bundle.origins, self.nerf_origins.to(ray_bundle.origins))
        return self._usage(camera_d)[1]

    def get_outputs(self, ray_bundle: RayBundle) -> dict[str, Tensor]:
        shape = ray_bundle.origins.shape[:-1]
        flat = ray_bundle.flatten() if len(shape) != 1 else ray_bundle
        outputs = self._blend(flat, self.nerf_samples(flat, self.used_nerfs(flat)))
        return {k: v.reshape(*shape, v.shape[-1]) for k, v in outputs.items()}

    def blend_samples(self, ray_bundle: RayBundle, per_nerf: list[QueriedSamples | None]) -> dict[str, Tensor]:
        """Blends samples from :meth:`nerf_samples` (flat rays) under the current settings: re-blending the same
        samples with other settings (a gamma sweep) needs no new sub-model queries."""
        return self._blend(ray_bundle, per_nerf)

    # --- blending ---------------------------------------------------------------------------------------------------

    def _stack_samples(
        self, per_nerf: list[QueriedSamples | None], ids: list[int], used: Bool[Tensor, "num_nerfs num_rays"]
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The samples of NeRFs ``ids`` as ``[len(ids), R, K]`` tensors in common-frame distances.

        Rays a NeRF was not queried on get zero-weight samples, and ``have`` (``[len(ids), R]``) says which are real.
        """
        num_rays = used.shape[1]
        kmax = max(per_nerf[i].samples.starts.shape[-1] for i in ids)  # type: ignore[union-attr]
        stacks: list[list[Tensor]] = [[], [], [], [], [], []]
        for i in ids:
            q = per_nerf[i]
            if q is None:
                raise ValueError(f"nerfuser: NeRF {i} ({self.nerf_names[i]}) is used but was not queried")
            s = q.samples
            st, en = s.starts / q.scale, s.ends / q.scale
            last = en[..., -1]
            rgbs, background = s.rgbs, s.background_rgb
            if self.blend_settings.appearance_matching and self._colour_mapped[i]:
                rgbs = apply_colour_map(rgbs, self.colour_maps[i])
                background = apply_colour_map(background, self.colour_maps[i])
            parts = [
                _pad_samples(st, kmax, last, -1),
                _pad_samples(en, kmax, last, -1),
                _pad_samples(s.weights, kmax, 0.0, -1),
                _pad_samples(rgbs, kmax, 0.0, -2),
                background,
            ]
            have = torch.ones(num_rays, dtype=torch.bool, device=st.device)
            if q.rows is not None:
                have = torch.zeros_like(have)
                have[q.rows] = True
                if bool((used[i] & ~have).any()):
                    raise ValueError(f"nerfuser: NeRF {i} ({self.nerf_names[i]}) is used on rays it was not queried on")
                full = []
                for x in parts:
                    y = x.new_zeros((num_rays,) + x.shape[1:])
                    y[q.rows] = x
                    full.append(y)
                parts = full
            for stack, x in zip(stacks, parts + [have], strict=True):
                stack.append(x)
        return tuple(torch.stack(x) for x in stacks)  # type: ignore[return-value]

    def _blend(self, ray_bundle: RayBundle, per_nerf: list[QueriedSamples | None]) -> dict[str, Tensor]:
        n = self.num_nerfs
        origins, directions = ray_bundle.origins, ray_bundle.directions
        nerf_origins = self.nerf_origins.to(origins)
        _, used = self._usage(blending.camera_to_origin_distances(origins, nerf_origins))
        # Only the NeRFs some ray uses take part; the nearest always does, so the distance test and the nearest NeRF
        # come out the same on this subset as on all N.
        ids = [i for i in range(n) if bool(used[i].any())]
        starts_t, ends_t, p, c, bg, have = self._stack_samples(per_nerf, ids, used)
        # A NeRF's missing rays become zero-length, massless samples at the ray's far end, which split nothing.
        far = torch.where(have, ends_t[..., -1], -math.inf).amax(dim=0)[None, :, None]
        starts_t = torch.where(have[..., None], starts_t, far)
        ends_t = torch.where(have[..., None], ends_t, far)
        settings = self.blend_settings if n > 1 else self.blend_settings.replace(tau=None)
        ref = self.reference_nerf % n
        methods = self._methods()
        cameras = self._coverage_cameras(ids) if any(m in COVERAGE_METHODS for m in methods) else None
        pixel_widths = ray_bundle.pixel_area[..., 0].sqrt() if cameras is not None else None
        results = blending.blend(methods, starts_t, ends_t, p, c, bg, origins, directions, nerf_origins[ids],
                                 settings, reference=ids.index(ref) if ref in ids else 0, cameras=cameras,
                                 pixel_widths=pixel_widths)  # fmt: skip
        main = results[self.active_method]
        outputs = {
            "rgb": main["rgb"],
            "accumulation": main["accumulation"][..., None],
            "depth": main["depth"][..., None],
            "expected_depth": main["expected_depth"][..., None],
        }
        if self.config.share_outputs:
            share = torch.zeros_like(used, dtype=main["share"].dtype)
            share[ids] = main["share"]  # [N, R]
            for i in range(n):
                outputs[f"share_{i}"] = share[i][..., None]
            palette = SHARE_PALETTE.to(share)[torch.arange(n, device=share.device) % len(SHARE_PALETTE)]
            outputs["nerf_share"] = (share.T @ palette).clamp(0.0, 1.0)
        if self.config.render_all_methods:
            for method, res in results.items():
                outputs[f"rgb_{method.replace('-', '_')}"] = res["rgb"]
        return outputs

    def _coverage_cameras(self, ids: list[int]) -> list[CameraIndex] | None:
        """The training-camera indices of NeRFs ``ids`` on the model's device, or None (one warning per model) when
        one of them has none: ``coverage`` is IDW-Sample then, ``coverage-3d`` IDW-2D."""
        missing = [self.nerf_names[i] for i in ids if self.nerf_cameras[i] is None]
        if missing:
            if not self._coverage_warned:
                self._coverage_warned = True
                warnings.warn(f"nerfuser: blend methods 'coverage' and 'coverage-3d' need every NeRF's training "
                              f"cameras; {missing} have none in the registration file (registered before they were "
                              "recorded, or their datasets were gone): IDW-Sample and IDW-2D are used instead",
                              stacklevel=2)  # fmt: skip
            return None
        device = self.nerf_origins.device
        if device not in self._cameras_on:
            self._cameras_on[device] = [None if c is None else c.to(device) for c in self.nerf_cameras]
        return [self._cameras_on[device][i] for i in ids]  # type: ignore[misc]

    def get_rgba_image(self, outputs: dict[str, Tensor], output_name: str = "rgb") -> Tensor:
        """The blend's colour with its accumulation as alpha (nerfstudio's default, for a background other than
        "random", is an alpha of 1): ``ns-export pointcloud`` keeps the rays above 0.5, those that end on a surface
        of the fused NeRFs rather than in their backgrounds; ``ns-render --rendered-output-names rgba`` shows it."""
        accumulation_name = output_name.replace("rgb", "accumulation", 1)
        if accumulation_name not in outputs:  # e.g. rgb_<method> of render_all_methods: as nerfstudio's Model says
            raise NotImplementedError(f"nerfuser: no {accumulation_name} output to give {output_name} an alpha")
        accumulation = outputs[accumulation_name]
        return torch.cat([outputs[output_name], accumulation.reshape(*outputs[output_name].shape[:-1], 1)], dim=-1)

    # --- evaluation -------------------------------------------------------------------------------------------------

    def _metrics(self, gt: Tensor, pred: Tensor) -> dict[str, float]:
        gt_b = torch.moveaxis(gt, -1, 0)[None]
        pred_b = torch.moveaxis(pred, -1, 0)[None]
        return {
            "psnr": float(self.psnr(pred_b, gt_b).item()),
            "ssim": float(self.ssim(pred_b, gt_b)),  # type: ignore[arg-type]
            "lpips": float(self.lpips(pred_b, gt_b)),
        }

    def get_image_metrics_and_images(
        self, outputs: dict[str, Tensor], batch: dict[str, Tensor]
    ) -> tuple[dict[str, float], dict[str, Tensor]]:
        gt = batch["image"].to(self.device).float()
        if gt.shape[-1] == 4:  # RGBA ground truth: on black, as nerfacto's "last_sample" does for metrics
            gt = gt[..., :3] * gt[..., 3:]
        pred = outputs["rgb"]
        metrics = self._metrics(gt, pred)
        if self.config.render_all_methods:
            for method in BLEND_METHODS:
                key = f"rgb_{method.replace('-', '_')}"
                if key in outputs:
                    for name, value in self._metrics(gt, outputs[key]).items():
                        metrics[f"{name}_{method.replace('-', '_')}"] = value
        images = {
            "img": torch.cat([gt, pred], dim=1),
            "accumulation": colormaps.apply_colormap(outputs["accumulation"]),
            "depth": colormaps.apply_depth_colormap(outputs["depth"], accumulation=outputs["accumulation"]),
        }
        if "nerf_share" in outputs:
            images["nerf_share"] = outputs["nerf_share"]
        return metrics, images


def _camera_index(cameras: TrainingCameras | CameraIndex | None, nerf_to_common: Tensor) -> CameraIndex | None:
    """A NeRF's training cameras (its own frame) as a look-up index in the common frame."""
    if cameras is None:
        return None
    if isinstance(cameras, TrainingCameras):
        cameras = CameraIndex.from_cameras(cameras.c2w, cameras.intrinsics)
    if not isinstance(cameras, CameraIndex):
        raise TypeError(f"nerfuser: training cameras must be TrainingCameras or CameraIndex, got {type(cameras)}")
    return cameras.transformed(nerf_to_common).to("cpu")


def check_mergeable(spec: FusionSpec) -> None:
    """:class:`~nerfuser_ns.adapters.UnsupportedRunError` naming the first run of ``spec`` whose model class no adapter
    takes (judged from its config.yml, nothing loaded)."""
    for entry in spec.nerfs:
        run = read_config(entry.config_path)
        check_model_class(entry.name, run.pipeline.model._target, run.method_name)


def fuse_models(
    nerfs: Sequence[tuple[Any, ...]], config: NerfuserModelConfig | None = None, **overrides: Any
) -> NerfuserModel:
    """A fused model from already loaded sub-models ``(name, model, nerf_to_common 4x4)``, optionally followed by
    the NeRF's training cameras and its colour map to the reference (tests, scripts).

    ``overrides`` set config fields (e.g. ``blend_method="nearest"``, ``gamma=2.0``).
    """
    config = config or NerfuserModelConfig()
    for key, value in overrides.items():
        if not hasattr(config, key):
            raise TypeError(f"NerfuserModelConfig has no field {key!r}")
        setattr(config, key, value)
    device = next(iter(nerfs))[1].device if nerfs else torch.device("cpu")
    model = config.setup(
        scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])),
        num_train_data=1,
        metadata={"nerfuser_models": list(nerfs)},
    )
    return model.to(device).eval()


__all__ = [
    "ADAPTERS",
    "NerfAdapter",
    "NerfSamples",
    "NerfactoAdapter",
    "NerfuserModel",
    "NerfuserModelConfig",
    "QueriedSamples",
    "fuse_models",
    "make_adapter",
    "map_rays",
]
