"""The datamanager and trainer config of the ``nerfuser`` method: the fused scene's datasets (test images of the
fusion spec, or placeholders when it has none) and the check of the whole configuration before a run folder exists.

The fusion spec and the registration file it reads are :mod:`nerfuser_ns.spec`'s.
"""
from __future__ import annotations

import copy
import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import DataManager, VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader, RandIndicesEvalDataloader
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE
from rich.markup import escape
from torch.nn import Parameter

from nerfuser_ns.adapters import UnsupportedRunError
from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.model import NerfuserModelConfig, check_mergeable
from nerfuser_ns.registration import RegistrationConfig
from nerfuser_ns.runs import RunLoadError, applied_transform, run_views, stored_to_nerf, training_cameras
from nerfuser_ns.sim3 import transform_poses
from nerfuser_ns.spec import METADATA_KEY, FusionSpec, FusionSpecError, one_line, read_fusion_spec, spec_error

# ----------------------------------------------------------------------------------------------------------------------
# Datasets


def fused_scene_box(spec: FusionSpec) -> SceneBox:
    """Axis-aligned box of the common frame holding every NeRF's [-1, 1]^3 cube (for the viewer)."""
    corners = np.array(np.meshgrid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0], indexing="ij")).reshape(3, -1).T
    pts = np.concatenate([corners @ n.nerf_to_common[:3, :3].T + n.nerf_to_common[:3, 3] for n in spec.nerfs])
    return SceneBox(aabb=torch.tensor(np.stack([pts.min(0), pts.max(0)]), dtype=torch.float32))


def _transform_cameras(cameras: Cameras, T: np.ndarray) -> Cameras:
    c2w = cameras.camera_to_worlds.detach().cpu().numpy().astype(np.float64)
    out = transform_poses(T, c2w)[..., :3, :4]
    cameras.camera_to_worlds = torch.tensor(out, dtype=torch.float32)
    return cameras


def test_parser_config(data: Path | None = None) -> NerfstudioDataParserConfig:
    """How test images are read: poses as stored (no re-centring, re-orientation or re-scaling), all as test split."""
    return NerfstudioDataParserConfig(
        data=data or Path(),
        downscale_factor=1,
        orientation_method="none",
        center_method="none",
        auto_scale_poses=False,
        scale_factor=1.0,
        eval_mode="interval",  # with interval 1 every image is a test image ("all" warns about camera optimisation)
        eval_interval=1,
    )


def load_test_dataparser_outputs(
    spec: FusionSpec, metadata: dict, parser_config: NerfstudioDataParserConfig | None = None
) -> DataparserOutputs:
    """The test images with their poses in the common frame: the stored poses of ``test_data`` mapped by
    ``test_to_common``, or the held-out images of the run ``test_run`` (:func:`held_out_dataparser_outputs`)."""
    if spec.test_run is not None:
        return held_out_dataparser_outputs(spec, metadata)
    assert spec.test_data is not None
    parser_config = copy.deepcopy(parser_config) if parser_config is not None else test_parser_config()
    parser_config.data = spec.test_data
    try:
        parsed = parser_config.setup().get_dataparser_outputs(split="test")
    except Exception as e:  # noqa: BLE001 - any parsing failure is the dataset's fault
        raise spec_error(spec.test_data, f"unreadable test dataset ({type(e).__name__}: {e})") from None
    # The parser's own normalisation (identity with the defaults) composes with test_to_common. What it reports also
    # holds the dataset's applied_transform / applied_scale, which it never applied to the stored poses.
    meta = json.loads((spec.test_data / "transforms.json").read_text())
    applied, applied_scale = applied_transform(spec.test_data, meta)
    to_parser = stored_to_nerf(parsed.dataparser_transform.double().numpy(), parsed.dataparser_scale, applied,
                               applied_scale)  # fmt: skip
    cameras = _transform_cameras(parsed.cameras, spec.test_to_common @ np.linalg.inv(to_parser))
    return DataparserOutputs(
        image_filenames=parsed.image_filenames,
        cameras=cameras,
        scene_box=fused_scene_box(spec),
        metadata=metadata,
        dataparser_transform=torch.eye(4)[:3],
        dataparser_scale=1.0,
    )


