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
from bench_appearance import BenchAppearance, measure
from rich.console import Console

from nerfuser_ns.bench.evaluation import SceneRuns
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.scripts import register


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
    bench = BenchAppearance()
    out = cfg.registration or cfg.output.with_name("registration_ref.json")
    if not out.is_file():
        args = ["--configs", *map(str, scene.configs), "--output", str(out), "--work-dir",
                str(out.with_name("registration_work")), "--sampling.size", str(bench.registration_size),
                "--sampling.max-training-poses", str(bench.registration_poses)]  # fmt: skip
        if register.run(tyro.cli(register.RegisterCommand, args=args)) != 0:
            raise SystemExit(f"validate_appearance: {cfg.scene}: registration failed (see above)")
    result = measure(scene, out, bench, console)
    write_text_atomic(cfg.output, json.dumps(result, indent=2) + "\n")
    console.print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(ValidateAppearance))
