"""The practitioner benchmark's cases (``scripts/bench_practitioner.py``): each case's generated layout, where each
stage leaves its runs, fused run and ``ns-eval`` JSON, the blend columns its reports show, and its ground truth (every
capture's COLMAP frame tied to the world). The benchmark writes these folders; its reports and the other scripts that
use its runs (``scripts/report_practitioner_appearance.py``, ``scripts/bench_known_geometry.py``) read them through
here."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from nerfstudio.process_data.process_data_utils import list_images

import nerfuser_ns
from nerfuser_ns import runs, sim3
from nerfuser_ns.bench.scenes import make_layout
from nerfuser_ns.blend_choice import ALONG_A_PATH, AROUND_OBJECTS, ON_A_RIG, choose_blend_method
from nerfuser_ns.capture_check import (
    LARGER_SIDE_NAME,
    RADIAL_FOLDER_SUFFIX,
    REPOSED_FOLDER_SUFFIX,
    check_dataset_intrinsics,
)
from nerfuser_ns.coverage import CameraIndex
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.match_check import check_dataset_matches
from nerfuser_ns.registration.record import write_registration
from nerfuser_ns.spec import read_registered_nerfs

BLEND_COLUMNS = [("nerf", "NeRF (ref.)"), ("nearest", "Nearest"), ("idw_2d", "IDW-2D"), ("idw_3d", "IDW-3D"),
                 ("idw_sample", "IDW-Sample"), ("coverage", "Coverage (ours)"),
                 ("coverage_3d", "Coverage-3D (ours)")]  # fmt: skip
"""``ns-eval``'s metric suffix and the report's column name of each blend method."""
AUTO_COLUMN = ("auto", "Auto (ours, the default)")
"""The column of ``auto``: the score of the method it renders a case with (:func:`with_auto`)."""


def case_layout(
    case: str, width: int = 320, height: int = 240, num_captures: int = 2, appearance_jitter: float = 0.0,
    appearance_bracket: bool = False,
):  # noqa: ANN201 - a scenes layout
    """The generated layout of a case ``layout:seed`` as the benchmark renders it (64 views per capture, 96 on drives,
    12 test views; ``num_captures`` for streets and drives; per-capture appearance differences when jittered)."""
    name, seed = case.rsplit(":", 1)
    params = dict(seed=int(seed), num_views=64, num_test_views=12, width=width, height=height)
    if name in ("street", "drive"):
        params["num_captures"] = num_captures
    if name == "drive":
        params["num_views"] = 96
    if appearance_jitter > 0:
        params.update(appearance_jitter=appearance_jitter, appearance_bracket=appearance_bracket)
    return make_layout(name, **params)


def case_registration(spec: str) -> tuple[str, Path, Path]:
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]`` -> (the case, its folder, its registration file; default
    ``registration.json``), for the diagnostics that read a case's registration; a malformed spec exits with one
    line."""
    case, _, rest = spec.partition("=")
    folder, _, registration_file = rest.partition(",")
    if not case or not folder:
        raise SystemExit(f"case {spec!r}: expected LAYOUT:SEED=FOLDER[,REGISTRATION]")
    return case, Path(folder), Path(folder) / (registration_file or "registration.json")


def run_config(case_dir: Path, capture: str) -> Path:
    """A capture's stock nerfacto run (the ``train`` stage)."""
    return case_dir / "runs" / capture / "nerfacto" / "bench" / "config.yml"


def register_command(layout, case_dir: Path, output: Path, *options: str) -> list[str]:
    """``ns-nerfuser-register`` of this Python's environment on the case's runs into ``output``, every option at its
    default but ``options``."""
    return [str(Path(sys.executable).parent / "ns-nerfuser-register"), "--configs",
            *[str(run_config(case_dir, c.name)) for c in layout.captures], "--output", str(output), *options]


def rejected_registration(case_dir: Path) -> Path:
    """A refused registration's solution (``ns-nerfuser-register`` keeps it as its work folder's
    ``rejected_registration.json``), copied into the case folder and scored: never a result, a diagnostic."""
    return case_dir / "registration_rejected.json"


def fused_config(case_dir: Path, label: str | None) -> Path:
    """The fused run of the ``fuse`` stage (``label`` None) or of the ``matched`` / ``unmatched`` stage."""
    return case_dir / ("fused" if label is None else f"fused_{label}") / "fused" / "nerfuser" / "bench" / "config.yml"


