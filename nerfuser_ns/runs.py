"""Load any trained nerfstudio run from its ``config.yml`` and render it from arbitrary camera poses.

The run is rebuilt from its OWN saved config (never a default one: nerfstudio 1.x's ``average_init_density``
alone makes densities 100x off otherwise) and its latest (or chosen) checkpoint. By default only the model is
built, so the dataset folder need not exist: the scene box and the number of training images are read back from
the checkpoint. ``with_data=True`` builds the whole pipeline (datamanager included) for users who need the
training cameras; then the dataset must be where config.yml says, or at ``data_override``.

Frames: a run's "NeRF frame" is the normalised frame nerfstudio trains in. ``dataparser_transforms.json`` beside
config.yml, with the dataset's ``applied_transform`` / ``applied_scale`` (``ns-process-data`` writes them), maps the
frame of the dataset's stored poses into it; :attr:`LoadedRun.data_to_nerf` is that map as a 4x4 SIM(3)
(``[[s R, s t], [0, 1]]``, points as columns).
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import functools
import hashlib
import json
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path, PurePath
from typing import Literal

import numpy as np
import torch
import yaml
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.base_model import Model
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from torch import Tensor

from nerfuser_ns import runtime
from nerfuser_ns.cameras import Intrinsics


class RunLoadError(ValueError):
    """A run folder or config.yml cannot be used; the message names the file and what to do."""


@dataclass
class LoadedRun:
    """A trained nerfstudio run, rebuilt from its own config.yml."""

    config_path: Path
    """The run's config.yml."""
    config: TrainerConfig
    """The config as saved by ``ns-train`` (output_dir patched to where the run lies now)."""
    model: Model
    """The model, in eval mode, on :attr:`device`."""
    checkpoint_path: Path
    """The checkpoint that was loaded."""
    step: int
    """Its training step."""
    pipeline: object | None = None
    """The full pipeline when loaded with ``with_data=True``."""
    data_override: Path | None = None
    """The dataset folder given instead of the one config.yml records."""

    @property
    def name(self) -> str:
        return f"{self.config.experiment_name}/{self.config.method_name}/{self.config_path.parent.name}"

    @property
    def device(self) -> torch.device:
        return self.model.device

    @functools.cached_property
    def data_to_nerf(self) -> np.ndarray | None:
        """4x4 SIM(3) from the dataset's stored pose frame to the NeRF frame (:func:`read_dataparser_transform`; None
        when dataparser_transforms.json is absent). Read on first use: rendering alone never needs the dataset."""
        return read_dataparser_transform(self.config_path, self.data_override)


def resolve_config_path(config_path: Path | str) -> Path:
    """The run's config.yml, given it or its run folder; a one-line error naming the path otherwise."""
    config_path = Path(config_path)
    if not config_path.exists():
        raise RunLoadError(f"{config_path}: no such file; pass the config.yml that ns-train wrote in the run folder")
    if config_path.is_dir():
        if (config_path / "config.yml").is_file():
            config_path = config_path / "config.yml"
        else:
            raise RunLoadError(f"{config_path}: is a folder without config.yml; pass the run's config.yml")
    return config_path


def run_names(config_paths: list[Path | str]) -> list[str]:
    """Names for runs in messages and records: ``experiment/method/timestamp`` (the folders ``ns-train`` writes
    above config.yml), longer trailing paths where those are not distinct, the paths as given as a last resort."""
    parts = [PurePath(p).parts for p in config_paths]
    parts = [q[:-1] if len(q) > 1 and q[-1] in ("config.yml", "config.yaml") else q for q in parts]
    longest = max((len(q) for q in parts), default=1)
    for k in range(min(3, longest), longest + 1):
        names = ["/".join(q[-k:]) for q in parts]
        if len(set(names)) == len(names):
            return names
    return [str(p) for p in config_paths]


class UnsafeConfigError(RunLoadError):
    """A config.yml names Python objects a nerfstudio config never holds (it could run code when loaded)."""


