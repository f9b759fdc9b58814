"""``ns-nerfuser-check-capture``: has COLMAP folded a capture, or let its camera drift? Check ``ns-process-data``'s
output before training.

Example::

    ns-process-data images --data images/east --output-dir data/east
    ns-nerfuser-check-capture data/east data/west             # a verdict per capture; exit 1 if folded or drifted
    ns-nerfuser-check-capture data/east --write-larger-side   # also writes data/east/transforms_larger_side.json
    ns-train nerfacto --data data/east/transforms_larger_side.json
    ns-nerfuser-check-capture data/east --write-images-to-repose   # a few misposed views: images to pose again
    ns-process-data images --data data/east/images_to_repose --output-dir data/east_reposed

On repeated structure COLMAP can pose a block of a capture's views by the wrong copy of the structure (see
:mod:`nerfuser_ns.capture_check`); a run trained on such poses cannot be registered correctly by any method. The check
needs views filmed in sequence (file names in the order taken; a multi-camera rig's views interleaved exposure by
exposure are checked camera by camera) and says so when the order is no sequence. A second check needs no order: it
asks whether COLMAP's reconstruction explains the image matches COLMAP itself verified (:mod:`nerfuser_ns.match_check`,
from the ``colmap`` folder ``ns-process-data`` leaves in the dataset), and where the unexplained pairs join two
groups of views that each explain their own, names the smaller group as the fold's side. A camera whose vertical
focal length COLMAP let drift from the horizontal one (views along one line, as from a car) stretches the capture's
geometry: it is reported with what to run instead.
"""

from __future__ import annotations

import itertools
import json
import os
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro
from rich.console import Console
from rich.text import Text

from nerfuser_ns.capture_check import (
    FOLD_TURN_DEG,
    LARGER_SIDE_NAME,
    MAX_RIG_CAMERAS,
    RADIAL_FOLDER_SUFFIX,
    REPOSE_FOLDER_NAME,
    REPOSED_FOLDER_SUFFIX,
    SEQUENCE_STEP_DEG,
    SQUARE_PIXEL_ADVICE,
    IntrinsicsCheck,
    check_dataset,
    check_dataset_intrinsics,
    dataset_file,
    process_data_command,
    simple_radial_recipe,
    write_larger_side,
    write_repose_images,
)
from nerfuser_ns.match_check import MatchCheck, check_dataset_matches
from nerfuser_ns.scripts.cli import parse

CONSOLE = Console(soft_wrap=True)
ERR_CONSOLE = Console(stderr=True, soft_wrap=True)
POSE_AGAIN_ADVICE = (
    "pose the capture again and check again (COLMAP's mapping does not repeat itself: run again, the same command "
    "posed one of our folded drive captures consistently, though not our folded rooms). Sequential matching "
    "(ns-process-data --matching-method sequential, its files in the order they were taken) is no sure remedy: on "
    "our generated captures it cut one folded room's misposed views from 27 to 1 but barely two others', and left a "
    "street folded in a way this check then could not see (it compares few pairs). Where no view holds something "
    "unique to its part of the place, film it again with such views"
)
"""What is left for a capture the matches show folded with no side to train on and no few views to leave out, with
what posing again did on our captures (``reports/colmap_fold_check.md``, ``reports/repose_in_order_street20.md``,
``reports/colmap_quality_drive17_simple_pinhole_again.md``)."""
ONE_FOCAL_ADVICE = (
    "It was posed with one focal length (fy = fx); COLMAP's SIMPLE_RADIAL camera is another posing to try (the recipe "
    "in nerfuser_ns's docs/your_own_captures.md): on two of our drives a capture posed again with ns-process-data's "
    "simple_pinhole camera came out folded, and with SIMPLE_RADIAL consistent"
)
"""Added to :data:`POSE_AGAIN_ADVICE` for a capture posed with one focal length (``reports/colmap_quality_drive25.md``,
``reports/bench_practitioner_drive28_checked.md``: two cases, so offered as a try)."""


