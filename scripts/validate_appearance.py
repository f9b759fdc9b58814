"""Appearance matching on one jittered pair only (a validation seed): ``ns-nerfuser-register`` with the settings of
``scripts/bench_appearance.py``, then the blends unmatched, with the cross-render maps alone, with the reference
NeRF's map to its images composed in, and with the true maps, scored against the ground truth in the reference
capture's appearance.

Example (the validation pair, object-centric seed 5 with the bracketed jitter of bench_appearance.py --bracket):
    python scripts/validate_appearance.py --scene outputs/appfit/val5/scene --runs outputs/appfit/val5/runs \\
        --output outputs/appfit/val5/validation_reference_colour.json
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import tyro
from rich.console import Console

from nerfuser_ns.bench.appearance_blends import (
    MAX_TEST_VIEWS,
    REGISTRATION_POSES,
    REGISTRATION_SIZE,
    measure,
    register_pair,
)
from nerfuser_ns.bench.evaluation import SceneRuns
from nerfuser_ns.files import write_text_atomic


@dataclass
class ValidateAppearance:
    """Blends of one pair with and without appearance matching, against its ground truth."""

    scene: Path
    """The generated (jittered) scene."""
    runs: Path
    """Its runs (scripts/bench_appearance.py's layout: <capture>/nerfacto-cpu/demo/config.yml)."""
    output: Path
    """JSON results."""
    registration: Path | None = None
    """Registration file (made here, next to --output, when missing)."""


def main(cfg: ValidateAppearance) -> None:
    console = Console()
    scene = SceneRuns.from_dirs("validation", cfg.scene, cfg.runs)
    out = cfg.registration or cfg.output.with_name("registration_ref.json")
    if not out.is_file():
        register_pair(scene, out, out.with_name("registration_work"), REGISTRATION_SIZE, REGISTRATION_POSES, console)
    result = measure(scene, out, MAX_TEST_VIEWS, console)
    write_text_atomic(cfg.output, json.dumps(result, indent=2) + "\n")
    console.print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(ValidateAppearance))