def _trusted_packages() -> frozenset[str]:
    """Top-level packages whose classes a run config may name: nerfstudio, ours, and installed nerfstudio plugins."""
    names = {"nerfstudio", "nerfuser_ns"}
    for group in ("nerfstudio.method_configs", "nerfstudio.dataparser_configs"):
        names.update(ep.value.split(":")[0].split(".")[0] for ep in entry_points(group=group))
    return frozenset(names)


class _ConfigLoader(yaml.Loader):
    """PyYAML's loader for nerfstudio's Python-tagged configs, restricted to what such a config holds: config
    dataclasses and enums of nerfstudio, ours and installed nerfstudio plugins, pathlib paths, and references to their
    classes and functions (plus torch optimisers). Anything else (``os.system``, ``subprocess``, a function applied
    to arguments, a module) is refused before its module is even imported."""

    trusted: frozenset[str] = frozenset()

    def _check_name(self, kind: str, suffix: str, node: yaml.Node) -> None:
        top = suffix.split(".")[0]
        if kind == "name" and (top in self.trusted or suffix.startswith("torch.optim.")):
            return
        if kind in ("object", "apply") and (top in self.trusted or top == "pathlib"):
            return
        self._refuse(suffix, node)

    def _object(self, suffix: str, node: yaml.Node) -> object:
        self._check_name("object", suffix, node)
        cls = self.find_python_name(suffix, node.start_mark)
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            raise UnsafeConfigError(f"refusing !!python/object:{suffix}: not a config dataclass")
        return self.construct_python_object(suffix, node)

    def _apply(self, suffix: str, node: yaml.Node) -> object:
        self._check_name("apply", suffix, node)
        cls = self.find_python_name(suffix, node.start_mark)
        if not (isinstance(cls, type) and issubclass(cls, (enum.Enum, PurePath))):
            raise UnsafeConfigError(f"refusing !!python/object/apply:{suffix}: only enums and paths are built")
        return self.construct_python_object_apply(suffix, node)

    def _name(self, suffix: str, node: yaml.Node) -> object:
        self._check_name("name", suffix, node)
        return self.construct_python_name(suffix, node)

    def _refuse(self, suffix: str, node: yaml.Node) -> object:
        tag = node.tag.replace("tag:yaml.org,2002:", "!!")  # the tag as written (!!python/object/apply:os.system)
        raise UnsafeConfigError(f"refusing {tag} at line {node.start_mark.line + 1}")


_ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/object:", _ConfigLoader._object)
_ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/object/apply:", _ConfigLoader._apply)
_ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/name:", _ConfigLoader._name)
_ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/object/new:", _ConfigLoader._refuse)
_ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/module:", _ConfigLoader._refuse)


def load_config_yaml(text: str) -> object:
    """Parse a run's config.yml text with :class:`_ConfigLoader` (raises :class:`UnsafeConfigError`)."""
    _ConfigLoader.trusted = _trusted_packages()
    return yaml.load(text, Loader=_ConfigLoader)


def read_config(config_path: Path | str) -> TrainerConfig:
    """Read a run's config.yml, checking it is one; output_dir is re-anchored to where the run lies now."""
    config_path = resolve_config_path(config_path)
    try:
        config = load_config_yaml(config_path.read_text())
    except UnsafeConfigError as e:
        message = f"{config_path}: {e}; not a nerfstudio run config (or its plugin is not installed)"
        raise UnsafeConfigError(message) from None
    except Exception as e:  # noqa: BLE001 - YAML or import errors are the file's fault
        first_line = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise RunLoadError(f"{config_path}: not a readable nerfstudio config ({first_line})") from None
    if not isinstance(config, TrainerConfig):
        raise RunLoadError(f"{config_path}: not a nerfstudio run config (got {type(config).__name__})")
    # config.yml lives at <output_dir>/<experiment>/<method>/<timestamp>/config.yml, saved with a relative
    # output_dir: anchor it where the file is so the run works from any working directory.
    run_root = config_path.parent.parent.parent.parent
    _anchor_dataset(config, run_root)
    config.output_dir = run_root
    config.timestamp = config_path.parent.name
    config.load_dir = config_path.parent / config.relative_model_dir
    return config