def held_out_evals(case_dir: Path, capture: str) -> tuple[Path, Path]:
    """``ns-eval``'s JSON of the ``held-out`` stage on one capture's held-out images: the fused run's (every blend
    method) and nerfstudio's own of that capture's run."""
    return case_dir / f"eval_held_out_{capture}.json", case_dir / f"eval_own_{capture}.json"


def held_out_fused_config(case_dir: Path, capture: str) -> Path:
    """The fused run of the ``held-out`` stage whose spec names ``capture``'s run as ``test_run``."""
    return case_dir / "fused_held_out" / "fused" / "nerfuser" / capture / "config.yml"


TRUTH_BLENDS = {
    "truth": ("stored", "stored"),
    "content_estimated": ("content", "estimated"),
    "content": ("content", "content"),
}
"""The ``truth`` stage's fused runs: label -> (the truth that places the test views, the transforms blended). The
``fuse`` stage's run is ("stored", "estimated")."""


def truth_evals(case_dir: Path) -> dict[str, Path]:
    """``ns-eval``'s JSON of each fused run of the ``truth`` stage, by label (:data:`TRUTH_BLENDS`)."""
    return {label: case_dir / f"eval_{label}.json" for label in TRUTH_BLENDS}


def registration_with_transforms(source: Path, transforms: list[np.ndarray], name: str) -> Path:
    """A copy of the registration file ``source`` named ``name``, beside it (so its relative paths hold), with each
    NeRF's transform to the reference replaced by ``transforms[i]``, both keys; every other field (colour maps,
    training cameras, diagnostics) as registered."""
    record = json.loads(source.read_text())
    if len(record["nerfs"]) != len(transforms):
        raise ValueError(f"{source}: {len(record['nerfs'])} NeRFs, {len(transforms)} transforms given")
    for n, T in zip(record["nerfs"], transforms, strict=True):
        n["T_to_reference"] = n["transform"] = np.asarray(T, dtype=np.float64).tolist()
    return write_registration(record, source.with_name(name))


def blend_table(eval_json: Path) -> dict[str, dict]:
    """``blend_psnr`` / ``blend_ssim`` of every blend method (:data:`BLEND_COLUMNS`) from one ``ns-eval`` JSON (None
    where it has no score; a run scored before ``render_all_methods`` gives its one score as IDW-Sample's)."""
    results = json.loads(eval_json.read_text())["results"]
    return {f"blend_{metric}": {k: results.get(f"{metric}_{k}", results.get(metric) if k == "idw_sample" else None)
                                for k, _ in BLEND_COLUMNS}
            for metric in ("psnr", "ssim")}  # fmt: skip


def fused_appearance_matching(case_dir: Path) -> bool | None:
    """Whether the ``fuse`` stage's run (the fused model's defaults when it ran) had appearance matching on; None
    before that stage. Read from the run's config: an ``NERFUSER_APPEARANCE_MATCHING`` override at ``ns-eval`` time
    would not show (the benchmark sets none)."""
    config = fused_config(case_dir, None)
    if not config.is_file():
        return None
    found = re.search(r"^\s*appearance_matching:\s*(true|false)\s*$", config.read_text(), re.MULTILINE)
    return False if found is None else found.group(1) == "true"  # runs before the option had none: off


def appearance_evals(case_dir: Path) -> dict[bool, Path]:
    """``ns-eval``'s JSON of the case per appearance-matching setting: the ``fuse`` stage's (the defaults) and the
    ``matched`` / ``unmatched`` stages' (each setting forced)."""
    out = {}
    default = fused_appearance_matching(case_dir)
    if default is not None and (case_dir / "eval.json").is_file():
        out[default] = case_dir / "eval.json"
    for setting, name in ((True, "eval_matched.json"), (False, "eval_unmatched.json")):
        if (case_dir / name).is_file():
            out[setting] = case_dir / name
    return out


def case_times(case_dir: Path) -> dict[str, float]:
    """The seconds each stage of a case took, by step (``times.json``; empty before any)."""
    path = case_dir / "times.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def images_done(case_dir: Path, capture: str) -> Path:
    """The marker the ``scene`` stage leaves once a capture's image folder is complete."""
    return case_dir / "images" / capture / ".done"


def colmap_matching(case_dir: Path) -> str:
    """The COLMAP matching the ``colmap`` stage posed the case with (``colmap_matching.txt``; exhaustive for cases
    posed before the file existed)."""
    file = case_dir / "colmap_matching.txt"
    return file.read_text().strip() if file.is_file() else "exhaustive"


