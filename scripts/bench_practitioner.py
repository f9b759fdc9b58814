"""The practitioner's path, measured from images in: COLMAP-posed captures, stock nerfacto, default options.

Per case (a generated scene and seed), as a user would do it:

1. ``scene``: render each capture of the scene to a plain image folder (no poses, no transforms.json), and the
   world-posed test views (the ground truth ``ns-eval`` scores against).
2. ``colmap``: ``ns-process-data images`` on each capture separately (Debian's ``colmap``, CPU SIFT, exhaustive
   matching: the default vocabulary-tree matcher downloads its tree). Each capture gets its own COLMAP frame and scale.
3. ``train``: stock ``ns-train nerfacto`` on each dataset; sizes reduced for the CPU through ns-train's own options
   (:data:`TRAIN_OPTIONS`), camera optimiser and datamanager left at nerfacto's defaults.
4. ``register``: ``ns-nerfuser-register --configs ...`` and nothing else (every default).
5. ``fuse``: ``ns-train nerfuser`` on a fusion spec naming the runs, the registration and the test views;
   ``ns-eval`` (every blend method scored in one pass), ``ns-render dataset``.
6. ``score``: ground truth. Each capture's COLMAP frame (transforms.json's stored poses) is tied to the world by a
   SIM(3) fitted to the true camera centres of the views COLMAP registered; composed with each run's dataparser
   transform (``applied_transform`` included) it gives every NeRF's true frame. r/t/s errors as the paper defines
   them, COLMAP's own pose noise beside them, the blend table from ``ns-eval``'s JSON, the time of every step.
7. ``held-out`` (not a default): the blend scored without ground truth, as a user can: on each capture's own
   held-out images (a fusion spec with ``test_run``), beside nerfstudio's ``ns-eval`` of that capture's run alone.
8. ``truth`` (not a default): the fused run again with the true transforms in place of the estimated ones, on the same
   test views: what the registration's error costs the blend.

Every stage is cached in ``<root>/<case>/`` (trained runs are never retrained unless deleted), so re-runs only redo
what is missing. Thresholds and defaults are the tools' own; nothing here is tuned per case.

Set up (Debian's colmap and ffmpeg, then the environment): ``VENV=$(bash scripts/setup_practitioner.sh)``. Example::

    $VENV/bin/python scripts/bench_practitioner.py --cases object-centric:1 drive:1 street:1 --root outputs/practitioner
    python scripts/bench_practitioner.py --report-only --cases ... --report reports/bench_practitioner.md
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import tyro
from PIL import Image
from rich.console import Console

from nerfuser_ns import registration, runs, sim3
from nerfuser_ns.bench import evaluation
from nerfuser_ns.bench.practitioner_cases import (
    BLEND_COLUMNS,
    SOURCE_FRAMES_NAME,
    TRUTH_BLENDS,
    appearance_evals,
    auto_blend_choice,
    blend_table,
    capture_ground_truth,
    captures_from,
    case_layout,
    case_times,
    colmap_camera,
    colmap_matching,
    colmap_tie,
    dataset_transforms,
    fused_appearance_matching,
    fused_config,
    held_out_evals,
    held_out_fused_config,
    images_done,
    last_posing,
    library_commit,
    radial_transforms,
    register_command,
    registration_with_transforms,
    rejected_registration,
    reposed_transforms,
    run_config,
    share_captures,
    source_frames,
    summarise,
    test_transforms,
    training_transforms,
    truth_evals,
    unregistered_verdict,
    with_auto,
)
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.bench.scenes import apply_appearance, render, to_uint8, write_capture
from nerfuser_ns.capture_check import (
    LARGER_SIDE_NAME,
    REPOSE_FOLDER_NAME,
    check_dataset,
    check_dataset_intrinsics,
    process_data_command,
    simple_radial_recipe,
)
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.match_check import check_dataset_matches
from nerfuser_ns.registration import RegistrationConfig, RegistrationFailed, read_registration
from nerfuser_ns.registration.record import iter_registered_nerfs
from nerfuser_ns.renderers import NerfstudioRenderer
from nerfuser_ns.spec import write_fusion_spec

CONSOLE = Console(width=120)
BIN = Path(sys.executable).parent

TRAIN_OPTIONS = [
    "--mixed-precision", "False",
    "--machine.device-type", "cpu",
    "--pipeline.model.implementation", "torch",
    "--pipeline.datamanager.train-num-rays-per-batch", "1024",
    "--pipeline.model.log2-hashmap-size", "15",
    "--pipeline.model.hidden-dim", "32",
    "--pipeline.model.hidden-dim-color", "32",
    "--pipeline.model.num-proposal-samples-per-ray", "64", "32",
    "--pipeline.model.num-nerf-samples-per-ray", "32",
    "--pipeline.model.eval-num-rays-per-chunk", "8192",
    "--steps-per-eval-image", "1000000",
    "--steps-per-eval-batch", "1000000",
    "--steps-per-eval-all-images", "1000000",
    "--vis", "tensorboard",
]  # fmt: skip
"""CPU-sized nerfacto through ns-train's own options (hash grid, MLP widths and samples as our CPU preset);
everything else (camera optimiser, parallel datamanager, scene contraction, losses) is stock nerfacto."""

STOCK_OPTIONS = ["--vis", "tensorboard"]
"""Stock nerfacto on the GPU: the viewer (ns-train's default) would keep the process alive after training."""

@dataclass
class BenchPractitioner:
    """Images in, registration and blend out, with every tool at its defaults."""

    cases: list[str] = field(default_factory=lambda: ["object-centric:1", "drive:1", "street:1"])
    """Cases as layout:seed (layouts: object-centric, street, drive, room)."""
    root: Path = Path("outputs/practitioner")
    """Work folder (one sub-folder per case; every stage cached there)."""
    width: int = 320
    """Capture image width (the same for every layout; SIFT needs more than the 192 px of our training scenes)."""
    height: int = 240
    """Capture image height."""
    num_captures: int = 2
    """Captures of street and drive scenes (object-centric always has 2, row houses 3). Such case folders get the
    suffix ``-<n>captures`` when it is not 2."""
    max_num_iterations: int = 2000
    """nerfacto steps per capture."""
    train_preset: Literal["cpu", "stock"] = "cpu"
    """cpu: nerfacto sized for the CPU (:data:`TRAIN_OPTIONS`); stock: nerfacto exactly as ``ns-train nerfacto``
    runs it on a GPU (every model and trainer option at its default but the step count; tensorboard, not the viewer,
    so that training ends)."""
    stages: list[str] = field(default_factory=lambda: ["scene", "colmap", "train", "register", "fuse"])
    """Stages to run (each skipped when its output exists); ``cost`` (not a default) also times the fused model's
    IDW-Sample, ``coverage`` and ``coverage-3d`` passes against the sub-models on the rays they are queried on;
    ``content`` (not a default) registers each run to the ground-truth scene placed by the stored truth
    (:func:`stage_content`);
    ``matched`` / ``unmatched`` (not defaults) score the fused run again with appearance matching forced on / off
    (:func:`stage_appearance`); ``truth`` (not a default) blends with the true transforms instead of the estimated
    ones (:func:`stage_truth`); ``held-out`` (not a default) scores the blend on each capture's own held-out images,
    the way a user without ground truth would (:func:`stage_held_out`); ``direct`` (not a default) registers again
    with the direct alignment set the other way and scores the blend with it (:func:`stage_direct`)."""
    report: Path | None = None
    """Write the markdown report here (after the stages)."""
    note: str | None = None
    """A paragraph for the report, under its protocol (e.g. which case chose a setting: a validation case)."""
    report_only: bool = False
    """Only collect the cases' records into the report."""
    coverage_report: Path | None = None
    """Also write the report of the ``coverage`` blend (ours) against the paper's IDW methods here."""
    appearance_jitter: float = 0.0
    """Give each capture its own exposure and white balance (stops; the generator's ``appearance_jitter``): the
    captures' images carry it, the test views the reference (first) capture's, which the blend is scored against.
    Case folders get the suffix ``-bracket<j>`` or ``-jitter<j>``."""
    appearance_bracket: bool = False
    """With ``appearance_jitter``: spread the captures over its range (the largest differences it allows) instead of
    drawing them."""
    camera_optimizer: Literal["default", "off"] = "default"
    """default: nerfacto's camera optimiser as ``ns-train`` sets it (on); off: trained with
    ``--pipeline.model.camera-optimizer.mode off``, so each NeRF's frame is exactly its stored COLMAP frame (a
    diagnostic of the truth, not a user default). Case folders get the suffix ``-camopt-off``."""
    matching_method: Literal["exhaustive", "sequential"] = "exhaustive"
    """COLMAP's feature matching in ``ns-process-data``: exhaustive (every pair of views; the benchmark's setting
    throughout, since nerfstudio's default ``vocab_tree`` downloads its tree) or sequential (neighbours in file order,
    what the registration's fold warning advises for a filmed sequence). Case folders get the suffix ``-sequential``;
    such a folder shares the images and test views of the exhaustive one (never its COLMAP datasets)."""
    camera_type: Literal["perspective", "simple_pinhole"] = "perspective"
    """``ns-process-data --camera-type``: perspective (its default: COLMAP's OPENCV camera, a focal length per axis)
    or simple_pinhole (one focal length, no distortion: what ``ns-nerfuser-check-capture`` advises for a capture whose
    vertical focal length drifted). Case folders get the suffix ``-simple-pinhole``; such a folder shares the images
    and test views of the perspective one (never its COLMAP datasets)."""
    check_captures: bool = False
    """Before training, run ``ns-nerfuser-check-capture --write-larger-side --write-images-to-repose`` on each
    capture's COLMAP dataset and follow its advice as a user would: a capture it finds folded trains on its larger
    side, one with a few misposed views is posed again without them, one whose camera drifted is posed again with one
    focal length, and one it then finds folded with one focal length and no side is posed once more by the guide's
    SIMPLE_RADIAL recipe (:func:`stage_check`). A folded capture it finds no remedy for (no side free of the fold,
    too many views to leave out, no SIMPLE_RADIAL posing left to try) stops the case before training: the check then
    advises posing it again, which is a user's choice, not a rule. Case folders get the suffix ``-checked``."""
    share_captures: bool = True
    """Before the ``scene`` stage of a case folder with no images yet, copy the images, COLMAP datasets and test views
    of the same case trained the other way (the other ``--camera-optimizer`` folder), when that folder has them all:
    the pair then differs in training alone (CPU COLMAP does not pose a capture the same way twice). The report names
    the folder copied from."""


def _run(cmd: list[str], log: Path, cwd: Path | None = None) -> float:
    """Run a tool as a user would, its output in ``log``; the seconds it took. Raises with the log's tail."""
    CONSOLE.print(f"[dim]$ {' '.join(cmd)}[/]")
    start = time.perf_counter()
    with open(log, "w") as f:
        env = {**os.environ, "PYTHONWARNINGS": "ignore"}
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=cwd, env=env)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-15:]
        raise RuntimeError(f"{cmd[0]} failed (exit {proc.returncode}), see {log}:\n" + "\n".join(tail))
    return seconds


