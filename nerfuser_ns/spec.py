"""The fusion spec (which runs to fuse, and how they are registered) and the registration file's fused view.

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
* ``test_run`` (optional, instead of ``test_data``): the name (or index in ``runs``) of a run whose held-out images are
  the test images: the images its dataparser kept out of training (nerfstudio's eval split, by default 10% of the
  capture, evenly spread), posed as that run's dataparser poses them (as nerfstudio's own ``ns-eval`` of the run does)
  and mapped into the common frame by its registered transform. No matrix to write: ``"test_run": 0`` scores the blend
  on the first run's held-out views. Needs that run's dataset where its config.yml records it.

Relative paths are relative to the spec file's folder. ``--data`` may also point at a registration file directly
(then its runs are fused, without test images).

Registration file
-----------------
All reading of it goes through :func:`read_registered_nerfs`, which parses it with
:mod:`nerfuser_ns.registration.record` (the one owner of the file's format) and checks the runs and transforms. It
reads what ``ns-nerfuser-register`` (:mod:`nerfuser_ns.registration`) writes (``kind: nerfuser_registration``; per
NeRF ``name``, ``config``, ``T_to_reference``), and a minimal hand-written form
(:func:`~nerfuser_ns.registration.record.write_minimal_registration`)::

    {"nerfs": [{"name": "a", "config": "path/to/config.yml", "transform": <4x4 list>}, ...]}

``T_to_reference`` / ``transform`` maps points of that NeRF's frame (the normalised frame nerfstudio trained it in)
into the common frame: ``p_common = T @ [p_nerf, 1]``, ``T = [[s R, t], [0, 0, 0, 1]]`` (the reference NeRF's frame,
the first by default, so its transform is the identity). Relative ``config`` paths are relative to the registration
file's folder. Optional per NeRF (both forms): ``training_cameras`` (its training cameras in its own frame, for the
``coverage`` blend method) and ``colour_to_reference`` (its colour map for appearance matching); absent means unknown
(``coverage`` falls back to IDW-Sample) and the identity.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float
from rich.console import Console
from rich.markup import escape

from nerfuser_ns import registration
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig
from nerfuser_ns.registration.record import NerfEntry, RegistrationFileError, iter_registered_nerfs
from nerfuser_ns.runs import RunLoadError, checkpoint_identity, default_device, read_config, resolve_config_path

SPEC_FILENAME = "fusion.json"
"""Name of the spec file looked up when ``--data`` is a folder."""
REGISTRATION_FILENAME = "registration.json"
"""Default name of the registration file, beside the spec."""
METADATA_KEY = "nerfuser"
"""Key of the :class:`FusionSpec` in the train dataset's metadata (how the pipeline hands it to the model)."""

_SIM3_TOL = 1e-4
CONSOLE = Console(width=120)


class FusionSpecError(ValueError):
    """The fusion spec or registration file cannot be used; the message (one line) names the file and the fix."""


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
    test_run: int | None = None
    """Index in ``nerfs`` of the run whose held-out images are the test images (instead of ``test_data``)."""

    @property
    def has_test_images(self) -> bool:
        return self.test_data is not None or self.test_run is not None

    @property
    def transforms(self) -> Float[np.ndarray, "n 4 4"]:
        return np.stack([n.nerf_to_common for n in self.nerfs])

    @property
    def origins(self) -> Float[np.ndarray, "n 3"]:
        return np.stack([n.origin for n in self.nerfs])

    def capture_warnings(self) -> list[str]:
        """One line per NeRF whose capture the registration's checks flagged (folded by COLMAP, or a drifted camera):
        the run was trained on those poses, so the fused scene inherits them; said each time a fused run is loaded,
        since a warning printed once at the start of a long registration scrolls away."""
        return [f"NeRF {n.name}'s capture: {'; '.join(n.capture_findings)}, as the registration's checks found. The "
                "run was trained on those poses and the fusion inherits them: check its dataset with "
                "ns-nerfuser-check-capture, fix it as it advises and train again (docs/your_own_captures.md)"
                for n in self.nerfs if n.capture_findings]  # fmt: skip


# ----------------------------------------------------------------------------------------------------------------------
# Validation helpers


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def spec_error(where: Path | str | None, message: str) -> FusionSpecError:
    prefix = f"{where}: " if where is not None else ""
    return FusionSpecError(one_line(prefix + message))