@dataclass
class CheckCaptureCommand:
    """Check COLMAP-posed captures (ns-process-data outputs) for folds by repeated structure and drifted cameras."""

    data: tyro.conf.Positional[list[Path]]
    """Dataset folders (or their transforms.json), one per capture."""
    write_larger_side: bool = False
    """For each folded capture, write ``transforms_larger_side.json`` beside its transforms.json: every frame but the
    smaller side of the fold (a consistent capture by itself), as the file order shows it, or, for unordered views,
    the matches where they form two sides. The dataset's own file is never changed."""
    write_images_to_repose: bool = False
    """For each capture whose unexplained matches all go through a few views (and form no two sides), copy its images
    but those views to ``images_to_repose/`` beside its transforms.json, to pose again with ``ns-process-data``."""

    def main(self) -> int:
        """The exit status: 0 when no capture is folded or drifted, 1 when one is (or an input is bad)."""
        if not self.data:
            raise ValueError("no dataset given: pass the folders ns-process-data wrote (or their transforms.json), "
                             "e.g. ns-nerfuser-check-capture data/part_a data/part_b")
        found = False
        # every input read before anything is written
        checks = [(path, check_dataset(path), check_dataset_intrinsics(path), check_dataset_matches(path))
                  for path in self.data]  # fmt: skip
        # the captures to pose again without a few views (a fold the file order shows is trained on its larger side)
        repose = {path: matches.repose_without for path, check, _, matches in checks
                  if matches.repose_without is not None and not check.folded}  # fmt: skip
        if self.write_images_to_repose:  # no capture's folder written while another's cannot be
            for path in repose:
                if (out := dataset_file(path).parent / REPOSE_FOLDER_NAME).exists():
                    raise ValueError(f"{out}: already exists (an earlier check wrote it?); remove it to write it again")
        for path, check, camera, matches in checks:
            if _report_matches(path, matches, camera):
                found = True
            camera_warning = camera.warning(str(path))
            if camera_warning is not None:
                found = True
                CONSOLE.print(f"[yellow]{camera_warning}[/]")
                if path in repose and self.write_images_to_repose:  # one posing for both: the commands below
                    CONSOLE.print(f"  {SQUARE_PIXEL_ADVICE}: below, without its misposed views")
                else:
                    _print_commands(f"{SQUARE_PIXEL_ADVICE}. For this capture (the images are the dataset's copies; "
                                    "add the options you posed it with, e.g. --no-gpu, --matching-method):",
                                    one_focal_lines(path))  # fmt: skip
            # every fold verdict also carries the camera's, so that "not folded" never reads as "fine" and a
            # folded capture's camera is not left unsaid
            camera_verdict = (f"its camera drifted (fy/fx {camera.aspect:.3f}, above)" if camera.drifted
                              else f"camera fy/fx {camera.aspect:.3f} (square pixels)")  # fmt: skip
            camera_note = f"; {'but ' if camera.drifted else ''}{camera_verdict}"
            if not check.checked:
                CONSOLE.print(f"{path}: not checked for folds by file order: the median turn between views in it is "
                              f"{check.median_turn_deg:.0f} deg (above {SEQUENCE_STEP_DEG:.0f}), so the file order "
                              f"is not a filmed sequence, nor a rig of up to {MAX_RIG_CAMERAS} cameras "
                              f"interleaved{camera_note}")  # fmt: skip
            elif (fold_warning := check.warning(str(path))) is None:
                rig = f", each of {check.rig_cameras} rig cameras" if check.rig_cameras > 1 else ""
                CONSOLE.print(f"{path}: not folded ({check.num_views} views{rig}, median turn "
                              f"{check.median_turn_deg:.1f} deg, no turn above {FOLD_TURN_DEG:.0f} deg)"
                              f"{camera_note}")  # fmt: skip
            else:
                found = True
                CONSOLE.print(f"[yellow]{fold_warning}[/]")
                CONSOLE.print(f"  suspect views: {', '.join(Path(s).name for s in check.suspect)}")
                CONSOLE.print(f"  {camera_verdict}")
            if path in repose:
                self._repose(path, repose[path], camera.drifted)
            # the file order's sides where it sees the fold, else the matches' (unordered views)
            drop, found_by = (check.suspect, "file order") if check.folded else (matches.smaller_side, "matches")
            if not drop:
                continue
            if self.write_larger_side:
                out = write_larger_side(path, drop, dataset_file(path).parent / LARGER_SIDE_NAME, found_by)
                kept = len(json.loads(out.read_text())["frames"])
                CONSOLE.print(f"  wrote {out} ({kept} views, the larger side by the {found_by}): train with "
                              f"ns-train nerfacto --data {out}")  # fmt: skip
            else:
                CONSOLE.print("  train on its larger side (--write-larger-side: a consistent capture by itself), or "
                              "pose it again and check again")  # fmt: skip
        return 1 if found else 0

    def _repose(self, path: Path, views: tuple[str, ...], drifted: bool) -> None:
        """Advise posing a capture again without its few misposed views, or copy its other images and print the
        commands that pose them (with one focal length where its camera ``drifted``)."""
        names = ", ".join(Path(v).name for v in views)
        if not self.write_images_to_repose:
            CONSOLE.print(f"  pose it again without {names} (in every unexplained pair; --write-images-to-repose "
                          "copies the other images) and check again")  # fmt: skip
            return
        out, kept = write_repose_images(path, views, dataset_file(path).parent / REPOSE_FOLDER_NAME)
        how = ", with one focal length (its camera drifted)" if drifted else ""
        _print_commands(f"wrote {out} ({kept} images, without {names}); pose them again{how}, check the new dataset "
                        "and train on it (add the options you posed it with, e.g. --no-gpu, --matching-method):",
                        repose_lines(path, out, drifted))  # fmt: skip


