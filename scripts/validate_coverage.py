"""The ``coverage`` blend's constants (ours) on validation cases: every setting of a fixed grid scored on the test
views of fused practitioner runs (``scripts/bench_practitioner.py`` case folders of a validation seed, never of a
reported case), against the paper's IDW methods at the run's own defaults.

The sub-models are queried once per ray chunk and re-blended per setting (``evaluation.blend_sweep``). The choice
rule is fixed here, before any run: the setting with the largest mean over the cases of ``coverage - best IDW``
(PSNR, dB); on a tie (within 0.01 dB) the current defaults stay. The fused model's ``gamma`` is not swept: it is
one exponent shared with the IDW methods.

Example (a street validation seed, after ``python scripts/bench_practitioner.py --cases street:0``):
    python scripts/validate_coverage.py --cases outputs/practitioner/street-0 \\
        --output reports/validate_coverage.json

Cases scored by an earlier run (its JSON, the same grid) join the choice with ``--earlier``, so a validation seed
of another layout adds to the ones already scored without scoring them again.
"""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import tyro
from rich.console import Console

from nerfuser_ns import runs
from nerfuser_ns.bench import evaluation
from nerfuser_ns.bench.practitioner_cases import fused_config
from nerfuser_ns.coverage import CoverageParams
from nerfuser_ns.files import write_text_atomic

IDW_METHODS = ("idw-2d", "idw-3d", "idw-sample")
METHODS = ("nearest", *IDW_METHODS, "coverage")
TIE_DB = 0.01


@dataclass
class ValidateCoverage:
    """Score a grid of coverage constants on validation cases and pick one by the rule above."""

    cases: list[Path]
    """Practitioner case folders of validation seeds, each with its fused run (the ``fuse`` stage)."""
    output: Path
    """JSON results (a markdown table is written beside it)."""
    sigma_deg: list[float] = field(default_factory=lambda: [10.0, 20.0, 40.0])
    """Angular widths to try."""
    k: list[int] = field(default_factory=lambda: [1, 4])
    """Cameras per score to try."""
    max_views: int | None = None
    """Score at most this many test views per case (evenly spaced); None: all."""
    earlier: list[Path] = field(default_factory=list)
    """JSON outputs of earlier runs whose cases join the choice (their grid and defaults must be this run's)."""


CONSTANTS = ("sigma_deg", "k", "candidates")
"""The coverage constants a grid setting, a case's defaults and the library's defaults are compared by."""


def _constants(setting: dict) -> tuple:
    return tuple(setting[x] for x in CONSTANTS)


def _grid(cfg: ValidateCoverage) -> list[dict]:
    # gamma stays the run's: the fused model's one exponent, shared with the IDW methods
    return [{"sigma_deg": s, "k": k, "candidates": max(16, k)} for s, k in itertools.product(cfg.sigma_deg, cfg.k)]


def _test_views(pipeline, max_views: int | None) -> tuple:  # noqa: ANN001 - a nerfstudio pipeline
    dataset = pipeline.datamanager.eval_dataset
    ids = np.arange(len(dataset))
    if max_views is not None and len(ids) > max_views:
        ids = np.unique(np.linspace(0, len(ids) - 1, max_views).round().astype(int))
    target = torch.stack([dataset.get_image_float32(int(i))[..., :3] for i in ids])
    return dataset.cameras[torch.from_numpy(ids)], target


def score_case(case_dir: Path, grid: list[dict], max_views: int | None, console: Console, defaults: dict) -> dict:
    """Every method at the run's defaults, and coverage under every grid setting, on the case's test views;
    SystemExit (one line), before the sweep, where the fused run's coverage settings are not ``defaults``."""
    loaded = runs.load_run(fused_config(case_dir, None), device=runs.default_device(), with_data=True,
                           test_mode="test")
    model = loaded.pipeline.model  # type: ignore[union-attr]
    model.config.render_all_methods = True
    settings_now = model.blend_settings
    if _constants(asdict(settings_now.coverage)) != _constants(defaults):
        raise SystemExit(f"validate_coverage: {case_dir}: its fused run overrides the coverage settings "
                         f"({settings_now.coverage}); the choice compares against the library's, {defaults}")
    cameras, target = _test_views(loaded.pipeline, max_views)
    settings = [{}] + [{"coverage": CoverageParams(g["sigma_deg"], g["k"], g["candidates"])} for g in grid]
    start = time.perf_counter()
    results = evaluation.blend_sweep(model, cameras, target, settings, METHODS, f"{case_dir.name}: sweep")
    seconds = time.perf_counter() - start
    best_idw = max(results[0][m]["psnr"] for m in IDW_METHODS)
    best_idw_ssim = max(results[0][m]["ssim"] for m in IDW_METHODS)
    rows = [{**g, "psnr": r["coverage"]["psnr"], "ssim": r["coverage"]["ssim"],
             "minus_best_idw_db": r["coverage"]["psnr"] - best_idw} for g, r in zip(grid, results[1:], strict=True)]
    console.print(f"{case_dir.name}: {len(target)} views, {len(grid)} settings in {seconds:.0f} s; best IDW "
                  f"{best_idw:.2f} dB, coverage at the defaults {results[0]['coverage']['psnr']:.2f} dB")
    return {"case": case_dir.name, "views": len(target), "seconds": round(seconds, 1),
            "defaults": {"gamma": settings_now.gamma, "tau": settings_now.tau, **asdict(settings_now.coverage)},
            "at_defaults": results[0], "best_idw_psnr": best_idw, "best_idw_ssim": best_idw_ssim,
            "grid": rows}  # fmt: skip


