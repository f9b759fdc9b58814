"""Registration of many NeRFs: the pose graph (``--mode graph``, ours) against the one SfM over all renders (``--mode
sfm``, the paper's default pipeline) as a drive gets longer, on ground-truth renderers (no trained NeRFs).

The scene is the drive layout (``nerfuser_ns.bench.scenes.make_drive``: a car's 8-camera roof rig along a street, one
NeRF per block of rig stops) of ``--world-blocks`` blocks (default: the largest N); each case registers its first N
blocks, N from ``--blocks``. Each NeRF is a ground-truth scene renderer (exact colour and depth: a perfect NeRF) of
its block in the block's own frame. By default each block's renderer holds
only the street within ``--crop-m`` metres of its cameras: a ray-cast's cost grows with the number of primitives, so
without the crop every render of a long drive costs more than one of a short drive (measured: 0.75 s per 240 x 180
render at 8 blocks, 3.4 s at 32 blocks), which a trained NeRF's would not.

Per N and case (graph with the serial executor; graph with Ray on this machine, ``--ray``; the one SfM): the wall time
of the registration (and its steps), peak memory, per-NeRF r/t/s errors against ground truth (median and max over
the non-reference NeRFs, in the reference's units), and the drift: the error of the last block in the first block's
frame (rotation degrees, translation relative to the distance between the two blocks, and in metres).
``--inject-wrong-edge`` adds a graph case in which one accepted edge (on a cycle, so that it can be checked) is
replaced by a wrong SIM(3) just before the pose-graph solve, and reports whether the cycle check dropped it.

Every case runs in a fresh process (``multiprocessing`` spawn) in a fresh work folder (renders not reused; the
wrong-edge case reuses the serial graph case's renders), so its peak memory is its own: ``ru_maxrss`` of the case's
process (``resource.getrusage``, the driver only) and the peak, sampled every ``--memory-interval-s`` by psutil, of
the summed PSS of the case's process and all its descendants (Ray's raylet and workers included).

Example::

    OMP_NUM_THREADS=1 python scripts/bench_scale.py --blocks 8 32 --ray --inject-wrong-edge \\
        --output outputs/bench/scale.json --report reports/bench_scale.md
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import multiprocessing
import os
import platform
import resource
import shlex
import statistics
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import psutil
import tyro
from rich.console import Console

CASES = ("graph", "graph-ray", "sfm", "graph-wrong-edge")
"""graph: pose graph, serial executor; graph-ray: the same on Ray; sfm: the one SfM; graph-wrong-edge: graph, serial,
one wrong edge injected before the solve."""
TARGET_RATIO_32_8 = 4.5
"""Target of the graph mode: time(32 blocks) / time(8 blocks) <= 4.5 (linear, with 12.5% slack)."""


@dataclass
class BenchScale:
    """Pose graph vs one SfM on a drive of N blocks, with ground-truth renderers: time, memory, accuracy, drift."""

    blocks: list[int] = field(default_factory=lambda: [4, 8])
    """Blocks (NeRFs) of the drive, one case per value."""
    modes: list[str] = field(default_factory=lambda: ["graph", "sfm"])
    """graph: the pose graph (serial executor); sfm: the one SfM over all renders (the default pipeline)."""
    ray: bool = False
    """Also run the graph mode on Ray started on this machine (said and skipped when ray is not importable)."""
    inject_wrong_edge: bool = False
    """Also run the graph mode (serial, the serial case's renders reused) with one accepted edge on a cycle replaced by
    a wrong SIM(3) before the pose-graph solve; the report says whether it was dropped."""
    wrong_edge_rotation_deg: float = 15.0
    """Rotation of the wrong edge's error (about a random axis, in its first NeRF's frame)."""
    wrong_edge_translation: float = 0.3
    """Translation of the wrong edge's error (random direction), in length scales of its first NeRF."""
    wrong_edge_log_scale: float = 0.1
    """``log s`` of the wrong edge's scale error."""
    wrong_edge_heaviest: bool = True
    """Give the wrong edge twice the weight of the heaviest edge (a confident wrong registration: the spanning tree
    would take it); --no-wrong-edge-heaviest keeps its own weight."""
    neighbours: Literal["retrieval", "block-order"] = "retrieval"
    """Graph mode's candidate pairs: found from the renders (the default of ns-nerfuser-register), or given in block
    order as a user who knows it would (``--graph.neighbours``: each block with the next two, so every pair lies on a
    cycle)."""
    renders: int = 16
    """Training poses rendered per NeRF (--sampling.max-training-poses; evenly spaced through the block's cameras)."""
    width: int = 240
    """Render width in pixels (the field of view is the rig cameras', 65 deg)."""
    height: int = 180
    """Render height in pixels."""
    stops: int = 12
    """Rig stops per block (8 cameras each); 12 is the drive layout's benchmark value."""
    world_blocks: int | None = None
    """Blocks of the one drive that every case takes its first N blocks from (default: the largest of --blocks), so
    that a block and its street are the same whatever N. A drive built for each N instead gives a short drive's
    blocks less street within their crop (an 8-block street, 80 m, is shorter than a block's 86 m crop window):
    fewer primitives per render, cheaper pair tasks, and a time ratio that mixes the scene's growth with the
    pipeline's."""
    crop_m: float = 40.0
    """Each block's renderer holds the street within this many metres (along it) of the block's cameras (0: the whole
    street): render cost and memory independent of the drive's length. What changes: views along the street show the
    backdrop instead of buildings farther than about this (at 28 m: 15% of the pixels of a forward view, all beyond
    30 m; none of the side views)."""
    self_check_views: int = 4
    """Cross-render self-check views per direction and NeRF pair (the registration's default)."""
    seed: int = 1
    """Layout seed: the street and the cameras (seed 0 is the validation seed)."""
    sampling_seed: int = 0
    """--sampling.seed (0: the evenly spaced training-pose subset; others: a random subset)."""
    sfm_seed: int = 0
    """pycolmap's random seed (--sfm.seed)."""
    wrong_edge_seed: int = 0
    """Seed of the wrong edge's choice and of its error's axis and direction."""
    threads: int = -1
    """Threads of pycolmap's SIFT, matching and mapping (--sfm.num-threads; -1: all cores)."""
    memory_interval_s: float = 0.5
    """How often the case's process tree's memory is sampled."""
    work_dir: Path = Path("outputs/bench/scale_work")
    """Renders and SfM folders, one per case (emptied before each timed case)."""
    output: Path = Path("outputs/bench/scale.json")
    """JSON results (rewritten atomically after every case)."""
    report: Path | None = None
    """Markdown report (written atomically after every case, only when given)."""
    resume: bool = False
    """Keep the cases already in the output (same settings) instead of running them again."""
    verbose: bool = False
    """Show the registrations' own progress."""

    def cases(self) -> list[str]:
        out = [c for c in ("graph", "sfm") if c in self.modes]
        if self.ray:
            out.insert(1 if "graph" in out else 0, "graph-ray")
        if self.inject_wrong_edge:
            out.append("graph-wrong-edge")
        return out

    def world(self) -> int:
        """Blocks of the drive the cases are taken from."""
        return self.world_blocks or max(self.blocks)

    def settings(self) -> dict:
        """What a result depends on (``--resume`` keeps cases run under the same)."""
        skip = {"blocks", "modes", "ray", "inject_wrong_edge", "work_dir", "output", "report", "resume", "verbose",
                "memory_interval_s"}  # fmt: skip
        return {**{k: v for k, v in dataclasses.asdict(self).items() if k not in skip}, "world_blocks": self.world()}