def _anchor_dataset(config: TrainerConfig, run_root: Path) -> None:
    """A relative dataset path is relative to where ns-train ran; when it does not resolve from here, recover that
    folder from the relative output_dir saved beside it (``<train cwd>/<output_dir>`` is ``run_root``)."""
    data, saved_out = config.pipeline.datamanager.data, Path(config.output_dir)
    if data is None or Path(data).is_absolute() or Path(data).exists() or saved_out.is_absolute():
        return
    n = len(saved_out.parts)
    if n == 0 or run_root.absolute().parts[-n:] != saved_out.parts:
        return
    train_cwd = Path(*run_root.absolute().parts[:-n])
    if (train_cwd / data).exists():
        config.pipeline.datamanager.data = train_cwd / data


def find_checkpoint(config_path: Path, config: TrainerConfig, step: int | None = None) -> tuple[Path, int]:
    """The checkpoint of a run (the latest, or the given step) and its step; one-line errors when there is none."""
    ckpt_dir = config_path.parent / config.relative_model_dir
    ckpts = sorted(ckpt_dir.glob("step-*.ckpt")) if ckpt_dir.is_dir() else []
    if not ckpts:
        raise RunLoadError(
            f"{config_path}: the run has no checkpoint in {ckpt_dir}; train it longer (checkpoints are saved "
            "every --steps-per-save steps) or pass the config.yml of a finished run"
        )
    steps = {int(p.stem.split("-")[1]): p for p in ckpts}
    if step is None:
        step = max(steps)
    if step not in steps:
        raise RunLoadError(f"{config_path}: no checkpoint for step {step}; available: {sorted(steps)}")
    return steps[step], step


COLMAP_APPLIED_TRANSFORM = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]])
"""What nerfstudio's dataparser assumes for a dataset with ``colmap/sparse/0`` and no ``applied_transform`` key."""


def applied_transform(data_dir: Path, meta: dict) -> tuple[Float[np.ndarray, "4 4"], float]:
    """The ``applied_transform`` (as 4x4) and ``applied_scale`` of a nerfstudio dataset, as nerfstudio reads them.

    ``ns-process-data`` stores poses already mapped by ``applied_transform`` (original COLMAP frame -> stored frame);
    nerfstudio's dataparser folds it, and ``applied_scale``, into ``dataparser_transforms.json`` without applying them
    to the stored poses. Missing keys mean identity and 1 (or nerfstudio's COLMAP default when ``colmap/sparse/0``
    exists, as its dataparser does).
    """
    value = meta.get("applied_transform")
    if value is None and (Path(data_dir) / "colmap" / "sparse" / "0").exists():
        value = COLMAP_APPLIED_TRANSFORM
    A = np.eye(4)
    if value is not None:
        value = np.asarray(value, dtype=np.float64)
        if value.shape not in ((3, 4), (4, 4)) or not np.isfinite(value).all():
            raise RunLoadError(f"{data_dir}/transforms.json: 'applied_transform' must be a finite 3x4 matrix")
        A[:3, :4] = value[:3, :4]
    scale = float(meta.get("applied_scale", 1.0))
    if not (np.isfinite(scale) and scale > 0):
        raise RunLoadError(f"{data_dir}/transforms.json: 'applied_scale' must be positive, got {scale}")
    return A, scale


def stored_to_nerf(
    transform: Float[np.ndarray, "3 4"],
    scale: float,
    applied: Float[np.ndarray, "4 4"] | None = None,
    applied_scale: float = 1.0,
) -> Float[np.ndarray, "4 4"]:
    """SIM(3) from a dataset's stored pose frame to the dataparser's output frame.

    ``transform``/``scale`` are what nerfstudio reports (``dataparser_transforms.json``, ``DataparserOutputs``): they
    map the ORIGINAL frame (before ``applied_transform``) and include ``applied_scale``. The stored poses were only
    re-oriented, centred and scaled by the dataparser's own part: ``S(scale / applied_scale) transform applied^-1``.
    """
    T = np.eye(4)
    T[:3, :4] = np.asarray(transform, dtype=np.float64)[:3, :4]
    if applied is not None:
        T = T @ np.linalg.inv(applied)
    out = T.copy()
    out[:3, :] *= float(scale) / float(applied_scale)
    return out


