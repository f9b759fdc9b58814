"""The SfM mode's twin check (``--twin-check``, off by default) on registrations made without it: would it refuse them?

For each practitioner case (a folder of ``scripts/bench_practitioner.py``), the registered transforms of its
registration file are checked as the pipeline checks the SfM's link (:func:`nerfuser_ns.registration.twin_check`),
on the registration's own renders (with depth), every other setting at its default; the result is printed beside the
link's errors against the case's truth (stored tie and pose tie). A correct registration that the check refuses is a
false alarm; a wrong one that it passes, a miss::

    python scripts/twin_check_cases.py --cases drive:12=outputs/practitioner/drive-12 \\
        room:4=outputs/practitioner/room-4 --report reports/twin_check_cases.md

A case is ``LAYOUT:SEED=FOLDER[,REGISTRATION]`` (default ``registration.json``). The check runs on the final
transforms (after the direct alignment), where the pipeline runs it before that alignment: the same link, refined.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import (
    capture_ground_truth,
    case_layout,
    case_registration,
    reference_links,
    run_config,
)
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig, read_registration
from nerfuser_ns.registration.render_cache import ViewSet, load_render_intrinsics
from nerfuser_ns.registration.self_check import spanning_pairs
from nerfuser_ns.registration.twin_check import twin_check
from nerfuser_ns.renderers import NerfstudioRenderer


@dataclass
class TwinCheckCases:
    """The twin check on existing practitioner registrations."""

    cases: list[str]
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]`` (the case folder, the registration file in it)."""
    report: Path
    """Markdown report (a JSON of the rows beside it)."""


def measure(spec: str, console: Console) -> dict:
    case, case_dir, path = case_registration(spec)
    reg = read_registration(path)
    layout = case_layout(case)
    names = [c.name for c in layout.captures]
    renderers = [NerfstudioRenderer(run_config(case_dir, c), name=n["name"]) for c, n in zip(names, reg["nerfs"],
                                                                                            strict=True)]  # fmt: skip
    views = [ViewSet.from_folder(n["render_folder"], n["name"]) for n in reg["nerfs"]]
    if not all(v.has_depth for v in views):
        raise SystemExit(f"{path}: its renders carry no depth; the twin check needs it")
    intr = load_render_intrinsics(views[0].folder)
    links = reference_links(reg, capture_ground_truth(layout, case_dir, optimized=False))
    T, ref = links["registered"], reg["reference"]["index"]
    truths = {"nerf_to_world": links["stored truth"], "nerf_to_world_pose": links["pose truth"]}
    overlap = np.zeros((len(T), len(T)), dtype=int)
    for p in reg["pairs"]:
        overlap[p["i"], p["j"]] = overlap[p["j"], p["i"]] = p.get("covisible_points") or 1
    pairs = spanning_pairs(overlap)
    cfg = RegistrationConfig()
    start = time.perf_counter()
    verdict = twin_check(renderers, views, T, pairs, intr, cfg, console)
    seconds = time.perf_counter() - start
    errors = {}
    for key, truth in truths.items():
        e = [sim3.sim3_errors(T[i], truth[i]) for i in range(len(T)) if i != ref]
        errors[key] = [[float(x.r_err_deg), float(x.t_err), float(x.s_err)] for x in e]
    row = {"case": case, "registration": path.as_posix(), "sampling": (reg.get("sampling_choice") or {}).get("source"),
           "errors": errors, "refusal": verdict.refusal, "warning": verdict.warning, "summary": verdict.summary,
           "seconds": round(seconds, 1)}  # fmt: skip
    console.print({k: v for k, v in row.items() if k != "summary"}, verdict.summary)
    return row


def _f(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def main(cfg: TwinCheckCases) -> None:
    console = Console()
    rows = [measure(spec, console) for spec in cfg.cases]
    lines = [
        "# The twin check on registrations made before it",
        "",
        f"`python scripts/twin_check_cases.py {' '.join(sys.argv[1:])}`",
        "",
        "Each case's registered link checked as `ns-nerfuser-register --twin-check` checks the SfM's link (every other "
        "setting at its default, the registration's own renders), beside its errors against the stored truth and the "
        "pose truth (r deg / t / s). The rule (a rival better by `known_geometry.ambiguity_margin`, 0.05, in its "
        "worst view) was fixed before any of these cases was checked.",
        "",
        "| case | registered with | errors (stored truth) | errors (pose truth) | rivals | SfM link NCC "
        "| best rival NCC "
        "| rival rotation (deg) | verdict | seconds |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | --- | ---: |",
    ]
    for r in rows:
        for n, p in enumerate(r["summary"].get("pairs", [{}])):
            stored, pose = (r["errors"][k][min(n, len(r["errors"][k]) - 1)] for k in ("nerf_to_world",
                                                                                     "nerf_to_world_pose"))
            lines.append(
                f"| {r['case']} | {r['sampling']} | {stored[0]:.2f} / {stored[1]:.4f} / {stored[2]:.4f} | "
                f"{pose[0]:.2f} / {pose[1]:.4f} / {pose[2]:.4f} | {p.get('rivals', '-')} | "
                f"{_f(p.get('sfm_ncc'), '.3f')} | {_f(p.get('rival_ncc'), '.3f')} | "
                f"{_f(p.get('rival_rotation_deg'), '.1f')} | {p.get('verdict', r['summary'].get('skipped'))} | "
                f"{r['seconds']:.0f} |"
            )
    lines += ["", *[f"- {r['case']}: {r['refusal'] or r['warning'] or 'passed'}" for r in rows]]
    write_text_atomic(cfg.report.with_suffix(".json"), json.dumps(rows, indent=1) + "\n")
    write_text_atomic(cfg.report, "\n".join(lines) + "\n")
    console.print(f"wrote {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(TwinCheckCases))