def held_out_dataparser_outputs(spec: FusionSpec, metadata: dict) -> DataparserOutputs:
    """The images the run ``spec.test_run`` kept out of its training (its own dataparser's eval split), with the
    cameras that dataparser gives them in the run's NeRF frame mapped by the run's registered transform."""
    assert spec.test_run is not None
    entry = spec.nerfs[spec.test_run]
    where = f"{spec.spec_path}: test_run {entry.name!r}"
    hint = "put it back where config.yml records it, or give its images as test_data with test_to_common"
    try:
        views = run_views(entry.config_path, "test", missing_hint=hint)
    except RunLoadError as e:
        raise spec_error(None, f"{where}: {e}") from None
    if len(views.image_filenames) == 0:
        raise spec_error(None, f"{where}: the run held no images out of training (its dataparser's eval split is "
                               "empty); give test images as test_data with test_to_common")  # fmt: skip
    return DataparserOutputs(
        image_filenames=views.image_filenames,
        cameras=_transform_cameras(views.cameras, entry.nerf_to_common),
        scene_box=fused_scene_box(spec),
        metadata=metadata,
        dataparser_transform=torch.eye(4)[:3],
        dataparser_scale=1.0,
    )


class PlaceholderImageDataset(InputDataset):
    """Cameras without images (mid-grey placeholders): what the viewer shows when the spec has no test images."""

    def get_data(self, image_idx: int, image_type: Literal["uint8", "float32"] = "float32") -> dict:
        cam = self._dataparser_outputs.cameras
        h, w = int(cam.height[image_idx]), int(cam.width[image_idx])
        if image_type == "uint8":
            image = torch.full((h, w, 3), 128, dtype=torch.uint8)
        else:
            image = torch.full((h, w, 3), 0.5)
        return {"image_idx": image_idx, "image": image}


def nerf_training_cameras(spec: FusionSpec) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], list[str]]:
    """Every fused NeRF's training cameras in the common frame, where each NeRF was trained to render: per NeRF that
    has any, its name, their poses ``[N, 3, 4]`` and pinhole intrinsics ``[N, 6]`` (fx, fy, cx, cy, width, height);
    those the registration file carries (camera-optimiser corrections applied), else those of the run's dataset
    (distortion left out: a ray is a ray, no image is compared). Also the names of the NeRFs with neither."""
    found, missing = [], []
    for entry in spec.nerfs:
        if entry.training_cameras is not None:
            c2w, intr = entry.training_cameras.c2w, entry.training_cameras.intrinsics
        else:
            try:
                cams = training_cameras(entry.config_path)
            except RunLoadError:
                missing.append(entry.name)
                continue
            c2w = cams.camera_to_worlds.detach().cpu().numpy().astype(np.float64)
            intr = torch.cat([cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height], dim=-1).double().numpy()
        found.append((entry.name, transform_poses(entry.nerf_to_common, c2w)[..., :3, :4],
                      np.broadcast_to(intr, (len(c2w), 6))))  # fmt: skip
    return found, missing


def _pinholes(found: list[tuple[str, np.ndarray, np.ndarray]]) -> Cameras:
    """One :class:`Cameras` of the pinholes :func:`nerf_training_cameras` found, in its order (on the CPU)."""
    c2w = torch.tensor(np.concatenate([c for _, c, _ in found]), dtype=torch.float32)
    k = torch.tensor(np.concatenate([i for _, _, i in found]), dtype=torch.float32)
    return Cameras(camera_to_worlds=c2w, fx=k[:, 0:1], fy=k[:, 1:2], cx=k[:, 2:3], cy=k[:, 3:4],
                   width=k[:, 4:5].round().long(), height=k[:, 5:6].round().long(),
                   camera_type=CameraType.PERSPECTIVE)  # fmt: skip


def render_cameras_dataparser_outputs(spec: FusionSpec, metadata: dict) -> DataparserOutputs | None:
    """Cameras to render a fused run from when its spec has no test images (``ns-render spiral``/``interpolate``/
    ``dataset``, ``ns-export tsdf``, the viewer's camera frustums): every fused NeRF's training cameras in the common
    frame (:func:`nerf_training_cameras`), without images (named ``<nerf name>/train_00000`` ...), in the spec's
    order. None when no NeRF has any."""
    found, _ = nerf_training_cameras(spec)
    if not found:
        return None
    return DataparserOutputs(
        image_filenames=[Path(f"<{name}>") / f"train_{i:05d}" for name, c2w, _ in found for i in range(len(c2w))],
        cameras=_pinholes(found),
        scene_box=fused_scene_box(spec),
        metadata=metadata,
        dataparser_transform=torch.eye(4)[:3],
        dataparser_scale=1.0,
    )