def dataset_path(config: TrainerConfig, data_override: Path | None = None) -> Path | None:
    """The run's dataset folder: the override, or the path recorded in config.yml (None when it records none)."""
    if data_override is not None:
        return Path(data_override)
    data = config.pipeline.datamanager.data or getattr(config.pipeline.datamanager.dataparser, "data", None)
    return None if data is None else Path(data)


def check_dataset_folder(path: Path | str, what: str = "--data") -> Path:
    """``path`` as a dataset a nerfstudio dataparser reads: a folder with ``transforms.json`` (nerfstudio-data), a
    ``colmap/sparse`` or ``sparse`` model (COLMAP), or a ``transforms.json`` file; RunLoadError (one line) otherwise."""
    path = Path(path)
    if not path.exists():
        raise RunLoadError(f"{what} {path}: no such folder; pass the dataset folder the run was trained on")
    if path.is_file():
        if path.suffix != ".json":
            raise RunLoadError(f"{what} {path}: a file that is not a transforms.json; pass the dataset folder")
        return path
    if not any((path / p).exists() for p in ("transforms.json", "colmap/sparse", "sparse")):
        raise RunLoadError(f"{what} {path}: not a dataset folder (no transforms.json, colmap/sparse or sparse); "
                           "pass the folder ns-process-data wrote")  # fmt: skip
    return path


@functools.lru_cache(maxsize=64)
def _sha256(path: Path, mtime_ns: int, size: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def checkpoint_identity(config_path: Path | str) -> dict:
    """Which weights a run renders with now: its latest checkpoint's file name, step and SHA-256 (what a registration
    records, so that a run retrained afterwards is not fused with a transform of its old weights)."""
    config_path = resolve_config_path(config_path)
    path, step = find_checkpoint(config_path, read_config(config_path))
    stat = path.stat()
    return {"file": path.name, "step": int(step), "sha256": _sha256(path.absolute(), stat.st_mtime_ns, stat.st_size)}


def read_dataparser_transform(config_path: Path, data_override: Path | None = None) -> np.ndarray | None:
    """The 4x4 SIM(3) dataset frame -> NeRF frame (``p_nerf = T p_data``), where the dataset frame is the frame of the
    poses stored in the run's ``transforms.json``.

    Built from ``dataparser_transforms.json`` beside config.yml and, for nerfstudio-format datasets, the dataset's
    ``applied_transform`` / ``applied_scale`` (see :func:`stored_to_nerf`): the dataset must then be readable (at the
    path config.yml records, or ``data_override``). None when the run has no dataparser_transforms.json.
    """
    config_path = Path(config_path)
    path = config_path.parent / "dataparser_transforms.json"
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
        transform = np.asarray(meta["transform"], dtype=np.float64)
        scale = float(meta["scale"])
    except Exception as e:  # noqa: BLE001
        raise RunLoadError(f"{path}: unreadable dataparser transform ({type(e).__name__}: {e})") from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not np.isfinite(scale) or scale <= 0:
        raise RunLoadError(f"{path}: expected a finite 3x4 'transform' and a positive 'scale'")
    config = read_config(config_path)
    if not isinstance(config.pipeline.datamanager.dataparser, NerfstudioDataParserConfig):
        # Other dataparsers report the map from the frame they read poses in.
        return stored_to_nerf(transform, scale)
    data = dataset_path(config, data_override)
    dataset_meta = _read_transforms_json(config_path, data)
    A, applied_scale = applied_transform(data.parent if data.suffix == ".json" else data, dataset_meta)
    return stored_to_nerf(transform, scale, A, applied_scale)


def _read_transforms_json(config_path: Path, data: Path | None) -> dict:
    """The dataset's transforms.json (nerfstudio accepts the folder or the file itself as --data)."""
    if data is None:
        raise RunLoadError(f"{config_path}: records no dataset; pass the run's dataset folder (--data)")
    path = data if data.suffix == ".json" else data / "transforms.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise RunLoadError(
            f"{path}: cannot read the run's dataset ({type(e).__name__}), needed to map the dataset frame into the "
            "NeRF frame (nerfstudio's applied_transform lives there); pass the dataset folder (--data)"
        ) from None