def _layout(case: str, cfg: BenchPractitioner):
    return case_layout(case, cfg.width, cfg.height, cfg.num_captures, cfg.appearance_jitter, cfg.appearance_bracket)


def case_folder(case: str, cfg: BenchPractitioner) -> str:
    """A case's folder name: ``layout-seed``, with the number of captures of a street or drive when it is not 2, the
    appearance differences it was rendered with and the camera optimiser's setting when it is not nerfacto's
    default."""
    name = case.replace(":", "-")
    if case.rsplit(":", 1)[0] in ("street", "drive") and cfg.num_captures != 2:
        name += f"-{cfg.num_captures}captures"
    if cfg.appearance_jitter > 0:
        name += f"-{'bracket' if cfg.appearance_bracket else 'jitter'}{cfg.appearance_jitter:g}"
    name += "-sequential" if cfg.matching_method == "sequential" else ""
    name += "-simple-pinhole" if cfg.camera_type == "simple_pinhole" else ""
    name += "-checked" if cfg.check_captures else ""
    return name + ("-camopt-off" if cfg.camera_optimizer == "off" else "")


def training_siblings(case: str, cfg: BenchPractitioner) -> list[str]:
    """The folders of the same case (same images and COLMAP datasets) trained otherwise: every other camera-optimiser
    setting, checked or not (``--check-captures``)."""
    own = case_folder(case, cfg)
    names = [case_folder(case, replace(cfg, camera_optimizer=v, check_captures=c))
             for v in ("default", "off") for c in (False, True)]  # fmt: skip
    return [n for n in names if n != own]


def image_siblings(case: str, cfg: BenchPractitioner) -> list[str]:
    """The other folders of the same case (same images) posed otherwise (COLMAP matching or camera) or checked
    otherwise."""
    own = case_folder(case, cfg)
    names = [case_folder(case, replace(cfg, matching_method=m, camera_type=t, camera_optimizer=v, check_captures=c))
             for m in ("exhaustive", "sequential") for t in ("perspective", "simple_pinhole")
             for v in ("default", "off") for c in (False, True)]  # fmt: skip
    return [n for n in names if n != own and n not in training_siblings(case, cfg)]


def case_options(cfg: BenchPractitioner) -> list[str]:
    """The command-line options that shape a case beyond ``--cases`` (its images and its training), as given to this
    script: a report's command must carry them to make the same case again."""
    opts = []
    if cfg.num_captures != 2:
        opts += ["--num-captures", str(cfg.num_captures)]
    if cfg.appearance_jitter > 0:
        opts += ["--appearance-jitter", f"{cfg.appearance_jitter:g}"]
        opts += ["--appearance-bracket"] if cfg.appearance_bracket else []
    if cfg.train_preset != "cpu":
        opts += ["--train-preset", cfg.train_preset]
    if cfg.max_num_iterations != 2000:
        opts += ["--max-num-iterations", str(cfg.max_num_iterations)]
    if cfg.camera_optimizer != "default":
        opts += ["--camera-optimizer", cfg.camera_optimizer]
    if cfg.matching_method != "exhaustive":
        opts += ["--matching-method", cfg.matching_method]
    if cfg.camera_type != "perspective":
        opts += ["--camera-type", cfg.camera_type]
    if cfg.check_captures:
        opts += ["--check-captures"]
    return opts


def _add_time(case_dir: Path, key: str, seconds: float) -> None:
    times = case_times(case_dir)
    times[key] = round(seconds, 1)
    write_text_atomic(case_dir / "times.json", json.dumps(times, indent=2) + "\n")


def stage_scene(layout, case_dir: Path) -> None:
    for cap in layout.captures:
        done = images_done(case_dir, cap.name)
        folder = done.parent
        if done.is_file():
            continue
        start = time.perf_counter()
        folder.mkdir(parents=True, exist_ok=True)
        for i in range(cap.num_views):
            out = render(layout.scene, cap.c2w_world[i], cap.intrinsics, supersample=2)
            rgb = apply_appearance(out.rgb, cap.appearance_gains)
            Image.fromarray(to_uint8(rgb)).save(folder / f"view_{i:05d}.png")
        done.write_text("")
        _add_time(case_dir, f"images {cap.name}", time.perf_counter() - start)
    gains = [None if cap.appearance_gains is None else cap.appearance_gains.tolist() for cap in layout.captures]
    if any(g is not None for g in gains) and not (case_dir / "appearance.json").is_file():
        write_text_atomic(case_dir / "appearance.json", json.dumps(
            {"captures": [cap.name for cap in layout.captures], "gains": gains, "test": "the first capture's"},
            indent=2) + "\n")  # fmt: skip
    if not test_transforms(case_dir).is_file():
        # scored in the reference capture's appearance: the colours a matched blend renders
        ref = layout.captures[0]
        view = replace(layout.test, exposure=ref.exposure, white_balance=ref.white_balance)
        write_capture(layout, view, test_transforms(case_dir).parent, world_frame=True, supersample=2)


def stage_colmap(
    layout, case_dir: Path, matching_method: str = "exhaustive", camera_type: str = "perspective"
) -> None:
    """Pose each capture with ``ns-process-data images`` (COLMAP, CPU SIFT); ``colmap_matching.txt`` names the
    matching (cases without it were posed by exhaustive matching), ``colmap_camera.txt`` ns-process-data's
    ``--camera-type`` (cases without it: perspective, its default)."""
    if not (case_dir / "colmap_matching.txt").is_file():
        write_text_atomic(case_dir / "colmap_matching.txt", matching_method + "\n")
    if not (case_dir / "colmap_camera.txt").is_file():
        write_text_atomic(case_dir / "colmap_camera.txt", camera_type + "\n")
    for cap in layout.captures:
        out = dataset_transforms(case_dir, cap.name)
        if out.is_file():
            continue
        if not images_done(case_dir, cap.name).is_file():
            raise SystemExit(f"{images_done(case_dir, cap.name).parent}: no complete image folder; run the scene "
                             "stage first (--stages scene colmap: it also copies a sibling folder's images)")
        seconds = _process_data(images_done(case_dir, cap.name).parent, out, matching_method, camera_type,
                                case_dir / f"colmap_{cap.name}.log")  # fmt: skip
        _add_time(case_dir, f"colmap {cap.name}", seconds)


def _process_data(images: Path, out: Path, matching_method: str, camera_type: str, log: Path) -> float:
    """``ns-process-data images`` (COLMAP, CPU SIFT) on ``images`` into ``out``'s folder; its time."""
    cmd = process_data_command(images, out.parent, camera_type, matching_method, use_gpu=False,
                               ns_process_data=str(BIN / "ns-process-data"), num_downscales=0)  # fmt: skip
    seconds = _run(cmd, log)
    if not out.is_file():
        raise RuntimeError(f"ns-process-data wrote no transforms.json from {images}: COLMAP posed nothing")
    return seconds


def _training_data(case_dir: Path, capture: str) -> Path:
    """``ns-train``'s ``--data``: the dataset folder, or the larger side's transforms file of a folded capture."""
    file = training_transforms(case_dir, capture)
    return file if file.name == LARGER_SIDE_NAME else file.parent


def stage_check(layout, case_dir: Path, matching_method: str = "exhaustive", camera_type: str = "perspective") -> None:
    """The user's guide before training: ``ns-nerfuser-check-capture --write-larger-side --write-images-to-repose`` on
    every capture's dataset (exit 1 means a capture is folded or drifted: expected, not an error), then its advice
    followed: a capture whose check named a few misposed views is posed again without them, and a capture whose
    camera drifted is posed again with one focal length (``--camera-type simple_pinhole``, every view, or every view
    but the named ones where both apply), each as the first time into :func:`reposed_transforms`, and checked again;
    a capture then folded with one focal length and no side is posed once more by the SIMPLE_RADIAL recipe
    (:func:`stage_radial`). What it found goes to ``capture_check.json``."""
    out = case_dir / "capture_check.json"
    if not out.is_file():
        _check_and_repose(layout, case_dir, matching_method, camera_type)
    stage_radial(layout, case_dir, matching_method)


def _check_and_repose(layout, case_dir: Path, matching_method: str, camera_type: str) -> None:
    """:func:`stage_check`'s first check and the re-posing it advises, into ``capture_check.json``."""
    out = case_dir / "capture_check.json"
    datasets = [dataset_transforms(case_dir, cap.name).parent for cap in layout.captures]
    for d in datasets:  # an interrupted check's copy: written again from the same dataset
        shutil.rmtree(d / REPOSE_FOLDER_NAME, ignore_errors=True)
    _check_captures(datasets, case_dir / "check_capture.log", "--write-larger-side", "--write-images-to-repose")
    checks = {cap.name: _check_record(d) for cap, d in zip(layout.captures, datasets, strict=True)}
    for cap, d in zip(layout.captures, datasets, strict=True):
        without_views = (d / REPOSE_FOLDER_NAME).is_dir()
        drifted = checks[cap.name]["camera"]["drifted"] and camera_type != "simple_pinhole"
        if not (without_views or drifted):
            continue
        images = d / REPOSE_FOLDER_NAME if without_views else images_done(case_dir, cap.name).parent
        camera = "simple_pinhole" if drifted else camera_type
        reposed = reposed_transforms(case_dir, cap.name)
        if not reposed.is_file():
            seconds = _process_data(images, reposed, matching_method, camera,
                                    case_dir / f"colmap_{cap.name}_reposed.log")  # fmt: skip
            _add_time(case_dir, f"colmap {cap.name} reposed", seconds)
        if without_views:  # numbered afresh, a view left out shifting the rest; the truth reads the first numbers
            write_text_atomic(reposed.parent / SOURCE_FRAMES_NAME, json.dumps(source_frames(images), indent=1) + "\n")
        _check_captures([reposed.parent], case_dir / f"check_capture_{cap.name}_reposed.log", "--write-larger-side")
        checks[cap.name]["reposed"] = {**_check_record(reposed.parent), "camera_type": camera,
                                       "without_views": without_views, "for_drift": drifted}  # fmt: skip
    write_text_atomic(case_dir / "check_commit.txt", library_commit() + "\n")
    write_text_atomic(out, json.dumps(checks, indent=2) + "\n")