def export_cameras(spec: FusionSpec) -> tuple[Cameras, list[str]]:
    """Every fused NeRF's training cameras in the common frame (:func:`nerf_training_cameras`), the rays
    ``ns-export pointcloud`` samples, and the names of the NeRFs without any; FusionSpecError when no NeRF has any."""
    found, missing = nerf_training_cameras(spec)
    if not found:
        raise spec_error(spec.spec_path, "no fused NeRF has training cameras to sample rays from (the registration "
                                         "file records none and no run's dataset is readable): register the runs "
                                         "again with their datasets in place")  # fmt: skip
    return _pinholes(found), missing


@dataclass
class RayBatchSize:
    """The datamanager's ``train_pixel_sampler``: ``ns-export`` sets ``num_rays_per_batch`` on it (nerfuser samples
    the rays itself, :meth:`NerfuserDataManager.next_train`)."""

    num_rays_per_batch: int = 4096


def placeholder_dataparser_outputs(spec: FusionSpec, metadata: dict) -> DataparserOutputs:
    """One small camera per NeRF, at its origin looking along its -z axis (stand-ins for the viewer)."""
    n = len(spec.nerfs)
    c2w = []
    for entry in spec.nerfs:
        R = entry.nerf_to_common[:3, :3] / entry.scale
        c2w.append(np.concatenate([R, entry.origin[:, None]], axis=1))
    cameras = Cameras(
        camera_to_worlds=torch.tensor(np.stack(c2w), dtype=torch.float32),
        fx=torch.full((n, 1), 32.0),
        fy=torch.full((n, 1), 32.0),
        cx=torch.full((n, 1), 32.0),
        cy=torch.full((n, 1), 24.0),
        width=torch.full((n, 1), 64, dtype=torch.long),
        height=torch.full((n, 1), 48, dtype=torch.long),
        camera_type=CameraType.PERSPECTIVE,
    )
    return DataparserOutputs(
        image_filenames=[Path(f"<{entry.name}>") for entry in spec.nerfs],
        cameras=cameras,
        scene_box=fused_scene_box(spec),
        metadata=metadata,
        dataparser_transform=torch.eye(4)[:3],
        dataparser_scale=1.0,
    )


# ----------------------------------------------------------------------------------------------------------------------
# Datamanager