def _report_matches(path: Path, matches: MatchCheck, camera: IntrinsicsCheck) -> bool:
    """Print the match check's verdict (:mod:`nerfuser_ns.match_check`); True when the capture looks folded."""
    if not matches.checked:
        CONSOLE.print(f"{path}: matches not checked: {matches.reason}")
        return False
    warning = matches.warning(str(path))
    if warning is None:
        explained = matches.pairs - len(matches.unexplained)
        CONSOLE.print(f"{path}: COLMAP's poses explain its verified matches ({explained} of {matches.pairs} image "
                      "pairs)")  # fmt: skip
        if (blind := matches.blind_spot()) is not None:
            CONSOLE.print(f"  [yellow]but {blind}[/]")
        return False
    CONSOLE.print(f"[yellow]{warning}[/]")
    smaller = matches.smaller_side
    if smaller is not None:
        CONSOLE.print(f"  its views form two sides, each explained by itself and joined by few pairs, mostly "
                      f"unexplained: the smaller side's {len(smaller)} views were posed by the fold "
                      f"({', '.join(Path(s).name for s in smaller[:12])}{', ...' if len(smaller) > 12 else ''})")
        return True
    views = ", ".join(f"{Path(name).name} ({n})" for name, n in matches.views()[:8])
    CONSOLE.print(f"  views in the most unexplained pairs: {views}")
    if matches.repose_without is not None:
        names = ", ".join(Path(v).name for v in matches.repose_without)
        CONSOLE.print(f"  every unexplained pair goes through {names}, posed inconsistently with the other views; a "
                      "run trained on these poses cannot be registered correctly")  # fmt: skip
        return True  # what to do follows (CheckCaptureCommand._repose)
    CONSOLE.print(f"  {POSE_AGAIN_ADVICE}; a run trained on these poses cannot be registered correctly")
    if camera.one_focal_length:
        _print_commands(f"{ONE_FOCAL_ADVICE}. For this capture (without CUDA add --SiftExtraction.use_gpu 0 and "
                        "--SiftMatching.use_gpu 0; the images are the dataset's copies):",
                        radial_recipe_lines(path))  # fmt: skip
    return True


def _print_commands(advice: str, lines: list[str]) -> None:
    """An advice line, then the shell lines that follow it, printed as they are (paths may hold rich markup)."""
    CONSOLE.print(f"  {advice}")
    for line in lines:
        CONSOLE.print(f"    {line}", markup=False, highlight=False)


def _dataset_images(path: Path) -> Path:
    """The folder of the images a dataset's frames name (the copies ``ns-process-data`` made)."""
    file = dataset_file(path)
    frames = json.loads(file.read_text())["frames"]
    return Path(os.path.commonpath([(file.parent / f["file_path"]).parent for f in frames]))


def _new_dataset_folder(path: Path, suffix: str) -> Path:
    """A new dataset folder beside the dataset at ``path``, named as it with ``suffix`` (and a number where that
    folder exists: never one to write over)."""
    folder = dataset_file(path).parent
    names = (folder.name + suffix + (f"_{i}" if i > 1 else "") for i in itertools.count(1))
    return next(out for name in names if not (out := folder.with_name(name)).exists())


def one_focal_lines(path: Path) -> list[str]:
    """:data:`SQUARE_PIXEL_ADVICE` for the dataset at ``path`` as shell lines: its images posed again with one focal
    length into a new dataset beside it, named with :data:`REPOSED_FOLDER_SUFFIX`, then checked."""
    return repose_lines(path, _dataset_images(path), one_focal_length=True)


def repose_lines(path: Path, images: Path, one_focal_length: bool) -> list[str]:
    """``images`` (the dataset's, or those ``--write-images-to-repose`` copied) posed again into a new dataset beside
    the dataset at ``path``, named with :data:`REPOSED_FOLDER_SUFFIX` (``--camera-type simple_pinhole`` where
    ``one_focal_length``), then checked, as shell lines."""
    out = _new_dataset_folder(path, REPOSED_FOLDER_SUFFIX)
    camera_type = "simple_pinhole" if one_focal_length else "perspective"
    return [shlex.join(process_data_command(images, out, camera_type)),
            shlex.join(["ns-nerfuser-check-capture", str(out)])]  # fmt: skip


def radial_recipe_lines(path: Path) -> list[str]:
    """:data:`ONE_FOCAL_ADVICE`'s recipe for the dataset at ``path`` as shell lines: its images posed by
    :func:`~nerfuser_ns.capture_check.simple_radial_recipe` into a new dataset beside it, named with
    :data:`RADIAL_FOLDER_SUFFIX`, then checked."""
    images, out = _dataset_images(path), _new_dataset_folder(path, RADIAL_FOLDER_SUFFIX)
    return [shlex.join(["mkdir", "-p", str(out / "colmap" / "sparse")]),
            *(shlex.join(cmd) for cmd in simple_radial_recipe(images, out).values()),
            shlex.join(["ns-nerfuser-check-capture", str(out)])]  # fmt: skip


def run(command: CheckCaptureCommand) -> int:
    try:
        return command.main()
    except (ValueError, OSError) as e:
        ERR_CONSOLE.print(Text.assemble(("error: ", "bold red"), (str(e).splitlines()[0], "red")), highlight=False)
        return 1


def entrypoint() -> None:
    """Console script ``ns-nerfuser-check-capture``."""
    tyro.extras.set_accent_color("bright_yellow")
    sys.exit(run(parse(CheckCaptureCommand)))


if __name__ == "__main__":
    entrypoint()
