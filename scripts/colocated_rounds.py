"""The re-render refinement (``nerfuser_ns.registration.colocated``) round by round on a practitioner case's
registration (or the solution its checks refused), each round scored against the case's truths.

    python scripts/colocated_rounds.py --case drive:10 \
        --registration outputs/practitioner/drive-10/registration_rejected.json --rounds 2

Diagnostic only: it changes no registration file. Prints per round the refinement's summary and the link's r/t/s
errors against the stored truth, the pose truth and (after ``bench_practitioner.py --stages content``) the content
truth.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_practitioner import content_ground_truth  # noqa: E402

from nerfuser_ns import sim3  # noqa: E402
from nerfuser_ns.bench.practitioner_cases import capture_ground_truth, case_layout  # noqa: E402
from nerfuser_ns.registration.colocated import refine_pair  # noqa: E402
from nerfuser_ns.registration.config import ColocatedConfig  # noqa: E402
from nerfuser_ns.registration.render_cache import ViewSet, load_render_intrinsics  # noqa: E402
from nerfuser_ns.renderers import NerfstudioRenderer  # noqa: E402


@dataclass
class ColocatedRounds:
    case: str
    """The practitioner case (``layout:seed``), as bench_practitioner.py names it."""
    registration: Path
    """Its registration file or refused solution (two NeRFs; their render folders must carry depth)."""
    root: Path = Path("outputs/practitioner")
    """Where bench_practitioner.py keeps the cases."""
    rounds: int = 2
    """Rounds to run, one at a time (each renders again at the link the previous one found)."""
    device: str = "cpu"
    """Where the NeRFs render."""


def main(cfg: ColocatedRounds) -> None:
    case_dir = cfg.root / cfg.case.replace(":", "-")
    layout = case_layout(cfg.case, 320, 240, 2, 0.0, False)  # bench_practitioner.py's defaults
    gt = capture_ground_truth(layout, case_dir, optimized=False)
    truths = {"stored": [g["nerf_to_world"] for g in gt], "pose": [g["nerf_to_world_pose"] for g in gt],
              "content": content_ground_truth(case_dir, gt)}  # fmt: skip
    reg = json.loads(cfg.registration.read_text())
    ref = reg["reference"]["index"]
    other = 1 - ref

    def score(T: np.ndarray, label: str) -> None:
        parts = [label]
        for name, truth in truths.items():
            if truth is not None:
                e = sim3.sim3_errors(T, sim3.compose(sim3.invert_sim3(truth[ref]), truth[other]))
                parts.append(f"{name} {e.r_err_deg:.3f} deg / {e.t_err:.4f} / {e.s_err:.4f}")
        print(" | ".join(parts), flush=True)

    T = np.asarray(reg["nerfs"][other]["T_to_reference"], dtype=np.float64)
    score(T, "start")
    ra, rb = (NerfstudioRenderer(reg["nerfs"][i]["config"], device=cfg.device, name=reg["nerfs"][i]["name"])
              for i in (ref, other))  # fmt: skip
    va, vb = (ViewSet.from_folder(reg["nerfs"][i]["render_folder"]) for i in (ref, other))
    intr = load_render_intrinsics(reg["nerfs"][ref]["render_folder"])
    one = replace(ColocatedConfig(), iterations=1)
    for n in range(cfg.rounds):
        T, outcome = refine_pair(ra, rb, va, vb, T, intr, one)
        print(json.dumps(outcome.rounds), "kept" if outcome.kept else f"kept the link: {outcome.reason}", flush=True)
        score(T, f"round {n + 1}")


if __name__ == "__main__":
    main(tyro.cli(ColocatedRounds))
