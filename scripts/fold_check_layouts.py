"""The fold check of ``ns-nerfuser-check-capture`` on the true poses of generated captures, in file order.

Two questions per capture, no rendering and no COLMAP (the poses are the layouts' ground truth):

* **False alarms**: the true poses are never folded, so a capture the check calls folded is a false alarm; and which
  captures it checks at all (one sequence, a rig at some lag, or not checked: unordered views).
* **Recall**: the same poses with a block of consecutive views (``--block`` of them, at a seeded random place) turned
  by a half turn about the vertical axis through the capture's centre, as COLMAP poses a block of views by the
  wrong copy of a half-turn-symmetric room: found exactly when the suspects are that block.

::

    python scripts/fold_check_layouts.py --seeds 200 250 --output reports/fold_check_layouts.md
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import case_layout
from nerfuser_ns.bench.scenes import LAYOUT_NAMES
from nerfuser_ns.capture_check import fold_check
from nerfuser_ns.files import write_text_atomic


@dataclass
class FoldCheckLayouts:
    """The fold check on generated captures' true poses, clean and with a folded block."""

    output: Path
    """Markdown report; the rows go beside it as JSON."""
    seeds: tuple[int, int] = (200, 250)
    """Layout seeds, from the first up to (not including) the second."""
    layouts: list[str] = field(default_factory=lambda: list(LAYOUT_NAMES))
    """Layouts to generate (the benchmark's view counts: 64 per capture, 96 on drives)."""
    block: float = 0.25
    """Fraction of a capture's views in the folded block."""


def names(n: int) -> list[str]:
    """File names as ``ns-process-data`` writes them."""
    return [f"images/frame_{i + 1:05d}.png" for i in range(n)]


def folded_block(c2w: np.ndarray, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``c2w`` with a block of consecutive views turned half about the vertical through the views' centre."""
    n = len(c2w)
    size = max(1, round(fraction * n))
    start = int(rng.integers(1, n - size))  # never the first view: the check's tie rule keeps the first view's side
    centre = c2w[:, :3, 3].mean(0)
    R = sim3.so3_exp(np.radians([0.0, 0.0, 180.0]))
    folded = c2w.copy()
    block = np.arange(start, start + size)
    folded[block] = sim3.transform_poses(sim3.make_sim3(R, centre - R @ centre), c2w[block])
    return folded, block


def measure(layout: str, seed: int, fraction: float) -> list[dict]:
    rows = []
    rng = np.random.default_rng(seed)
    for cap in case_layout(f"{layout}:{seed}", width=64, height=48).captures:
        c2w = np.asarray(cap.c2w_world, dtype=np.float64)
        files = names(len(c2w))
        clean = fold_check(c2w, files)
        folded_poses, block = folded_block(c2w, fraction, rng)
        folded = fold_check(folded_poses, files)
        expected = {files[i] for i in block} if 2 * len(block) < len(c2w) else set(files) - {files[i] for i in block}
        rows.append({"layout": layout, "seed": seed, "capture": cap.name, "views": len(c2w),
                     "checked": clean.checked, "rig_cameras": clean.rig_cameras,
                     "median_turn_deg": clean.median_turn_deg,
                     "false_alarm": clean.folded, "folded_checked": folded.checked, "folded_found": folded.folded,
                     "suspects_exact": set(folded.suspect) == expected})  # fmt: skip
    return rows


def write_report(rows: list[dict], cfg: FoldCheckLayouts, command: str) -> None:
    lines = ["# The fold check on generated captures' true poses", "", f"`{command}`", "",
             "Per layout, over its captures: how many the check checks (one sequence in file order, or an interleaved "
             "rig at the lag given), false alarms on the true poses (never folded), and, with a block of "
             f"{cfg.block:.0%} of the views turned half about the vertical through the capture's centre, how many "
             "it finds folded and how many with exactly that block as the suspects.", "",
             "| layout | captures | checked | lags (rig cameras) | median turn (deg) | false alarms | folded: found | "
             "folded: suspects exact |", "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for layout in cfg.layouts:
        mine = [r for r in rows if r["layout"] == layout]
        if not mine:
            continue
        checked = [r for r in mine if r["checked"]]
        lags = sorted({r["rig_cameras"] for r in checked})
        median = float(np.median([r["median_turn_deg"] for r in mine]))
        lines.append(f"| {layout} | {len(mine)} | {len(checked)} | {', '.join(map(str, lags)) or '-'} | {median:.1f} | "
                     f"{sum(r['false_alarm'] for r in mine)} | {sum(r['folded_found'] for r in mine)} | "
                     f"{sum(r['suspects_exact'] for r in mine)} |")  # fmt: skip
    write_text_atomic(cfg.output, "\n".join(lines) + "\n")
    write_text_atomic(cfg.output.with_suffix(".json"), json.dumps(rows, indent=2) + "\n")


def main(cfg: FoldCheckLayouts) -> None:
    unknown = [layout for layout in cfg.layouts if layout not in LAYOUT_NAMES]
    if unknown:
        raise SystemExit(f"--layouts: unknown {unknown}; choose from {list(LAYOUT_NAMES)}")
    if not 0 < cfg.block < 1:
        raise SystemExit(f"--block {cfg.block}: expected a fraction in (0, 1)")
    rows = [r for layout in cfg.layouts for seed in range(*cfg.seeds) for r in measure(layout, seed, cfg.block)]
    write_report(rows, cfg, "python " + " ".join(["scripts/fold_check_layouts.py", *sys.argv[1:]]))
    print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(FoldCheckLayouts))