def stage_radial(layout, case_dir: Path, matching_method: str = "exhaustive") -> None:
    """The check's advice for a capture it found folded with no side to train on, posed with one focal length
    (``ONE_FOCAL_ADVICE`` of ``ns-nerfuser-check-capture``): pose it once more by the user's guide's SIMPLE_RADIAL
    recipe (:func:`_process_data_radial`) from the images that posing read, into :func:`radial_transforms`, and check
    it again (``--write-larger-side``); what the check found goes to ``capture_check.json``'s ``radial``. Runs once per
    capture, also on a case checked before this step existed."""
    out = case_dir / "capture_check.json"
    checks = json.loads(out.read_text())
    for cap in layout.captures:
        found = checks[cap.name]
        again = found.get("reposed")
        dataset = dataset_transforms(case_dir, cap.name)
        if "radial" in found or not _stuck(_last_check(found)):
            continue
        last = last_posing(case_dir, cap.name)  # the radial posing itself where an interrupted run wrote it
        if not check_dataset_intrinsics(last).one_focal_length:  # the check's advice is for one focal length
            continue
        without_views = again is not None and again.get("without_views", True)
        images = dataset.parent / REPOSE_FOLDER_NAME if without_views else images_done(case_dir, cap.name).parent
        radial = radial_transforms(case_dir, cap.name)
        if not radial.is_file():
            CONSOLE.print(f"{case_dir.name}: {cap.name} is folded with one focal length and no side to train on; "
                          "posing it once more by the guide's SIMPLE_RADIAL recipe, as the check advises")  # fmt: skip
            shutil.rmtree(radial.parent, ignore_errors=True)  # an interrupted posing's leftovers
            seconds = _process_data_radial(images, radial, matching_method, case_dir / f"colmap_{cap.name}_radial.log")
            _add_time(case_dir, f"colmap {cap.name} radial", seconds)
        if without_views:
            write_text_atomic(radial.parent / SOURCE_FRAMES_NAME, json.dumps(source_frames(images), indent=1) + "\n")
        _check_captures([radial.parent], case_dir / f"check_capture_{cap.name}_radial.log", "--write-larger-side")
        found["radial"] = {**_check_record(radial.parent), "without_views": without_views}
        write_text_atomic(out, json.dumps(checks, indent=2) + "\n")


def _process_data_radial(images: Path, out: Path, matching_method: str, log: Path) -> float:
    """The check's SIMPLE_RADIAL recipe (``capture_check.simple_radial_recipe``, the commands the check prints) on
    ``images`` into ``out``'s folder, with CPU SIFT and no downscaled copies as the benchmark's other posings; its time.
    Each step's output goes to a log beside ``log``."""
    sparse = out.parent / "colmap" / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    steps = simple_radial_recipe(images, out.parent, matching_method, use_gpu=False,
                                 ns_process_data=str(BIN / "ns-process-data"), num_downscales=0)  # fmt: skip
    seconds = sum(_run(cmd, log.with_name(f"{log.stem}_{step}.log")) for step, cmd in steps.items())
    if not out.is_file():
        raise RuntimeError(f"ns-process-data wrote no transforms.json from {sparse / '0'}: COLMAP posed nothing")
    return seconds


def _last_check(found: dict) -> dict:
    """A capture's check record (``capture_check.json``) after its last posing: the SIMPLE_RADIAL one, else the
    re-posing, else the first."""
    return found.get("radial", found.get("reposed", found))


def _stuck(found: dict) -> bool:
    """Whether a check record (``capture_check.json``) found the capture folded with no larger side to train on."""
    return (found["folded"] or found["matches"]["folded"]) and found["larger_side"] is None


def unremedied_captures(case_dir: Path) -> list[str]:
    """The captures :func:`stage_check` found folded (by file order or by COLMAP's matches; after their last posing,
    where the check's advice led to one) with no larger side to train on: a run trained on them cannot be registered
    correctly."""
    checks = json.loads((case_dir / "capture_check.json").read_text())
    return [name for name, found in checks.items() if _stuck(_last_check(found))]


def _check_captures(datasets: list[Path], log: Path, *options: str) -> None:
    cmd = [str(BIN / "ns-nerfuser-check-capture"), *map(str, datasets), *options]
    CONSOLE.print(f"[dim]$ {' '.join(cmd)}[/]")
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode not in (0, 1) or "error:" in log.read_text():
        raise RuntimeError(f"ns-nerfuser-check-capture failed (exit {proc.returncode}), see {log}")


def _check_record(dataset: Path) -> dict:
    larger = dataset / LARGER_SIDE_NAME
    return {**check_dataset(dataset).to_record(), "matches": check_dataset_matches(dataset).to_record(),
            "camera": check_dataset_intrinsics(dataset).to_record(),
            "larger_side": json.loads(larger.read_text())["nerfuser_larger_side"] if larger.is_file() else None}


def stage_train(layout, case_dir: Path, cfg: BenchPractitioner) -> None:
    for cap in layout.captures:
        config = run_config(case_dir, cap.name)
        if config.is_file() and list((config.parent / "nerfstudio_models").glob("step-*.ckpt")):
            continue
        cmd = [str(BIN / "ns-train"), "nerfacto", "--data", str(_training_data(case_dir, cap.name)),
               "--output-dir", str(case_dir / "runs"), "--experiment-name", cap.name, "--timestamp", "bench",
               "--max-num-iterations", str(cfg.max_num_iterations), "--steps-per-save", str(cfg.max_num_iterations),
               *(TRAIN_OPTIONS if cfg.train_preset == "cpu" else STOCK_OPTIONS)]  # fmt: skip
        if cfg.camera_optimizer == "off":
            cmd += ["--pipeline.model.camera-optimizer.mode", "off"]
        seconds = _run(cmd, case_dir / f"train_{cap.name}.log")
        _add_time(case_dir, f"train {cap.name}", seconds)


def stage_register(layout, case_dir: Path) -> None:
    output = case_dir / "registration.json"
    if output.is_file():
        return
    cmd = register_command(layout, case_dir, output)
    log = case_dir / "register.log"
    write_text_atomic(case_dir / "register_commit.txt", library_commit() + "\n")
    start, started_at = time.perf_counter(), time.time()
    try:
        seconds = _run(cmd, log)
    except RuntimeError as e:
        # A refused registration is a result (a failure), not a crash of the benchmark; the refused solution is kept
        # beside it (the work folder's copy is overwritten by later registrations) and scored by score_case.
        CONSOLE.print(f"[red]{case_dir.name}: registration failed[/]: {str(e).splitlines()[-1]}")
        _add_time(case_dir, "register", time.perf_counter() - start)
        rejected = case_dir / "registration_work" / "rejected_registration.json"
        if rejected.is_file() and rejected.stat().st_mtime >= started_at:  # this run's, not an earlier one's
            shutil.copyfile(rejected, rejected_registration(case_dir))
        write_text_atomic(case_dir / "register_failed.txt", str(e) + "\n")
        return
    _add_time(case_dir, "register", seconds)


def stage_fuse(layout, case_dir: Path, gt: list[dict]) -> None:
    """``ns-train nerfuser`` + ``ns-eval`` (cached by eval.json), then ``ns-render dataset`` (cached by its time in
    times.json, into a temporary folder renamed when complete): a stage stopped in either step resumes there."""
    if not (case_dir / "registration.json").is_file():
        return
    if not (case_dir / "eval.json").is_file():
        _fuse_on_test_views(layout, case_dir, "registration.json", sim3.invert_sim3(gt[0]["nerf_to_world"]))
    if "ns-render dataset" in case_times(case_dir):
        return
    renders, partial = case_dir / "renders", case_dir / "renders.partial"
    shutil.rmtree(partial, ignore_errors=True)
    seconds = _run([str(BIN / "ns-render"), "dataset", "--load-config", str(fused_config(case_dir, None)),
                    "--output-path", str(partial), "--split", "test", "--rendered-output-names", "rgb"],
                   case_dir / "render.log")  # fmt: skip
    shutil.rmtree(renders, ignore_errors=True)
    partial.rename(renders)
    _add_time(case_dir, "ns-render dataset", seconds)


def _fuse_on_test_views(
    layout, case_dir: Path, registration_file: str, world_to_ref: np.ndarray, label: str | None = None
) -> None:
    """:func:`_fuse_and_eval` on a spec (``fusion[_<label>].json``) naming the case's runs, ``registration_file`` and
    the world-posed test views mapped into the reference run's frame by ``world_to_ref``."""
    spec = write_fusion_spec(
        case_dir / ("fusion.json" if label is None else f"fusion_{label}.json"),
        [run_config(case_dir, c.name) for c in layout.captures],
        registration=registration_file, test_data="test", test_to_common=world_to_ref,
    )  # fmt: skip
    _fuse_and_eval(case_dir, spec, label)


def _fuse_and_eval(case_dir: Path, spec: Path, label: str | None = None, options: tuple[str, ...] = ()) -> None:
    """``ns-train nerfuser`` on the spec with ``options``, every blend method scored by ``ns-eval`` in one pass into
    ``eval[_<label>].json``; the run lies at :func:`fused_config` (``label`` None: the ``fuse`` stage's)."""
    name = "" if label is None else f"_{label}"
    config = fused_config(case_dir, label)
    seconds = _run([str(BIN / "ns-train"), "nerfuser", "--data", str(spec), "--output-dir",
                    str(config.parents[3]), "--experiment-name", "fused", "--timestamp", "bench",
                    "--pipeline.model.render-all-methods", "True", *options],
                   case_dir / f"fuse{name}_train.log")  # fmt: skip
    suffix = "" if label is None else f" ({label})"
    _add_time(case_dir, f"ns-train nerfuser{suffix}", seconds)
    seconds = _run([str(BIN / "ns-eval"), "--load-config", str(config), "--output-path",
                    str(case_dir / f"eval{name}.json")], case_dir / f"eval{name}.log")  # fmt: skip
    _add_time(case_dir, f"ns-eval{suffix}", seconds)