REGISTER_WITHOUT_DATASET = (
    "pass the dataset folder (ns-nerfuser-register --data) or register without training poses "
    "(--sampling.source hemisphere)"
)
"""What to do when a run's dataset is gone, where registration reads its training views."""


def training_cameras(config_path: Path | str, data_override: Path | None = None) -> Cameras:
    """The run's training cameras in its NeRF frame, parsed from its dataset with the run's own dataparser settings.

    Only transforms.json (and the first image's size) is read: no images are loaded and no datamanager (stock
    nerfacto's spawns worker processes) is built. Raises :class:`RunLoadError` naming the dataset when it is gone.
    """
    return training_views(config_path, data_override).cameras


def training_views(config_path: Path | str, data_override: Path | None = None) -> DataparserOutputs:
    """The run's training split as its dataparser gives it (cameras in the NeRF frame, image file names in the same
    order, which is the order of the camera optimiser's adjustments); as :func:`training_cameras`, no image is read."""
    return run_views(config_path, "train", data_override)


def run_views(
    config_path: Path | str,
    split: Literal["train", "test"],
    data_override: Path | None = None,
    missing_hint: str = REGISTER_WITHOUT_DATASET,
) -> DataparserOutputs:
    """The run's ``train`` split, or the images it held out (``test``: its dataparser's eval split), with the run's
    own dataparser settings: cameras in the NeRF frame, no image read. RunLoadError (one line, ending with
    ``missing_hint`` when the dataset is gone) when the dataset is gone or cannot be parsed."""
    config_path = resolve_config_path(config_path)
    config = read_config(config_path)
    data = dataset_path(config, data_override)
    if data is None or not data.exists():
        raise RunLoadError(f"{config_path}: its dataset {data} is missing; {missing_hint}")
    parser_config = copy.deepcopy(config.pipeline.datamanager.dataparser)
    parser_config.data = data
    try:
        return parser_config.setup().get_dataparser_outputs(split=split)
    except Exception as e:  # noqa: BLE001 - any parsing failure is the dataset's fault
        raise RunLoadError(f"{data}: the run's dataset cannot be parsed ({type(e).__name__}: {e})") from None


def camera_optimizer_mode(config: TrainerConfig) -> str | None:
    """The run's camera optimiser mode as trained (``"off"``, ``"SO3xR3"``, ``"SE3"``); None when its model has none
    (e.g. instant-ngp)."""
    optimizer = getattr(config.pipeline.model, "camera_optimizer", None)
    mode = getattr(optimizer, "mode", None)
    return None if mode is None else str(mode)


def optimized_poses(model: Model, c2w: Float[Tensor, "n 3|4 4"]) -> Float[Tensor, "n 3 4"]:
    """Training poses corrected by the run's camera optimiser, as nerfstudio applies it (``apply_to_camera``: the
    correction's rotation left-multiplies the camera's, its translation adds to the centre). Unchanged when the model
    has no optimiser, it is off, or its number of cameras differs from ``c2w``'s."""
    c2w = torch.as_tensor(c2w)[..., :3, :4]
    optimizer = getattr(model, "camera_optimizer", None)
    adjustment = getattr(optimizer, "pose_adjustment", None)
    if optimizer is None or adjustment is None or optimizer.config.mode == "off" or len(adjustment) != len(c2w):
        return c2w
    with torch.no_grad():
        adj = optimizer(torch.arange(len(c2w), device=adjustment.device)).to(c2w)
    return torch.cat([adj[:, :3, :3] @ c2w[:, :3, :3], c2w[:, :3, 3:] + adj[:, :3, 3:]], dim=-1)


def default_device() -> str:
    """Where runs render unless told otherwise: the GPU when torch sees one, else the CPU."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def check_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch device that exists on this machine; :class:`RunLoadError` naming those that do."""
    cuda = torch.cuda.device_count() if torch.cuda.is_available() else 0
    available = ", ".join(["cpu"] + [f"cuda:{i}" for i in range(cuda)])
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise RunLoadError(f"--device {device!r} is not a torch device; this machine has: {available}") from None
    usable = parsed.type == "cpu" or (parsed.type == "cuda" and (parsed.index or 0) < cuda)
    if not usable:
        raise RunLoadError(f"--device {device!r} is not on this machine; it has: {available}")
    return parsed


