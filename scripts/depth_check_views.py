"""Where the cross-render depth check looks: a practitioner case's registered link and its true link, cross-rendered at
each NeRF's views evenly spread, nearest the other NeRF's views under the link, or nearest among the views rendered at
training cameras (``training``: what the self-check now uses, :func:`nerfuser_ns.registration.self_check.depth_views`).
``--scale-errors`` adds the truth with NeRF 1's scale off by each given log scale about its origin (a link the depth
check must still refuse at the views it uses).

The views that share the most SfM points with the other NeRF (the NCC's, and the depth's before) are the content an
SfM link was fitted to; the registration file records the check there (``pairs[].self_check``), printed beside::

    python scripts/depth_check_views.py \\
        --cases drive:6=outputs/practitioner_rerun/drive-6,at_922940c/registration.json \\
        drive:7=outputs/practitioner/drive-7 --report reports/depth_check_views.md

A case is ``LAYOUT:SEED=FOLDER[,REGISTRATION]``: a case folder of ``scripts/bench_practitioner.py`` (its runs and
stored truth) and the registration in it (default ``registration.json``), whose render folders (the registration's
work folder) are reused as they are.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout, case_registration, run_config
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig, read_registration
from nerfuser_ns.registration.render_cache import ViewSet, load_render_intrinsics
from nerfuser_ns.registration.self_check import depth_views, nearest_views, spread_views, view_nccs
from nerfuser_ns.renderers import NerfstudioRenderer

Choice = Literal["spread", "nearest", "training"]
"""Where the depth is compared: views evenly spread, nearest the other NeRF's, or nearest among training views."""


@dataclass
class DepthCheckViews:
    """The depth check's log ratio and the NCC of a case's link and its truth at choices of views."""

    cases: list[str]
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]`` (the case folder, the registration file in it)."""
    report: Path
    """Markdown report (a JSON of the rows beside it)."""
    choices: list[Choice] = field(default_factory=lambda: ["spread", "nearest", "training"])
    """View choices to measure."""
    scale_errors: list[float] = field(default_factory=list)
    """Also check the truth with NeRF 1 scaled by ``exp(e)`` about its origin, for each ``e`` (log scale)."""


@dataclass
class Row:
    case: str
    link: str
    views: str
    ncc_0_in_1: float
    ncc_1_in_0: float
    depth_0_in_1: float
    depth_1_in_0: float
    r_err_deg: float
    t_err: float
    s_err: float


def _median(x) -> float:
    x = np.asarray(x, dtype=np.float64)
    return float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")


def direction(src: ViewSet, dst, T: np.ndarray, order: list[int], intr, cfg: RegistrationConfig) -> tuple[float, float]:
    """(median NCC, median log depth ratio) of ``dst`` rendered at ``src``'s first views of ``order`` through ``T``."""
    depths: list[float] = []
    scores = view_nccs(src, dst, T, order[: cfg.self_check_views], intr, cfg, depths=depths)
    return _median(scores), _median(depths)


def measure(spec: str, choices: list[Choice], scale_errors: list[float], console: Console) -> tuple[list[Row], dict]:
    case, case_dir, registration_path = case_registration(spec)
    reg = read_registration(registration_path)
    layout = case_layout(case)
    captures = [c.name for c in layout.captures]
    renderers = [NerfstudioRenderer(run_config(case_dir, c), name=c) for c in captures]
    views = [ViewSet.from_folder(n["render_folder"]) for n in reg["nerfs"]]
    intr = load_render_intrinsics(views[0].folder)
    truth = sim3.to_reference_frame(
        np.stack([g["nerf_to_world"] for g in capture_ground_truth(layout, case_dir, optimized=False)])
    )
    links = {
        "registered": np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in reg["nerfs"]]),
        "truth": truth,
    }
    for e in scale_errors:
        links[f"truth, scale {e:+g}"] = np.stack([truth[0], sim3.rescaled_about_origin(truth[1], e)])
    cfg = RegistrationConfig(colour_views=0)
    rows = []
    for label, T in links.items():
        T_01 = sim3.relative_sim3(T[1], T[0])
        T_10 = sim3.invert_sim3(T_01)
        e = sim3.sim3_errors(T[1], truth[1])
        spread = [[int(k) for k in spread_views(v, cfg.self_check_views)] for v in views]
        orders = {
            "spread": spread,
            "nearest": [nearest_views(views[0], T_01, views[1]), nearest_views(views[1], T_10, views[0])],
            "training": [depth_views(views[0], T_01, views[1]), depth_views(views[1], T_10, views[0])],
        }
        for choice in choices:
            o0, o1 = orders[choice]
            n01, d01 = direction(views[0], renderers[1], T_01, o0, intr, cfg)
            n10, d10 = direction(views[1], renderers[0], T_10, o1, intr, cfg)
            row = Row(
                registration_path.as_posix(),
                label,
                choice,
                n01,
                n10,
                d01,
                d10,
                float(e.r_err_deg),
                float(e.t_err),
                float(e.s_err),
            )
            console.print(row)
            rows.append(row)
    recorded = reg["pairs"][0].get("self_check", {})
    return rows, {"case": registration_path.as_posix(), "sampling": reg.get("sampling_choice"), "self_check": recorded}


def main(cfg: DepthCheckViews) -> None:
    console = Console()
    rows, recorded = [], []
    for spec in cfg.cases:
        r, rec = measure(spec, cfg.choices, cfg.scale_errors, console)
        rows += r
        recorded.append(rec)
    lines = [
        "# The depth check at spread, nearest and nearest training views",
        "",
        f"`python scripts/depth_check_views.py {' '.join(sys.argv[1:])}`",
        "",
        "| registration | link | views | r_err (deg) | t_err | s_err | NCC 0 in 1 | NCC 1 in 0 | depth 0 in 1 | "
        "depth 1 in 0 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r.case} | {r.link} | {r.views} | {r.r_err_deg:.3f} | {r.t_err:.4f} | {r.s_err:.4f} | "
            f"{r.ncc_0_in_1:.3f} | {r.ncc_1_in_0:.3f} | {r.depth_0_in_1:+.3f} | {r.depth_1_in_0:+.3f} |"
        )
    lines += ["", "The registration's own check (views sharing the most SfM points), as recorded in its file:", ""]
    for rec in recorded:
        sc = rec["self_check"]
        lines.append(
            f"- {rec['case']}: NCC {sc.get('ncc_i_in_j', float('nan')):.3f} / "
            f"{sc.get('ncc_j_in_i', float('nan')):.3f}, depth {sc.get('depth_i_in_j', float('nan')):+.3f} / "
            f"{sc.get('depth_j_in_i', float('nan')):+.3f}"
        )
    write_text_atomic(
        cfg.report.with_suffix(".json"),
        json.dumps({"rows": [asdict(r) for r in rows], "recorded": recorded}, indent=1) + "\n",
    )
    write_text_atomic(cfg.report, "\n".join(lines) + "\n")
    console.print(f"wrote {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(DepthCheckViews))
