"""The fusion spec (which runs to fuse, and how they are registered) and the datamanager of the ``nerfuser`` method.

Fusion spec
-----------
``ns-train nerfuser --data <spec>`` takes a JSON file (or a folder holding ``fusion.json``)::

    {
      "runs": ["runs/a/nerfacto-cpu/run/config.yml", {"name": "b", "config": "runs/b/nerfacto-cpu/run/config.yml"}],
      "registration": "registration.json",
      "test_data": "scene/test",
      "test_to_common": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    }

* ``runs``: the trained runs' ``config.yml`` (or run folders); optional when the registration file names them.
* ``registration``: the registration file (default ``registration.json`` beside the spec). When it does not exist the
  registration is run (``ns-nerfuser-register``) and written there, so a later ``ns-render``/``ns-eval`` of the fused
  run finds it. With a single run and no registration file, the common frame is that run's frame.
* ``test_data`` (optional): a nerfstudio dataset (transforms.json + images) whose poses are in the frame given by
  ``test_to_common`` (a 4x4 SIM(3) into the common frame, default identity). ``ns-eval`` scores the blended renders
  against its images. Its poses are used as stored: no re-centring, re-orientation or re-scaling (and its
  ``applied_transform`` / ``applied_scale``, which describe how the stored poses were made, are not applied again).

Relative paths are relative to the spec file's folder. ``--data`` may also point at a registration file directly
(then its runs are fused, without test images).

Registration file
-----------------
All reading of it goes through :func:`read_registration`. It reads what ``ns-nerfuser-register``
(:mod:`nerfuser_ns.registration`) writes (``kind: nerfuser_registration``; per NeRF ``name``, ``config``,
``T_to_reference``), and a minimal hand-written form::

    {"nerfs": [{"name": "a", "config": "path/to/config.yml", "transform": <4x4 list>}, ...]}

``T_to_reference`` / ``transform`` maps points of that NeRF's frame (the normalised frame nerfstudio trained it in)
into the common frame: ``p_common = T @ [p_nerf, 1]``, ``T = [[s R, t], [0, 0, 0, 1]]`` (the reference NeRF's frame,
the first by default, so its transform is the identity). Relative ``config`` paths are relative to the registration
file's folder.
"""

from __future__ import annotations

import copy
import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.datamanagers.base_datamanager import DataManager, VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader, RandIndicesEvalDataloader
from nerfstudio.engine.trainer import TrainerConfig
from torch.nn import Parameter

from nerfuser_ns.model import BlendSettings, NerfuserModelConfig
from nerfuser_ns.registration import RegistrationConfig
from nerfuser_ns.runs import applied_transform, checkpoint_identity, default_device, stored_to_nerf

SPEC_FILENAME = "fusion.json"
"""Name of the spec file looked up when ``--data`` is a folder."""
REGISTRATION_FILENAME = "registration.json"
"""Default name of the registration file, beside the spec."""
METADATA_KEY = "nerfuser"
"""Key of the :class:`FusionSpec` in the train dataset's metadata (how the pipeline hands it to the model)."""

_SIM3_TOL = 1e-4


class FusionSpecError(ValueError):
    """The fusion spec or registration file cannot be used; the message (one line) names the file and the fix."""


@dataclass(frozen=True)
class NerfEntry:
    """One NeRF of the fusion: its run and its place in the common frame."""

    name: str
    """Unique name (share maps and logs use it)."""
    config_path: Path
    """The run's config.yml (absolute)."""
    nerf_to_common: Float[np.ndarray, "4 4"] = field(compare=False)
    """SIM(3) ``T`` with ``p_common = T @ [p_nerf, 1]`` (float64)."""

    @property
    def scale(self) -> float:
        """``s`` of ``T``: a length L in NeRF units is ``s * L`` in common units."""
        return float(np.cbrt(np.linalg.det(self.nerf_to_common[:3, :3])))

    @property
    def origin(self) -> Float[np.ndarray, "3"]:
        """The NeRF's origin in the common frame."""
        return self.nerf_to_common[:3, 3].copy()