# ---------------------------------------------------------------------------------------------------------------------
# The scene: the drive of N blocks, one ground-truth renderer per block


def drive_layout(cfg: BenchScale, n: int):
    """The first ``n`` blocks of the drive of ``cfg.world()`` blocks (its world and test views unchanged)."""
    from nerfuser_ns.bench import scenes

    world = max(cfg.world(), n)
    layout = scenes.make_layout("drive", seed=cfg.seed, num_captures=world,
                                num_views=scenes.DRIVE_RIG_CAMERAS * cfg.stops, num_test_views=world - 1, width=192,
                                height=144)  # fmt: skip
    return dataclasses.replace(layout, captures=layout.captures[:n])


def crop_scene(scene, x_lo: float, x_hi: float):
    """The primitives of ``scene`` whose x extent meets ``[x_lo, x_hi]`` (the enclosure and the road span the whole
    street and stay); textures and objects unchanged."""
    import torch

    def meets(lo, hi):
        return (hi >= x_lo) & (lo <= x_hi)

    c, u, v = scene.quad_corner[:, 0], scene.quad_u[:, 0], scene.quad_v[:, 0]
    corners = torch.stack([c, c + u, c + v, c + u + v])
    q = meets(corners.min(0).values, corners.max(0).values)
    s = meets(scene.sphere_center[:, 0] - scene.sphere_radius, scene.sphere_center[:, 0] + scene.sphere_radius)
    y = meets(scene.cylinder_base[:, 0] - scene.cylinder_radius, scene.cylinder_base[:, 0] + scene.cylinder_radius)
    d = meets(scene.disk_center[:, 0] - scene.disk_radius, scene.disk_center[:, 0] + scene.disk_radius)
    return dataclasses.replace(
        scene, quad_corner=scene.quad_corner[q], quad_u=scene.quad_u[q], quad_v=scene.quad_v[q],
        quad_surface=scene.quad_surface[q], sphere_center=scene.sphere_center[s], sphere_radius=scene.sphere_radius[s],
        sphere_surface=scene.sphere_surface[s], cylinder_base=scene.cylinder_base[y],
        cylinder_radius=scene.cylinder_radius[y], cylinder_height=scene.cylinder_height[y],
        cylinder_surface=scene.cylinder_surface[y], disk_center=scene.disk_center[d], disk_radius=scene.disk_radius[d],
        disk_surface=scene.disk_surface[d],
    )  # fmt: skip


