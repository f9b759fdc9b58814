"""What the ``auto`` blend method (ours, the default) chooses, and the measures it chooses by, per NeRF.

Two kinds of input, each one row per case:

* generated layouts by name and seed (``--layouts street --seeds 900 901``): each capture's true cameras, as the
  validation that fixed ``nerfuser_ns.blend_choice``'s constants saw them;
* registration files (``--registrations outputs/practitioner/*/registration.json``): the training cameras the
  registration recorded for each run (COLMAP-posed, camera-optimised), what the fused model decides from.

    python scripts/report_blend_choice.py --layouts object-centric street drive room row-houses --seeds 900 901 902 \\
        --registrations outputs/practitioner/*/registration.json --report reports/blend_choice.md

Reads cameras only: no model is loaded, nothing is rendered.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from nerfuser_ns.bench.practitioner_cases import registered_cameras
from nerfuser_ns.bench.scenes import benchmark_params, make_layout
from nerfuser_ns.blend_choice import (
    CENTRE_MISS_DEG,
    CENTRE_SPREAD,
    RIG_OFFSET,
    RIG_TURN_DEG,
    choose_blend_method,
    forms_rig,
    looks_at_centre,
)
from nerfuser_ns.coverage import CameraIndex
from nerfuser_ns.files import write_text_atomic


@dataclass
class ReportBlendChoice:
    """A table of ``auto``'s choice on generated layouts and on registration files."""

    report: Path
    """Write the markdown table here."""
    layouts: list[str] = field(default_factory=list)
    """Generated layouts whose true cameras to judge (object-centric, street, drive, room, row-houses)."""
    seeds: list[int] = field(default_factory=list)
    """Seeds of each layout."""
    registrations: list[Path] = field(default_factory=list)
    """Registration files whose recorded training cameras to judge (a case's name: the file's folder)."""


def _row(case: str, source: str, names: list[str], cameras: list[CameraIndex | None]) -> str:
    method, _ = choose_blend_method(cameras, names)
    cells = []
    for name, c in zip(names, cameras, strict=True):
        if c is None:
            cells.append(f"{name}: not recorded")
            continue
        inward, miss, spread = looks_at_centre(c)
        rig, offset = forms_rig(c)
        measures = "no focus" if miss is None else f"{miss:.1f} deg, R {spread:.2f}"
        measures += ", rig offset " + ("-" if offset is None else f"{offset:.3f}")
        cells.append(f"{name}: {measures}{' (centre)' if inward else ''}{' (rig)' if rig else ''}")
    return f"| {case} | {source} | {'; '.join(cells)} | {method} |"


def main(cfg: ReportBlendChoice) -> None:
    rows = []
    intrinsics = [100.0, 100.0, 96.0, 72.0, 192.0, 144.0]  # the verdict reads poses only
    for layout in cfg.layouts:
        for seed in cfg.seeds:
            built = make_layout(layout, **benchmark_params(layout, seed))
            cameras = [CameraIndex.from_cameras(c.c2w_world, intrinsics) for c in built.captures]
            rows.append(_row(f"{layout}-{seed}", "true cameras", [c.name for c in built.captures], cameras))
    for path in cfg.registrations:
        try:
            names, cameras = registered_cameras(path)
        except (OSError, ValueError) as e:
            raise SystemExit(f"{path}: not a readable registration file ({e})") from None
        rows.append(_row(path.parent.name, "registration file", [n.split("/")[0] for n in names], cameras))
    lines = ["# What the blend method `auto` chooses", "",
             f"Made by `python scripts/report_blend_choice.py {' '.join(sys.argv[1:])}`. Per NeRF: the median angle "
             "by which its training cameras' optical axes miss their focus of attention, and their spread R around "
             f"it (0: all around, 1: all on one side). A NeRF looks at a centre with at most {CENTRE_MISS_DEG:g} deg "
             f"and R at most {CENTRE_SPREAD:g}. The rig offset: the median distance from a camera to the nearest "
             f"camera turned more than {RIG_TURN_DEG:g} deg from it, over the capture's extent (the median distance "
             f"of the centres from their mean); the cameras form a rig at {RIG_OFFSET:g} or less. `auto` renders with "
             "IDW-Sample (the paper's) when every NeRF looks at a centre, with IDW-2D (the paper's) when every NeRF's "
             "cameras form a rig, with coverage (ours) otherwise (`nerfuser_ns/blend_choice.py`).", "",
             "| case | cameras | per NeRF: median miss angle, spread R, rig offset | auto |",
             "| --- | --- | --- | --- |",
             *rows, ""]  # fmt: skip
    write_text_atomic(cfg.report, "\n".join(lines))
    print(f"report: {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(ReportBlendChoice))
