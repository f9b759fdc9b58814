"""Does sequential matching mend a capture COLMAP folded, once its photos are in the order they were taken? (ours, a
diagnostic of ``ns-nerfuser-check-capture``'s advice)

For a capture folded all through (no side to train on, no few views to leave out) the check advises posing it again
with ``ns-process-data --matching-method sequential`` where its files are in the order they were taken, renamed in
that order first if need be. Our generated street captures' files are in no filmed order, so this script puts a
capture's images in an order a person filming the street could have taken them: along one facade in +x, then back
along the other in -x, each view looking along the street taken in the pass that walks its way (:func:`walk_order`).
It poses them with ``ns-process-data images --matching-method sequential`` (the benchmark's other options: CPU SIFT,
no downscales), then scores both datasets, the case's own (exhaustive matching, files in generated order) and the
re-posed one, against the capture's true poses: views posed, views misposed (more than 5 deg off the tie fitted to
the views' poses, the benchmark's rule), median rotation error of that tie, and the match check's and the file-order
check's verdicts. Nothing is trained.

Example:
    python scripts/repose_in_order.py --cases street:20=outputs/practitioner/street-20 \\
        --output-root outputs/scratch/repose_in_order --report reports/repose_in_order_street20.md
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns.bench.practitioner_cases import (
    SOURCE_FRAMES_NAME,
    case_layout,
    dataset_transforms,
    images_done,
    misposed_frames,
    stored_poses,
)
from nerfuser_ns.capture_check import check_dataset, process_data_command
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.match_check import check_dataset_matches
from nerfuser_ns.sim3 import estimate_sim3_from_poses

CONSOLE = Console()
BIN = Path(sys.executable).parent


@dataclass
class ReposeInOrder:
    """Pose captures again with sequential matching in a filmed order and score both posings against the truth."""

    cases: list[str]
    """``layout:seed=case folder`` (a practitioner case: ``images/<capture>``, ``datasets/<capture>``)."""
    output_root: Path
    """Where the reordered images and the re-posed datasets go (``<case folder name>/<capture>/``)."""
    report: Path
    """Markdown report (a JSON of the same rows beside it)."""
    captures: list[str] = field(default_factory=list)
    """Only these captures (all of the case's when empty)."""


def walk_order(c2w: np.ndarray) -> np.ndarray:
    """Indices of a street capture's views in the order of a walk along +x filming the facade on +y (and looking
    ahead, +x), then back along -x filming the facade on -y (looking ahead, -x). OpenGL cameras: forward is -z."""
    forward = -c2w[:, :3, 2]
    x = c2w[:, 0, 3]
    along = np.abs(forward[:, 0]) > np.abs(forward[:, 1])
    out_pass = np.where(along, forward[:, 0] > 0, forward[:, 1] > 0)
    first = np.flatnonzero(out_pass)[np.argsort(x[out_pass], kind="stable")]
    back = np.flatnonzero(~out_pass)[np.argsort(-x[~out_pass], kind="stable")]
    return np.concatenate([first, back])


def score(dataset: Path, true_c2w: np.ndarray) -> dict:
    """A dataset's posing against the capture's true poses, and both fold checks' verdicts."""
    idx, stored = stored_poses(dataset / "transforms.json")
    est = estimate_sim3_from_poses(stored, true_c2w[idx])
    matches = check_dataset_matches(dataset)
    order = check_dataset(dataset)
    return {
        "posed": len(idx),
        "misposed": int(misposed_frames(stored, true_c2w[idx]).sum()),
        "rot_err_deg_median": float(np.median(est.rot_residuals_deg)),
        "match_pairs": matches.pairs,
        "match_unexplained_share": round(matches.unexplained_share, 4),
        "match_folded": matches.folded,
        "match_two_sides": matches.smaller_side is not None,
        "order_checked": order.checked,
        "order_folded": order.folded,
    }


def repose(images: Path, order: np.ndarray, out: Path, log: Path) -> float:
    """Copy ``images`` (``view_<i>.png``) as ``shot_<k>.png`` in ``order`` and pose them with sequential matching into
    ``out``; the seconds ns-process-data took."""
    shots = out.parent / "images_in_order"
    shutil.rmtree(shots, ignore_errors=True)
    shots.mkdir(parents=True)
    for k, i in enumerate(order):
        shutil.copy2(images / f"view_{i:05d}.png", shots / f"shot_{k:05d}.png")
    cmd = process_data_command(shots, out, matching_method="sequential", use_gpu=False,
                               ns_process_data=str(BIN / "ns-process-data"), num_downscales=0)  # fmt: skip
    CONSOLE.print(f"[dim]$ {' '.join(cmd)}[/]")
    start = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - start
    if proc.returncode != 0 or not (out / "transforms.json").is_file():
        raise SystemExit(f"ns-process-data failed on {shots} (exit {proc.returncode}); see {log}")
    return seconds


def write_source_frames(order: np.ndarray, dataset: Path) -> None:
    """Which view each frame of the re-posed dataset is, as the benchmark's re-posed datasets keep it
    (:data:`SOURCE_FRAMES_NAME`: ns-process-data's name -> the name it gave that view in the case's own dataset)."""
    names = {f"frame_{k + 1:05d}.png": f"frame_{i + 1:05d}.png" for k, i in enumerate(order)}
    write_text_atomic(dataset / SOURCE_FRAMES_NAME, json.dumps(names, indent=1) + "\n")


def main(cfg: ReposeInOrder) -> None:
    rows = []
    for spec in cfg.cases:
        case, folder = spec.split("=", 1)
        case_dir = Path(folder)
        layout = case_layout(case)
        for cap in layout.captures:
            if cfg.captures and cap.name not in cfg.captures:
                continue
            if layout.layout not in ("street", "row-houses"):
                raise SystemExit(f"{case}: the walk order is defined for street layouts only")
            out = cfg.output_root / case_dir.name / cap.name
            out.mkdir(parents=True, exist_ok=True)
            order = walk_order(cap.c2w_world)
            dataset = out / "dataset"
            if not (dataset / "transforms.json").is_file():
                seconds = repose(images_done(case_dir, cap.name).parent, order, dataset, out / "process_data.log")
                write_text_atomic(out / "seconds.txt", f"{seconds:.1f}\n")
            seconds = float((out / "seconds.txt").read_text()) if (out / "seconds.txt").is_file() else None
            write_source_frames(order, dataset)
            row = {"case": case, "capture": cap.name, "views": cap.num_views,
                   "exhaustive, generated order": score(dataset_transforms(case_dir, cap.name).parent, cap.c2w_world),
                   "sequential, walk order": score(dataset, cap.c2w_world), "seconds": seconds}  # fmt: skip
            CONSOLE.print(row)
            rows.append(row)
    write_report(cfg, rows)


def write_report(cfg: ReposeInOrder, rows: list[dict]) -> None:
    cmd = "python scripts/repose_in_order.py " + " ".join(f"--cases {c}" if i == 0 else c for i, c in
                                                         enumerate(cfg.cases))  # fmt: skip
    cmd += f" --output-root {cfg.output_root} --report {cfg.report}"
    cmd += f" --captures {' '.join(cfg.captures)}" if cfg.captures else ""
    lines = [
        "# Posing a folded capture again in filmed order with sequential matching (ours, a diagnostic)",
        "",
        f"Command: `{cmd}`. Nothing trained; the images are the case's own, put in the order of a walk along one "
        "facade and back along the other (`walk_order` in the script), then posed by `ns-process-data images "
        "--matching-method sequential --no-gpu --num-downscales 0`. *Misposed*: views more than 5 deg off the tie "
        "fitted to the views' poses (the benchmark's rule); *rot err*: the median rotation residual of that tie; "
        "*match check*: share of verified pairs the reconstruction does not explain (folded above 2%); *order "
        "check*: the file-order fold check (`checked` only where the turns between neighbouring files are small).",
        "",
        "| case | capture | matching | posed | misposed | rot err (deg) | match check | order check | time (s) |",
        "| --- | --- | --- | ---: | ---: | ---: | --- | --- | ---: |",
    ]
    for r in rows:
        for key in ("exhaustive, generated order", "sequential, walk order"):
            s = r[key]
            sides = ", two sides" if s["match_two_sides"] else ""
            verdict = f"folded{sides}" if s["match_folded"] else "consistent"
            order = ("folded" if s["order_folded"] else "not folded") if s["order_checked"] else "not checked"
            seconds = "-" if key.startswith("exhaustive") or r["seconds"] is None else f"{r['seconds']:.0f}"
            lines.append(f"| {r['case']} | {r['capture']} | {key} | {s['posed']}/{r['views']} | {s['misposed']} | "
                         f"{s['rot_err_deg_median']:.3f} | {verdict} ({100 * s['match_unexplained_share']:.1f}% of "
                         f"{s['match_pairs']}) | {order} | {seconds} |")  # fmt: skip
    write_text_atomic(cfg.report, "\n".join(lines) + "\n")
    write_text_atomic(cfg.report.with_suffix(".json"), json.dumps(rows, indent=1) + "\n")
    CONSOLE.print(f"wrote {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(ReposeInOrder))