@dataclass
class NerfuserDataManagerConfig(VanillaDataManagerConfig):
    """Loads a fusion spec: the runs to fuse, their registration, and optional test images posed in the common frame.

    A VanillaDataManagerConfig only so that ``ns-render dataset`` accepts it; its ray-batch fields are unused.
    """

    _target: type = field(default_factory=lambda: NerfuserDataManager)
    data: Path | None = None
    """The fusion spec (``--data``): a JSON file, or a folder holding fusion.json (see nerfuser_ns.data)."""
    dataparser: NerfstudioDataParserConfig = field(default_factory=test_parser_config)
    """How the spec's test images are read (``data`` is taken from the spec)."""
    register_if_missing: bool = True
    """Run the registration when the spec's registration file does not exist (and write it there)."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """Settings of that registration (as ns-nerfuser-register's options; e.g. ``sampling.source training`` where
    hemisphere views of the NeRFs do not overlap)."""


class NerfuserDataManager(VanillaDataManager):
    """Datamanager of the ``nerfuser`` method.

    Nothing is trained: the train dataset only carries the :class:`FusionSpec` to the model (its ``metadata``) and
    the cameras to render from (viewer, ``ns-render spiral/interpolate/dataset``). Those are the test images when the
    spec has them (``ns-eval`` scores them), else every fused NeRF's training cameras
    (:func:`render_cameras_dataparser_outputs`, without images, so ``ns-eval`` refuses them), both as train and eval
    dataset; without either, placeholder cameras at the NeRF origins (for the viewer only) and no eval dataset.

    A :class:`VanillaDataManager` only because ``ns-render spiral`` asserts one; none of its set-up runs (its
    ``__init__`` parses a dataset and builds ray samplers). Its "training" rays are random rays of every fused NeRF's
    training cameras (:meth:`next_train`): what ``ns-export pointcloud`` turns into points.
    """

    config: NerfuserDataManagerConfig

    def __init__(
        self,
        config: NerfuserDataManagerConfig,
        device: torch.device | str = "cpu",
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        **kwargs,
    ):
        self.config = config
        self.device = device
        self.world_size = world_size
        self.local_rank = local_rank
        self.test_mode = test_mode
        # getattr: fused runs saved before the field existed have no ``registration`` in their config.yml
        self.spec = read_fusion_spec(config.data, register=config.register_if_missing,
                                     registration_config=getattr(config, "registration", None))  # fmt: skip
        for line in self.spec.capture_warnings():
            CONSOLE.print(f"[yellow]nerfuser: warning: {escape(line)}[/]", soft_wrap=True, highlight=False)
        metadata = {METADATA_KEY: self.spec}
        if self.spec.has_test_images:
            self.train_dataparser_outputs = load_test_dataparser_outputs(self.spec, metadata, config.dataparser)
            self.train_dataset = InputDataset(self.train_dataparser_outputs)
            self.eval_dataset = InputDataset(self.train_dataparser_outputs)
        elif (outputs := render_cameras_dataparser_outputs(self.spec, metadata)) is not None:
            self.train_dataparser_outputs = outputs
            self.train_dataset = PlaceholderImageDataset(outputs)
            self.eval_dataset = self.train_dataset
        else:
            self.train_dataparser_outputs = placeholder_dataparser_outputs(self.spec, metadata)
            self.train_dataset = PlaceholderImageDataset(self.train_dataparser_outputs)
            self.eval_dataset = None
        DataManager.__init__(self)  # not VanillaDataManager's (see the class docstring)
        self.train_pixel_sampler = RayBatchSize()
        self._ray_generator = torch.Generator().manual_seed(0)  # on the CPU: the same rays on every device

    def setup_train(self) -> None:
        """Nothing to set up: the method does not train."""

    def setup_eval(self) -> None:
        assert self.eval_dataset is not None
        self.eval_dataloader = RandIndicesEvalDataloader(input_dataset=self.eval_dataset, device=self.device)
        self._fixed_indices_eval_dataloader = FixedIndicesEvalDataloader(
            input_dataset=self.eval_dataset, device=self.device
        )

    @functools.cached_property
    def eval_dataloader(self) -> RandIndicesEvalDataloader:
        """The eval cameras (``ns-render spiral`` starts at the first). Only reached before ``setup_eval`` set the
        attribute (``inference`` mode), or without cameras: then one line naming what to use instead. A cached
        property, skipped by the viewer (see below)."""
        if self.eval_dataset is not None:
            self.setup_eval()
            return self.__dict__["eval_dataloader"]
        raise SystemExit(
            one_line(
                f"nerfuser: {self.spec.spec_path or self.config.data}: no cameras to render a spiral or an "
                "interpolation from (the fusion spec has no test images, the registration file records no training "
                "cameras and no dataset of the fused runs is readable); "
                "render a camera path made in the viewer's Render tab (ns-render camera-path), or add 'test_data' to "
                "the spec and render its views (ns-render dataset --split test)"
            )
        )

    @functools.cached_property
    def fixed_indices_eval_dataloader(self) -> FixedIndicesEvalDataloader:
        """All test images in order (``ns-eval``). A cached property: nerfstudio's viewer reads every plain attribute
        and property of the pipeline but skips cached ones, so a spec without test images still opens in it."""
        if not self.spec.has_test_images:
            raise RuntimeError(
                f"{self.spec.spec_path or self.config.data}: the fusion spec has no test images; add 'test_data' "
                "(a nerfstudio dataset posed in the common frame) or 'test_run' (a run's held-out images) to evaluate"
            )
        if not hasattr(self, "_fixed_indices_eval_dataloader"):
            self.setup_eval()
        return self._fixed_indices_eval_dataloader

    @functools.cached_property
    def export_cameras(self) -> Cameras:
        """Every fused NeRF's training cameras in the common frame (:func:`export_cameras`), on the device; the NeRFs
        without any are named once. A cached property (skipped by the viewer, see below)."""
        cameras, missing = export_cameras(self.spec)
        if missing:
            CONSOLE.print(f"[yellow]nerfuser: no training cameras for {', '.join(missing)} (not in the registration "
                          "file, dataset gone): their rays are left out[/]")  # fmt: skip
        return cameras.to(self.device)

    @functools.cached_property
    def _export_image_sizes(self) -> torch.Tensor:
        """``[N, 2]`` rows and columns of :attr:`export_cameras`, kept on the CPU where the rays are drawn (copied
        from the device once, not per batch)."""
        return torch.cat([self.export_cameras.height, self.export_cameras.width], dim=-1).detach().cpu().float()

    def next_train(self, step: int) -> tuple[RayBundle, dict]:
        """``train_pixel_sampler.num_rays_per_batch`` random rays of the fused NeRFs' training cameras in the common
        frame (``ns-export pointcloud`` reads these), each through a uniform point of a uniformly drawn camera's
        image; ``indices`` (camera, row, column) as nerfstudio's. Seeded once: the same calls give the same rays.
        Nothing trains on them (``ns-train nerfuser`` runs no iteration)."""
        cams, n, g = self.export_cameras, int(self.train_pixel_sampler.num_rays_per_batch), self._ray_generator
        cam = torch.randint(len(cams), (n,), generator=g)
        coords = torch.rand((n, 2), generator=g) * self._export_image_sizes[cam]
        cam, coords = cam.to(self.device), coords.to(self.device)
        bundle = cams.generate_rays(camera_indices=cam.unsqueeze(-1), coords=coords)
        return bundle, {"indices": torch.cat([cam.unsqueeze(-1), coords.long()], dim=-1)}

    def next_eval(self, step: int) -> tuple[Cameras, dict]:
        return self.next_eval_image(step)

    def next_eval_image(self, step: int) -> tuple[Cameras, dict]:
        if not self.spec.has_test_images:
            raise RuntimeError("the fusion spec has no test images")
        if "eval_dataloader" not in self.__dict__:  # not hasattr: the class attribute would raise
            self.setup_eval()
        for camera, batch in self.eval_dataloader:
            return camera, batch
        raise ValueError("no more eval images")

    def get_train_rays_per_batch(self) -> int:
        return int(self.train_pixel_sampler.num_rays_per_batch)

    def get_eval_rays_per_batch(self) -> int:
        return 1

    def get_datapath(self) -> Path:
        return Path(self.config.data) if self.config.data is not None else Path(".")

    def get_param_groups(self) -> dict[str, list[Parameter]]:
        return {}


@dataclass
class NerfuserTrainerConfig(TrainerConfig):
    """TrainerConfig that validates the fusion spec before ``ns-train`` writes anything.

    ``ns-train`` saves config.yml before the pipeline (and its datamanager) is built; checking the blend settings and
    the spec (registering the runs when the registration file is missing) in ``save_config`` makes bad settings, a bad
    spec or a failed registration fail with one line and no run folder.
    """

    def save_config(self) -> None:
        data = self.data or self.pipeline.datamanager.data
        datamanager = self.pipeline.datamanager
        if self.max_num_iterations > 0:  # next_train's rays carry no images to train on
            raise SystemExit("nerfuser: nothing to train (the sub-models are frozen): run ns-train nerfuser with "
                             f"--max-num-iterations 0 (its default), not {self.max_num_iterations}")
        try:
            if isinstance(self.pipeline.model, NerfuserModelConfig):
                BlendSettings.from_config(self.pipeline.model)  # bad gamma / tau / NERFUSER_* values
            # The whole spec, and the registration when it is missing (minutes, announced by the registration
            # itself): a failure leaves no run folder behind.
            spec = read_fusion_spec(data, register=getattr(datamanager, "register_if_missing", True),
                                    registration_config=getattr(datamanager, "registration", None))  # fmt: skip
            if spec.test_run is not None:
                held_out_dataparser_outputs(spec, {})  # its dataset must parse and hold images out
            check_mergeable(spec)  # a method whose samples cannot be merged fails here, not after the run folder
        except (FusionSpecError, ValueError, UnsupportedRunError) as e:
            raise SystemExit(f"nerfuser: {one_line(str(e)).removeprefix('nerfuser: ')}") from None
        data = Path(data).absolute()
        self.pipeline.datamanager.data = data
        if hasattr(self.pipeline.model, "fusion_spec"):
            self.pipeline.model.fusion_spec = data  # so the model alone (runs.load_run) finds its sub-models
        super().save_config()


__all__ = ["NerfuserDataManager", "NerfuserDataManagerConfig", "NerfuserTrainerConfig"]