@dataclass
class FusionSpec:
    """A validated fusion spec: the NeRFs, their registration, and the optional test images."""

    nerfs: list[NerfEntry]
    registration_path: Path | None
    """Where the registration was read from (None: single run, identity)."""
    spec_path: Path | None = None
    """The spec file (None when built in code or when ``--data`` was the registration file)."""
    test_data: Path | None = None
    """Optional nerfstudio dataset of test images."""
    test_to_common: Float[np.ndarray, "4 4"] = field(default_factory=lambda: np.eye(4))
    """SIM(3) from the test dataset's frame into the common frame."""

    @property
    def transforms(self) -> Float[np.ndarray, "n 4 4"]:
        return np.stack([n.nerf_to_common for n in self.nerfs])

    @property
    def origins(self) -> Float[np.ndarray, "n 3"]:
        return np.stack([n.origin for n in self.nerfs])


# ----------------------------------------------------------------------------------------------------------------------
# Validation helpers


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _err(where: Path | str | None, message: str) -> FusionSpecError:
    prefix = f"{where}: " if where is not None else ""
    return FusionSpecError(_one_line(prefix + message))


def validate_sim3(value: Any, where: str) -> Float[np.ndarray, "4 4"]:
    """A 4x4 (or 3x4, completed) finite SIM(3) ``[[s R, t], [0, 1]]`` with ``s > 0`` and ``det R = +1``."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FusionSpecError(_one_line(f"{where}: not a numeric 4x4 matrix")) from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise FusionSpecError(_one_line(f"{where}: expected a 4x4 (or 3x4) matrix, got shape {T.shape}"))
    if not np.isfinite(T).all():
        raise FusionSpecError(_one_line(f"{where}: has non-finite values"))
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise FusionSpecError(_one_line(f"{where}: last row must be [0, 0, 0, 1], got {T[3].tolist()}"))
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if not det > 0:
        raise FusionSpecError(_one_line(f"{where}: not a similarity (det of the 3x3 block is {det:.3g}, must be > 0)"))
    s = det ** (1.0 / 3.0)
    R = A / s
    if not np.allclose(R.T @ R, np.eye(3), atol=_SIM3_TOL):
        raise FusionSpecError(_one_line(f"{where}: the 3x3 block is not a scaled rotation (s R with R orthonormal)"))
    return T


def _resolve(base: Path, value: Any, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise FusionSpecError(_one_line(f"{where}: expected a path string, got {value!r}"))
    p = Path(value).expanduser()
    return (p if p.is_absolute() else base / p).absolute()


def _check_run(config_path: Path, where: str) -> Path:
    """The run's config.yml (given it or its folder), checked to exist, parse and have a checkpoint."""
    from nerfuser_ns.runs import RunLoadError, read_config, resolve_config_path

    try:
        config_path = resolve_config_path(config_path)
        config = read_config(config_path)
    except RunLoadError as e:
        raise FusionSpecError(_one_line(f"{where}: {e}")) from None
    ckpt_dir = config_path.parent / config.relative_model_dir
    if not (ckpt_dir.is_dir() and any(ckpt_dir.glob("step-*.ckpt"))):
        raise FusionSpecError(_one_line(f"{where}: {config_path} has no checkpoint in {ckpt_dir}"))
    return config_path.absolute()