def _model_state(state: dict, config_path: Path) -> dict[str, Tensor]:
    pipeline_state = state["pipeline"]
    model_state = {}
    for key, value in pipeline_state.items():
        key = key[len("module.") :] if key.startswith("module.") else key
        if key.startswith("_model."):
            key = key[len("_model.") :]
            key = key[len("module.") :] if key.startswith("module.") else key
            model_state[key] = value
    if not model_state:
        raise RunLoadError(f"{config_path}: the checkpoint holds no model weights")
    return model_state


def _infer_model_kwargs(config: TrainerConfig, model_state: dict[str, Tensor]) -> tuple[SceneBox, int]:
    """Scene box and number of training images, read back from the checkpoint (no dataset needed)."""
    aabb = model_state.get("field.aabb")
    if aabb is None:
        # nerfstudio's dataparsers build a cube of side 2 * scene_scale around the origin.
        scale = float(getattr(config.pipeline.datamanager.dataparser, "scene_scale", 1.0))
        aabb = torch.tensor([[-scale] * 3, [scale] * 3], dtype=torch.float32)
    num_train_data = 1
    for key in ("field.embedding_appearance.embedding.weight", "camera_optimizer.pose_adjustment"):
        if key in model_state:
            num_train_data = int(model_state[key].shape[0])
            break
    return SceneBox(aabb=aabb.float().clone()), num_train_data


def _replay_step_state(model: Model, step: int) -> None:
    """Restore state that training callbacks set from the step number (e.g. nerfacto's proposal-weight anneal).

    nerfstudio's own loaders leave it at its initial value, which changes renders of runs shorter than the anneal
    schedule. Callbacks that need an optimizer or trainer are skipped: they do not hold render state.
    """
    attrs = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=None)
    try:
        callbacks = model.get_training_callbacks(attrs)
    except Exception:  # noqa: BLE001 - models whose callbacks need a live trainer have no such state
        return
    for callback in callbacks:
        if TrainingCallbackLocation.BEFORE_TRAIN_ITERATION not in callback.where_to_run:
            continue
        try:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        except Exception:  # noqa: BLE001
            continue


def load_run(
    config_path: Path | str,
    device: str | torch.device = "cpu",
    step: int | None = None,
    with_data: bool = False,
    data_override: Path | None = None,
    test_mode: Literal["test", "val", "inference"] = "inference",
    eval_num_rays_per_chunk: int | None = None,
) -> LoadedRun:
    """Rebuild a trained nerfstudio run from its config.yml and checkpoint.

    Args:
        config_path: the run's config.yml (or the run folder holding it).
        device: where to put the model.
        step: checkpoint step to load (default: the latest).
        with_data: also build the datamanager (needs the dataset); otherwise the model alone.
        data_override: dataset folder to use instead of the one recorded in config.yml.
        test_mode: passed to the datamanager when ``with_data``.
        eval_num_rays_per_chunk: rays per forward pass when rendering (default: the run's own).
    """
    runtime.install()
    config_path = resolve_config_path(config_path)
    config = read_config(config_path)
    if eval_num_rays_per_chunk:
        config.pipeline.model.eval_num_rays_per_chunk = eval_num_rays_per_chunk
    ckpt_path, ckpt_step = find_checkpoint(config_path, config, step)
    try:
        state = runtime.load_checkpoint(ckpt_path)
    except (FileNotFoundError, ValueError) as e:
        raise RunLoadError(str(e)) from None
    device = torch.device(device)
    pipeline = None
    if with_data:
        if data_override is not None:
            config.pipeline.datamanager.data = Path(data_override)
        data = config.pipeline.datamanager.data or getattr(config.pipeline.datamanager.dataparser, "data", None)
        if data is not None and not Path(data).exists():
            raise RunLoadError(
                f"{config_path}: its dataset {data} is missing; pass the dataset folder (ns-nerfuser-register "
                "--data, load_run(data_override=...)) or load without data (the model alone needs no dataset)"
            )
        pipeline = config.pipeline.setup(device=device, test_mode=test_mode)
        pipeline.eval()
        pipeline.load_pipeline(state["pipeline"], state["step"])
        model = pipeline.model
        _replay_step_state(model, int(state["step"]))  # as below: both paths must render alike
    else:
        model_state = _model_state(state, config_path)
        scene_box, num_train_data = _infer_model_kwargs(config, model_state)
        model = config.pipeline.model.setup(
            scene_box=scene_box, num_train_data=num_train_data, metadata={}, device=device, grad_scaler=None
        )
        # LPIPS weights in GPU-trained checkpoints are not model state we need (our LPIPS is lazy).
        model_state = {k: v for k, v in model_state.items() if not k.startswith("lpips.")}
        missing, unexpected = model.load_state_dict(model_state, strict=False)
        if missing or unexpected:
            raise RunLoadError(
                f"{ckpt_path}: checkpoint does not match the model in {config_path.name} "
                f"(missing {list(missing)[:3]}, unexpected {list(unexpected)[:3]}); was it trained with tcnn? "
                "Re-train with --pipeline.model.implementation torch or load it on a CUDA machine with tcnn"
            )
        model.update_to_step(int(state["step"]))
        _replay_step_state(model, int(state["step"]))
        model.to(device)
        model.eval()
    return LoadedRun(
        config_path=config_path,
        config=config,
        model=model,
        checkpoint_path=ckpt_path,
        step=ckpt_step,
        pipeline=pipeline,
        data_override=data_override,
    )