def earlier_cases(paths: list[Path], grid: list[dict], defaults: dict) -> list[dict]:
    """The cases scored by earlier runs (their JSON outputs), each marked with its file; SystemExit (one line) where
    a file is unreadable or scored another grid or other defaults, whose figures the choice cannot mix."""
    out = []
    for path in paths:
        try:
            cases = json.loads(Path(path).read_text())["cases"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"validate_coverage: --earlier {path}: not an output of this script ({e})") from None
        for case in cases:
            if [_constants(g) for g in case["grid"]] != [_constants(g) for g in grid]:
                raise SystemExit(f"validate_coverage: --earlier {path}: {case['case']} was scored on another grid; "
                                 "run with the same --sigma-deg and --k")  # fmt: skip
            if _constants(case["defaults"]) != _constants(defaults):
                raise SystemExit(f"validate_coverage: --earlier {path}: {case['case']} was scored against other "
                                 "defaults; score it again")  # fmt: skip
            out.append({**case, "from": str(path)})
    return out


def choose(cases: list[dict], defaults: dict) -> dict:
    """The rule of the module docstring: the grid setting with the best mean ``coverage - best IDW``."""
    grid = cases[0]["grid"]
    means = [float(np.mean([c["grid"][j]["minus_best_idw_db"] for c in cases])) for j in range(len(grid))]
    at_defaults = next((j for j, g in enumerate(grid) if _constants(g) == _constants(defaults)), None)
    best = int(np.argmax(means))
    if at_defaults is not None and means[best] - means[at_defaults] <= TIE_DB:
        best = at_defaults
    return {**dict(zip(CONSTANTS, _constants(grid[best]), strict=True)), "mean_minus_best_idw_db": means[best],
            "mean_minus_best_idw_db_at_defaults": None if at_defaults is None else means[at_defaults]}  # fmt: skip


def _markdown(cases: list[dict], choice: dict, command: str) -> str:
    earlier = [f"{c['case']} from `{c['from']}`" for c in cases if "from" in c]
    lines = ["# Coverage constants on validation cases (ours)", "", f"`{command}`", "",
             *([f"Scored by earlier runs: {', '.join(earlier)}.", ""] if earlier else []),
             "Coverage PSNR minus the best of IDW-2D / IDW-3D / IDW-Sample at the run's defaults (dB); the choice rule "
             "(fixed before the run): best mean over the cases, the defaults on a tie within "
             f"{TIE_DB} dB.", "",
             "| sigma (deg) | k | " + " | ".join(c["case"] for c in cases) + " | mean |",
             "| ---: | ---: | " + " | ".join("---:" for _ in cases) + " | ---: |"]  # fmt: skip
    for j, g in enumerate(cases[0]["grid"]):
        values = [c["grid"][j]["minus_best_idw_db"] for c in cases]
        lines.append(f"| {g['sigma_deg']:g} | {g['k']} | "
                     + " | ".join(f"{v:+.2f}" for v in values) + f" | {np.mean(values):+.3f} |")  # fmt: skip
    lines += ["", f"Chosen: sigma {choice['sigma_deg']:g} deg, k {choice['k']}, candidates {choice['candidates']} "
              f"(mean {choice['mean_minus_best_idw_db']:+.3f} dB)."]  # fmt: skip
    return "\n".join(lines) + "\n"


def main(cfg: ValidateCoverage) -> None:
    console = Console()
    for case in cfg.cases:
        if not fused_config(case, None).is_file():
            raise SystemExit(f"validate_coverage: {case} has no fused run ({fused_config(case, None)}); run "
                             "scripts/bench_practitioner.py's fuse stage on it first")  # fmt: skip
    grid = _grid(cfg)
    defaults = asdict(CoverageParams())
    earlier = earlier_cases(cfg.earlier, grid, defaults)  # before any work
    names = [c["case"] for c in earlier] + [Path(c).name for c in cfg.cases]
    if not names:
        raise SystemExit("validate_coverage: no cases: name fused case folders with --cases (or --earlier outputs)")
    if len(set(names)) < len(names):
        raise SystemExit(f"validate_coverage: a case is named twice among --cases and --earlier: {names}")
    cases = [score_case(case, grid, cfg.max_views, console, defaults) for case in cfg.cases] + earlier
    choice = choose(cases, defaults)  # every case was scored against these (checked above)
    command = (f"python scripts/validate_coverage.py --cases {' '.join(map(str, cfg.cases))} --output {cfg.output} "
               f"--sigma-deg {' '.join(map(str, cfg.sigma_deg))} --k {' '.join(map(str, cfg.k))}"
               + ("" if cfg.max_views is None else f" --max-views {cfg.max_views}")
               + (f" --earlier {' '.join(map(str, cfg.earlier))}" if cfg.earlier else ""))  # fmt: skip
    write_text_atomic(cfg.output, json.dumps({"command": command, "cases": cases, "choice": choice}, indent=2) + "\n")
    write_text_atomic(cfg.output.with_suffix(".md"), _markdown(cases, choice, command))
    console.print(f"chosen: {choice}; wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(ValidateCoverage))
