"""Blends of a generated pair with and without appearance matching, against its ground truth in the reference
capture's colours: what ``scripts/bench_appearance.py`` (a plain and a jittered scene) and
``scripts/validate_appearance.py`` (one validation pair) measure."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
import tyro
from rich.console import Console

from nerfuser_ns import appearance, runs
from nerfuser_ns.bench.evaluation import SceneRuns, blend_metrics
from nerfuser_ns.bench.ground_truth import load_ground_truth_captures, nerf_to_world_from_captures, score_registration
from nerfuser_ns.bench.scenes import apply_appearance
from nerfuser_ns.blending import PAPER_MISSION_BAY, PAPER_OBJECT_CENTRIC
from nerfuser_ns.registration import read_registration
from nerfuser_ns.scripts import register
from nerfuser_ns.spec import read_registered_nerfs

REGISTRATION_SIZE = 192
"""Longer side of the registration renders (the generated scenes' training images)."""
REGISTRATION_POSES = 32
"""Training poses per NeRF rendered for the registration."""
MAX_TEST_VIEWS = 12
"""World-frame test views blended."""


def register_pair(scene: SceneRuns, output: Path, work_dir: Path, size: int, poses: int, console: Console) -> None:
    """``ns-nerfuser-register`` on the scene's runs (in capture order) with its defaults but the render size and the
    number of training poses; SystemExit when it fails."""
    args = ["--configs", *map(str, scene.configs), "--output", str(output), "--work-dir", str(work_dir),
            "--sampling.size", str(size), "--sampling.max-training-poses", str(poses)]  # fmt: skip
    console.print(f"[bold]{scene.name}: ns-nerfuser-register {' '.join(args)}")
    if register.run(tyro.cli(register.RegisterCommand, args=args)) != 0:
        raise SystemExit(f"{scene.name}: registration failed (see above)")


def capture_gains(scene: SceneRuns) -> list[np.ndarray]:
    """Each capture's linear-RGB gains (exposure x white balance; ones when it has none)."""
    out = []
    for c in scene.ground_truth["captures"]:
        a = c.get("appearance")
        out.append(np.ones(3) if a is None else a["exposure"] * np.asarray(a["white_balance"], dtype=np.float64))
    return out


def registration_errors(scene: SceneRuns, record: dict) -> dict:
    """The registration (its record) against the scene's truth (the paper's errors of the worst NeRF) and what it
    chose."""
    truth = nerf_to_world_from_captures(load_ground_truth_captures(scene.scene_dir, scene.captures),
                                        [runs.read_dataparser_transform(p) for p in scene.configs])  # fmt: skip
    scored = score_registration(record, truth)
    worst = max((n["ground_truth"] for n in scored["nerfs"]),
                key=lambda g: np.inf if g["r_err_deg"] is None else g["r_err_deg"])  # None: NaN, a failure
    choice = record.get("sampling_choice") or {}
    return {**{k: worst[k] for k in ("r_err_deg", "t_err", "s_err", "failure")},
            "source": choice.get("source"), "mode": choice.get("mode", record["settings"].get("mode"))}


def measure(scene: SceneRuns, reg: Path, max_test_views: int, console: Console) -> dict:
    """Every paper blend method on the scene's world-frame test views with the registration's transforms: unmatched,
    with the cross-render colour maps alone, matched (the registration's maps) and, where the captures differ, with
    the true maps."""
    layout = scene.ground_truth["layout"]
    gamma, tau = PAPER_OBJECT_CENTRIC if layout == "object-centric" else PAPER_MISSION_BAY
    models = [(n, runs.load_run(p).model) for n, p in zip(scene.captures, scene.configs, strict=True)]
    # registered in the scene's capture order (_register passes the configs so): the names are the runs' paths
    entries = read_registered_nerfs(reg, check_runs=False)
    if [e.config_path.resolve() for e in entries] != [p.resolve() for p in scene.configs]:
        raise SystemExit(
            f"{reg} registers other runs than {scene.name}'s; delete it to register again"
        )
    transforms = [e.nerf_to_common for e in entries]
    maps = [e.colour_to_reference for e in entries]
    # the maps as the cross-renders alone fitted them: the reference NeRF's map to its images taken back out
    record = read_registration(reg)
    ref_colour = (record.get("reference_colour") or {}).get("map")
    pair_maps = maps if ref_colour is None else [
        None if m is None else appearance.compose(appearance.invert(np.asarray(ref_colour)), m) for m in maps]
    gains = capture_gains(scene)
    cams, target = scene.test_views(reference=0, max_views=max_test_views)
    target = apply_appearance(target, None if np.array_equal(gains[0], np.ones(3)) else gains[0])
    result: dict = {"scene": str(scene.scene_dir), "gains": [g.tolist() for g in gains],
                    "true_maps": [(gains[0] / g).tolist() for g in gains],  # reference colours from NeRF i's
                    "fitted_maps": [None if m is None else np.diag(m[:, :3]).tolist() for m in maps],
                    "pair_maps": [None if m is None else np.diag(m[:, :3]).tolist() for m in pair_maps],
                    "reference_colour": None if ref_colour is None else np.diag(np.asarray(ref_colour)[:, :3]).tolist(),
                    "registration": registration_errors(scene, record)}  # fmt: skip
    # the true maps applied to the same runs: what matching could reach with an exact fit (plain: the identity,
    # which is the unmatched blend)
    true_maps = [np.hstack([np.diag(gains[0] / g), np.zeros((3, 1))]) for g in gains]
    differs = any(not np.allclose(g, gains[0]) for g in gains)
    passes = [("unmatched", None)] + ([("matched_pairs", pair_maps)] if ref_colour is not None else [])
    passes += [("matched", maps)] + ([("true_matched", true_maps)] if differs else [])
    for label, colour_maps in passes:
        t = time.perf_counter()
        with torch.no_grad():
            result[label] = blend_metrics(models, transforms, cams, target, gamma=gamma, tau=tau,
                                          description=f"{scene.name} {label}", colour_maps=colour_maps)  # fmt: skip
        console.print(f"{scene.name} {label}: " + ", ".join(f"{m} {v['psnr']:.2f}" for m, v in result[label].items())
                      + f" ({time.perf_counter() - t:.0f} s)")  # fmt: skip
    return result