def stage_appearance(case_dir: Path, matching: bool) -> None:
    """The same fused run with appearance matching (ours) forced on (the ``matched`` stage) or off (``unmatched``),
    scored by ``ns-eval``: every blend method in one pass. Skipped when the ``fuse`` stage's run already had it."""
    if (case_dir / "fusion.json").is_file() and matching not in appearance_evals(case_dir):
        _fuse_and_eval(case_dir, case_dir / "fusion.json", "matched" if matching else "unmatched",
                       ("--pipeline.model.appearance-matching", str(matching)))


def stage_held_out(layout, case_dir: Path) -> None:
    """Each capture's own held-out images (its run's eval split: nerfstudio's default keeps 10% out) as the test
    views, the way a user scores a fused run without ground truth: a fusion spec with ``test_run``, ``ns-train
    nerfuser`` and ``ns-eval`` (every blend method), and nerfstudio's own ``ns-eval`` of that capture's run on the same
    images (its NeRF alone, no registration involved)."""
    if not (case_dir / "registration.json").is_file():
        return
    configs = [run_config(case_dir, c.name) for c in layout.captures]
    for i, cap in enumerate(layout.captures):
        fused_json, own_json = held_out_evals(case_dir, cap.name)
        if not fused_json.is_file():
            spec = write_fusion_spec(case_dir / f"fusion_held_out_{cap.name}.json", configs,
                                     registration="registration.json", test_run=i)  # fmt: skip
            config = held_out_fused_config(case_dir, cap.name)
            seconds = _run([str(BIN / "ns-train"), "nerfuser", "--data", str(spec), "--output-dir",
                            str(config.parents[3]), "--experiment-name", "fused", "--timestamp", cap.name,
                            "--pipeline.model.render-all-methods", "True"],
                           case_dir / f"fuse_held_out_{cap.name}_train.log")  # fmt: skip
            _add_time(case_dir, f"ns-train nerfuser (held-out {cap.name})", seconds)
            seconds = _run([str(BIN / "ns-eval"), "--load-config", str(config), "--output-path", str(fused_json)],
                           case_dir / f"eval_held_out_{cap.name}.log")  # fmt: skip
            _add_time(case_dir, f"ns-eval (held-out {cap.name})", seconds)
        if not own_json.is_file():
            seconds = _run([str(BIN / "ns-eval"), "--load-config", str(configs[i]), "--output-path", str(own_json)],
                           case_dir / f"eval_own_{cap.name}.log")  # fmt: skip
            _add_time(case_dir, f"ns-eval of the run (held-out {cap.name})", seconds)


def stage_content(layout, case_dir: Path, gt: list[dict]) -> None:
    """Where each run's trained content lies against the stored truth: the run registered (every default) to the
    ground-truth scene placed in the run's NeRF frame by that truth. The SIM(3) found is the identity where the truth
    holds for the content; what it finds beyond the identity bounds what a NeRF-to-NeRF registration can reach against
    that truth (within this registration's own error on a NeRF beside an exact renderer)."""
    output = case_dir / "content_truth.json"
    if output.is_file():
        return
    results = {}
    for cap, g in zip(layout.captures, gt, strict=True):
        nerf = NerfstudioRenderer(run_config(case_dir, cap.name), name=cap.name)
        truth = SceneFrameRenderer(layout.scene, g["nerf_to_world"], "ground truth", nerf.training_poses())
        start = time.perf_counter()
        # the registration's work folder: the run's renders at its training poses are reused from there
        try:
            record, refused = registration.register([nerf, truth], RegistrationConfig(), case_dir / "registration_work",
                                                    CONSOLE).to_record(), None  # fmt: skip
        except RegistrationFailed as failed:  # a blurry run can fail the NCC check beside the exact scene itself
            record, refused = failed.result.to_record(), str(failed)
            CONSOLE.print(f"{case_dir.name} {cap.name}: the run-to-scene registration was refused ({refused}); its "
                          "solution is kept as the content truth, marked refused")  # fmt: skip
        T = np.asarray(record["nerfs"][1]["T_to_reference"])  # the truth's frame -> the content's (NeRF) frame
        e = sim3.sim3_errors(T, np.eye(4))
        results[cap.name] = {"truth_to_content": T.tolist(), "r_deg": float(e.r_err_deg), "t": float(e.t_err),
                             "s": float(e.s_err), "source": record.get("sampling_choice", {}).get("source"),
                             "seconds": round(time.perf_counter() - start, 1), "refused": refused}  # fmt: skip
        CONSOLE.print(f"{case_dir.name} {cap.name}: content vs stored truth r {e.r_err_deg:.4f} deg, t {e.t_err:.5f}, "
                      f"s {e.s_err:.5f}")
    write_text_atomic(output, json.dumps(results, indent=2) + "\n")


def content_ground_truth(case_dir: Path, gt: list[dict]) -> list[np.ndarray] | None:
    """Each capture's content frame in the world (:func:`stage_content`): its stored truth moved by what the
    run-to-scene registration found; None before that stage."""
    path = case_dir / "content_truth.json"
    found = json.loads(path.read_text()) if path.is_file() else {}
    if not all(g["capture"] in found for g in gt):
        return None
    return [sim3.compose(g["nerf_to_world"], sim3.invert_sim3(np.asarray(found[g["capture"]]["truth_to_content"])))
            for g in gt]  # fmt: skip


def stage_truth(layout, case_dir: Path, gt: list[dict]) -> None:
    """What the registration's error costs the blend: the fused run made again with the registration's transforms
    replaced by a truth's (every other field of the registration, colour maps among them, as registered), scored on
    the same test views (:data:`TRUTH_BLENDS`). Against the stored truth, the test views placed as the ``fuse`` stage
    places them; after the ``content`` stage also against the content's frames, with the test views placed by the
    reference run's content frame, blended with the true and with the estimated transforms."""
    reg_path = case_dir / "registration.json"
    if not reg_path.is_file():
        return
    ref = read_registration(reg_path)["reference"]["index"]
    truths = {"stored": [g["nerf_to_world"] for g in gt], "content": content_ground_truth(case_dir, gt)}
    for label, (placement, transforms) in TRUTH_BLENDS.items():
        to_world = truths[placement]
        if to_world is None or truth_evals(case_dir)[label].is_file():
            continue
        world_to_ref = sim3.invert_sim3(to_world[ref])
        registration_file = "registration.json"
        if transforms != "estimated":
            truth = [sim3.compose(world_to_ref, T) for T in truths[transforms]]
            registration_file = registration_with_transforms(reg_path, truth, f"registration_{label}.json").name
        _fuse_on_test_views(layout, case_dir, registration_file, world_to_ref, label)


def direct_label(case_dir: Path) -> str | None:
    """The ``direct`` stage's label: the direct alignment set the other way from the ``register`` stage's record
    (``direct_on`` when that one ran without it), None before that stage."""
    reg_path = case_dir / "registration.json"
    if not reg_path.is_file():
        return None
    was = read_registration(reg_path)["settings"].get("direct", {}).get("enabled", False)
    return "direct_off" if was else "direct_on"


def stage_direct(layout, case_dir: Path, gt: list[dict]) -> None:
    """The direct alignment (ours, ``--direct.enabled``) against the registration without it: ``ns-nerfuser-register``
    again with that one option set the other way from the ``register`` stage's (renders and SfM reused from its work
    folder), then the fused run with it, scored by ``ns-eval`` on the test views the ``fuse`` stage places (stored
    truth) and, after the ``content`` stage, on those the content frames place (as the ``truth`` stage does)."""
    label = direct_label(case_dir)
    if label is None:
        return
    output = case_dir / f"registration_{label}.json"
    if not output.is_file():
        cmd = register_command(layout, case_dir, output, "--work-dir", str(case_dir / "registration_work"),
                               "--direct.enabled" if label == "direct_on" else "--direct.no-enabled")  # fmt: skip
        _add_time(case_dir, f"register ({label})", _run(cmd, case_dir / f"register_{label}.log"))
    ref = read_registration(output)["reference"]["index"]
    for placement, to_world in (("stored", [g["nerf_to_world"] for g in gt]),
                                ("content", content_ground_truth(case_dir, gt))):  # fmt: skip
        name = label if placement == "stored" else f"content_{label}"
        if to_world is None or (case_dir / f"eval_{name}.json").is_file():
            continue
        _fuse_on_test_views(layout, case_dir, output.name, sim3.invert_sim3(to_world[ref]), name)


COST_METHODS = ("idw-sample", "coverage", "coverage-3d")


def stage_cost(layout, case_dir: Path) -> None:
    """Render cost of the fused model per method, on random rays of the reference run's training cameras (the common
    frame is the reference NeRF's), with the estimated registration and the tool's default gamma / tau."""
    output = case_dir / "cost.json"
    if output.is_file() or not (case_dir / "registration.json").is_file():
        return
    reg = read_registration(case_dir / "registration.json")
    stored = list(iter_registered_nerfs(case_dir / "registration.json"))
    models = [(n["name"], runs.load_run(n["config"]).model) for n in reg["nerfs"]]
    cameras = runs.training_cameras(reg["nerfs"][reg["reference"]["index"]]["config"])
    costs = {}
    for method in COST_METHODS:
        cost = evaluation.measure_render_cost(models, [n["T_to_reference"] for n in reg["nerfs"]], cameras,
                                              method=method, nerf_cameras=[n.training_cameras for n in stored])
        costs[method] = cost.as_dict()
        CONSOLE.print(f"{case_dir.name} {method}: fused / sub-models on the queried rays {cost.ratio_used:.3f}")
    write_text_atomic(output, json.dumps(costs, indent=2) + "\n")


def _errors(reg: dict, gt: list[dict], truth: str) -> list[dict]:
    """r/t/s errors of every registered NeRF against the true map ``truth`` (a key of :func:`capture_ground_truth`)."""
    ref = reg["reference"]["index"]
    errors = []
    for i, n in enumerate(reg["nerfs"]):
        if i == ref:
            continue
        T_true = sim3.compose(sim3.invert_sim3(gt[ref][truth]), gt[i][truth])
        e = sim3.sim3_errors(np.asarray(n["T_to_reference"]), T_true)
        errors.append({"nerf": n["name"], "r_err_deg": float(e.r_err_deg), "t_err": float(e.t_err),
                       "s_err": float(e.s_err), "failure": bool(e.is_failure())})
    return errors