def _read_json(path: Path, what: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FusionSpecError(_one_line(f"{path}: no such {what} file")) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FusionSpecError(_one_line(f"{path}: not a readable JSON {what} file ({e})")) from None
    if not isinstance(data, dict):
        raise FusionSpecError(_one_line(f"{path}: expected a JSON object at the top level"))
    return data


def _check_same_weights(config_path: Path, registered: Any, registration_path: Path) -> None:
    """The run still renders with the checkpoint it was registered with (step and content)."""
    now = checkpoint_identity(config_path)
    if not isinstance(registered, dict) or (registered.get("step"), registered.get("sha256")) != (
        now["step"], now["sha256"]
    ):
        step = registered.get("step") if isinstance(registered, dict) else None
        raise FusionSpecError(
            _one_line(
                f"{registration_path}: {config_path} changed since it was registered (registered step {step}, "
                f"now step {now['step']}, {now['file']}: other weights); re-run ns-nerfuser-register on the runs "
                f"(or delete {registration_path.name} and ns-train nerfuser registers them again)"
            )
        )


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.samefile(b)
    except OSError:
        return a.absolute() == b.absolute()


# ----------------------------------------------------------------------------------------------------------------------
# Registration file


def read_registration(path: Path | str, check_runs: bool = True) -> list[NerfEntry]:
    """Every NeRF of a registration file: name, config.yml and its SIM(3) into the common frame.

    The ONE place that knows the registration file's format: ``ns-nerfuser-register``'s record
    (``kind: nerfuser_registration``; per NeRF ``name``, ``config``, ``T_to_reference``) or the minimal
    ``{"nerfs": [{name, config, transform}]}`` (see the module docstring).

    Args:
        path: the registration file.
        check_runs: also check that every run exists and has a checkpoint.

    Raises:
        FusionSpecError: unreadable file, missing keys, bad transform (shape, non-finite, not a SIM(3)), missing run
            or duplicate names; one line naming the file and the entry.
    """
    path = Path(path).absolute()
    data = _read_json(path, "registration")
    if data.get("kind", "nerfuser_registration") != "nerfuser_registration":
        raise _err(path, f"not a registration file (kind {data.get('kind')!r})")
    nerfs = data.get("nerfs")
    if not isinstance(nerfs, list) or not nerfs:
        raise _err(path, "expected a non-empty list 'nerfs' of {name, config, transform}")
    entries: list[NerfEntry] = []
    for i, item in enumerate(nerfs):
        where = f"{path}: nerfs[{i}]"
        if not isinstance(item, dict):
            raise FusionSpecError(_one_line(f"{where}: expected an object with name, config, transform"))
        key = "T_to_reference" if "T_to_reference" in item else "transform"
        missing = [k for k in ("config", key) if k not in item]
        if missing:
            raise FusionSpecError(_one_line(f"{where}: missing {', '.join(missing)}"))
        if item["config"] is None:
            raise FusionSpecError(_one_line(f"{where}: registers no nerfstudio run (config is null); cannot fuse it"))
        config_path = _resolve(path.parent, item["config"], f"{where}.config")
        if check_runs:
            config_path = _check_run(config_path, f"{where}.config")
            if item.get("checkpoint") is not None:
                _check_same_weights(config_path, item["checkpoint"], path)
        T = validate_sim3(item[key], f"{where}.{key}")
        name = item.get("name") or f"nerf{i}"
        entries.append(NerfEntry(name=str(name), config_path=config_path, nerf_to_common=T))
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise _err(path, f"duplicate NeRF names {sorted({n for n in names if names.count(n) > 1})}")
    return entries


def write_registration(path: Path | str, nerfs: list[NerfEntry]) -> Path:
    """Writes a registration file in the format :func:`read_registration` reads (config paths stay absolute)."""
    path = Path(path)
    data = {
        "nerfs": [
            {"name": n.name, "config": str(n.config_path), "transform": np.asarray(n.nerf_to_common).tolist()}
            for n in nerfs
        ]
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)
    return path


def run_registration(
    config_paths: list[Path], names: list[str], output: Path, config: RegistrationConfig | None = None
) -> list[NerfEntry]:
    """Registers the runs (NeRFuser Sec. 3.2, ``nerfuser_ns.registration`` with ``config``, default settings when
    None), writes the registration file at ``output`` (its renders and SfM files in ``<output stem>_work/``) and
    reads it back. ``ns-train nerfuser`` passes ``--pipeline.datamanager.registration.*`` here.
    """
    from nerfuser_ns import registration
    from nerfuser_ns.runs import RunLoadError

    try:
        registration.register_runs(config_paths, output, config=config, names=names, device=default_device())
    except (registration.RegistrationError, RunLoadError) as e:
        raise FusionSpecError(
            _one_line(f"{output}: automatic registration failed: {e} (run ns-nerfuser-register with other settings)")
        ) from None
    return read_registration(output)


# ----------------------------------------------------------------------------------------------------------------------
# Fusion spec


def read_fusion_spec(
    path: Path | str, register: bool = True, registration_config: RegistrationConfig | None = None
) -> FusionSpec:
    """Reads and validates a fusion spec (or a registration file used as one); see the module docstring.

    Nothing is written, except the registration file when it is absent and ``register`` is True (and only after
    the spec itself validated); ``registration_config`` holds that registration's settings.

    Raises:
        FusionSpecError: with a one-line message naming the file and what to fix.
    """
    if path is None:
        raise FusionSpecError("no fusion spec: pass --data <fusion.json> (see nerfuser_ns.data)")
    path = Path(path).expanduser().absolute()
    if path.is_dir():
        if (path / SPEC_FILENAME).is_file():
            path = path / SPEC_FILENAME
        elif (path / REGISTRATION_FILENAME).is_file():
            path = path / REGISTRATION_FILENAME
        else:
            raise _err(path, f"folder without {SPEC_FILENAME} or {REGISTRATION_FILENAME}; pass the fusion spec file")
    data = _read_json(path, "fusion spec")
    if "nerfs" in data and "runs" not in data:  # --data is a registration file
        return FusionSpec(nerfs=read_registration(path), registration_path=path, spec_path=None)

    known = {"runs", "registration", "test_data", "test_to_common"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise _err(path, f"unknown keys {unknown}; expected some of {sorted(known)}")
    base = path.parent

    runs_value = data.get("runs")
    spec_runs: list[tuple[str | None, Path]] | None = None
    if runs_value is not None:
        if not isinstance(runs_value, list) or not runs_value:
            raise _err(path, "'runs' must be a non-empty list of config.yml paths or {name, config} objects")
        spec_runs = []
        for i, item in enumerate(runs_value):
            where = f"{path}: runs[{i}]"
            if isinstance(item, dict):
                if "config" not in item:
                    raise FusionSpecError(_one_line(f"{where}: missing 'config'"))
                name, value = item.get("name"), item["config"]
            else:
                name, value = None, item
            spec_runs.append((None if name is None else str(name), _check_run(_resolve(base, value, where), where)))

    registration_path = _resolve(base, data.get("registration", REGISTRATION_FILENAME), f"{path}: registration")

    test_data = None
    if data.get("test_data") is not None:
        test_data = _resolve(base, data["test_data"], f"{path}: test_data")
        if not (test_data / "transforms.json").is_file():
            raise _err(path, f"test_data {test_data} is not a nerfstudio dataset (no transforms.json)")
    test_to_common = np.eye(4)
    if data.get("test_to_common") is not None:
        test_to_common = validate_sim3(data["test_to_common"], f"{path}: test_to_common")

    if registration_path.is_file():
        nerfs = read_registration(registration_path)
        if spec_runs is not None:
            nerfs = _match_runs(spec_runs, nerfs, path, registration_path)
    elif spec_runs is None:
        raise _err(path, f"no 'runs' and no registration file at {registration_path}")
    elif len(spec_runs) == 1:
        # One NeRF: the common frame is its own.
        name, config_path = spec_runs[0]
        nerfs = [NerfEntry(name or "nerf0", config_path, np.eye(4))]
        registration_path = None
    elif register:
        names = _default_names(spec_runs)
        nerfs = run_registration([c for _, c in spec_runs], names, registration_path, registration_config)
    else:
        raise _err(path, f"no registration file at {registration_path}; run ns-nerfuser-register first")
    return FusionSpec(
        nerfs=nerfs,
        registration_path=registration_path,
        spec_path=path,
        test_data=test_data,
        test_to_common=test_to_common,
    )


def _default_names(spec_runs: list[tuple[str | None, Path]]) -> list[str]:
    names = [name or f"nerf{i}" for i, (name, _) in enumerate(spec_runs)]
    if len(set(names)) != len(names):
        raise FusionSpecError(_one_line(f"duplicate run names {names}"))
    return names


def _match_runs(
    spec_runs: list[tuple[str | None, Path]], nerfs: list[NerfEntry], spec_path: Path, registration_path: Path
) -> list[NerfEntry]:
    """The registration's entries for the spec's runs, in the spec's order; an error if the sets differ."""
    out: list[NerfEntry] = []
    used: set[int] = set()
    for name, config_path in spec_runs:
        match = [j for j, n in enumerate(nerfs) if j not in used and _same_file(n.config_path, config_path)]
        if not match:
            raise FusionSpecError(
                _one_line(
                    f"{spec_path}: run {config_path} is not in the registration {registration_path} (it registers "
                    f"{[str(n.config_path) for n in nerfs]}); re-run ns-nerfuser-register on these runs"
                )
            )
        used.add(match[0])
        entry = nerfs[match[0]]
        out.append(NerfEntry(name or entry.name, entry.config_path, entry.nerf_to_common))
    extra = [str(nerfs[j].config_path) for j in range(len(nerfs)) if j not in used]
    if extra:
        raise FusionSpecError(
            _one_line(
                f"{spec_path}: the registration {registration_path} also registers runs the spec does not list: "
                f"{extra}; list them under 'runs' or re-run ns-nerfuser-register"
            )
        )
    names = [n.name for n in out]
    if len(set(names)) != len(names):
        raise _err(spec_path, f"duplicate NeRF names {names}")
    return out


def write_fusion_spec(
    path: Path | str,
    runs: list[Path | str],
    registration: Path | str | None = None,
    test_data: Path | str | None = None,
    test_to_common: np.ndarray | None = None,
    names: list[str] | None = None,
) -> Path:
    """Writes a fusion spec JSON (paths stored as given)."""
    path = Path(path)
    if names is not None:
        runs_value: list[Any] = [{"name": n, "config": str(r)} for n, r in zip(names, runs, strict=True)]
    else:
        runs_value = [str(r) for r in runs]
    data: dict[str, Any] = {"runs": runs_value}
    if registration is not None:
        data["registration"] = str(registration)
    if test_data is not None:
        data["test_data"] = str(test_data)
    if test_to_common is not None:
        data["test_to_common"] = np.asarray(test_to_common, dtype=np.float64).tolist()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    return path


# ----------------------------------------------------------------------------------------------------------------------
# Datasets


def fused_scene_box(spec: FusionSpec) -> SceneBox:
    """Axis-aligned box of the common frame holding every NeRF's [-1, 1]^3 cube (for the viewer)."""
    corners = np.array(np.meshgrid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0], indexing="ij")).reshape(3, -1).T
    pts = np.concatenate([corners @ n.nerf_to_common[:3, :3].T + n.nerf_to_common[:3, 3] for n in spec.nerfs])
    return SceneBox(aabb=torch.tensor(np.stack([pts.min(0), pts.max(0)]), dtype=torch.float32))