def colmap_camera(case_dir: Path) -> str:
    """``ns-process-data --camera-type`` of the ``colmap`` stage (``colmap_camera.txt``; perspective, its default, for
    cases posed before the file existed)."""
    file = case_dir / "colmap_camera.txt"
    return file.read_text().strip() if file.is_file() else "perspective"


def dataset_transforms(case_dir: Path, capture: str) -> Path:
    """A capture's COLMAP dataset (``ns-process-data``'s transforms.json): the ``colmap`` stage's output."""
    return case_dir / "datasets" / capture / "transforms.json"


def reposed_transforms(case_dir: Path, capture: str) -> Path:
    """A capture posed again without the few views the match check named (``ns-nerfuser-check-capture
    --write-images-to-repose``, then ``ns-process-data``): the checked case's ``check`` stage writes it."""
    return case_dir / "datasets" / f"{capture}{REPOSED_FOLDER_SUFFIX}" / "transforms.json"


def radial_transforms(case_dir: Path, capture: str) -> Path:
    """A capture posed once more by the user's guide's SIMPLE_RADIAL recipe (COLMAP run by hand with one focal length
    and one radial term, then ``ns-process-data --skip-colmap``), where the check found it folded, posed with one focal
    length and with no side to train on: the checked case's ``check`` stage writes it."""
    return case_dir / "datasets" / f"{capture}{RADIAL_FOLDER_SUFFIX}" / "transforms.json"


SOURCE_FRAMES_NAME = "source_frames.json"
"""In a re-posed dataset: its image names -> the first dataset's names of the same images (``ns-process-data``
numbers its inputs afresh, and a view left out shifts the numbers after it)."""


def last_posing(case_dir: Path, capture: str) -> Path:
    """The transforms file of a capture's last posing: the one the check's advice last led to (the SIMPLE_RADIAL
    recipe's, :func:`radial_transforms`, else the capture posed again, :func:`reposed_transforms`), else the COLMAP
    dataset."""
    posings = (radial_transforms(case_dir, capture), reposed_transforms(case_dir, capture))
    return next((p for p in posings if p.is_file()), dataset_transforms(case_dir, capture))


def training_transforms(case_dir: Path, capture: str) -> Path:
    """The transforms file a capture's run trains on: its :func:`last_posing`, or that posing's larger side where the
    capture is folded and ``ns-nerfuser-check-capture --write-larger-side`` wrote one."""
    dataset = last_posing(case_dir, capture)
    larger = dataset.with_name(LARGER_SIDE_NAME)
    return larger if larger.is_file() else dataset


def test_transforms(case_dir: Path) -> Path:
    """The world-posed test views (the ``scene`` stage's last output)."""
    return case_dir / "test" / "transforms.json"


def captures_ready(case_dir: Path, captures: list[str]) -> bool:
    """Whether a case folder holds every capture's images and COLMAP dataset and the test views (the ``scene`` and
    ``colmap`` stages done)."""
    return test_transforms(case_dir).is_file() and all(
        images_done(case_dir, c).is_file() and dataset_transforms(case_dir, c).is_file() for c in captures
    )


def share_captures(
    case_dir: Path, captures: list[str], siblings: list[Path], parts: tuple[str, ...] = ("images", "datasets", "test")
) -> Path | None:
    """Copy the images, COLMAP datasets and test views (``parts``) of the first sibling that has them all into
    ``case_dir``, when ``case_dir`` has none yet; the sibling copied from, or None.

    Siblings are folders of the same case that differ only in training (e.g. the camera optimiser): sharing their
    inputs makes a pair that differs in training alone, since CPU COLMAP does not pose a capture the same way twice.
    The times of the copied stages and COLMAP's logs come along; ``captures_from.txt`` names the sibling. Each folder
    is copied under a temporary name and renamed, so an interrupted copy leaves nothing a stage would take as done."""
    if any((case_dir / d).exists() for d in ("images", "datasets", "test")):
        return None
    source = next((s for s in siblings if s.resolve() != case_dir.resolve() and captures_ready(s, captures)), None)
    if source is None:
        return None
    case_dir.mkdir(parents=True, exist_ok=True)
    for name in parts:
        tmp = case_dir / f".{name}.partial"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(source / name, tmp, symlinks=True)
        tmp.rename(case_dir / name)
    stages = ("images ", "colmap ") if "datasets" in parts else ("images ",)
    if "datasets" in parts:
        for log in source.glob("colmap_*.log"):
            shutil.copy2(log, case_dir / log.name)
    shared = {k: v for k, v in case_times(source).items() if k.startswith(stages)}
    write_text_atomic(case_dir / "times.json", json.dumps({**shared, **case_times(case_dir)}, indent=2) + "\n")
    write_text_atomic(case_dir / "captures_from.txt", source.name + "\n")
    return source