def _attempts(choice: dict | None, ref: int, gt: list[dict]) -> list[dict]:
    """The pose sources tried before the recorded one (``sampling_choice.tried_before``), each refused solution scored
    against the stored truth (``errors``; None where the attempt left no solution), its transforms left out."""
    out = []
    for attempt in (choice or {}).get("tried_before", []):
        entry = {k: v for k, v in attempt.items() if k != "refused_transforms"}
        transforms = attempt.get("refused_transforms")
        entry["errors"] = None if transforms is None else _errors(
            {"reference": {"index": ref}, "nerfs": [{"name": n.get("capture"), "T_to_reference": T}
                                                    for n, T in zip(gt, transforms, strict=True)]}, gt, "nerf_to_world")
        out.append(entry)
    return out


def stopped_record(layout, case_dir: Path, spec: str, stuck: list[str]) -> dict:
    """The record of a case the capture check stopped before training (``stuck``: :func:`unremedied_captures`): a
    failure of the guide's path, scored as a refused registration, with what COLMAP made of each capture (the
    dataset the run would have trained on); no registration or blend exists to score."""
    record: dict = {"case": case_dir.name, "spec": spec, "case_dir": str(case_dir),
                    "captures": [colmap_tie(cap, case_dir)[0] for cap in layout.captures],
                    "registration": {"errors": None, "stopped": f"ns-nerfuser-check-capture found {', '.join(stuck)} "
                                     "folded with no remedy it can apply; the guide's path stops before training"}}
    record.update(_provenance(case_dir, "check_commit.txt"))  # the library that checked: nothing was registered
    return record


def _provenance(case_dir: Path, commit_file: str = "register_commit.txt") -> dict:
    """What every record says of how its case ran: the time of each step, the library that registered it (named in
    ``commit_file``), shared inputs, COLMAP's matching and camera, and what the capture check found."""
    commit = case_dir / commit_file
    check = case_dir / "capture_check.json"
    return {"times_s": case_times(case_dir),
            "registered_at_commit": commit.read_text().strip() if commit.is_file() else None,
            "captures_from": captures_from(case_dir), "colmap_matching": colmap_matching(case_dir),
            "colmap_camera": colmap_camera(case_dir),
            "capture_check": json.loads(check.read_text()) if check.is_file() else None}  # fmt: skip


def score_case(layout, case_dir: Path, spec: str, gt: list[dict]) -> dict:
    """The case's record for the reports; ``gt``: :func:`capture_ground_truth` of the case."""
    captures = [{k: v for k, v in g.items() if not k.startswith("nerf_to_world")} for g in gt]
    record: dict = {"case": case_dir.name, "spec": spec, "captures": captures, "case_dir": str(case_dir)}
    reg_path = case_dir / "registration.json"
    solution = None  # the registration, or the solution the checks refused, scored against the content frames below
    if reg_path.is_file():
        reg = solution = read_registration(reg_path)
        record["registration"] = {"errors": _errors(reg, gt, "nerf_to_world"),
                                  "sampling_choice": reg.get("sampling_choice"), "timings_s": reg.get("timings_s"),
                                  "attempts": _attempts(reg.get("sampling_choice"), reg["reference"]["index"], gt),
                                  "direct_pairs": (reg.get("direct") or {}).get("pairs")}
        if all("nerf_to_world_optimized" in g for g in gt):
            record["registration"]["errors_optimized"] = _errors(reg, gt, "nerf_to_world_optimized")
        record["registration"]["errors_pose"] = _errors(reg, gt, "nerf_to_world_pose")
    else:
        record["registration"] = {"errors": None, "refused": (case_dir / "register_failed.txt").is_file()}
        rejected = rejected_registration(case_dir)
        if rejected.is_file():  # the solution the checks refused, against the same truth
            rej = solution = read_registration(rejected)
            record["registration"].update(rejected_errors=_errors(rej, gt, "nerf_to_world"),
                                          rejected_mode=rej["settings"]["mode"],
                                          sampling_choice=rej.get("sampling_choice"),
                                          attempts=_attempts(rej.get("sampling_choice"), rej["reference"]["index"], gt))
    eval_json = case_dir / "eval.json"
    if eval_json.is_file():
        record["fused_appearance_matching"] = fused_appearance_matching(case_dir)
        record.update(blend_table(eval_json))
        if reg_path.is_file():
            record["auto_blend"] = auto_blend_choice(reg_path)
    content = case_dir / "content_truth.json"
    if content.is_file():
        found = json.loads(content.read_text())
        record["content_truth"] = {k: {m: v.get(m) for m in ("r_deg", "t", "s", "source", "seconds", "refused")}
                                   for k, v in found.items()}  # fmt: skip
        content_to_world = content_ground_truth(case_dir, gt)
        if content_to_world is not None:
            for g, T in zip(gt, content_to_world, strict=True):
                g["nerf_to_world_content"] = T
            if solution is not None:
                key = "errors_content" if reg_path.is_file() else "rejected_errors_content"
                record["registration"][key] = _errors(solution, gt, "nerf_to_world_content")
    truth_blends = {label: blend_table(path) for label, path in truth_evals(case_dir).items() if path.is_file()}
    if truth_blends:
        record["truth_blends"] = truth_blends
    label = direct_label(case_dir)
    if label is not None and (case_dir / f"registration_{label}.json").is_file():
        other = read_registration(case_dir / f"registration_{label}.json")
        truths = [t for t in ("nerf_to_world", "nerf_to_world_optimized", "nerf_to_world_content")
                  if all(t in g for g in gt)]  # fmt: skip
        record["direct"] = {"label": label, "errors": {t: _errors(other, gt, t) for t in truths},
                            "pairs": (other.get("direct") or {}).get("pairs"), "timings_s": other.get("timings_s"),
                            "blends": {placement: blend_table(path) for placement, path in
                                       (("stored", case_dir / f"eval_{label}.json"),
                                        ("content", case_dir / f"eval_content_{label}.json")) if path.is_file()}}
    held_out = {}
    for cap in layout.captures:
        fused_json, own_json = held_out_evals(case_dir, cap.name)
        if fused_json.is_file() and own_json.is_file():
            fused, own = (json.loads(f.read_text())["results"] for f in (fused_json, own_json))
            held_out[cap.name] = {
                "views": len(runs.run_views(run_config(case_dir, cap.name), "test").image_filenames),
                **{f"blend_{m}": {k: fused.get(f"{m}_{k}") for k, _ in BLEND_COLUMNS} for m in ("psnr", "ssim")},
                **{f"own_{m}": own[m] for m in ("psnr", "ssim")},
            }
    if held_out:
        record["held_out"] = held_out
    cost = case_dir / "cost.json"
    if cost.is_file():
        record["cost"] = {m: {k: c[k] for k in ("ratio", "ratio_used", "fused_s", "sub_used_s", "used_rays")}
                          for m, c in json.loads(cost.read_text()).items()}  # fmt: skip
    record.update(_provenance(case_dir))
    return record


def _short(name: str) -> str:
    """A run's experiment name (``.../<experiment>/<method>/<timestamp>/config.yml``), or the name as given."""
    path = Path(name)
    return path.parents[2].name if path.name == "config.yml" and len(path.parents) > 3 else name


def _blend_header(*lead: str) -> list[str]:
    """A blend table's header and separator rows: the ``lead`` columns, then one per method (:data:`BLEND_COLUMNS`)."""
    names = [*lead, *(n for _, n in BLEND_COLUMNS)]
    return ["| " + " | ".join(names) + " |", "|" + " --- |" * len(names)]


def _psnr_cells(b: dict) -> str:
    """One blend table's PSNR cells, in :data:`BLEND_COLUMNS` order ("-" for a method not scored)."""
    return " | ".join("-" if b[k] is None else f"{b[k]:.2f}" for k, _ in BLEND_COLUMNS)


def _posed_cell(c: dict) -> str:
    """``posed/views``, with the misposed views (more than 5 deg off the pose tie) and the views the run trained on
    where they are recorded and differ from the posed ones."""
    cell = f"{c['posed_by_colmap']}/{c['views']}"
    extra = [f"{c['pose_tie_misposed_views']} misposed"] if c.get("pose_tie_misposed_views") else []
    for label, how in (("reposed", "posed again as the check advised"),
                       ("radial", "posed by the SIMPLE_RADIAL recipe")):  # fmt: skip
        if f"{label}_posed_by_colmap" in c:
            extra.append(f"{how}: {c[f'{label}_posed_by_colmap']} posed, {c[f'{label}_misposed_views']} misposed")
    if c.get("trained_views", c["posed_by_colmap"]) != c["posed_by_colmap"]:
        extra.append(f"trained on {c['trained_views']}")
    return cell + (f" ({'; '.join(extra)})" if extra else "")


def _capture_check_cell(c: dict, stopped: bool = False) -> str:
    """What ``ns-nerfuser-check-capture --write-larger-side`` found for one capture (``capture_check.json``; records
    before the match check was recorded there carry the file order's verdict alone), and how it was posed again;
    ``stopped``: the case stopped before training (:func:`stopped_record`), as it does since the path stops at a fold
    it cannot remedy (earlier records trained on every view of such a capture)."""
    camera = c.get("camera")  # records of before the camera was recorded here: not said
    drift = ("" if camera is None else f"; camera drifted (fy/fx {camera['aspect']:.3f})" if camera["drifted"]
             else f"; camera fy/fx {camera['aspect']:.3f}")  # fmt: skip
    reposed = "reposed" in c  # then trained on what it was posed again into, not on this dataset
    side = c.get("larger_side")
    if side is not None:
        dropped = f"folded (by the {side.get('found_by', 'file order')}), {len(side['dropped'])} of {c['num_views']}"
        return (f"{dropped} views on its smaller side{drift}{_reposed_cell(c)}" if reposed
                else f"{dropped} views dropped, trained on the larger side{drift}")  # fmt: skip
    # records of before the match check: the stage wrote the larger side of every capture the file order folded
    trained = ", trained on the larger side" if "larger_side" not in c else ""
    order = ("not checked by file order (no sequence)" if not c["checked"] else
             f"folded by file order, {c['suspect_views']} of {c['num_views']} views suspect{trained}" if c["folded"]
             else "not folded by file order")  # fmt: skip
    matches = c.get("matches")
    if not matches or not matches["checked"]:
        return order + drift + _reposed_cell(c)
    if matches.get("repose_without") and reposed:
        verdict = f"; the match check named {', '.join(matches['repose_without'])} in every unexplained pair"
    elif matches["folded"]:
        trained = "the guide's path stops here" if stopped else "trained on every view"
        verdict = "; folded by the match check, no sides" + ("" if reposed else f" to train on: {trained}")
    else:
        verdict = "; the match check found it consistent"
    return order + verdict + drift + _reposed_cell(c)