def block_renderers(layout, crop_m: float) -> list:
    """One ground-truth renderer per block, in the block's frame; with ``crop_m`` > 0 each holds only its part of the
    street (its cache key says so)."""
    from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer

    out = []
    for k, cap in enumerate(layout.captures):
        lay = layout
        if crop_m > 0:
            x = cap.c2w_world[:, 0, 3]
            params = {**layout.params, "crop_m": crop_m, "crop_block": k}
            lay = dataclasses.replace(layout, scene=crop_scene(layout.scene, x.min() - crop_m, x.max() + crop_m),
                                      params=params)  # fmt: skip
        out.append(SceneFrameRenderer.from_layout(lay, cap.name))
    return out


# ---------------------------------------------------------------------------------------------------------------------
# The wrong edge (graph.py has no hook between the pairwise registrations and the solve: its module-level
# solve_pose_graph is wrapped)


def install_wrong_edge(cfg: BenchScale, info: dict) -> None:
    """Make the graph mode's pose-graph solve see one accepted edge replaced by a wrong one; ``info`` says which."""
    from nerfuser_ns import sim3
    from nerfuser_ns.registration import graph as graph_module
    from nerfuser_ns.registration import pose_graph as pg

    original = pg.solve_pose_graph

    def solve(num_nodes, edges, reference=0, lengths=None, names=None, *args, **kwargs):
        edges = list(edges)
        if not edges:
            return original(num_nodes, edges, reference, lengths, names, *args, **kwargs)
        rng = np.random.default_rng(cfg.wrong_edge_seed)
        # an edge on one verifying cycle only (a lone triangle) cannot be told from the cycle's other edges: the
        # check then drops the lightest; take one on two or more cycles where there is one
        cycles, _ = pg.verifying_cycles(num_nodes, edges, np.ones(len(edges), bool))
        through = np.zeros(len(edges), int)
        for cycle in cycles:
            through[cycle] += 1
        pool = next(p for p in (np.flatnonzero(through >= 2), np.flatnonzero(through >= 1), np.arange(len(edges)))
                    if len(p))  # fmt: skip
        n = int(rng.choice(pool))
        e = edges[n]
        axis, direction = (a / np.linalg.norm(a) for a in rng.normal(size=(2, 3)))
        length = 1.0 if lengths is None else float(lengths[e.i])
        error = sim3.make_sim3(
            sim3.so3_exp(axis * math.radians(cfg.wrong_edge_rotation_deg)),
            direction * cfg.wrong_edge_translation * length,
            math.exp(cfg.wrong_edge_log_scale),
        )
        weight = 2.0 * max(x.weight for x in edges) if cfg.wrong_edge_heaviest else e.weight
        edges[n] = pg.Edge(e.i, e.j, error @ sim3.to_homogeneous(e.T), weight)  # fmt: skip
        label = (names[e.i], names[e.j]) if names is not None else (str(e.i), str(e.j))
        info.update(pair=list(label), cycles=int(through[n]), identifiable=bool(through[n] >= 2), edges=len(edges),
                    weight=weight)  # fmt: skip
        err = sim3.sim3_errors(edges[n].T, e.T)
        info["error"] = {"rotation_deg": float(err.r_err_deg), "translation": float(err.t_err) / length,
                         "log_scale": float(err.s_err)}  # fmt: skip
        result = original(num_nodes, edges, reference, lengths, names, *args, **kwargs)
        got = result.edges[n]
        info.update(status=got.status, detected=got.status == "dropped", reason=got.reason,
                    residual_rotation_deg=got.residual.rotation_deg,
                    others_dropped=[[label_of(names, x.i), label_of(names, x.j)] for m, x in enumerate(result.edges)
                                    if x.status == "dropped" and m != n])  # fmt: skip
        return result

    graph_module.solve_pose_graph = solve