__all__ = [
    "FusionSpec",
    "FusionSpecError",
    "NerfEntry",
    "read_fusion_spec",
    "read_registered_nerfs",
    "run_registration",
    "validate_sim3",
    "write_fusion_spec",
]


def validate_sim3(value: Any, where: str) -> Float[np.ndarray, "4 4"]:
    """A 4x4 (or 3x4, completed) finite SIM(3) ``[[s R, t], [0, 1]]`` with ``s > 0`` and ``det R = +1``."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FusionSpecError(one_line(f"{where}: not a numeric 4x4 matrix")) from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise FusionSpecError(one_line(f"{where}: expected a 4x4 (or 3x4) matrix, got shape {T.shape}"))
    if not np.isfinite(T).all():
        raise FusionSpecError(one_line(f"{where}: has non-finite values"))
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise FusionSpecError(one_line(f"{where}: last row must be [0, 0, 0, 1], got {T[3].tolist()}"))
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if not det > 0:
        raise FusionSpecError(one_line(f"{where}: not a similarity (det of the 3x3 block is {det:.3g}, must be > 0)"))
    s = det ** (1.0 / 3.0)
    R = A / s
    if not np.allclose(R.T @ R, np.eye(3), atol=_SIM3_TOL):
        raise FusionSpecError(one_line(f"{where}: the 3x3 block is not a scaled rotation (s R with R orthonormal)"))
    return T


def _resolve(base: Path, value: Any, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise FusionSpecError(one_line(f"{where}: expected a path string, got {value!r}"))
    p = Path(value).expanduser()
    return (p if p.is_absolute() else base / p).absolute()


def _check_run(config_path: Path, where: str) -> Path:
    """The run's config.yml (given it or its folder), checked to exist, parse and have a checkpoint."""
    try:
        config_path = resolve_config_path(config_path)
        config = read_config(config_path)
    except RunLoadError as e:
        raise FusionSpecError(one_line(f"{where}: {e}")) from None
    ckpt_dir = config_path.parent / config.relative_model_dir
    if not (ckpt_dir.is_dir() and any(ckpt_dir.glob("step-*.ckpt"))):
        raise FusionSpecError(one_line(f"{where}: {config_path} has no checkpoint in {ckpt_dir}"))
    return config_path.absolute()