def make_cameras(
    camera_to_worlds: Float[Tensor, "num_cams 3 4"] | Float[np.ndarray, "num_cams 3 4"], intrinsics: Intrinsics
) -> Cameras:
    """Pinhole cameras in nerfstudio's convention (OpenGL axes: the camera looks along -z), all with ``intrinsics``."""
    k = intrinsics
    fx, fy, cx, cy, width, height = k.fx, k.fy, k.cx, k.cy, k.width, k.height
    c2w = torch.as_tensor(np.asarray(camera_to_worlds), dtype=torch.float32)
    if c2w.ndim == 2:
        c2w = c2w[None]
    if c2w.shape[-2:] == (4, 4):
        c2w = c2w[:, :3, :]
    if c2w.ndim != 3 or c2w.shape[-2:] != (3, 4):
        raise ValueError(f"camera_to_worlds must be [N, 3, 4] or [N, 4, 4], got {tuple(c2w.shape)}")
    if width <= 0 or height <= 0 or fx <= 0 or fy <= 0:
        raise ValueError(f"image size and focal lengths must be positive (got {width}x{height}, f={fx},{fy})")
    n = c2w.shape[0]
    return Cameras(
        camera_to_worlds=c2w,
        fx=torch.full((n, 1), float(fx)),
        fy=torch.full((n, 1), float(fy)),
        cx=torch.full((n, 1), float(cx)),
        cy=torch.full((n, 1), float(cy)),
        width=torch.full((n, 1), int(width), dtype=torch.long),
        height=torch.full((n, 1), int(height), dtype=torch.long),
        camera_type=CameraType.PERSPECTIVE,
    )


@torch.no_grad()
def render_views(
    model: Model,
    cameras: Cameras,
    outputs: tuple[str, ...] = ("rgb", "depth", "accumulation"),
    progress: bool = True,
    description: str = "rendering",
) -> dict[str, Float[Tensor, "num_cams height width channels"]]:
    """Render every camera through ``model.get_outputs_for_camera`` (chunked by the run's eval chunk size).

    Returns a dict of CPU tensors ``[N, H, W, C]`` for each requested output the model produces.
    """
    cameras = cameras.to(model.device)
    frames: dict[str, list[Tensor]] = {k: [] for k in outputs}
    columns = (TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, disable=not progress, transient=True) as bar:
        task = bar.add_task(description, total=len(cameras))
        for i in range(len(cameras)):
            out = model.get_outputs_for_camera(cameras[i : i + 1])
            for key in outputs:
                if key not in out:
                    raise KeyError(f"the model renders no '{key}' (it renders {sorted(out)})")
                frames[key].append(out[key].detach().cpu())
            bar.advance(task)
    return {k: torch.stack(v) for k, v in frames.items()}