def captures_from(case_dir: Path) -> str | None:
    """The sibling case folder whose images and COLMAP datasets this case shares (:func:`share_captures`), if any."""
    path = case_dir / "captures_from.txt"
    return path.read_text().strip() if path.is_file() else None


@dataclass(frozen=True)
class Summary:
    """The registration and blend figures of a set of cases, as every practitioner report states them."""

    cases: int
    nerfs: int
    """Registered NeRFs (a refused registration counts as one, a failure)."""
    success: float
    """Share of ``nerfs`` registered within the paper's failure rule."""
    median: dict[str, float]
    """Median ``r_err_deg`` / ``t_err`` / ``s_err`` over the NeRFs with errors (NaN when none)."""
    idw_sample_over_nearest: list[bool]
    """Per case with a blend: IDW-Sample >= Nearest."""
    coverage_over_nearest: list[bool] = field(default_factory=list)
    """Per case with a ``coverage`` (ours) score: coverage >= Nearest."""
    auto_over_nearest: list[bool] = field(default_factory=list)
    """Per case with a score of the method ``auto`` (ours, the default) renders it with: that score >= Nearest."""

    def line(self, prefix: str = "") -> str:
        return (f"{prefix}{self.cases} case(s), {self.nerfs} registered NeRF(s): median r_err "
                f"{self.median['r_err_deg']:.4f} deg, t_err {self.median['t_err']:.5f}, s_err "
                f"{self.median['s_err']:.5f}; success rate {self.success:.2f}.")  # fmt: skip

    def targets(self) -> list[tuple[str, bool]]:
        """The practitioner benchmark's targets (defaults only) and whether they are met."""
        blends = self.idw_sample_over_nearest
        return [
            ("success rate >= 0.95", self.success >= 0.95),
            ("median r_err <= 0.1 deg", self.median["r_err_deg"] <= 0.1),
            ("median t_err <= 0.005", self.median["t_err"] <= 0.005),
            ("median s_err <= 0.005", self.median["s_err"] <= 0.005),
            ("IDW-Sample >= Nearest on every scene", bool(blends) and all(blends)),
            (f"at least 6 cases (have {self.cases})", self.cases >= 6),
        ]


def summarise(records: list[dict], errors: str = "errors") -> Summary:
    """:class:`Summary` of case records (``scripts/bench_practitioner.py``'s), their registration errors under the key
    ``errors`` (``errors_optimized``: against the camera-optimised truth; records without that key are left out)."""
    rows = [r for r in records if errors == "errors" or r["registration"].get(errors)]
    scored: list[dict | None] = []
    for r in rows:
        errs = r["registration"].get(errors)
        scored += [None] if errs is None else errs  # None: the registration was refused
    ok = [e for e in scored if e is not None]
    median = {k: float(np.median([e[k] for e in ok])) if ok else float("nan") for k in ("r_err_deg", "t_err", "s_err")}
    success = sum(not e["failure"] for e in ok) / max(len(scored), 1)
    blends = [with_auto(r)["blend_psnr"] for r in rows if r.get("blend_psnr")]
    return Summary(len(rows), len(scored), success, median, [b["idw_sample"] >= b["nearest"] for b in blends],
                   [b["coverage"] >= b["nearest"] for b in blends if b.get("coverage") is not None],
                   [b["auto"] >= b["nearest"] for b in blends if b.get("auto") is not None])  # fmt: skip


REFUSAL_CHECKS = {
    "camera": "its SfM cameras disagree with its registered transform",
    "model": "another SfM model (",
    "twin": "twin check: ",
    "NCC": "cross-render self-check failed",
    "depth": "cross-render depth check failed",
}
"""Per check that can refuse a registration: how its line goes on after the NeRF (or pair) it names
(``self_check.camera_failure``, ``model_failure_line``, ``pair_failure``), or, the twin check's, how its line begins."""