def _read_json(path: Path, what: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FusionSpecError(one_line(f"{path}: no such {what} file")) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FusionSpecError(one_line(f"{path}: not a readable JSON {what} file ({e})")) from None
    if not isinstance(data, dict):
        raise FusionSpecError(one_line(f"{path}: expected a JSON object at the top level"))
    return data


def _check_same_weights(config_path: Path, registered: Any, registration_path: Path) -> None:
    """The run still renders with the checkpoint it was registered with (step and content)."""
    now = checkpoint_identity(config_path)
    if not isinstance(registered, dict) or (registered.get("step"), registered.get("sha256")) != (
        now["step"], now["sha256"]
    ):
        step = registered.get("step") if isinstance(registered, dict) else None
        raise FusionSpecError(
            one_line(
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


def read_registered_nerfs(path: Path | str, check_runs: bool = True) -> list[NerfEntry]:
    """Every NeRF of a registration file: name, config.yml and its SIM(3) into the common frame.

    The file is parsed by :func:`nerfuser_ns.registration.record.iter_registered_nerfs` (``ns-nerfuser-register``'s
    record or the minimal ``{"nerfs": [{name, config, transform}]}``, see the module docstring); here each entry's
    run and transform are checked for fusion.

    Args:
        path: the registration file.
        check_runs: also check that every run exists and has a checkpoint.

    Raises:
        FusionSpecError: unreadable file, missing keys, bad transform (shape, non-finite, not a SIM(3)), missing run
            or duplicate names; one line naming the file and the entry.
    """
    path = Path(path).absolute()
    entries: list[NerfEntry] = []
    try:
        for item in iter_registered_nerfs(path):  # entry by entry: an entry's errors come before the next one's
            where = f"{path}: nerfs[{item.index}]"
            if item.config is None:
                raise FusionSpecError(
                    one_line(f"{where}: registers no nerfstudio run (config is null); cannot fuse it")
                )
            config_path = _resolve(path.parent, item.config, f"{where}.config")
            if check_runs:
                config_path = _check_run(config_path, f"{where}.config")
                if item.checkpoint is not None:
                    _check_same_weights(config_path, item.checkpoint, path)
            T = validate_sim3(item.transform, f"{where}.{item.transform_key}")
            name = item.name or f"nerf{item.index}"
            entries.append(NerfEntry(name=str(name), config_path=config_path, nerf_to_common=T,
                                     training_cameras=item.training_cameras,
                                     colour_to_reference=item.colour_to_reference,
                                     capture_findings=item.capture_findings))  # fmt: skip
    except RegistrationFileError as e:
        raise FusionSpecError(one_line(str(e))) from None
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise spec_error(path, f"duplicate NeRF names {sorted({n for n in names if names.count(n) > 1})}")
    return entries


def run_registration(
    config_paths: list[Path], names: list[str], output: Path, config: RegistrationConfig | None = None
) -> list[NerfEntry]:
    """Registers the runs (NeRFuser Sec. 3.2, ``nerfuser_ns.registration`` with ``config``, default settings when
    None), writes the registration file at ``output`` (its renders and SfM files in ``<output stem>_work/``) and
    reads it back. ``ns-train nerfuser`` passes ``--pipeline.datamanager.registration.*`` here. Says what it runs,
    with which settings, before it starts: it renders every run (minutes).
    """
    config = config or RegistrationConfig()
    device = default_device()
    sc = config.sampling
    camera = "the reference run's camera" if sc.width is None else f"{sc.width}x{sc.height} at {sc.fov_deg} deg"
    CONSOLE.print(
        f"[bold]nerfuser:[/] no registration file at {escape(str(output))}: registering {len(config_paths)} runs now "
        f"(pose source {sc.source}, renders {camera}, {sc.size} px, estimator {config.estimator}, "
        f"refine {config.refine}, device {device}; change with --pipeline.datamanager.registration.*, or run "
        "ns-nerfuser-register yourself)"
    )
    try:
        registration.register_runs(config_paths, output, config=config, names=names, device=device)
    except (registration.RegistrationError, RunLoadError) as e:
        raise FusionSpecError(
            one_line(f"{output}: automatic registration failed: {e} (run ns-nerfuser-register with other settings)")
        ) from None
    return read_registered_nerfs(output)


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
            raise spec_error(
                path, f"folder without {SPEC_FILENAME} or {REGISTRATION_FILENAME}; pass the fusion spec file"
            )
    data = _read_json(path, "fusion spec")
    if "nerfs" in data and "runs" not in data:  # --data is a registration file
        return FusionSpec(nerfs=read_registered_nerfs(path), registration_path=path, spec_path=None)

    known = {"runs", "registration", "test_data", "test_to_common", "test_run"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise spec_error(path, f"unknown keys {unknown}; expected some of {sorted(known)}")
    base = path.parent

    runs_value = data.get("runs")
    spec_runs: list[tuple[str | None, Path]] | None = None
    if runs_value is not None:
        if not isinstance(runs_value, list) or not runs_value:
            raise spec_error(path, "'runs' must be a non-empty list of config.yml paths or {name, config} objects")
        spec_runs = []
        for i, item in enumerate(runs_value):
            where = f"{path}: runs[{i}]"
            if isinstance(item, dict):
                if "config" not in item:
                    raise FusionSpecError(one_line(f"{where}: missing 'config'"))
                name, value = item.get("name"), item["config"]
            else:
                name, value = None, item
            spec_runs.append((None if name is None else str(name), _check_run(_resolve(base, value, where), where)))

    registration_path = _resolve(base, data.get("registration", REGISTRATION_FILENAME), f"{path}: registration")

    test_data = None
    if data.get("test_data") is not None:
        test_data = _resolve(base, data["test_data"], f"{path}: test_data")
        if not (test_data / "transforms.json").is_file():
            raise spec_error(path, f"test_data {test_data} is not a nerfstudio dataset (no transforms.json)")
    test_to_common = np.eye(4)
    if data.get("test_to_common") is not None:
        test_to_common = validate_sim3(data["test_to_common"], f"{path}: test_to_common")
    if data.get("test_run") is not None and (test_data is not None or data.get("test_to_common") is not None):
        raise spec_error(path, "test_run names the test images itself; drop test_data / test_to_common or test_run")

    if registration_path.is_file():
        nerfs = read_registered_nerfs(registration_path)
        if spec_runs is not None:
            nerfs = _match_runs(spec_runs, nerfs, path, registration_path)
    elif spec_runs is None:
        raise spec_error(path, f"no 'runs' and no registration file at {registration_path}")
    elif len(spec_runs) == 1:
        # One NeRF: the common frame is its own.
        name, config_path = spec_runs[0]
        nerfs = [NerfEntry(name or "nerf0", config_path, np.eye(4))]
        registration_path = None
    elif register:
        names = _default_names(spec_runs)
        nerfs = run_registration([c for _, c in spec_runs], names, registration_path, registration_config)
    else:
        raise spec_error(path, f"no registration file at {registration_path}; run ns-nerfuser-register first")
    return FusionSpec(
        nerfs=nerfs,
        registration_path=registration_path,
        spec_path=path,
        test_data=test_data,
        test_to_common=test_to_common,
        test_run=_test_run_index(data.get("test_run"), nerfs, path),
    )


def _test_run_index(value: Any, nerfs: list[NerfEntry], path: Path) -> int | None:
    """``test_run`` (a run's name, or its index in ``runs``) as an index in ``nerfs``."""
    if value is None:
        return None
    names = [n.name for n in nerfs]
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise spec_error(path, f"test_run must be a run's name (one of {names}) or its index, not {value!r}")
    if isinstance(value, int):
        if not 0 <= value < len(nerfs):
            raise spec_error(path, f"test_run {value} is not an index of the {len(nerfs)} runs {names}")
        return value
    if value not in names:
        raise spec_error(path, f"test_run {value!r} names no run; the runs are {names}")
    return names.index(value)


def _default_names(spec_runs: list[tuple[str | None, Path]]) -> list[str]:
    names = [name or f"nerf{i}" for i, (name, _) in enumerate(spec_runs)]
    if len(set(names)) != len(names):
        raise FusionSpecError(one_line(f"duplicate run names {names}"))
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
                one_line(
                    f"{spec_path}: run {config_path} is not in the registration {registration_path} (it registers "
                    f"{[str(n.config_path) for n in nerfs]}); re-run ns-nerfuser-register on these runs"
                )
            )
        used.add(match[0])
        entry = nerfs[match[0]]
        out.append(dataclasses.replace(entry, name=name or entry.name))
    extra = [str(nerfs[j].config_path) for j in range(len(nerfs)) if j not in used]
    if extra:
        raise FusionSpecError(
            one_line(
                f"{spec_path}: the registration {registration_path} also registers runs the spec does not list: "
                f"{extra}; list them under 'runs' or re-run ns-nerfuser-register"
            )
        )
    names = [n.name for n in out]
    if len(set(names)) != len(names):
        raise spec_error(spec_path, f"duplicate NeRF names {names}")
    return out


def write_fusion_spec(
    path: Path | str,
    runs: list[Path | str],
    registration: Path | str | None = None,
    test_data: Path | str | None = None,
    test_to_common: np.ndarray | None = None,
    names: list[str] | None = None,
    test_run: str | int | None = None,
) -> Path:
    """Writes a fusion spec JSON (paths stored as given), atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = fusion_spec_text(runs, registration, test_data, test_to_common, names, test_run)
    return write_text_atomic(path, text)


def fusion_spec_text(
    runs: list[Path | str] | None = None,
    registration: Path | str | None = None,
    test_data: Path | str | None = None,
    test_to_common: np.ndarray | None = None,
    names: list[str] | None = None,
    test_run: str | int | None = None,
) -> str:
    """A fusion spec's JSON text (paths stored as given; no ``runs`` key where ``runs`` is None: the registration
    file's runs)."""
    data: dict[str, Any] = {}
    if runs is not None and names is not None:
        data["runs"] = [{"name": n, "config": str(r)} for n, r in zip(names, runs, strict=True)]
    elif runs is not None:
        data["runs"] = [str(r) for r in runs]
    if registration is not None:
        data["registration"] = str(registration)
    if test_data is not None:
        data["test_data"] = str(test_data)
    if test_to_common is not None:
        data["test_to_common"] = np.asarray(test_to_common, dtype=np.float64).tolist()
    if test_run is not None:
        data["test_run"] = test_run
    return json.dumps(data, indent=2) + "\n"
