"""The registration file: the one module that defines, writes and reads it, and the work-folder convention.

``ns-nerfuser-register`` writes a JSON record (``kind: nerfuser_registration``): per NeRF its SIM(3)
``T_to_reference`` (``p_ref = T @ [p, 1]``, also stored as ``transform``, the key of the minimal hand-written form),
diagnostics, the pairs and their self-check, the SfM summary (mode ``sfm``) or the 3D matching and hypotheses (mode
``known-geometry``: ``sfm`` is null), the settings and timings. :class:`RegistrationResult`
is that record typed (one field per value; :meth:`~RegistrationResult.to_record` writes the keys, aliases included).
The fusion reads either form through :func:`iter_registered_nerfs` (:mod:`nerfuser_ns.spec` then checks the runs).

Renders and SfM files go to a work folder, by default ``<output stem>_work`` beside the registration file
(:func:`work_dir_for`); :func:`render_folders` and :func:`read_render_poses` read the views each NeRF was rendered
from, for display.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from jaxtyping import Bool, Float

from nerfuser_ns import appearance
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration.config import (
    FORMAT_VERSION,
    RegistrationError,
)
from nerfuser_ns.registration.render_cache import load_render_meta
from nerfuser_ns.registration.self_check import CrossRenderCheck
from nerfuser_ns.renderers import Renderer

KIND = "nerfuser_registration"
"""``kind`` of a registration record (a minimal hand-written file may omit it)."""
CONVENTIONS = {
    "sim3": "T = [[s R, t], [0, 0, 0, 1]]; T_to_reference maps points of the NeRF's frame into the "
            "reference NeRF's frame: p_ref = T @ [p, 1]",
    "poses": "camera-to-world, OpenGL camera axes (nerfstudio)",
    "pairs": "T_j_to_i maps NeRF j's points into NeRF i's frame",
}
WORK_DIR_SUFFIX = "_work"


def work_dir_for(output: Path | str) -> Path:
    """The default work folder of a registration written to ``output``: ``<output stem>_work`` beside it."""
    output = Path(output)
    return output.with_name(output.stem + WORK_DIR_SUFFIX)


def matrix(T) -> Float[np.ndarray, "4 4"]:
    """A stored matrix: float64, rounded to 12 digits (as written)."""
    return np.round(np.asarray(T, dtype=np.float64), 12)


# ---------------------------------------------------------------------------------------------------------------------
# What travels with the fused run: training cameras and colour maps


@dataclass
class TrainingCameras:
    """One NeRF's training cameras in its own frame (as it finally saw them: camera-optimiser corrections applied),
    for the ``coverage`` blend method; compact: a 3x4 pose and six intrinsics per camera."""

    c2w: Float[np.ndarray, "n 4 4"]
    """Camera-to-world, OpenGL axes, the NeRF's frame."""
    intrinsics: Float[np.ndarray, "n 6"]
    """``fx, fy, cx, cy, width, height`` in pixels."""

    def to_record(self) -> dict:
        return {"c2w": np.round(self.c2w[:, :3, :4], 6).tolist(), "intrinsics": np.round(self.intrinsics, 4).tolist()}

    @classmethod
    def from_record(cls, value: Any, where: str) -> TrainingCameras | None:
        """Parsed and checked (None for null); :class:`RegistrationFileError` naming ``where`` when malformed."""
        if value is None:
            return None
        try:
            c2w = np.asarray(value["c2w"], dtype=np.float64)
            intr = np.asarray(value["intrinsics"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as e:
            raise RegistrationFileError(f"{where}: training_cameras needs c2w and intrinsics lists ({e})") from None
        if c2w.ndim != 3 or c2w.shape[1:] not in ((3, 4), (4, 4)) or intr.shape != (len(c2w), 6):
            raise RegistrationFileError(f"{where}: training_cameras must hold [n, 3, 4] c2w and [n, 6] intrinsics, "
                                        f"got {c2w.shape} and {intr.shape}")  # fmt: skip
        if not (np.isfinite(c2w).all() and np.isfinite(intr).all() and (intr[:, [0, 1, 4, 5]] > 0).all()):
            raise RegistrationFileError(f"{where}: training_cameras must be finite, focal lengths and sizes positive")
        full = np.tile(np.eye(4), (len(c2w), 1, 1))
        full[:, :3, :4] = c2w[:, :3, :4]
        return cls(full, intr)


def training_cameras_of(renderer: Renderer) -> TrainingCameras | None:
    """A renderer's training cameras (its ``training_poses`` with per-camera intrinsics from ``training_cameras()``
    or the shared ``training_intrinsics()``); None when it has none or its dataset cannot be read."""
    try:
        poses = renderer.training_poses()
        if poses is None or len(poses) == 0:
            return None
        if hasattr(renderer, "training_cameras"):
            cams = renderer.training_cameras()
            intr = np.concatenate([np.asarray(x, dtype=np.float64).reshape(-1, 1)
                                   for x in (cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height)], axis=1)
        else:  # fmt: skip
            k = renderer.training_intrinsics() if hasattr(renderer, "training_intrinsics") else None
            if k is None:
                return None
            intr = np.tile([k.fx, k.fy, k.cx, k.cy, k.width, k.height], (len(poses), 1)).astype(np.float64)
    except (RegistrationError, ValueError, OSError):  # runs.RunLoadError is a ValueError
        return None
    poses = np.asarray(poses, dtype=np.float64)
    return TrainingCameras(poses, intr) if len(intr) == len(poses) else None


def colour_map_from_record(value: Any, where: str) -> Float[np.ndarray, "3 4"] | None:
    """A stored colour map (3x4, linear RGB; None for null); :class:`RegistrationFileError` when malformed."""
    if value is None:
        return None
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (3, 4) or not np.isfinite(m).all():
        raise RegistrationFileError(f"{where}: colour_to_reference must be a finite 3x4 matrix")
    return m


def colour_maps_to_reference(
    k: int, ref: int, checks: Sequence[CrossRenderCheck]
) -> list[Float[np.ndarray, "3 4"] | None]:
    """Per NeRF its colour map to the reference, chained along the self-checked pairs."""
    pair_maps = {}
    for c in checks:
        pair_maps[(c.i, c.j)] = c.colour_j_to_i
        pair_maps[(c.j, c.i)] = c.colour_i_to_j
    return appearance.chain_to_reference(k, ref, pair_maps)


def colour_record(m: np.ndarray | None) -> list | None:
    return None if m is None else np.round(m, 8).tolist()


# ---------------------------------------------------------------------------------------------------------------------
# The typed result


@dataclass
class ViewCounts:
    """One NeRF's views: rendered, kept for the SfM (enough accumulation), registered in its largest model."""

    rendered: int
    kept: int
    registered: int
    sources: dict[str, int]
    """Rendered views per pose source ("hemisphere", "training")."""


@dataclass
class Residuals:
    """The SfM's cameras of one NeRF against its final transform (rotation in degrees, centres in its units)."""

    rotation_deg_median: float | None
    rotation_deg_max: float | None
    centre_median: float | None
    centre_max: float | None

    def to_record(self) -> dict:
        return {**asdict(self), "centre_units": "this NeRF's units",
                "of": "the SfM's cameras against the final transform"}  # fmt: skip


@dataclass
class NerfResult:
    """One registered NeRF."""

    name: str
    config: str | None
    """Its run's config.yml (absolute), None for renderers that are not nerfstudio runs."""
    checkpoint: dict | None
    """Which weights were registered: fusing them after a retraining is refused (:mod:`nerfuser_ns.spec`)."""
    T_to_reference: Float[np.ndarray, "4 4"]
    """``p_reference = T @ [p_nerf, 1]`` (written twice: as ``T_to_reference`` and as its ``transform`` alias)."""
    scale_to_reference: float
    T_to_sfm: Float[np.ndarray, "4 4"]
    """Into the solve's common frame: the SfM's (mode sfm) or the reference NeRF's (mode known-geometry)."""
    views: ViewCounts
    """``registered``: views in the SfM's model (mode sfm) or with inlier 3D matches (mode known-geometry)."""
    render_folder: str
    renders_reused: bool
    estimator: str
    refinement_change: dict | None
    """How far the refinement moved the estimator's transform (r_deg, t, s); None when not refined."""
    cameras_used: int
    scale_to_sfm: float
    scale_spread: float | None
    """The estimator's spread of per-camera scales (None in mode known-geometry, which has no cameras to compare)."""
    scale_outlier_fraction: float | None
    residuals: Residuals
    training_cameras: TrainingCameras | None = None
    """Its training cameras in its own frame (None: unknown, e.g. its dataset was gone; records before they were
    written have none)."""
    colour_to_reference: Float[np.ndarray, "3 4"] | None = None
    """Affine colour map (linear RGB) from its renders to the reference's (:mod:`nerfuser_ns.appearance`); None:
    not estimated."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Keys this version does not write (e.g. the benchmark kit's ``ground_truth``), kept as read."""

    OPTIONAL = ("training_cameras", "colour_to_reference")
    """Keys older records lack (read as None)."""

    def to_record(self) -> dict:
        return {
            "name": self.name,
            "config": self.config,
            "checkpoint": self.checkpoint,
            "T_to_reference": self.T_to_reference.tolist(),
            "transform": self.T_to_reference.tolist(),  # alias read by the fusion (p_reference = T @ [p_nerf, 1])
            "scale_to_reference": self.scale_to_reference,
            "T_to_sfm": self.T_to_sfm.tolist(),
            "views": asdict(self.views),
            "render_folder": self.render_folder,
            "renders_reused": self.renders_reused,
            "estimator": self.estimator,
            "refinement_change": self.refinement_change,
            "cameras_used": self.cameras_used,
            "scale_to_sfm": self.scale_to_sfm,
            "scale_spread": self.scale_spread,
            "scale_outlier_fraction": self.scale_outlier_fraction,
            "residuals": self.residuals.to_record(),
            # Written only when known: a record without them reads back (and rewrites) unchanged.
            **({} if self.training_cameras is None else {"training_cameras": self.training_cameras.to_record()}),
            **({} if self.colour_to_reference is None
               else {"colour_to_reference": colour_record(self.colour_to_reference)}),
            **self.extra,
        }

    @classmethod
    def from_record(cls, n: dict) -> NerfResult:
        known = {f for f in cls.__dataclass_fields__ if f != "extra"} | {"transform"}
        residuals = {k: n["residuals"][k] for k in Residuals.__dataclass_fields__}
        where = f"nerfs entry {n.get('name')!r}"
        return cls(**{
            **{k: n[k] for k in known - {"transform", *cls.OPTIONAL}},
            "training_cameras": TrainingCameras.from_record(n.get("training_cameras"), where),
            "colour_to_reference": colour_map_from_record(n.get("colour_to_reference"), where),
            "T_to_reference": matrix(n["T_to_reference"]), "T_to_sfm": matrix(n["T_to_sfm"]),
            "views": ViewCounts(**n["views"]), "residuals": Residuals(**residuals),
            "extra": {k: v for k, v in n.items() if k not in known},
        })  # fmt: skip


@dataclass
class PairCheck:
    """The cross-render self-check of one NeRF pair."""

    ncc: float | None
    """The worse direction's NCC (null: a direction saw nothing in common)."""
    ncc_i_in_j: float | None
    ncc_j_in_i: float | None
    views_per_direction: int
    threshold: float
    passed: bool
    colour_j_to_i: list | None = None
    """Affine colour map (3x4, linear RGB) from j's renders to i's, fitted on the cross-renders (None: not fitted)."""
    colour_i_to_j: list | None = None
    colour_pixels: int = 0
    """Pixel pairs the colour maps were fitted on."""
    depth_i_in_j: float | None = None
    """Median log ratio of j's depth at i's views (mapped through the link) over i's own (null: not measured)."""
    depth_j_in_i: float | None = None
    depth_threshold: float | None = None
    """The depth check's threshold on the larger of the two (null: records before it, or not measured)."""

    def to_record(self) -> dict:
        record = asdict(self)
        if self.colour_pixels == 0 and self.colour_j_to_i is None and self.colour_i_to_j is None:
            for key in ("colour_j_to_i", "colour_i_to_j", "colour_pixels"):  # not fitted: as records before them
                del record[key]
        if self.depth_threshold is None and self.depth_i_in_j is None and self.depth_j_in_i is None:
            for key in ("depth_i_in_j", "depth_j_in_i", "depth_threshold"):  # as records before the depth check
                del record[key]
        return record


@dataclass
class PairResult:
    """One NeRF pair (i < j): its relative transform and overlap, and its self-check when it was checked."""

    i: int
    j: int
    T_j_to_i: Float[np.ndarray, "4 4"]
    covisible_points: int
    self_check: PairCheck | None

    def to_record(self, names: Sequence[str]) -> dict:
        return {"i": self.i, "j": self.j, "names": [names[self.i], names[self.j]], "T_j_to_i": self.T_j_to_i.tolist(),
                "covisible_points": self.covisible_points,
                "self_check": None if self.self_check is None else self.self_check.to_record()}  # fmt: skip

    @classmethod
    def from_record(cls, p: dict) -> PairResult:
        check = p["self_check"]
        return cls(p["i"], p["j"], matrix(p["T_j_to_i"]), p["covisible_points"],
                   None if check is None else PairCheck(**check))  # fmt: skip


@dataclass
class SfMSummary:
    """The SfM run: images, how many registered, matching scheme, per-model view counts, points, reprojection."""

    images: int
    registered: int
    matching: str
    models: list[list[int]]
    points3D: int
    mean_reprojection_error_px: float | None
    reused: bool
    intrinsics: dict
    """The render camera (fx, fy, cx, cy, width, height)."""


@dataclass
class RegistrationResult:
    """A registration, typed: :meth:`to_record` is the JSON record :func:`write_registration` stores."""

    created: str
    """UTC time, ISO 8601."""
    reference: int
    """Index of the NeRF whose frame is the common frame."""
    nerfs: list[NerfResult]
    pairs: list[PairResult]
    sfm: SfMSummary | None
    """The SfM run (None in mode known-geometry)."""
    refinement: dict | None
    """The rigid-set bundle adjustment's summary (:func:`nerfuser_ns.registration.refine.refine_transforms`)."""
    settings: dict
    """The :class:`RegistrationConfig` used, as a dict."""
    timings_s: dict[str, float]
    """Seconds per step in this run (reused renders and SfM cost nearly nothing)."""
    compute_timings_s: dict[str, float | None]
    """Seconds per step as computed (reused renders and SfM report what they took when made)."""
    sampling_choice: dict | None = None
    """The automatic pose-source choice (``register`` adds it)."""
    known_geometry: dict | None = None
    """Mode known-geometry: per NeRF its keypoint counts, per pair its 3D matches and scored SIM(3) hypotheses, the
    joint solve (:func:`.assemble.build_known_geometry_result`)."""
    graph: dict | None = None
    """Mode graph: the candidate NeRF pairs, per NeRF its length scale and transforms, per pair (edge) its status,
    reason and residual, per cycle its residual (:func:`.assemble.graph_section`)."""
    direct: dict | None = None
    """Direct alignment (``--direct.enabled``): per NeRF pair what it did (:class:`.direct.PairAlignment`), and its
    settings."""
    colocated: dict | None = None
    """Re-render refinement (``--colocated.enabled``): per NeRF pair its rounds (:class:`.colocated.PairRefinement`)."""
    twin_check: dict | None = None
    """Mode sfm's twin check (``--twin-check``): per checked pair its 3D matches, hypotheses, and the SfM link's and
    the best rival's worst-view NCC (:mod:`.twin_check`), or why it was skipped."""
    model_check: dict | None = None
    """Mode sfm's model check, where another SfM model linked two NeRFs otherwise: per such link its difference from
    the registration's, both links' cross-render scores and the verdict (``pipeline.contest_models``)."""
    reference_colour: dict | None = None
    """Appearance matching: the reference NeRF's colour map to its training images (``map``, ``views``, ``pixels``)
    or why there is none (``skipped``); already composed into every ``colour_to_reference``."""
    capture_checks: dict | None = None
    """Per NeRF name, the checks of its capture (:func:`nerfuser_ns.registration.pipeline.check_captures`): the fold
    check's record (:class:`nerfuser_ns.capture_check.FoldCheck`), with the match check's under ``matches`` and the
    camera check's under ``camera``; :func:`capture_findings` says what they found wrong."""
    format_version: int = FORMAT_VERSION
    extra: dict[str, Any] = field(default_factory=dict)
    """Keys this version does not write (e.g. the benchmark kit's ``ground_truth``), kept as read."""

    def to_record(self) -> dict:
        """The JSON record (key order as written since format version 1)."""
        names = [n.name for n in self.nerfs]
        record = {
            "format_version": self.format_version,
            "kind": KIND,
            "created": self.created,
            "reference": {"index": self.reference, "name": names[self.reference]},
            "conventions": dict(CONVENTIONS),
            "nerfs": [n.to_record() for n in self.nerfs],
            "pairs": [p.to_record(names) for p in self.pairs],
            "sfm": None if self.sfm is None else asdict(self.sfm),
            "refinement": self.refinement,
            "settings": self.settings,
            "timings_s": self.timings_s,
            "compute_timings_s": self.compute_timings_s,
            "reused": {"renders": [n.renders_reused for n in self.nerfs],
                       "sfm": self.sfm is not None and self.sfm.reused},
        }
        if self.known_geometry is not None:
            record["known_geometry"] = self.known_geometry
        if self.graph is not None:
            record["graph"] = self.graph
        if self.sampling_choice is not None:
            record["sampling_choice"] = self.sampling_choice
        if self.direct is not None:
            record["direct"] = self.direct
        if self.colocated is not None:
            record["colocated"] = self.colocated
        if self.twin_check is not None:
            record["twin_check"] = self.twin_check
        if self.model_check is not None:
            record["model_check"] = self.model_check
        if self.reference_colour is not None:
            record["reference_colour"] = self.reference_colour
        if self.capture_checks is not None:
            record["capture_checks"] = self.capture_checks
        return {**record, **self.extra}

    @classmethod
    def from_record(cls, record: dict) -> RegistrationResult:
        """The typed result of a record of this format (as :func:`read_registration` returns it); unknown keys are
        kept in ``extra``. Raises :class:`RegistrationError` when a key is missing or malformed."""
        known = {"format_version", "kind", "created", "reference", "conventions", "nerfs", "pairs", "sfm",
                 "refinement", "settings", "timings_s", "compute_timings_s", "reused", "sampling_choice",
                 "known_geometry", "graph", "reference_colour", "direct", "colocated", "twin_check",
                 "model_check", "capture_checks"}  # fmt: skip
        try:
            if record.get("kind") != KIND:
                raise ValueError(f"kind {record.get('kind')!r} is not {KIND!r}")
            return cls(
                created=record["created"], reference=record["reference"]["index"],
                nerfs=[NerfResult.from_record(n) for n in record["nerfs"]],
                pairs=[PairResult.from_record(p) for p in record["pairs"]],
                sfm=None if record["sfm"] is None else SfMSummary(**record["sfm"]),
                known_geometry=record.get("known_geometry"), graph=record.get("graph"),
                refinement=record["refinement"], settings=record["settings"], timings_s=record["timings_s"],
                compute_timings_s=record["compute_timings_s"], sampling_choice=record.get("sampling_choice"),
                reference_colour=record.get("reference_colour"), direct=record.get("direct"),
                colocated=record.get("colocated"), twin_check=record.get("twin_check"),
                model_check=record.get("model_check"), capture_checks=record.get("capture_checks"),
                format_version=record["format_version"],
                extra={k: v for k, v in record.items() if k not in known},
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise RegistrationError(f"not a registration record of format {FORMAT_VERSION} "
                                    f"({type(e).__name__}: {e})") from None  # fmt: skip


# ---------------------------------------------------------------------------------------------------------------------
# The file


def _load_json(path: Path) -> Any:
    """The one JSON parse of a registration file (raises ``OSError`` / ``ValueError``)."""
    return json.loads(Path(path).read_text())


def dumps(value: Any, indent: int = 0) -> str:
    """JSON with one item per line, except lists of plain values, which stay on one line (a matrix row, a camera's
    intrinsics): a record with hundreds of cameras stays readable."""
    pad, inner = " " * indent, " " * (indent + 2)
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(str(k))}: {dumps(v, indent + 2)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + ",\n".join(f"{inner}{dumps(v, indent + 2)}" for v in value) + f"\n{pad}]"
    return json.dumps(value)


def write_registration(record: RegistrationResult | dict, path: Path | str) -> Path:
    """Write a registration (the typed result or its record) as JSON, atomically (temp file + rename)."""
    path = Path(path)
    if isinstance(record, RegistrationResult):
        record = record.to_record()
    write_text_atomic(path, dumps(record) + "\n")
    return path


def read_registration(path: Path | str) -> dict:
    """Read a registration file; ``T_to_reference`` of each NeRF comes back as a [4, 4] array."""
    path = Path(path)
    try:
        record = _load_json(path)
        if record.get("kind") != KIND:
            raise ValueError("not a registration file")
        for n in record["nerfs"]:
            n["T_to_reference"] = np.asarray(n["T_to_reference"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise RegistrationError(f"{path}: not a readable registration file ({type(e).__name__}: {e})") from None
    return record


# ---------------------------------------------------------------------------------------------------------------------
# The fusion's view: each NeRF's run and transform, from a record or the minimal hand-written form


@dataclass(frozen=True)
class NerfEntry:
    """One NeRF of the fusion: its run and its place in the common frame."""

    name: str
    """Unique name (share maps and logs use it)."""
    config_path: Path
    """The run's config.yml (absolute)."""
    nerf_to_common: Float[np.ndarray, "4 4"] = field(compare=False)
    """SIM(3) ``T`` with ``p_common = T @ [p_nerf, 1]`` (float64)."""
    training_cameras: TrainingCameras | None = field(default=None, compare=False)
    """Its training cameras in its own frame (the ``coverage`` blend method); None: unknown."""
    colour_to_reference: Float[np.ndarray, "3 4"] | None = field(default=None, compare=False)
    """Its colour map to the reference NeRF's colours (appearance matching); None: identity."""
    capture_findings: tuple[str, ...] = field(default=(), compare=False)
    """What the registration's checks of its capture found wrong (:func:`capture_findings`); a fold or a drifted
    camera the run was trained with, which the fusion inherits."""

    @property
    def scale(self) -> float:
        """``s`` of ``T``: a length L in NeRF units is ``s * L`` in common units."""
        return float(np.cbrt(np.linalg.det(self.nerf_to_common[:3, :3])))

    @property
    def origin(self) -> Float[np.ndarray, "3"]:
        """The NeRF's origin in the common frame."""
        return self.nerf_to_common[:3, 3].copy()


class RegistrationFileError(RegistrationError):
    """A registration file the fusion cannot read; the message names the file (and the entry)."""


@dataclass(frozen=True)
class RegisteredNerf:
    """One ``nerfs`` entry of a registration file as stored (the fusion checks the run and the transform)."""

    index: int
    name: str | None
    """As stored (None or empty: unnamed)."""
    config: Any
    """The run's config.yml as stored (None: the entry registers no nerfstudio run)."""
    transform_key: str
    """``T_to_reference`` (what ``ns-nerfuser-register`` writes, preferred) or ``transform`` (the minimal form)."""
    transform: Any
    """The stored 4x4 (or 3x4) SIM(3) into the common frame."""
    checkpoint: Any = None
    """The registered weights (file, step, sha256), when recorded."""
    training_cameras: TrainingCameras | None = None
    """Its training cameras, when recorded (checked)."""
    colour_to_reference: Float[np.ndarray, "3 4"] | None = None
    """Its colour map to the reference, when recorded (checked)."""
    capture_findings: tuple[str, ...] = ()
    """What the registration's checks of its capture found wrong (:func:`capture_findings`), when recorded."""


def capture_folded(checks: Mapping[str, Any]) -> bool:
    """Whether one NeRF's capture checks (its ``capture_checks`` entry) found its COLMAP poses folded, by file order
    or by its matches."""
    return bool(checks.get("folded") or (checks.get("matches") or {}).get("folded"))


def capture_findings(checks: Mapping[str, Any] | None) -> tuple[str, ...]:
    """What one NeRF's capture checks (its ``capture_checks`` entry) found wrong, one phrase each; empty when they
    found nothing or were not run (a record written before them, or a minimal file)."""
    if not isinstance(checks, Mapping):
        return ()
    found = []
    if checks.get("folded"):
        views = f"{checks.get('suspect_views', '?')} of {checks.get('num_views', '?')} views"
        found.append(f"folded by COLMAP in file order ({views} posed by the wrong copy of repeated structure)")
    matches = checks.get("matches")
    if isinstance(matches, Mapping) and matches.get("folded"):
        share = matches.get("unexplained_share")
        found.append(f"folded by COLMAP: its reconstruction does not explain {matches.get('unexplained_pairs', '?')} "
                     f"of {matches.get('pairs', '?')} verified image pairs"
                     + ("" if share is None else f" ({100 * share:.1f}%)"))  # fmt: skip
    camera = checks.get("camera")
    if isinstance(camera, Mapping) and camera.get("drifted"):
        aspect = camera.get("aspect")
        found.append("its camera drifted" + ("" if aspect is None else f" (fy/fx {aspect:.3f})"))
    return tuple(found)


def iter_registered_nerfs(path: Path | str) -> Iterator[RegisteredNerf]:
    """The NeRFs of a registration file, in order: a record (``kind: nerfuser_registration``) or the minimal
    ``{"nerfs": [{name, config, transform}]}``.

    Raises :class:`RegistrationFileError` (one line naming the file and the entry) for an unreadable file, another
    kind, a solution the checks refused (``refused``: why), no ``nerfs`` list, or an entry without ``config`` and a
    transform, when iteration reaches it.
    """
    path = Path(path)
    try:
        data = _load_json(path)
    except FileNotFoundError:
        raise RegistrationFileError(f"{path}: no such registration file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise RegistrationFileError(f"{path}: not a readable JSON registration file ({e})") from None
    if not isinstance(data, dict):
        raise RegistrationFileError(f"{path}: expected a JSON object at the top level")
    if data.get("kind", KIND) != KIND:
        raise RegistrationFileError(f"{path}: not a registration file (kind {data.get('kind')!r})")
    if data.get("refused"):
        raise RegistrationFileError(
            f"{path}: a solution the registration's checks refused, kept for inspection, not for fusing (why: "
            f"{data['refused']}); to fuse it anyway, remove its \"refused\" key"
        )
    nerfs = data.get("nerfs")
    if not isinstance(nerfs, list) or not nerfs:
        raise RegistrationFileError(f"{path}: expected a non-empty list 'nerfs' of {{name, config, transform}}")
    checks = data.get("capture_checks")
    checks = checks if isinstance(checks, dict) else {}
    for i, item in enumerate(nerfs):
        where = f"{path}: nerfs[{i}]"
        if not isinstance(item, dict):
            raise RegistrationFileError(f"{where}: expected an object with name, config, transform")
        key = "T_to_reference" if "T_to_reference" in item else "transform"
        missing = [k for k in ("config", key) if k not in item]
        if missing:
            raise RegistrationFileError(f"{where}: missing {', '.join(missing)}")
        yield RegisteredNerf(i, item.get("name"), item["config"], key, item[key], item.get("checkpoint"),
                             TrainingCameras.from_record(item.get("training_cameras"), where),
                             colour_map_from_record(item.get("colour_to_reference"), where),
                             capture_findings(checks.get(str(item.get("name")))))  # fmt: skip


def write_minimal_registration(nerfs: Sequence[NerfEntry], path: Path | str) -> Path:
    """Write the minimal registration file ``{"nerfs": [{name, config, transform}]}`` (config paths as given; each
    NeRF's ``training_cameras`` and ``colour_to_reference`` too, when known), atomically."""
    data: dict[str, list] = {"nerfs": []}
    for n in nerfs:
        item: dict[str, Any] = {"name": n.name, "config": str(n.config_path),
                                "transform": np.asarray(n.nerf_to_common).tolist()}  # fmt: skip
        if n.training_cameras is not None:  # optional keys: only when known
            item["training_cameras"] = n.training_cameras.to_record()
        if n.colour_to_reference is not None:
            item["colour_to_reference"] = colour_record(n.colour_to_reference)
        data["nerfs"].append(item)
    return write_text_atomic(path, dumps(data) + "\n")


# ---------------------------------------------------------------------------------------------------------------------
# The views each NeRF was rendered from (for display)


class RenderFolder(NamedTuple):
    """Where one NeRF of a registration file was rendered."""

    name: str
    config: Path | None
    folder: Path | None
    """Its render folder (None when the file names none, e.g. the minimal form)."""


def render_folders(path: Path | str) -> list[RenderFolder]:
    """Per NeRF of a registration file, its name, run and render folder. A folder that is gone is looked up in the
    work folder beside the file (:func:`work_dir_for`: the work folder moved with it). Raises ``OSError``,
    ``ValueError``, ``TypeError`` or ``AttributeError`` on a malformed file."""
    path = Path(path)
    data = _load_json(path)
    out = []
    for item in data.get("nerfs", []):
        folder = item.get("render_folder")
        config = item.get("config")
        if folder is not None:
            folder = Path(folder)
            if not folder.is_absolute():
                folder = path.parent / folder
            if not folder.is_dir():
                # The work folder moved with the registration file: <stem>_work/renders/<key> beside it.
                moved = work_dir_for(path) / "renders" / folder.name
                folder = moved if moved.is_dir() else folder
        out.append(RenderFolder(str(item.get("name")), None if config is None else Path(config), folder))
    return out


class RenderPoses(NamedTuple):
    """The views of one render folder, in the NeRF's own frame."""

    c2w: Float[np.ndarray, "n 4 4"]
    kept: Bool[np.ndarray, " n"]
    """Whether the SfM used the view (enough accumulation)."""
    intrinsics: dict
    """The render camera: fx, fy, cx, cy, width, height."""


def read_render_poses(folder: Path | str) -> RenderPoses:
    """The poses a registration rendered one NeRF from (its render folder's ``poses.json``).

    Raises ``FileNotFoundError`` when it is gone; ``OSError``, ``ValueError``, ``KeyError`` or ``TypeError`` when it
    is unreadable.
    """
    meta = load_render_meta(folder)
    views = meta["views"]
    c2w = np.array([v["c2w"] for v in views], dtype=np.float64).reshape(-1, 4, 4)
    kept = np.array([bool(v.get("kept", True)) for v in views], dtype=bool)
    return RenderPoses(c2w, kept, meta["intrinsics"])
