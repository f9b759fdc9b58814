"""Compare the blends of fused practitioner runs under two gamma / tau settings, from ``ns-eval``'s JSON.

Each case folder holds ``eval.json`` (the ``fuse`` stage's run, scored with its own setting); the script scores the
same fused run again with ``ns-eval`` under ``NERFUSER_GAMMA`` / ``NERFUSER_TAU`` (into ``eval_gamma<g>_tau<t>.json``
beside it, reused when present). The report puts the two side by side per case: every blend method's PSNR / SSIM,
IDW-Sample minus Nearest, and the coverage blend (ours) minus the best IDW method, under each setting.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from nerfuser_ns import runs
from nerfuser_ns.bench.practitioner_cases import BLEND_COLUMNS, blend_table, fused_config
from nerfuser_ns.files import write_text_atomic

IDW = ("idw_2d", "idw_3d", "idw_sample")


@dataclass
class CompareBlendSettings:
    """Two gamma / tau settings of the same fused runs, side by side."""

    cases: list[Path] = field(default_factory=list)
    """Case folders of ``scripts/bench_practitioner.py``, each with the ``fuse`` stage's run and ``eval.json``."""
    gamma: float = 10.0
    """The other setting's gamma (default: the paper's Mission Bay)."""
    tau: float = 1.2
    """The other setting's tau."""
    report: Path = Path("reports/blend_setting_missionbay.md")
    """Where to write the markdown report."""
    note: str | None = None
    """A paragraph under the command (what the cases are: seen or fresh)."""


def _scores(path: Path) -> dict[str, tuple[float, float]]:
    """(PSNR, SSIM) per blend method that ``ns-eval`` scored."""
    table = blend_table(path)
    return {k: (p, table["blend_ssim"][k]) for k, p in table["blend_psnr"].items() if p is not None}


def score_again(case: Path, gamma: float, tau: float) -> Path:
    """``ns-eval`` of the case's fused run under ``gamma`` / ``tau`` (cached), written atomically."""
    out = case / f"eval_gamma{gamma:g}_tau{tau:g}.json"
    if out.is_file():
        return out
    partial = out.with_suffix(".partial.json")  # ns-eval wants a .json name
    env = {**os.environ, "NERFUSER_GAMMA": str(gamma), "NERFUSER_TAU": str(tau)}
    print(f"ns-eval of {case.name} with gamma {gamma:g}, tau {tau:g} (minutes on a CPU)", flush=True)
    start = time.perf_counter()
    with open(case / f"{out.stem}.log", "w") as log:
        done = subprocess.run([str(Path(sys.executable).parent / "ns-eval"), "--load-config",
                               str(fused_config(case, None)), "--output-path", str(partial)],
                              stdout=log, stderr=subprocess.STDOUT, env=env)  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"compare_blend_settings: ns-eval failed on {case}; see {case / (out.stem + '.log')}")
    partial.replace(out)
    print(f"  {time.perf_counter() - start:.0f} s", flush=True)
    return out


def main(cfg: CompareBlendSettings) -> None:
    lines = ["# One fused run, two blend settings", "",
             "Command: `python scripts/compare_blend_settings.py " + " ".join(sys.argv[1:]) + "`.", ""]
    if cfg.note:
        lines += [cfg.note, ""]
    lines += ["PSNR (dB) / SSIM from `ns-eval` on each case's world-posed test views, the same fused run (estimated "
              "registration) scored twice. NeRF (ref.) and Nearest do not depend on gamma / tau.", "",
              "| case | setting | " + " | ".join(name for _, name in BLEND_COLUMNS) + " | IDW-Sample - Nearest | "
              "Coverage - best IDW |", "| --- | --- |" + " --- |" * (len(BLEND_COLUMNS) + 2)]
    summary = []
    for case in cfg.cases:  # every case checked before the first ns-eval
        for needed in (case / "eval.json", fused_config(case, None)):
            if not needed.is_file():
                raise SystemExit(f"compare_blend_settings: {needed} is missing; run the case's fuse stage first")
    for case in cfg.cases:
        model = runs.read_config(fused_config(case, None)).pipeline.model
        own_label = f"gamma {model.gamma:g} / tau {model.tau or 'off'} (the run's)"
        other = (f"gamma {cfg.gamma:g} / tau {cfg.tau:g}", score_again(case, cfg.gamma, cfg.tau))
        rows = []
        for label, path in ((own_label, case / "eval.json"), other):
            s = _scores(path)
            rows.append(s)
            cells = " | ".join("-" if k not in s else f"{s[k][0]:.2f} / {s[k][1]:.3f}" for k, _ in BLEND_COLUMNS)
            d_near = s["idw_sample"][0] - s["nearest"][0]
            best = max(IDW, key=lambda k: s[k][0])
            d_cov = s["coverage"][0] - s[best][0] if "coverage" in s else float("nan")
            lines.append(f"| {case.name} | {label} | {cells} | {d_near:+.2f} | {d_cov:+.2f} |")
        a, b = rows
        summary.append(f"- {case.name}: IDW-Sample {a['idw_sample'][0]:.2f} -> {b['idw_sample'][0]:.2f} dB "
                       f"({b['idw_sample'][0] - a['idw_sample'][0]:+.2f}; Nearest {a['nearest'][0]:.2f}), IDW-2D "
                       f"{b['idw_2d'][0] - a['idw_2d'][0]:+.2f}, IDW-3D {b['idw_3d'][0] - a['idw_3d'][0]:+.2f}, "
                       f"coverage {b['coverage'][0] - a['coverage'][0]:+.2f}.")
    lines += ["", "Per case, the other setting against the run's own:", "", *summary, ""]
    write_text_atomic(cfg.report, "\n".join(lines))
    print(f"wrote {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(CompareBlendSettings))