def _reposed_cell(c: dict) -> str:
    """How a checked capture was posed again (``capture_check.json``'s ``reposed``) and once more by the SIMPLE_RADIAL
    recipe (its ``radial``), and what the check said of each."""
    again = c.get("reposed")
    if again is None:
        return _radial_cell(c)
    how = ["without those views"] if again.get("without_views", True) else []
    if again.get("for_drift", False):
        how.append("with one focal length (--camera-type simple_pinhole)")
    return f": posed again {' and '.join(how)}, then {_verdict_cell(again)}" + _radial_cell(c)


def _radial_cell(c: dict) -> str:
    """How a capture folded with one focal length was posed once more (``capture_check.json``'s ``radial``)."""
    again = c.get("radial")
    return "" if again is None else f"; posed once more by the SIMPLE_RADIAL recipe, then {_verdict_cell(again)}"


def _verdict_cell(found: dict) -> str:
    """What the match check said of a posing the check's advice led to, and the larger side trained on if any."""
    m = found["matches"]
    verdict = ("folded again" if m["folded"] else "consistent") if m["checked"] else "not checked"
    side = found.get("larger_side")
    trained = "" if side is None else f", {len(side['dropped'])} views dropped, trained on the larger side"
    return f"{verdict} by the match check ({m['unexplained_pairs']} of {m['pairs']} pairs unexplained){trained}"