def refusing_check(line: str) -> str | None:
    """The check (a key of :data:`REFUSAL_CHECKS`) whose refusal ``line`` is, else None (a registration error that is
    no check's refusal). Only the start counts: an automatic choice's summary names its attempts' checks later on."""
    if line.startswith(REFUSAL_CHECKS["twin"]):
        return "twin"
    rest = line.partition(": ")[2]
    return next((c for c, start in REFUSAL_CHECKS.items() if c != "twin" and rest.startswith(start)), None)


def unregistered_verdict(registration: dict) -> str:
    """How a report names a case with no registration: stopped before training by the capture check, or refused."""
    return "stopped before training" if registration.get("stopped") else "refused"


@dataclass(frozen=True)
class Refusal:
    """One pose source a check refused in a case, scored against the stored truth where the record kept it."""

    case: str
    check: str
    source: str
    mode: str
    r_err_deg: float | None
    """The refused link's worst rotation error over its NeRFs (None: the record kept no solution)."""
    failure: bool | None
    """The refused link fails the paper's rule, so the refusal was right (None: unscored)."""
    kept_r_err_deg: float | None = None
    """The worst rotation error of the link the case kept in the end (None: the case was refused)."""
    kept_failure: bool | None = None
    """That link fails the paper's rule (None: the case was refused)."""

    @property
    def outcome(self) -> str:
        """What the case kept after the refusal: ``success``, ``failure`` or ``refused``."""
        return "refused" if self.kept_failure is None else "failure" if self.kept_failure else "success"


def _worst(errors: list[dict] | None) -> tuple[float | None, bool | None]:
    """A link's worst rotation error over its NeRFs and whether it fails the paper's rule (None, None: no link)."""
    if not errors:
        return None, None
    return max(e["r_err_deg"] for e in errors), any(e["failure"] for e in errors)


def refusals_scored(records: list[dict]) -> list[Refusal]:
    """Every refusal the case records scored: each pose source an automatic choice tried before the one it kept (or
    refused last) and a check refused (``registration.attempts``). A refused case's last refusal is not among them:
    its line is not in the record."""
    out = []
    for r in records:
        kept = _worst(r["registration"]["errors"])
        for a in r["registration"].get("attempts") or []:
            if (check := refusing_check(a.get("error", ""))) is None:
                continue
            out.append(Refusal(r["case"], check, a["source"], a["mode"], *_worst(a.get("errors")), *kept))
    return out


def library_commit() -> str:
    """The short commit of the checkout this library was imported from (``-dirty`` with uncommitted changes to tracked
    files; ``unknown`` outside a git checkout): what a benchmark's commands run, whatever the current folder (a
    benchmark run from one checkout with ``PYTHONPATH`` set to another runs the other's library)."""
    root = Path(nerfuser_ns.__file__).resolve().parent.parent
    sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    if sha.returncode != 0:
        return "unknown"
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=root, capture_output=True).returncode != 0
    return sha.stdout.strip() + ("-dirty" if dirty else "")


AUTO_RULE = 2
"""The rule of ``auto`` a record's ``auto_blend`` was made with: 1 chose between IDW-Sample and coverage, 2
(:mod:`nerfuser_ns.blend_choice` now) takes IDW-2D for rigs."""

AUTO_BY_LAYOUT = {"object-centric": AROUND_OBJECTS, "drive": ON_A_RIG}
"""What ``auto`` (rule :data:`AUTO_RULE`) gives each generated layout's cameras (:data:`ALONG_A_PATH` for the others;
``tests/test_blend_choice.py`` checks every layout, ``scripts/report_blend_choice.py`` the registrations on disk)."""


def auto_blend_key(record: dict) -> str:
    """The blend column (:data:`BLEND_COLUMNS`) of the method ``auto`` renders a case with now: as the report recorded
    it (``auto_blend``, from the registration file's training cameras through :mod:`nerfuser_ns.blend_choice`, what
    the fused model does) when it was recorded with the rule in force (:data:`AUTO_RULE`), or else what its layout's
    cameras give under that rule (:data:`AUTO_BY_LAYOUT`)."""
    recorded = record.get("auto_blend") or {}
    method = recorded.get("method") if recorded.get("rule") == AUTO_RULE else None
    if method is None:
        method = AUTO_BY_LAYOUT.get(record["spec"].split(":")[0], ALONG_A_PATH)
    return method.replace("-", "_")


