"""The practitioner benchmark's case folders (``scripts/bench_practitioner.py``): where each stage leaves its fused
run and ``ns-eval`` JSON, and the blend columns its reports show. The benchmark writes these folders; its reports
(``scripts/report_practitioner_appearance.py`` among them) read them through here."""

from __future__ import annotations

import re
from pathlib import Path

BLEND_COLUMNS = [("nerf", "NeRF (ref.)"), ("nearest", "Nearest"), ("idw_2d", "IDW-2D"), ("idw_3d", "IDW-3D"),
                 ("idw_sample", "IDW-Sample"), ("coverage", "Coverage (ours)")]  # fmt: skip
"""``ns-eval``'s metric suffix and the report's column name of each blend method."""


def fused_config(case_dir: Path, label: str | None) -> Path:
    """The fused run of the ``fuse`` stage (``label`` None) or of the ``matched`` / ``unmatched`` stage."""
    return case_dir / ("fused" if label is None else f"fused_{label}") / "fused" / "nerfuser" / "bench" / "config.yml"


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