def label_of(names, i: int) -> str:
    return str(i) if names is None else names[i]


# ---------------------------------------------------------------------------------------------------------------------
# One case, in its own process


def _mib(x: float) -> float:
    return round(x / 2**20, 1)


def block_order_neighbours(n: int) -> tuple[str, ...]:
    """``--graph.neighbours`` of a drive of ``n`` blocks in order: each block with the next and the one after."""
    return tuple(f"{i}:{j}" for i in range(n) for j in (i + 1, i + 2) if j < n)


def run_case(cfg: BenchScale, n: int, case: str, work: Path) -> dict:
    """Build the drive of ``n`` blocks, register it as ``case`` says, score it against the truth."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    from nerfuser_ns import registration, sim3
    from nerfuser_ns.bench.ground_truth import ground_truth_errors
    from nerfuser_ns.registration import PoseSamplingConfig, RegistrationConfig, RegistrationError, RegistrationFailed

    t0 = time.perf_counter()
    layout = drive_layout(cfg, n)
    renderers = block_renderers(layout, cfg.crop_m)
    layout_s = time.perf_counter() - t0
    truth = [c.capture_to_world for c in layout.captures]

    sampling = PoseSamplingConfig(source="training", max_training_poses=cfg.renders, width=cfg.width,
                                  height=cfg.height, seed=cfg.sampling_seed)  # fmt: skip
    config = RegistrationConfig(mode="sfm" if case == "sfm" else "graph", sampling=sampling,
                                self_check_views=cfg.self_check_views)  # fmt: skip
    config.sfm.seed, config.sfm.num_threads = cfg.sfm_seed, cfg.threads
    config.graph.executor = "ray" if case == "graph-ray" else "serial"
    if cfg.neighbours == "block-order":
        config.graph.neighbours = block_order_neighbours(n)
    injected: dict = {}
    if case == "graph-wrong-edge":
        install_wrong_edge(cfg, injected)

    rss_before = psutil.Process().memory_info().rss
    status, error, record = "ok", None, None
    t = time.perf_counter()
    try:
        record = registration.register(renderers, config, work, Console(quiet=not cfg.verbose)).to_record()
    except RegistrationFailed as e:  # the self-check rejected the solution: still scored
        status, error, record = "self-check failed", str(e).splitlines()[0], e.record
    except RegistrationError as e:
        status, error = "error", str(e).splitlines()[0]
    wall = time.perf_counter() - t
    out = {
        "blocks": n, "case": case, "status": status, "error": error, "wall_s": round(wall, 2),
        "layout_s": round(layout_s, 2), "rss_before_mib": _mib(rss_before),
        "ru_maxrss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),  # KiB on Linux
    }  # fmt: skip
    if case == "graph-wrong-edge":
        out["wrong_edge"] = injected or {"injected": False}
    if record is None:
        return out

    timings = record.get("timings_s", {})
    render_s = float(timings.get("render") or 0.0)
    ref = int(record["reference"]["index"])
    T = np.stack([np.asarray(nerf["T_to_reference"], dtype=np.float64) for nerf in record["nerfs"]])
    errs = ground_truth_errors(T, truth, ref)
    others = [g for i, g in enumerate(errs) if i != ref]

    def stat(key: str, fn) -> float | None:
        vals = [g[key] for g in others]
        return None if any(v is None for v in vals) else float(fn(vals))

    last = n - 1 if ref == 0 else 0
    T_true_last = np.asarray(errs[last]["T_to_reference_true"])
    distance = float(np.linalg.norm(T_true_last[:3, 3]))  # reference units
    metres_per_unit = float(sim3.decompose_sim3(truth[ref])[2])
    g_last = errs[last]
    out.update({
        "timings_s": timings, "render_s": round(render_s, 2), "after_render_s": round(wall - render_s, 2),
        "renders_per_nerf": cfg.renders, "reference": record["reference"]["name"],
        "nerfs": [{"name": nerf["name"], **{k: g[k] for k in ("r_err_deg", "t_err", "s_err", "failure")}}
                  for nerf, g in zip(record["nerfs"], errs, strict=True)],
        "accuracy": {f"{fn_name}_{key}": stat(key, fn) for key in ("r_err_deg", "t_err", "s_err")
                     for fn_name, fn in (("median", statistics.median), ("max", max))},
        "failures": sum(g["failure"] for g in others),
        "drift": {
            "from": record["nerfs"][ref]["name"], "to": record["nerfs"][last]["name"],
            "rotation_deg": g_last["r_err_deg"], "translation": g_last["t_err"],
            "translation_relative": None if g_last["t_err"] is None else g_last["t_err"] / distance,
            "translation_m": None if g_last["t_err"] is None else g_last["t_err"] * metres_per_unit,
            "distance_m": distance * metres_per_unit, "log_scale": g_last["s_err"],
        },
        "T_to_reference": T.tolist(),
    })  # fmt: skip
    g = record.get("graph")
    if g is not None:
        status_of = [e["status"] for e in g["edges"]]
        out["graph"] = {
            "candidates": len(g["edges"]), "source": g["candidates"]["source"],
            **{s: status_of.count(s) for s in ("kept", "unverified", "dropped", "rejected")},
            "dropped_pairs": [e["names"] for e in g["edges"] if e["status"] == "dropped"],
            "cycles": len(g["cycles"]), "cycles_passed": sum(c["passed"] for c in g["cycles"]),
            "tasks_s": g.get("tasks_s"),
        }  # fmt: skip
    return out


def _case_process(cfg: BenchScale, n: int, case: str, work: str, conn) -> None:
    try:
        result = run_case(cfg, n, case, Path(work))
    except BaseException as e:  # reported as the case's result
        result = {"blocks": n, "case": case, "status": "crash", "error": f"{type(e).__name__}: {e}".splitlines()[0],
                  "traceback": traceback.format_exc()[-3000:]}  # fmt: skip
    conn.send(result)
    conn.close()


def _tree_memory(pid: int) -> int:
    """Summed PSS (RSS where PSS is unknown) of process ``pid`` and all its descendants, in bytes."""
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            m = p.memory_full_info()
            total += getattr(m, "pss", m.rss)
        except psutil.Error:
            pass
    return total


def run_in_process(cfg: BenchScale, n: int, case: str, work: Path) -> dict:
    ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    load = os.getloadavg()[0]
    t = time.perf_counter()
    proc = ctx.Process(target=_case_process, args=(cfg, n, case, str(work), send))
    proc.start()
    send.close()
    peak, result = 0, None
    while result is None:
        peak = max(peak, _tree_memory(proc.pid))
        if receive.poll(cfg.memory_interval_s):
            try:
                result = receive.recv()
            except EOFError:
                break
        elif not proc.is_alive():
            break
    proc.join()
    if result is None:
        result = {"blocks": n, "case": case, "status": "crash", "error": f"process exited {proc.exitcode}"}
    result["peak_tree_pss_mib"] = _mib(peak)
    result["case_s"] = round(time.perf_counter() - t, 1)
    result["load_avg_at_start"] = round(load, 2)
    return result


# ---------------------------------------------------------------------------------------------------------------------
# Results


def scaling(results: list[dict], case: str) -> dict | None:
    """time(N_max) / time(N_min) of a case (total wall time and after rendering), against linear."""
    rows = {r["blocks"]: r for r in results if r["case"] == case and r.get("status") in ("ok", "self-check failed")}
    if len(rows) < 2:
        return None
    lo, hi = min(rows), max(rows)
    return {"n_min": lo, "n_max": hi, "time_ratio": rows[hi]["wall_s"] / rows[lo]["wall_s"],
            "after_render_ratio": rows[hi]["after_render_s"] / rows[lo]["after_render_s"],
            "render_ratio": rows[hi]["render_s"] / rows[lo]["render_s"] if rows[lo]["render_s"] > 0 else None,
            "linear": hi / lo, "target": TARGET_RATIO_32_8 / 4.0 * hi / lo}  # fmt: skip


def ray_matches_serial(results: list[dict], n: int) -> float | None:
    """Largest difference between the graph mode's transforms on Ray and in this process (None: not both ran)."""
    rows = {r["case"]: r for r in results if r["blocks"] == n and "T_to_reference" in r}
    if "graph" not in rows or "graph-ray" not in rows:
        return None
    return float(np.abs(np.asarray(rows["graph"]["T_to_reference"]) - np.asarray(rows["graph-ray"]["T_to_reference"]))
                 .max())  # fmt: skip