def with_auto(record: dict) -> dict:
    """A copy of a case record whose blend tables also hold ``auto``: the score of the method it renders the case
    with (None where the case has no score of that method)."""
    out = dict(record)
    key = auto_blend_key(record)
    for table in ("blend_psnr", "blend_ssim"):
        if record.get(table):
            out[table] = {**record[table], "auto": record[table].get(key)}
    return out


def registered_cameras(registration: Path) -> tuple[list[str], list[CameraIndex | None]]:
    """The NeRFs of a registration file by name, and the training cameras it recorded for each (in the NeRF's own
    frame; None: not recorded)."""
    nerfs = read_registered_nerfs(registration, check_runs=False)
    cameras = [None if (c := n.training_cameras) is None else CameraIndex.from_cameras(c.c2w, c.intrinsics)
               for n in nerfs]  # fmt: skip
    return [n.name for n in nerfs], cameras


def auto_blend_choice(registration: Path) -> dict[str, str | int]:
    """``{"method", "reason", "rule"}``: what ``auto`` (rule :data:`AUTO_RULE`) renders the NeRFs of a registration
    file with (their recorded training cameras; the verdict does not depend on the frame, so each NeRF's own will
    do)."""
    names, cameras = registered_cameras(registration)
    method, reason = choose_blend_method(cameras, names)
    return {"method": method, "reason": reason, "rule": AUTO_RULE}


@dataclass
class BlendGain:
    """One blend method against a baseline method over the cases scored with both (PSNR, dB)."""

    cases: int
    median: float
    low: float
    high: float
    best: int
    """Cases where this method scored highest of the blend methods the case was scored with (the reference NeRF
    alone, ``nerf``, left out; a tie counts for each)."""

    def cell(self) -> str:
        return f"{self.median:+.2f} ({self.low:+.2f} to {self.high:+.2f}); best {self.best}/{self.cases}"


def blend_gains(records: list[dict], baseline: str = "idw_sample") -> dict[str, BlendGain]:
    """Per blend method of :data:`BLEND_COLUMNS` (but ``nerf``): its PSNR minus ``baseline``'s over the case records
    with a blend and a registration without a failure (a misregistered blend says nothing of the method)."""
    rows = [with_auto(r)["blend_psnr"] for r in records if r.get("blend_psnr") and r["registration"].get("errors")
            and not any(e["failure"] for e in r["registration"]["errors"])]  # fmt: skip
    methods = [k for k, _ in BLEND_COLUMNS if k != "nerf"]
    # each case's highest score, once (None: the case scored none of them, so no method below pairs with it)
    tops = [max((b[k] for k in methods if b.get(k) is not None), default=None) for b in rows]
    out = {}
    # ``auto`` is one of the methods under another name: scored, never a rival
    for m in [*methods, "auto"]:
        scored = [(b, top) for b, top in zip(rows, tops, strict=True) if b.get(m) is not None
                  and b.get(baseline) is not None]  # fmt: skip
        if not scored:
            continue
        gains = np.array([b[m] - b[baseline] for b, _ in scored])
        best = sum(b[m] >= top for b, top in scored)
        out[m] = BlendGain(len(scored), float(np.median(gains)), float(gains.min()), float(gains.max()), best)
    return out


# --------------------------------------------------------------------------------------------------------------------
# Ground truth


def frame_index(file_path: str) -> int:
    """ns-process-data renames the sorted inputs frame_00001.png...; our inputs are view_<i>.png in order."""
    return int(Path(file_path).stem.split("_")[-1]) - 1


def source_frames(images: Path) -> dict[str, str]:
    """``ns-process-data images --data <images>``'s name of each image of the folder -> the image's own name: it copies
    the images nerfstudio lists (sorted) to ``frame_00001...`` in that order (``process_data_utils.copy_images``)."""
    return {f"frame_{i + 1:05d}{p.suffix}": p.relative_to(images).as_posix() for i, p in enumerate(list_images(images))}


def view_indices(file_paths: list[str], dataset: Path) -> np.ndarray:
    """The capture's view numbers of a dataset's images (:func:`frame_index`); in a re-posed dataset through its
    :data:`SOURCE_FRAMES_NAME` (its inputs were the first dataset's images, a few left out)."""
    source = dataset / SOURCE_FRAMES_NAME
    names = json.loads(source.read_text()) if source.is_file() else None
    return np.array([frame_index(Path(f).name if names is None else names[Path(f).name]) for f in file_paths], int)