def _transform_cameras(cameras: Cameras, T: np.ndarray) -> Cameras:
    from nerfuser_ns.sim3 import transform_poses

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
    """The test images with their poses in the common frame (stored poses, mapped by ``test_to_common``)."""
    assert spec.test_data is not None
    parser_config = copy.deepcopy(parser_config) if parser_config is not None else test_parser_config()
    parser_config.data = spec.test_data
    try:
        parsed = parser_config.setup().get_dataparser_outputs(split="test")
    except Exception as e:  # noqa: BLE001 - any parsing failure is the dataset's fault
        raise _err(spec.test_data, f"unreadable test dataset ({type(e).__name__}: {e})") from None
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


def render_cameras_dataparser_outputs(spec: FusionSpec, metadata: dict) -> DataparserOutputs | None:
    """Cameras to render a fused run from when its spec has no test images (``ns-render spiral``/``interpolate``/
    ``dataset``, the viewer's camera frustums): the training cameras of the first NeRF whose dataset is still
    readable (the reference NeRF's, normally), mapped into the common frame, without images (named
    ``<nerf name>/train_00000`` ...). None when no NeRF's dataset is readable."""
    from nerfuser_ns.runs import RunLoadError, training_cameras

    for entry in spec.nerfs:
        try:
            cameras = training_cameras(entry.config_path)
        except RunLoadError:
            continue
        return DataparserOutputs(
            image_filenames=[Path(f"<{entry.name}>") / f"train_{i:05d}" for i in range(len(cameras))],
            cameras=_transform_cameras(cameras, entry.nerf_to_common),
            scene_box=fused_scene_box(spec),
            metadata=metadata,
            dataparser_transform=torch.eye(4)[:3],
            dataparser_scale=1.0,
        )
    return None


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
    spec has them (``ns-eval`` scores them), else the training cameras of the first NeRF whose dataset is readable
    (:func:`render_cameras_dataparser_outputs`, without images, so ``ns-eval`` refuses them), both as train and eval
    dataset; without either, placeholder cameras at the NeRF origins (for the viewer only) and no eval dataset.

    A :class:`VanillaDataManager` only because ``ns-render spiral`` asserts one; none of its set-up runs (its
    ``__init__`` parses a dataset and builds ray samplers).
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
        metadata = {METADATA_KEY: self.spec}
        if self.spec.test_data is not None:
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
            _one_line(
                f"nerfuser: {self.spec.spec_path or self.config.data}: no cameras to render a spiral or an "
                "interpolation from (the fusion spec has no test images and no dataset of the fused runs is readable); "
                "render a camera path made in the viewer's Render tab (ns-render camera-path), or add 'test_data' to "
                "the spec and render its views (ns-render dataset --split test)"
            )
        )

    @functools.cached_property
    def fixed_indices_eval_dataloader(self) -> FixedIndicesEvalDataloader:
        """All test images in order (``ns-eval``). A cached property: nerfstudio's viewer reads every plain attribute
        and property of the pipeline but skips cached ones, so a spec without test images still opens in it."""
        if self.spec.test_data is None:
            raise RuntimeError(
                f"{self.spec.spec_path or self.config.data}: the fusion spec has no test images; add 'test_data' "
                "(a nerfstudio dataset posed in the common frame) to evaluate"
            )
        if not hasattr(self, "_fixed_indices_eval_dataloader"):
            self.setup_eval()
        return self._fixed_indices_eval_dataloader

    def next_train(self, step: int) -> tuple[Cameras, dict]:
        raise RuntimeError(
            "nerfuser has nothing to train (the sub-models are frozen): run ns-train nerfuser with "
            "--max-num-iterations 0 (its default)"
        )

    def next_eval(self, step: int) -> tuple[Cameras, dict]:
        return self.next_eval_image(step)

    def next_eval_image(self, step: int) -> tuple[Cameras, dict]:
        if self.spec.test_data is None:
            raise RuntimeError("the fusion spec has no test images")
        if "eval_dataloader" not in self.__dict__:  # not hasattr: the class attribute would raise
            self.setup_eval()
        for camera, batch in self.eval_dataloader:
            return camera, batch
        raise ValueError("no more eval images")

    def get_train_rays_per_batch(self) -> int:
        return 1

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
        try:
            if isinstance(self.pipeline.model, NerfuserModelConfig):
                BlendSettings.from_config(self.pipeline.model)  # bad gamma / tau / NERFUSER_* values
            # The whole spec, and the registration when it is missing (minutes, announced by the registration
            # itself): a failure leaves no run folder behind.
            read_fusion_spec(data, register=getattr(datamanager, "register_if_missing", True),
                             registration_config=getattr(datamanager, "registration", None))  # fmt: skip
        except (FusionSpecError, ValueError) as e:
            raise SystemExit(f"nerfuser: {_one_line(str(e)).removeprefix('nerfuser: ')}") from None
        data = Path(data).absolute()
        self.pipeline.datamanager.data = data
        if hasattr(self.pipeline.model, "fusion_spec"):
            self.pipeline.model.fusion_spec = data  # so the model alone (runs.load_run) finds its sub-models
        super().save_config()


__all__ = [
    "FusionSpec",
    "FusionSpecError",
    "NerfEntry",
    "NerfuserDataManager",
    "NerfuserDataManagerConfig",
    "NerfuserTrainerConfig",
    "read_fusion_spec",
    "read_registration",
    "run_registration",
    "validate_sim3",
    "write_fusion_spec",
    "write_registration",
]