def _f(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _status(r: dict, width: int = 100) -> str:
    """A case's status with its error's start (the whole line is in the JSON)."""
    if r.get("error") is None:
        return r["status"]
    error = r["error"] if len(r["error"]) <= width else r["error"][: width - 3] + "..."
    return f"{r['status']}: {error}".replace("|", "/")


def markdown(report: dict) -> str:
    s = report["settings"]
    lines = [
        f"# Registration of many NeRFs: pose graph vs one SfM on a long drive ({report['date']})", "",
        f"`{report['command']}`", "",
        f"On {report['machine']['platform']}, {report['machine']['cpus']} CPUs, OMP_NUM_THREADS="
        f"{report['machine']['omp_num_threads']}, torch {report['machine']['torch_threads']} threads. Drive layout "
        f"(seed {s['seed']}, {s['stops']} rig stops of 8 cameras per block"
        + (f"; every case the first N blocks of one {s['world_blocks']}-block drive" if s.get("world_blocks") else
           "; a drive built for each N")
        + "), ground-truth renderers (each block's "
        + (f"street within {s['crop_m']:g} m of its cameras" if s["crop_m"] > 0 else "whole street")
        + f"), {s['renders']} training poses rendered per NeRF at {s['width']}x{s['height']}, self-check "
        f"{s['self_check_views']} views; sampling seed {s['sampling_seed']}, SfM seed {s['sfm_seed']}; the graph's "
        + ("candidate pairs in block order (`--graph.neighbours`: each block with the next two)"
           if s.get("neighbours") == "block-order" else "candidate pairs from the renders (retrieval)")
        + ". Errors "
        "against ground truth in the first block's frame (t in its units); drift: the last block's error, its "
        "translation relative to the distance between the first and last block. Memory: `ru_maxrss` of the case's "
        "process (`resource.getrusage`, the driver only) and the peak summed PSS of the case's process tree "
        f"(psutil, every {report['memory_interval_s']} s; Ray's raylet and workers included). Each case in a fresh "
        "process and work folder (renders made, not reused; the wrong-edge case reuses the serial graph case's). "
        "Load at start: the machine's 1-minute load average when the case started (other work slows the timings).",
        "",
    ]  # fmt: skip
    for case, sc in report["scaling"].items():
        if sc is None:
            continue
        verdict = "meets" if sc["time_ratio"] <= sc["target"] else "misses"
        lines.append(
            f"- **{case}**: `time(N_max)/time(N_min) = {sc['time_ratio']:.2f}` (N {sc['n_max']} / {sc['n_min']}; "
            f"linear {sc['linear']:.2f}; target {sc['target']:.2f}, as time(32)/time(8) <= {TARGET_RATIO_32_8}: "
            f"{verdict} it); after rendering {sc['after_render_ratio']:.2f}, rendering "
            f"{_f(sc['render_ratio'], '.2f')}"
        )
    lines.append("")
    for n in report["blocks"]:
        rows = [r for r in report["cases"] if r["blocks"] == n]
        if not rows:
            continue
        lines += [
            f"## {n} blocks",
            "",
            "| case | status | wall s | render s | after render s | ru_maxrss MiB | tree PSS MiB | edges kept / "
            "unverified / dropped / rejected | r med / max (deg) | t med / max | s med / max | drift r (deg) | "
            "drift t (rel) | drift t (m) | load at start |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for r in rows:
            a, d, g = r.get("accuracy") or {}, r.get("drift") or {}, r.get("graph")
            status = _status(r)
            edges = "-" if g is None else f"{g['kept']} / {g['unverified']} / {g['dropped']} / {g['rejected']}"
            lines.append(
                f"| {r['case']} | {status} | {_f(r.get('wall_s'), '.1f')} | {_f(r.get('render_s'), '.1f')} | "
                f"{_f(r.get('after_render_s'), '.1f')} | {_f(r.get('ru_maxrss_mib'), '.0f')} | "
                f"{_f(r.get('peak_tree_pss_mib'), '.0f')} | {edges} | "
                f"{_f(a.get('median_r_err_deg'), '.3f')} / {_f(a.get('max_r_err_deg'), '.3f')} | "
                f"{_f(a.get('median_t_err'), '.4f')} / {_f(a.get('max_t_err'), '.4f')} | "
                f"{_f(a.get('median_s_err'), '.4f')} / {_f(a.get('max_s_err'), '.4f')} | "
                f"{_f(d.get('rotation_deg'), '.3f')} | {_f(d.get('translation_relative'), '.4f')} | "
                f"{_f(d.get('translation_m'), '.3f')} | {_f(r.get('load_avg_at_start'), '.2f')} |"
            )
        diff = report["ray_vs_serial"].get(str(n))
        if diff is not None:
            lines += ["", f"Ray vs serial: largest transform difference {diff:.3g}."]
        lines.append("")
    tasks = [r for r in report["cases"] if (r.get("graph") or {}).get("tasks_s")]
    if tasks:
        lines += ["## Tasks of the graph mode", "",
                  "Each task's own time where it ran (no queueing, no transfers): what a Ray cluster runs side by "
                  "side. render and lift: one per NeRF; pair: one per candidate pair (3D matching, hypotheses, "
                  "cross-render choice and check).", "",
                  "| blocks | case | render s (median / max) | lift s | pair s | tasks |",
                  "| ---: | --- | --- | --- | --- | --- |"]  # fmt: skip
        for r in tasks:
            t = r["graph"]["tasks_s"]

            def cell(kind: str, t=t) -> str:
                v = sorted(t.get(kind) or [])
                return "-" if not v else f"{statistics.median(v):.1f} / {v[-1]:.1f}"

            lines.append(f"| {r['blocks']} | {r['case']} | {cell('render')} | {cell('lift')} | {cell('pair')} | "
                         + ", ".join(f"{len(v)} {k}" for k, v in t.items()) + " |")
        lines.append("")
    wrong = [r for r in report["cases"] if r["case"] == "graph-wrong-edge"]
    if wrong:
        lines += ["## One wrong edge injected before the solve", "",
                  "The wrong edge is drawn among the accepted edges on two or more verifying cycles (on one cycle "
                  "only, e.g. a lone triangle, no check can tell it from the cycle's other edges), else on one.",
                  "",
                  f"Error injected: {s['wrong_edge_rotation_deg']:g} deg, {s['wrong_edge_translation']:g} length "
                  f"scales, log s {s['wrong_edge_log_scale']:g}"
                  + ("; weight twice the heaviest edge's" if s["wrong_edge_heaviest"] else "; its own weight")
                  + f" (seed {s['wrong_edge_seed']}).", "",
                  "| blocks | wrong edge | verifying cycles through it | status | detected (dropped) | other edges "
                  "dropped | r max after (deg) | status of the registration |",
                  "| ---: | --- | --- | --- | --- | --- | ---: | --- |"]  # fmt: skip
        for r in wrong:
            w = r.get("wrong_edge") or {}
            others = ", ".join("/".join(p) for p in w.get("others_dropped", [])) or "none"
            lines.append(
                f"| {r['blocks']} | {'/'.join(w.get('pair', ['-']))} | {w.get('cycles', '-')} | "
                f"{w.get('status', 'not injected')} | {'yes' if w.get('detected') else 'no'} | {others} | "
                f"{_f((r.get('accuracy') or {}).get('max_r_err_deg'), '.3f')} | "
                f"{_status(r)} |"
            )
        lines.append("")
    return "\n".join(lines)


def write(cfg: BenchScale, results: list[dict]) -> dict:
    import torch

    from nerfuser_ns.files import write_text_atomic

    order = {c: k for k, c in enumerate(CASES)}
    results = sorted(results, key=lambda r: (r["blocks"], order.get(r["case"], 99)))
    report = {
        "command": shlex.join(["python", "scripts/bench_scale.py", *sys.argv[1:]]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "omp_num_threads": os.environ.get("OMP_NUM_THREADS", "unset"),
                    "torch_threads": torch.get_num_threads(), "torch": torch.__version__},  # fmt: skip
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "blocks": sorted(set(cfg.blocks)),
        "memory_interval_s": cfg.memory_interval_s,
        "settings": cfg.settings(),
        "scaling": {c: scaling(results, c) for c in ("graph", "graph-ray", "sfm")},
        "ray_vs_serial": {str(n): ray_matches_serial(results, n) for n in sorted(set(cfg.blocks))},
        "cases": results,
    }  # fmt: skip
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    if cfg.report is not None:
        write_text_atomic(cfg.report, markdown(report) + "\n")
    return report


def main(cfg: BenchScale) -> None:
    console = Console()
    bad = [m for m in cfg.modes if m not in ("graph", "sfm")]
    if bad or min(cfg.blocks, default=0) < 2 or cfg.renders < 2 or cfg.stops < 1 or cfg.world() < max(cfg.blocks):
        raise SystemExit(f"bench_scale: --modes takes graph and sfm (got {bad}), --blocks >= 2, --renders >= 2, "
                         "--stops >= 1, --world-blocks >= the largest of --blocks")  # fmt: skip
    cases = cfg.cases()
    if "graph-ray" in cases and importlib.util.find_spec("ray") is None:
        console.print('[yellow]bench_scale: ray is not importable (pip install "nerfuser_ns[city]"): the Ray case is '
                      "skipped[/]")  # fmt: skip
        cases.remove("graph-ray")
    done: dict[tuple[int, str], dict] = {}
    if cfg.resume and cfg.output.is_file():
        old = json.loads(cfg.output.read_text())
        if old.get("settings") == json.loads(json.dumps(cfg.settings())):
            done = {(r["blocks"], r["case"]): r for r in old["cases"]}
        else:
            console.print("[yellow]bench_scale: the output was made with other settings: every case runs again[/]")
    results = list(done.values())
    for n in sorted(set(cfg.blocks)):
        for case in cases:
            if (n, case) in done:
                continue
            folder = "graph" if case == "graph-wrong-edge" else case  # reuses the serial graph case's renders
            work = cfg.work_dir / f"blocks_{n}" / folder
            if case != "graph-wrong-edge" and work.exists():
                import shutil

                shutil.rmtree(work)
            console.rule(f"{n} blocks: {case}")
            result = run_in_process(cfg, n, case, work)
            brief = {k: result.get(k) for k in ("status", "error", "wall_s", "render_s", "after_render_s",
                                                "ru_maxrss_mib", "peak_tree_pss_mib", "accuracy", "drift", "graph",
                                                "wrong_edge", "case_s")}  # fmt: skip
            console.print({k: v for k, v in brief.items() if v is not None})
            if "traceback" in result:
                console.print(result["traceback"], markup=False, highlight=False)
            results.append(result)
            write(cfg, results)
    report = write(cfg, results)
    for case, sc in report["scaling"].items():
        if sc is not None:
            console.print(f"{case}: time(N_max)/time(N_min) = {sc['time_ratio']:.2f} (N {sc['n_max']} / "
                          f"{sc['n_min']}, linear {sc['linear']:.2f}, target {sc['target']:.2f}); after rendering "
                          f"{sc['after_render_ratio']:.2f}")  # fmt: skip
    console.print(f"[bold green]wrote[/] {cfg.output}" + (f" and {cfg.report}" if cfg.report else ""))


def entrypoint() -> None:
    main(tyro.cli(BenchScale))


if __name__ == "__main__":
    entrypoint()