def capture_ground_truth(layout, case_dir: Path, optimized: bool = True) -> list[dict]:
    """Per capture: the SIM(3) tying its stored (transforms.json) frame to the world, COLMAP's pose noise, and the
    true NeRF-frame -> world map of its run, the same through the tie fitted to the views' rotations as well
    (``nerf_to_world_pose``, :func:`tie_to_world`); with ``optimized``, also the tie through its camera-optimised
    poses (:func:`_optimized_ground_truth`, which loads the run's model)."""
    out = []
    for cap in layout.captures:
        record, data_to_world, pose_to_world, world_scale = colmap_tie(cap, case_dir)
        nerf_to_data = sim3.invert_sim3(runs.read_dataparser_transform(run_config(case_dir, cap.name)))
        record["nerf_to_world"] = sim3.compose(data_to_world, nerf_to_data)
        record["nerf_to_world_pose"] = sim3.compose(pose_to_world, nerf_to_data)
        if optimized:
            record.update(_optimized_ground_truth(run_config(case_dir, cap.name), cap.c2w_world, world_scale) or {})
        out.append(record)
    return out


def reference_links(reg: dict, gt: list[dict]) -> dict[str, np.ndarray]:
    """A registration's transforms into its reference NeRF's frame (``registered``, ``[k, 4, 4]``) beside the case's
    truths in that frame: ``stored truth`` (each capture tied by its camera centres) and ``pose truth`` (by its views'
    poses); ``reg`` a registration record, ``gt`` :func:`capture_ground_truth` of the case, captures in its order."""
    ref = reg["reference"]["index"]
    return {"registered": np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in reg["nerfs"]]),
            "stored truth": sim3.to_reference_frame(np.stack([g["nerf_to_world"] for g in gt]), ref),
            "pose truth": sim3.to_reference_frame(np.stack([g["nerf_to_world_pose"] for g in gt]), ref)}  # fmt: skip


def colmap_tie(cap, case_dir: Path) -> tuple[dict, np.ndarray, np.ndarray, float]:
    """What COLMAP made of one capture (``ns-process-data``'s transforms.json; no trained run needed): the record of
    :func:`capture_ground_truth` without its NeRF frames, the SIM(3) tying the stored frame to the world by the
    centres and by the poses (:func:`tie_to_world`), and the capture's world scale (mean distance of its true centres
    from their mean)."""
    misposed = colmap_misposed(cap, case_dir)  # what COLMAP made of the whole capture
    # the ties are those of the views the run trained on (the larger side of a checked capture)
    idx, stored = stored_poses(training_transforms(case_dir, cap.name))
    true = cap.c2w_world[idx]
    world_scale = float(np.linalg.norm(true[:, :3, 3] - true[:, :3, 3].mean(0), axis=-1).mean())
    data_to_world, rot_err, centre_err = tie_to_world(stored, true, world_scale)
    pose_to_world, pose_rot_err, _ = tie_to_world(stored, true, world_scale, rotations=True)
    record = {
        "capture": cap.name,
        "views": cap.num_views,
        "posed_by_colmap": len(misposed),
        "trained_views": len(idx),
        "colmap_rot_err_deg_median": rot_err,
        "colmap_centre_err_median": centre_err,
        "colmap_bend_deg": colmap_bend_deg(stored, true, idx, world_scale),
        "colmap_focal_ratio": check_dataset_intrinsics(training_transforms(case_dir, cap.name)).aspect,
        "pose_tie_rot_err_deg_median": pose_rot_err,
        "pose_tie_misposed_views": sum(misposed.values()),
    }
    # the posings the check's advice led to: again (without named views or with one focal length), SIMPLE_RADIAL
    for label, posing in (("reposed", reposed_transforms(case_dir, cap.name)),
                          ("radial", radial_transforms(case_dir, cap.name))):  # fmt: skip
        if posing.is_file():
            again = colmap_misposed(cap, case_dir, posing)
            record[f"{label}_posed_by_colmap"] = len(again)
            record[f"{label}_misposed_views"] = sum(again.values())
    matches = check_dataset_matches(dataset_transforms(case_dir, cap.name))
    if matches.checked:  # the fold check the user's guide runs before training (ns-nerfuser-check-capture)
        record["match_check_pairs"] = matches.pairs
        record["match_check_unexplained_share"] = round(matches.unexplained_share, 4)
        record["match_check_folded"] = matches.folded
    return record, data_to_world, pose_to_world, world_scale