def write_report(records: list[dict], path: Path, cfg: BenchPractitioner) -> None:
    training = (f"{cfg.max_num_iterations} steps with CPU-sized options ({' '.join(TRAIN_OPTIONS)})"
                if cfg.train_preset == "cpu" else
                f"{cfg.max_num_iterations} steps on a GPU with every other option at nerfacto's default "
                f"({' '.join(STOCK_OPTIONS)})")  # fmt: skip
    if cfg.camera_optimizer == "off":
        training += " and the camera optimiser off (`--pipeline.model.camera-optimizer.mode off`: a diagnostic)"
    where = "a 2-core CPU" if cfg.train_preset == "cpu" else "one H100 GPU with 16 CPU cores"
    lines = ["# The practitioner's path: images in, registration and blend out (defaults only)", "",
             "Command: `python scripts/bench_practitioner.py " + " ".join(["--cases", *(r["spec"] for r in records),
                                                             *case_options(cfg)])
             + "` (every stage cached per case; this "
             "file collected by `python scripts/bench_practitioner.py " + " ".join(sys.argv[1:]) + "`). Times are "
             f"wall-clock on {where}, where other jobs (tests, other trainings) often ran beside: compare them "
             "within a case, not across cases.", "",
             "Protocol: images in; each capture posed on its own by `ns-process-data images` (Debian's COLMAP 3.8, "
             "CPU SIFT, exhaustive matching), stock `ns-train nerfacto` for "
             f"{training}, then "
             "`ns-nerfuser-register --configs A B --output registration.json` and nothing else. Every threshold and "
             "default (the automatic pose source, the render camera, SfM thresholds, the self-check's NCC 0.4) was "
             "fixed before the first run on these scenes; nothing was tuned on them. Ground truth: each capture's "
             "stored (COLMAP) frame tied to the world by a SIM(3) fitted to the true centres of the views COLMAP "
             "posed, composed with the run's dataparser transform (applied_transform included). COLMAP's own pose "
             "noise (the same fit's residuals) is reported beside the errors: it bounds what any registration of "
             "these runs can reach; so does its bend (the rotation between the ties of the first and the second half "
             "of a capture's views, 0 where one SIM(3) fits the whole reconstruction). Test views: the scene's "
             "world-posed test capture, mapped into the reference "
             "NeRF's frame by the ground truth; the blend uses the estimated registration.", ""]  # fmt: skip
    if cfg.note:
        lines += [cfg.note, ""]
    shared = [(r["case"], r["captures_from"], r.get("colmap_matching", "exhaustive"),
               r.get("colmap_camera", "perspective")) for r in records if r.get("captures_from")]  # fmt: skip
    if shared:
        lines += ["Shared inputs: " + "; ".join(
            f"{c} uses the images, COLMAP datasets and test views of `{src}` (the same case trained otherwise, copied "
            "before its first stage), so the pair differs in training alone" if (m, k) == ("exhaustive", "perspective")
            else f"{c} uses the images and test views of `{src}` (copied before its first stage) and its own COLMAP "
            f"datasets ({m} matching, ns-process-data --camera-type {k}), so the pair differs from COLMAP on"
            for c, src, m, k in shared) + ".", ""]
    for r in records:
        if r.get("capture_check"):
            stopped = bool(r["registration"].get("stopped"))
            parts = [f"{cap}: {_capture_check_cell(c, stopped)}" for cap, c in r["capture_check"].items()]
            repose = " --write-images-to-repose" if any("reposed" in c for c in r["capture_check"].values()) else ""
            lines += [f"Capture check of {r['case']} (`ns-nerfuser-check-capture --write-larger-side{repose}` before "
                      f"training): {'; '.join(parts)}.", ""]  # fmt: skip
    for r in records:
        checked = [c for c in r["captures"] if "match_check_folded" in c]
        if checked:
            parts = [f"{c['capture']}: {'folded' if c['match_check_folded'] else 'consistent'} "
                     f"({100 * c['match_check_unexplained_share']:.1f}% of {c['match_check_pairs']} verified pairs "
                     "unexplained)" for c in checked]  # fmt: skip
            lines += [f"Match check of {r['case']} (COLMAP's verified matches against its reconstruction, as "
                      f"`ns-nerfuser-check-capture` runs it): {'; '.join(parts)}.", ""]  # fmt: skip
    lines += ["## Registration (every default of `ns-nerfuser-register`)", "",
              "| case | NeRF | r_err (deg) | t_err | s_err | ok | COLMAP rot err (deg, median per capture) | "
              "COLMAP centre err (median, / capture radius) | COLMAP bend (deg) | posed / views |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for r in records:
        colmap = r["captures"]
        # COLMAP's vertical over horizontal focal length, where the record has it (records before it did not)
        ratio = "" if "colmap_focal_ratio" not in colmap[0] else " (fy/fx " + ", ".join(
            f"{c['colmap_focal_ratio']:.3f}" for c in colmap) + ")"  # fmt: skip
        col = ", ".join(f"{c['colmap_rot_err_deg_median']:.3f}" for c in colmap) + ratio
        cen = ", ".join(f"{c['colmap_centre_err_median']:.4f}" for c in colmap)
        posed = ", ".join(_posed_cell(c) for c in colmap)
        bend = ", ".join(f"{c['colmap_bend_deg']:.2f}" for c in colmap)
        errs = r["registration"]["errors"]
        if errs is None:
            lines.append(f"| {r['case']} | - | {unregistered_verdict(r['registration'])} | | | FAIL | {col} | {cen} | "
                         f"{bend} | {posed} |")  # fmt: skip
            for e in r["registration"].get("rejected_errors") or []:
                lines.append(f"| {r['case']} (the refused solution, mode {r['registration']['rejected_mode']}) | "
                             f"{_short(e['nerf'])} | {e['r_err_deg']:.4f} | {e['t_err']:.5f} | {e['s_err']:.5f} | "
                             f"refused | {col} | {cen} | {bend} | {posed} |")  # fmt: skip
            continue
        for e in errs:
            lines.append(f"| {r['case']} | {_short(e['nerf'])} | {e['r_err_deg']:.4f} | {e['t_err']:.5f} | "
                         f"{e['s_err']:.5f} | {'FAIL' if e['failure'] else 'ok'} | {col} | {cen} | {bend} | {posed} |")
    for truth in OTHER_TRUTHS:
        lines += _other_truth_section(records, *truth)
    lines += _content_section(records)
    lines += ["", "## Blending (PSNR from `ns-eval`'s JSON, estimated registration, world-posed test views)", "",
              "The fused model's defaults when the case ran: appearance matching (ours) off, unless the case is "
              "marked *matched*.", "",
              *_blend_header("case")]
    for r in records:
        b = r.get("blend_psnr")
        if b:
            mark = " *matched*" if r.get("fused_appearance_matching") else ""
            lines.append(f"| {r['case']}{mark} | {_psnr_cells(b)} |")
    chosen = [r for r in records if r.get("auto_blend") and r.get("blend_psnr")]
    if chosen:
        lines += ["", "The blend method `auto` (ours, the default of `ns-train nerfuser` and the viewer) renders with, "
                  "from the registration file's training cameras:", ""]
        for r in chosen:
            score = with_auto(r)["blend_psnr"]["auto"]
            psnr = "-" if score is None else f"{score:.2f}"
            lines.append(f"- {r['case']}: {r['auto_blend']['reason']}; PSNR {psnr}")
    lines += _truth_blend_section(records)
    lines += _direct_section(records)
    lines += _held_out_section(records)
    lines += ["", "## Time of every step (s)", ""]
    for r in records:
        lines.append(f"- {r['case']} (registered with the code of {r.get('registered_at_commit')}): "
                     + ", ".join(f"{k} {v:.0f}" for k, v in r["times_s"].items()))  # fmt: skip
    lines += ["", "## What the automatic choice did", ""]
    for r in records:
        choice = r["registration"].get("sampling_choice") or {}
        # records scored before attempts were: as the registration recorded them (no solutions kept then)
        attempts = r["registration"].get("attempts") or choice.get("tried_before", [])
        if r["registration"].get("stopped"):
            lines.append(f"- {r['case']}: nothing registered ({r['registration']['stopped']})")
            continue
        lines.append(f"- {r['case']}: {choice.get('source', '-')} ({choice.get('reason', 'no registration')}); "
                     f"tried before: {[{k: v for k, v in a.items() if k != 'errors'} for a in attempts]}")
        for a in attempts:
            for e in a.get("errors") or []:
                lines.append(f"  - refused {a['source']} / {a['mode']}: {e['nerf']} r_err {e['r_err_deg']:.3f} deg, "
                             f"t_err {e['t_err']:.4f}, s_err {e['s_err']:.4f} "
                             f"({'a failure' if e['failure'] else 'a success'} by the paper's rule)")
    summary = summarise(records)
    lines += ["", "Targets (defaults only): " + "; ".join(f"{t}: {'met' if ok else 'NOT met'}"
                                                       for t, ok in summary.targets()) + ".",
              "", summary.line(), ""]  # fmt: skip
    write_text_atomic(path, "\n".join(lines))
    write_text_atomic(path.with_suffix(".json"), json.dumps(records, indent=2) + "\n")


def _other_truth_section(records: list[dict], key: str, name: str, text: str,
                         residuals: list[tuple[str, str, int]]) -> list[str]:  # fmt: skip
    """The registration table again, against another truth (errors under ``key``), with that truth's fit residuals
    per capture (``residuals``: column header, capture record key, decimals)."""
    rows = [r for r in records if r["registration"].get(key)]
    if not rows:
        return []
    lines = ["", f"### The same registrations against the {name} truth", "", text, "",
             "| case | NeRF | r_err (deg) | t_err | s_err | ok | " + " | ".join(h for h, _, _ in residuals) + " |",
             "|" + " --- |" * (6 + len(residuals))]  # fmt: skip
    for r in rows:
        fits = " | ".join(", ".join(f"{c[k]:.{d}f}" for c in r["captures"]) for _, k, d in residuals)
        for e in r["registration"][key]:
            lines.append(f"| {r['case']} | {_short(e['nerf'])} | {e['r_err_deg']:.4f} | {e['t_err']:.5f} | "
                         f"{e['s_err']:.5f} | {'FAIL' if e['failure'] else 'ok'} | {fits} |")
    lines += ["", summarise(records, key).line(f"Against the {name} truth, ")]
    return lines


OTHER_TRUTHS = [
    ("errors_optimized", "camera-optimised",
     "nerfacto's camera optimiser (on by default) moves the training cameras away from their stored COLMAP "
     "poses, and the trained content may follow them. Here each "
     "run's NeRF frame is tied to the world by a SIM(3) fitted to its optimised training poses (the "
     "checkpoint's `camera_optimizer.pose_adjustment` applied as nerfstudio applies it) instead of its stored "
     "ones; the residual columns are that fit's, beside the stored fit's (COLMAP's noise) above.",
     [("optimised rot err (deg, median per capture)", "optimized_rot_err_deg_median", 3),
      ("optimised centre err (median, / capture radius)", "optimized_centre_err_median", 4)]),
    ("errors_pose", "pose",
     "The stored truth ties each capture to the world by its camera centres alone; where those lie near a "
     "line (a drive: the second and third singular values of the centres 1-4% of the first) the roll about "
     "it is loosely fixed. Here each capture is tied by its views' rotations as well (rotation averaged "
     "over the views, then translation; `sim3.estimate_sim3_from_poses`). Added after the drive results "
     "were seen, as a diagnostic: no method or default follows from it. The residual column is that fit's "
     "(COLMAP's rotation noise per view).",
     [("pose fit rot err (deg, median per capture)", "pose_tie_rot_err_deg_median", 3)]),
]  # fmt: skip
"""The truths the registration table is repeated against (:func:`_other_truth_section`'s arguments after the records):
the record key of the errors, the truth's name, what it is, and its fit's residual columns."""


def _content_section(records: list[dict]) -> list[str]:
    """The runs' content against the stored truth (:func:`stage_content`), and the registration against the content."""
    rows = [r for r in records if r.get("content_truth")]
    if not rows:
        return []
    lines = ["", "### Where the trained content lies against the stored truth (`--stages content`)", "",
             "Each run registered (every default) to the ground-truth scene placed in its NeRF frame by the stored "
             "truth: the SIM(3) found would be the identity if that truth held for the trained content. It carries "
             "the registration's own error on a NeRF beside an exact renderer. *refused*: its self-check refused "
             "that run-to-scene registration (the run renders too differently from the exact scene for the NCC "
             "threshold); its solution is used all the same.", "",
             "| case | run | r (deg) | t | s | pose source | seconds | self-check |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        for name, c in r["content_truth"].items():
            lines.append(f"| {r['case']} | {name} | {c['r_deg']:.4f} | {c['t']:.5f} | {c['s']:.5f} | {c['source']} | "
                         f"{c['seconds']:.0f} | {'refused' if c.get('refused') else 'passed'} |")
    lines.append("")
    for r in rows:
        for e in r["registration"].get("errors_content") or []:
            lines.append(f"- {r['case']}, {_short(e['nerf'])}, the registration against the content's frames (each "
                         f"run's stored truth moved by the SIM(3) above): r_err {e['r_err_deg']:.4f} deg, t_err "
                         f"{e['t_err']:.5f}, s_err {e['s_err']:.5f}")
        for e in r["registration"].get("rejected_errors_content") or []:
            lines.append(f"- {r['case']}, {_short(e['nerf'])}, the refused solution against the content's frames: "
                         f"r_err {e['r_err_deg']:.4f} deg, t_err {e['t_err']:.5f}, s_err {e['s_err']:.5f} "
                         f"({'a failure' if e['failure'] else 'a success'} by the paper's rule)")
    return lines


def _truth_blend_section(records: list[dict]) -> list[str]:
    """The blend with the estimated and with the true transforms on the same test views (:func:`stage_truth`)."""
    rows = [r for r in records if r.get("truth_blends") and r.get("blend_psnr")]
    if not rows:
        return []
    lines = ["", "### The blend with the true transforms (`--stages truth`)", "",
             "The fused run made again with the registration's transforms replaced by a truth's (colour maps and "
             "everything else as registered), scored by `ns-eval` on the same world-posed test views, placed in the "
             "reference NeRF's frame by that truth: what the registration's error costs the blend. *Content*: the "
             "runs' content frames (`--stages content`).", "",
             *_blend_header("case", "test views placed by", "transforms")]
    notes = []
    for r in rows:
        tables = {("stored", "estimated"): r["blend_psnr"]}
        tables.update({TRUTH_BLENDS[label]: t["blend_psnr"] for label, t in r["truth_blends"].items()})
        for (placement, transforms), b in tables.items():
            blended = transforms if transforms == "estimated" else f"{transforms} truth"
            lines.append(f"| {r['case']} | {placement} truth | {blended} | {_psnr_cells(b)} |")
        for placement in ("stored", "content"):
            est, true = tables.get((placement, "estimated")), tables.get((placement, placement))
            if est and true:
                d_sample, d_nearest = est["idw_sample"] - true["idw_sample"], est["nearest"] - true["nearest"]
                notes.append(f"- {r['case']}, test views placed by the {placement} truth: estimated transforms "
                             f"minus true ones, IDW-Sample {d_sample:+.2f} dB, Nearest {d_nearest:+.2f} dB")
    return lines + ["", "PSNR (dB) from `ns-eval`'s JSON.", "", *notes]


def _direct_section(records: list[dict]) -> list[str]:
    """The registration and the blend with the direct alignment set either way (:func:`stage_direct`)."""
    rows = [r for r in records if r.get("direct") and r.get("registration", {}).get("errors")]
    if not rows:
        return []
    lines = ["", "### Direct alignment (`--stages direct`: `--direct.enabled`, ours)", "",
             "The registration again with the direct photometric alignment set the other way from the `register` "
             "stage's (renders and SfM reused), errors of the non-reference NeRF against each truth, and the fused "
             "run with it scored by `ns-eval` on the same test views (IDW-Sample / Nearest PSNR, dB).", "",
             "| case | direct | r / t / s vs stored truth | vs camera-optimised | vs content | IDW-Sample / Nearest "
             "(stored) | (content) |", "|" + " --- |" * 7]  # fmt: skip
    keys = ("nerf_to_world", "nerf_to_world_optimized", "nerf_to_world_content")
    for r in rows:
        d = r["direct"]
        own = {"nerf_to_world": r["registration"]["errors"],
               "nerf_to_world_optimized": r["registration"].get("errors_optimized"),
               "nerf_to_world_content": r["registration"].get("errors_content")}
        own_blends = {"stored": {"blend_psnr": r.get("blend_psnr")},
                      "content": r.get("truth_blends", {}).get("content_estimated")}
        own_pairs = r["registration"].get("direct_pairs")
        for setting, errors, blends, pairs in (
                ("off" if d["label"] == "direct_on" else "on", own, own_blends, own_pairs),
                ("on" if d["label"] == "direct_on" else "off", d["errors"], d["blends"], d.get("pairs"))):
            cells = []
            for k in keys:
                e = (errors.get(k) or [None])[0]
                cells.append("-" if e is None else f"{e['r_err_deg']:.3f} / {e['t_err']:.4f} / {e['s_err']:.4f}")
            for placement in ("stored", "content"):
                b = (blends.get(placement) or {}).get("blend_psnr")
                cells.append("-" if not b else f"{b['idw_sample']:.2f} / {b['nearest']:.2f}")
            lines.append(f"| {r['case']} | {setting} | " + " | ".join(cells) + " |")
            for p in pairs or []:  # the direct alignment's own account, on the row that ran it
                c = p["change"]
                lines.append(f"| | | {'kept' if p['used'] else 'not kept'}: {p['reason']}; {p['pixels']} pixels, "
                             f"change {c['r_deg']:.4f} deg / {c['t']:.5f} / {c['s']:.5f} | | | | |")
    return lines + ["", "r in degrees, t in the reference NeRF's units, s in log scale."]


def _held_out_section(records: list[dict]) -> list[str]:
    """The blend on each capture's own held-out images (:func:`stage_held_out`), beside that capture's NeRF alone."""
    rows = [r for r in records if r.get("held_out")]
    if not rows:
        return []
    lines = ["", "### On each capture's own held-out images (`--stages held-out`: the spec's `test_run`)", "",
             "What a user without ground truth can score: the images each capture's run kept out of its training "
             "(nerfstudio's eval split), posed through the estimated registration (`\"test_run\": i` in the fusion "
             "spec). *Own NeRF*: nerfstudio's `ns-eval` of that capture's run alone on the same images. NeRF (ref.) "
             "is the reference run's NeRF, whatever the capture.", "",
             *_blend_header("case", "capture (views)", "Own NeRF")]
    for r in rows:
        for cap, h in r["held_out"].items():
            b = h["blend_psnr"]
            lines.append(f"| {r['case']} | {cap} ({h['views']}) | {h['own_psnr']:.2f} | {_psnr_cells(b)} |")
    lines += ["", "PSNR (dB) from `ns-eval`'s JSON."]
    return lines


IDW_COLUMNS = ("idw_2d", "idw_3d", "idw_sample")


def _coverage_constants(case_dir: Path) -> str:
    """The coverage constants a case's fused run was made with (its config.yml), as the report states them."""
    try:
        cov = runs.read_config(fused_config(case_dir, None)).pipeline.model.coverage
    except (runs.RunLoadError, AttributeError):
        return f"{case_dir.name}: unknown (no fused run)"
    return f"sigma {cov.sigma_deg:g} deg, k {cov.k}, {cov.candidates} candidate cameras per ray"


def write_coverage_report(records: list[dict], path: Path) -> None:
    """``coverage`` (ours) against the best of the paper's IDW methods per case, PSNR and SSIM from ``ns-eval``."""
    rows = [r for r in records if r.get("blend_psnr") and r["blend_psnr"].get("coverage") is not None]
    layout_of = {r["case"]: r["spec"].rsplit(":", 1)[0] for r in rows}
    constants = sorted({_coverage_constants(Path(r["case_dir"])) for r in rows})
    lines = ["# Coverage-aware blending (ours) against the paper's IDW methods, on the practitioner cases", "",
             "Command: `python scripts/bench_practitioner.py " + " ".join(sys.argv[1:]) + "` (cases: COLMAP-posed "
             "captures, stock nerfacto runs, the registration `ns-nerfuser-register` makes with every default; "
             "`ns-eval` scores every blend method in one pass on the world-posed test views, with the estimated "
             "registration).", "",
             f"Constants of `coverage` as each case's fused run recorded them: {'; '.join(constants)}; the paper's "
             "gamma / tau (5 / 1.8, the tool's defaults) for every method and layout; appearance matching as the "
             "fused model's default had it when the case ran (off unless the case is marked *matched*). No case "
             "here chose them: sigma 20 deg / k 4 was set before any measurement; sigma 40 deg / k 4 was chosen on "
             "the validation seeds street-0 and drive-0 (`validate_coverage_drive0.md`). `coverage` is ours; NeRF, "
             "Nearest, IDW-2D, IDW-3D and IDW-Sample are the paper's (Table 2).", "",
             *_blend_header("case", "layout")]
    for r in rows:
        p, q = r["blend_psnr"], r["blend_ssim"]
        mark = " *matched*" if r.get("fused_appearance_matching") else ""
        lines.append(f"| {r['case']}{mark} | {layout_of[r['case']]} | " + " | ".join(
            "-" if p[k] is None else f"{p[k]:.2f} / {q[k]:.3f}" for k, _ in BLEND_COLUMNS) + " |")  # fmt: skip
    lines += ["", "PSNR (dB) / SSIM. Per case, `coverage` minus the best of IDW-2D / IDW-3D / IDW-Sample:", ""]
    verdicts = []
    for r in rows:
        p, q = r["blend_psnr"], r["blend_ssim"]
        best = max(IDW_COLUMNS, key=lambda k: p[k])
        d_psnr, d_ssim = p["coverage"] - p[best], q["coverage"] - max(q[k] for k in IDW_COLUMNS)
        d_sample = p["coverage"] - p["idw_sample"]
        lines.append(f"- {r['case']}: coverage - best IDW = {d_psnr:+.2f} dB (best: {best}); SSIM "
                     f"{d_ssim:+.4f}; against IDW-Sample {d_sample:+.2f} dB")  # fmt: skip
        if p.get("coverage_3d") is not None:  # scored by fused runs made since coverage-3d exists
            lines.append(f"- {r['case']}: coverage-3d - best IDW = {p['coverage_3d'] - p[best]:+.2f} dB; SSIM "
                         f"{q['coverage_3d'] - max(q[k] for k in IDW_COLUMNS):+.4f}; against IDW-Sample "
                         f"{p['coverage_3d'] - p['idw_sample']:+.2f} dB")  # fmt: skip
        if layout_of[r["case"]] == "object-centric":
            verdicts.append((f"{r['case']}: not below IDW-Sample by more than 0.05 dB", d_sample >= -0.05))
        else:
            verdicts.append((f"{r['case']}: >= best IDW + 0.3 dB and better SSIM", d_psnr >= 0.3 and d_ssim > 0))
    costs = [r for r in rows if r.get("cost")]
    if costs:
        lines += ["", "Render cost (`--stages cost`: one chunk of 4096 random rays of the reference run's training "
                  "cameras, 15 shuffled repeats, median of the per-repeat ratios): the fused model's time over the "
                  "sub-models' own forward passes on the rays it queries them on.", ""]  # fmt: skip
        for r in costs:
            c = r["cost"]
            c3 = f", coverage-3d {c['coverage-3d']['ratio_used']:.2f}x" if "coverage-3d" in c else ""
            lines.append(f"- {r['case']}: coverage {c['coverage']['ratio_used']:.2f}x, IDW-Sample "
                         f"{c['idw-sample']['ratio_used']:.2f}x{c3}")  # fmt: skip
            verdicts.append((f"{r['case']}: coverage cost <= 1.3x", c["coverage"]["ratio_used"] <= 1.3))
    both = [r for r in rows if len(appearance_evals(Path(r["case_dir"]))) == 2]
    if both:
        lines += ["", "Appearance matching (ours): the same fused runs with `--pipeline.model.appearance-matching "
                  "True` and `False` (the registration's colour maps applied or not), PSNR with - without, per "
                  "method. Captures without colour differences: the right maps are the identity.", ""]  # fmt: skip
        for r in both:
            evals = appearance_evals(Path(r["case_dir"]))
            on, off = (json.loads(evals[k].read_text())["results"] for k in (True, False))
            gains = [np.diag(np.asarray(n["colour_to_reference"])[:, :3]).round(3).tolist()
                     for n in read_registration(Path(r["case_dir"]) / "registration.json")["nerfs"]
                     if n.get("colour_to_reference") is not None]  # fmt: skip
            diffs = ", ".join(f"{name} {on[f'psnr_{k}'] - off[f'psnr_{k}']:+.2f}" for k, name in BLEND_COLUMNS
                              if f"psnr_{k}" in on and f"psnr_{k}" in off)  # fmt: skip
            lines.append(f"- {r['case']}: {diffs} dB (fitted gains per NeRF: {gains})")
    lines += ["", "Targets: " + "; ".join(f"{t}: {'met' if ok else 'NOT met'}" for t, ok in verdicts) + ".", ""]
    write_text_atomic(path, "\n".join(lines))


def main(cfg: BenchPractitioner) -> None:
    # ns-process-data's tools, needed by the colmap stage only (the others run where only the datasets were copied)
    missing = [tool for tool in ("colmap", "ffmpeg") if shutil.which(tool) is None]
    if missing and not cfg.report_only and "colmap" in cfg.stages:
        raise SystemExit(f"bench_practitioner: {', '.join(missing)} not on PATH; run scripts/setup_practitioner.sh")
    records = []
    for case in cfg.cases:
        layout = _layout(case, cfg)
        case_dir = (cfg.root / case_folder(case, cfg)).absolute()
        case_dir.mkdir(parents=True, exist_ok=True)
        if not cfg.report_only:
            CONSOLE.rule(case)
            if "scene" in cfg.stages:
                source = None if not cfg.share_captures else share_captures(
                    case_dir, [c.name for c in layout.captures],
                    [cfg.root.absolute() / f for f in training_siblings(case, cfg)])  # fmt: skip
                if source is not None:
                    CONSOLE.print(f"{case}: images, COLMAP datasets and test views copied from {source} "
                                  "(the same case trained otherwise; --no-share-captures to make them anew)")
                elif cfg.share_captures:
                    source = share_captures(case_dir, [c.name for c in layout.captures],
                                            [cfg.root.absolute() / f for f in image_siblings(case, cfg)],
                                            parts=("images", "test"))  # fmt: skip
                    if source is not None:
                        CONSOLE.print(f"{case}: images and test views copied from {source} (the same case posed by "
                                      "another COLMAP matching or camera; --no-share-captures to render them anew)")
                stage_scene(layout, case_dir)
            if "colmap" in cfg.stages:
                stage_colmap(layout, case_dir, cfg.matching_method, cfg.camera_type)
            if cfg.check_captures and "train" in cfg.stages:
                stage_check(layout, case_dir, cfg.matching_method, cfg.camera_type)
        if cfg.check_captures and (case_dir / "capture_check.json").is_file() and (
                stuck := unremedied_captures(case_dir)):  # fmt: skip
            CONSOLE.print(f"[yellow]{case}: ns-nerfuser-check-capture found {', '.join(stuck)} folded with no remedy "
                          "it can apply (no side free of the fold, too many views to leave out; see "
                          f"{case_dir / 'check_capture.log'}); the guide's path stops before training here: scored "
                          "as a failure[/]")  # fmt: skip
            records.append(stopped_record(layout, case_dir, case, stuck))
            continue
        if not cfg.report_only:
            if "train" in cfg.stages:
                stage_train(layout, case_dir, cfg)
            if "register" in cfg.stages:
                stage_register(layout, case_dir)
        trained = run_config(case_dir, layout.captures[-1].name).is_file()
        gt = capture_ground_truth(layout, case_dir) if trained else None  # once: it loads every run's model
        if not cfg.report_only and gt is not None:
            if "fuse" in cfg.stages:
                stage_fuse(layout, case_dir, gt)
            for setting, stage in ((True, "matched"), (False, "unmatched")):
                if stage in cfg.stages:
                    stage_appearance(case_dir, setting)
            if "content" in cfg.stages:
                stage_content(layout, case_dir, gt)
            if "truth" in cfg.stages:
                stage_truth(layout, case_dir, gt)
            if "direct" in cfg.stages:
                stage_direct(layout, case_dir, gt)
            if "held-out" in cfg.stages:
                stage_held_out(layout, case_dir)
        if not cfg.report_only and "cost" in cfg.stages:
            stage_cost(layout, case_dir)
        if gt is not None:
            records.append(score_case(layout, case_dir, case, gt))
            CONSOLE.print(json.dumps(records[-1], indent=1)[:2000])
    if cfg.report is not None and records:
        write_report(records, cfg.report, cfg)
        CONSOLE.print(f"report: {cfg.report}")
    if cfg.coverage_report is not None and records:
        write_coverage_report(records, cfg.coverage_report)
        CONSOLE.print(f"coverage report: {cfg.coverage_report}")


if __name__ == "__main__":
    main(tyro.cli(BenchPractitioner))