def colmap_misposed(cap, case_dir: Path, transforms: Path | None = None) -> dict[str, bool]:
    """Per view COLMAP posed (``file_path`` of ns-process-data's transforms.json, the first dataset's unless
    ``transforms`` names another), whether it is misposed (:func:`misposed_frames`, against the capture's true
    poses)."""
    transforms = dataset_transforms(case_dir, cap.name) if transforms is None else transforms
    idx, stored = stored_poses(transforms)
    files = [str(f["file_path"]) for f in json.loads(transforms.read_text())["frames"]]
    return dict(zip(files, map(bool, misposed_frames(stored, cap.c2w_world[idx])), strict=True))


def stored_poses(transforms: Path) -> tuple[np.ndarray, np.ndarray]:
    """A dataset's frame numbers and stored camera-to-world poses, in file order."""
    frames = json.loads(transforms.read_text())["frames"]
    idx = view_indices([str(f["file_path"]) for f in frames], transforms.parent)
    return idx, np.array([f["transform_matrix"] for f in frames], dtype=np.float64)


def _optimized_ground_truth(config: Path, c2w_world: np.ndarray, world_scale: float) -> dict | None:
    """The same tie through the run's camera-optimised training poses (NeRF frame) instead of the stored ones.

    The optimiser moves the cameras, and the trained content may follow them; a common part of its corrections would
    move the content's frame, which this fit follows (per-camera parts show as its residuals). None when the run has
    no optimiser (then both ties agree) or no checkpoint yet."""
    if not any(config.parent.glob("nerfstudio_models/*.ckpt")):
        return None
    views = runs.training_views(config)
    model = runs.load_run(config).model
    c2w = views.cameras.camera_to_worlds
    optimized = runs.optimized_poses(model, c2w).numpy().astype(np.float64)
    if np.array_equal(optimized, c2w.numpy()):
        return None
    files = [str(f) for f in views.image_filenames]
    T, rot_err, centre_err = tie_to_world(optimized, c2w_world[view_indices(files, Path(files[0]).parent.parent)],
                                           world_scale)  # fmt: skip
    return {"optimized_rot_err_deg_median": rot_err, "optimized_centre_err_median": centre_err,
            "nerf_to_world_optimized": T}  # fmt: skip


def colmap_bend_deg(stored: np.ndarray, true: np.ndarray, idx: np.ndarray, world_scale: float) -> float:
    """Rotation (deg) between the ties of the first and the second half of a capture's posed views (capture order):
    0 where one SIM(3) maps COLMAP's frame to the world; on a bent reconstruction no single tie is the truth, and the
    errors measured against it carry about this much."""
    order = np.argsort(idx)
    halves = [order[: len(order) // 2], order[len(order) // 2 :]]
    first, second = (tie_to_world(stored[h], true[h], world_scale)[0] for h in halves)
    return float(sim3.sim3_errors(first, second).r_err_deg)


MISPOSED_DEG = 5.0
"""A view COLMAP posed more than this off the capture's pose tie is misposed (the paper's rotation failure rule)."""


def misposed_frames(poses: np.ndarray, true: np.ndarray, max_deg: float = MISPOSED_DEG) -> np.ndarray:
    """Which of a capture's views ``poses`` (its stored frame) lie more than ``max_deg`` off their true rotation
    after the tie fitted to the views' rotations: on repeated structure COLMAP can pose part of a capture by the wrong
    copy (a room's views of one half taken for the other), which the median residuals hide."""
    est = sim3.estimate_sim3_from_poses(poses, true)
    return np.asarray(est.rot_residuals_deg) > max_deg


def tie_to_world(
    poses: np.ndarray, true: np.ndarray, world_scale: float, rotations: bool = False
) -> tuple[np.ndarray, float, float]:
    """The SIM(3) fitted to the true centres of ``poses`` (Umeyama, every view), and its residuals: median rotation
    (deg) and median centre distance over ``world_scale`` (world units; the fit reports them in the poses' units).

    With ``rotations``, fitted to the views' rotations as well (:func:`nerfuser_ns.sim3.estimate_sim3_from_poses`:
    rotation averaged over the views, then translation): on a capture whose centres lie near a line (a drive) the
    centres alone leave the roll about that line loosely fixed, the rotations fix it."""
    est = (sim3.estimate_sim3_from_poses(poses, true) if rotations
           else sim3.estimate_sim3_umeyama(poses, true, robust=False))  # fmt: skip
    return (est.T, float(np.median(est.rot_residuals_deg)),
            float(np.median(est.centre_residuals) * est.scale / world_scale))  # fmt: skip
