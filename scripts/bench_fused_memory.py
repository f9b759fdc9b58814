"""Peak memory of the fused model against the number of NeRFs, with a bounded sub-model cache and without one.

The scene is drive-like: N NeRFs side by side along a line (NeRF k's SIM(3) into the common frame a translation by
``k * --spacing`` along x, written as a registration file and a fusion spec with the library's own writers), and a
camera path of ``--views`` small views looking along the line, ``--offset`` to its side, moving from the first NeRF
to the last, so that each view passes the distance test (``--tau``) of one or two NeRFs only.

The NeRFs cost no training: one run is made once (a generated object-centric capture, ``--train-steps`` steps of
nerfacto with stock nerfacto's field sizes by default: the 2^19-entry, 16-level hash grid, 64-wide MLPs and its
proposal networks, torch backend; a realistic checkpoint with untrained weights, which memory does not depend on),
and the N runs are copies of it (their checkpoints hard links), all cached under ``--work-dir`` and reused across N.

Per N in ``--nerfs`` and resident limit in ``--limits`` (``None``: all resident, the default of the model), in a
fresh process (``multiprocessing`` spawn): the fused pipeline is built as ``ns-render``/``ns-eval`` build it (the
``nerfuser`` method's config with ``--pipeline.model.max-resident-nerfs``, ``pipeline.setup`` in inference mode:
datamanager, fusion spec, model; the fused checkpoint, which holds no sub-model weights, is not read), and the path
is rendered with ``get_outputs_for_camera``. Recorded: the case process's peak memory (``ru_maxrss`` from
``resource.getrusage``, and the peak PSS and RSS sampled by psutil every ``--memory-interval-s`` in a thread, per
phase), the setup and render times, the cache's ``loads``/``evictions``, and the largest pixel difference between
the limited and the all-resident render of the same N. The target: ``peak(16) <= 1.5 x peak(4)`` with the limit.

Example::

    OMP_NUM_THREADS=1 python scripts/bench_fused_memory.py --nerfs 4 8 16 --limits 3 None \\
        --output outputs/bench/fused_memory.json --report reports/bench_fused_memory.md
"""

from __future__ import annotations

import copy
import dataclasses
import gc
import json
import multiprocessing
import os
import platform
import resource
import shlex
import shutil
import statistics
import sys
import threading
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import psutil
import torch
import tyro
from nerfstudio.configs.method_configs import all_methods
from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config
from nerfuser_ns.method_configs.nerfuser import nerfuser_config
from rich.console import Console

from nerfuser_ns import blending
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.training import slim_checkpoint, train
from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.blending import PAPER_OBJECT_CENTRIC, BlendMethod
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import NerfEntry, write_minimal_registration
from nerfuser_ns.runs import default_device, make_cameras
from nerfuser_ns.sim3 import make_sim3
from nerfuser_ns.spec import read_fusion_spec, write_fusion_spec

TARGET_RATIO = 1.5
"""Target with a resident limit: peak memory at the most NeRFs (16) <= 1.5 x the peak at the fewest (4)."""
RUN_TIMESTAMP = "run"


@dataclass
class BenchFusedMemory:
    """Peak memory and render time of the fused model vs the number of NeRFs, with and without a resident limit."""

    nerfs: list[int] = field(default_factory=lambda: [4, 8, 16])
    """Numbers of NeRFs (one fusion per value)."""
    limits: list[int | None] = field(default_factory=lambda: [3, None])
    """``max_resident_nerfs`` values (``None``: no limit, all sub-models loaded at setup)."""
    views: int = 16
    """Views of the camera path."""
    width: int = 96
    """View width in pixels."""
    height: int = 72
    """View height in pixels."""
    fov_deg: float = 65.0
    """Horizontal field of view of the views."""
    spacing: float = 2.0
    """Distance between neighbouring NeRF origins (common units = the runs' own: side by side, as nerfacto's scene
    box is [-1, 1]^3)."""
    offset: float = 1.0
    """Distance of the camera path from the line of NeRF origins (with tau 1.8 and spacing 2: one NeRF passes the
    distance test by a NeRF's origin, two half-way between)."""
    blend_method: BlendMethod = "idw-sample"
    """Blend method (the model's default)."""
    gamma: float = PAPER_OBJECT_CENTRIC[0]
    """IDW rate (the model's default)."""
    tau: float | None = PAPER_OBJECT_CENTRIC[1]
    """Distance test ratio (the model's default)."""
    model_size: Literal["nerfacto", "nerfacto-cpu"] = "nerfacto"
    """Sub-models' sizes: stock nerfacto's model config (hash grid 2^19 x 16 levels up to 2048, 64-wide MLPs,
    proposal grids 2^17, (256, 96) + 48 samples; torch backend, camera optimiser off) or the plugin's nerfacto-cpu."""
    train_steps: int = 1
    """Training steps of the one source run (its weights are otherwise untrained; memory does not depend on them)."""
    scene_seed: int = 3
    """Seed of the generated capture the source run trains on."""
    seed: int = 0
    """Training seed of the source run, and torch's seed in every case."""
    device: str = field(default_factory=default_device)
    """Where the fused model and its sub-models live (default: cuda when torch sees it, else cpu)."""
    memory_interval_s: float = 0.2
    """How often the case process's memory is sampled (its ``ru_maxrss`` is exact)."""
    work_dir: Path = Path("outputs/bench/fused_memory_work")
    """Cache of the generated capture, the source run, its N copies, the fusion specs and the renders."""
    rebuild: bool = False
    """Make the capture and the runs again even when the cached ones match the settings."""
    output: Path = Path("outputs/bench/fused_memory.json")
    """JSON results (rewritten atomically after every case)."""
    report: Path | None = None
    """Markdown report (written atomically after every case, only when given)."""

    def runs_key(self) -> dict:
        """What the cached runs depend on."""
        return {"model_size": self.model_size, "train_steps": self.train_steps, "scene_seed": self.scene_seed,
                "seed": self.seed}  # fmt: skip

    def settings(self) -> dict:
        skip = {"nerfs", "limits", "work_dir", "rebuild", "output", "report"}
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in skip}


def _mib(x: float) -> float:
    return round(x / 2**20, 1)


# ---------------------------------------------------------------------------------------------------------------------
# The runs: one source run (untrained weights of realistic size), copied N times


def sub_model_config(cfg: BenchFusedMemory):
    """The trainer config of the source run: nerfacto-cpu's (CPU, torch hash grid, camera optimiser off), with stock
    nerfacto's model when ``model_size`` is ``nerfacto``."""
    config = nerfacto_cpu_config(cfg.train_steps)
    if cfg.model_size == "nerfacto":
        model = copy.deepcopy(all_methods["nerfacto"].pipeline.model)
        model.implementation = "torch"  # tcnn needs CUDA; same sizes
        model.camera_optimizer = copy.deepcopy(config.pipeline.model.camera_optimizer)  # off: exact generated poses
        config.pipeline.model = model
        config.method_name = "nerfacto"
    return config


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def run_config(work: Path, cfg: BenchFusedMemory, k: int) -> Path:
    method = "nerfacto" if cfg.model_size == "nerfacto" else "nerfacto-cpu"
    return (work / "runs" / f"nerf{k:02d}" / method / RUN_TIMESTAMP / "config.yml").absolute()


def build_runs(cfg: BenchFusedMemory, count: int) -> dict:
    """Makes (or reuses) the source run and ``count`` copies of it; returns the manifest (runs, parameters, sizes).
    Run in a process of its own (training leaves an optimiser and a trainer behind)."""
    work = cfg.work_dir.absolute()
    manifest_path = work / "runs.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    source = manifest.get("source")
    if cfg.rebuild or manifest.get("key") != cfg.runs_key() or not source or not Path(source).is_file():
        for folder in ("scene", "source", "runs"):
            shutil.rmtree(work / folder, ignore_errors=True)
        t = time.perf_counter()
        layout = scenes.make_layout("object-centric", seed=cfg.scene_seed, num_views=12, num_test_views=2, width=40,
                                    height=30)  # fmt: skip
        scenes.write_scene(layout, work / "scene", supersample=1)
        result = train(data=work / "scene" / "capture_a", output_dir=work / "source", experiment_name="nerf",
                       max_num_iterations=cfg.train_steps, seed=cfg.seed, timestamp=RUN_TIMESTAMP,
                       config=sub_model_config(cfg))  # fmt: skip
        params = sum(p.numel() for p in result.model.parameters())
        checkpoints = sorted((result.config_path.parent / "nerfstudio_models").glob("step-*.ckpt"))
        for ckpt in checkpoints:
            slim_checkpoint(ckpt)  # weights only, as a finished run keeps them (no optimiser state)
        manifest = {"key": cfg.runs_key(), "source": str(result.config_path), "step": result.step,
                    "parameters": params, "parameters_mib": _mib(4 * params),
                    "checkpoint_mib": _mib(checkpoints[-1].stat().st_size),
                    "build_s": round(time.perf_counter() - t, 1), "runs": []}  # fmt: skip
        del result
        gc.collect()
    runs = []
    for k in range(count):
        config = run_config(work, cfg, k)
        if not config.is_file():
            shutil.rmtree(config.parent, ignore_errors=True)
            shutil.copytree(Path(manifest["source"]).parent, config.parent, copy_function=_link_or_copy)
        runs.append(str(config))
    manifest["runs"] = sorted(set(manifest["runs"]) | set(runs))
    write_text_atomic(manifest_path, json.dumps(manifest, indent=2) + "\n")
    return manifest


def write_fusion(cfg: BenchFusedMemory, n: int) -> Path:
    """The registration file (NeRF k translated by ``k * spacing`` along x) and the fusion spec of ``n`` NeRFs."""
    folder = (cfg.work_dir / f"fusion_{n}").absolute()
    folder.mkdir(parents=True, exist_ok=True)
    configs = [run_config(cfg.work_dir, cfg, k) for k in range(n)]
    names = [f"nerf{k:02d}" for k in range(n)]
    entries = [NerfEntry(name, config, make_sim3(np.eye(3), np.array([k * cfg.spacing, 0.0, 0.0]), 1.0))
               for k, (name, config) in enumerate(zip(names, configs, strict=True))]  # fmt: skip
    write_minimal_registration(entries, folder / "registration.json")
    spec = write_fusion_spec(folder / "fusion.json", configs, registration="registration.json", names=names)
    read_fusion_spec(spec, register=False)  # checked as the fused pipeline reads it (runs and checkpoints present)
    return spec


def camera_path(cfg: BenchFusedMemory, n: int) -> np.ndarray:
    """``views`` cameras along the line of NeRF origins, ``offset`` to its side, looking along it (+x; nerfstudio's
    camera looks along its -z), at the mid-points of ``views`` equal steps from the first origin to the last."""
    x = (np.arange(cfg.views) + 0.5) / cfg.views * (n - 1) * cfg.spacing
    R = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: right -y, up +z, back -x
    c2w = np.tile(np.eye(4), (cfg.views, 1, 1))
    c2w[:, :3, :3] = R
    c2w[:, 0, 3], c2w[:, 1, 3] = x, -cfg.offset
    return c2w


# ---------------------------------------------------------------------------------------------------------------------
# One case, in its own process


class MemorySampler:
    """Samples this process's PSS (RSS where unknown) and RSS every ``interval_s`` in a thread; peaks per phase."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.process = psutil.Process()
        self.phase = "start"
        self.peaks: dict[str, dict[str, int]] = {}
        self.samples = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def sample(self) -> dict[str, int]:
        try:
            m = self.process.memory_full_info()
        except psutil.Error:
            return {}
        now = {"pss": int(getattr(m, "pss", m.rss)), "rss": int(m.rss)}
        with self._lock:
            peak = self.peaks.setdefault(self.phase, {"pss": 0, "rss": 0})
            for key, value in now.items():
                peak[key] = max(peak[key], value)
            self.samples += 1
        return now

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    def start(self) -> MemorySampler:
        self.sample()
        self._thread.start()
        return self

    def mark(self, phase: str) -> dict[str, int]:
        """Ends the current phase (one last sample) and starts ``phase``."""
        now = self.sample()
        with self._lock:
            self.phase = phase
        self.sample()
        return now

    def stop(self) -> dict[str, int]:
        now = self.sample()
        self._stop.set()
        self._thread.join()
        return now


def run_case(cfg: BenchFusedMemory, n: int, limit: int | None, spec: Path, render_path: Path) -> dict:
    """Builds the fused pipeline of spec ``spec`` with ``max_resident_nerfs=limit``, renders the path, measures."""
    torch.manual_seed(cfg.seed)
    cuda = torch.device(cfg.device).type == "cuda"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    sampler = MemorySampler(cfg.memory_interval_s).start()
    baseline = sampler.mark("setup")  # after the imports (those of ns-render: torch, nerfstudio, its method configs)

    t = time.perf_counter()
    config = nerfuser_config()  # what ns-train nerfuser writes and ns-render / ns-eval read back
    config.pipeline.datamanager.data = spec
    config.pipeline.datamanager.register_if_missing = False
    model_config = config.pipeline.model
    model_config.fusion_spec = spec
    model_config.max_resident_nerfs = limit
    model_config.blend_method, model_config.gamma, model_config.tau = cfg.blend_method, cfg.gamma, cfg.tau
    pipeline = config.pipeline.setup(device=cfg.device, test_mode="inference")
    pipeline.eval()
    model = pipeline.model
    setup_s = time.perf_counter() - t
    after_setup = sampler.mark("first view")  # the first view also pays the CPU fast path's one-off compile

    cameras = make_cameras(camera_path(cfg, n), Intrinsics.from_fov(cfg.width, cfg.height, cfg.fov_deg))
    centres = torch.as_tensor(camera_path(cfg, n)[:, :3, 3], dtype=torch.float32)
    per_view = blending.distance_mask(blending.camera_to_origin_distances(centres, model.nerf_origins.cpu()),
                                      model.tau).sum(0)  # fmt: skip
    cameras = cameras.to(model.device)
    cache = model.nerf_cache
    view_s, rgbs, most_resident = [], [], 0
    t = time.perf_counter()
    with torch.no_grad():
        for i in range(len(cameras)):
            tv = time.perf_counter()
            out = model.get_outputs_for_camera(cameras[i : i + 1])
            rgbs.append(out["rgb"].float().cpu().numpy())
            view_s.append(time.perf_counter() - tv)
            if i == 0:
                sampler.mark("later views")
            if cache is not None:
                most_resident = max(most_resident, len(cache.resident()))
    render_s = time.perf_counter() - t
    end = sampler.stop()
    ru_maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux
    np.save(render_path, np.stack(rgbs))

    peaks = sampler.peaks
    peak_pss = max(p["pss"] for p in peaks.values())
    peak_rss = max(p["rss"] for p in peaks.values())
    return {
        "nerfs": n,
        "limit": limit,
        "status": "ok",
        "device": str(model.device),
        "ru_maxrss_mib": _mib(ru_maxrss),
        "peak_pss_mib": _mib(peak_pss),
        "peak_rss_mib": _mib(peak_rss),
        "baseline_pss_mib": _mib(baseline.get("pss", 0)),
        "baseline_rss_mib": _mib(baseline.get("rss", 0)),
        "after_setup_pss_mib": _mib(after_setup.get("pss", 0)),
        "end_pss_mib": _mib(end.get("pss", 0)),
        "phase_peak_pss_mib": {k: _mib(v["pss"]) for k, v in peaks.items()},
        "memory_samples": sampler.samples,
        "cuda_max_allocated_mib": _mib(torch.cuda.max_memory_allocated()) if cuda else None,
        "setup_s": round(setup_s, 2),
        "render_s": round(render_s, 2),
        "view_s": [round(x, 3) for x in view_s],
        "first_view_s": round(view_s[0], 2),
        "median_view_s": round(statistics.median(view_s[1:] or view_s), 3),
        "loads": cache.loads if cache is not None else None,
        "evictions": cache.evictions if cache is not None else None,
        "loaded_at_setup": n if cache is None else 0,
        "most_resident": most_resident if cache is not None else n,
        "nerfs_per_view": per_view.tolist(),
        "torch_threads": torch.get_num_threads(),
    }


def _case(cfg: BenchFusedMemory, n: int, limit: int | None, spec: str, render_path: str) -> dict:
    try:
        return run_case(cfg, n, limit, Path(spec), Path(render_path))
    except BaseException as e:  # reported as the case's result
        return {"nerfs": n, "limit": limit, "status": "crash", "error": f"{type(e).__name__}: {e}".splitlines()[0],
                "traceback": traceback.format_exc()[-3000:]}  # fmt: skip


def in_fresh_process(fn, *args):  # noqa: ANN001, ANN002, ANN201
    """``fn(*args)`` in a new spawned process (its memory its own); exceptions come back as raised."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


# ---------------------------------------------------------------------------------------------------------------------
# Results


def _label(limit: int | None) -> str:
    return "none" if limit is None else str(limit)


def ratios(results: list[dict]) -> dict[str, dict]:
    """Per limit: peak(N_max) / peak(N_min), on ru_maxrss and on the sampled PSS."""
    out = {}
    for limit in dict.fromkeys(r["limit"] for r in results):
        rows = {r["nerfs"]: r for r in results if r["limit"] == limit and r.get("status") == "ok"}
        if len(rows) < 2:
            continue
        lo, hi = min(rows), max(rows)
        rss = rows[hi]["ru_maxrss_mib"] / rows[lo]["ru_maxrss_mib"]
        pss = rows[hi]["peak_pss_mib"] / rows[lo]["peak_pss_mib"]
        above = [rows[x]["peak_pss_mib"] - rows[x]["baseline_pss_mib"] for x in (hi, lo)]
        out[_label(limit)] = {"n_min": lo, "n_max": hi, "limit": limit, "ru_maxrss_ratio": round(rss, 3),
                              "pss_ratio": round(pss, 3), "pss_above_baseline_ratio": round(above[0] / above[1], 3),
                              "target": TARGET_RATIO if limit is not None else None,
                              "meets": (max(rss, pss) <= TARGET_RATIO) if limit is not None else None}  # fmt: skip
    return out


def pixel_differences(cfg: BenchFusedMemory, results: list[dict]) -> None:
    """Each limited case's largest |rgb difference| to the all-resident render of the same N (in place)."""
    done = {(r["nerfs"], r["limit"]) for r in results if r.get("status") == "ok"}
    for r in results:
        if r.get("status") != "ok" or r["limit"] is None or (r["nerfs"], None) not in done:
            continue
        a = np.load(render_file(cfg, r["nerfs"], r["limit"]))
        b = np.load(render_file(cfg, r["nerfs"], None))
        r["max_abs_rgb_diff_vs_all_resident"] = float(np.abs(a - b).max())


def render_file(cfg: BenchFusedMemory, n: int, limit: int | None) -> Path:
    return (cfg.work_dir / "renders" / f"nerfs_{n}_limit_{_label(limit)}.npy").absolute()


def _f(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def markdown(report: dict) -> str:
    s, runs = report["settings"], report["runs"]
    m = report["machine"]
    lines = [
        f"# Fused model: peak memory vs number of NeRFs, bounded sub-model cache ({report['date']})", "",
        f"`{report['command']}`", "",
        f"On {m['platform']}, {m['cpus']} CPUs, device {s['device']}, OMP_NUM_THREADS={m['omp_num_threads']}, torch "
        f"{m['torch']} ({m['torch_threads']} threads); load average {m['load_avg_at_start']} at the start (another "
        "benchmark ran beside this one: times are slower than on an idle machine, memory is not affected).", "",
        f"**Sub-models**: {s['model_size']} sizes ("
        + ("stock nerfacto's model config: hash grid 2^19 x 16 levels up to 2048, 64-wide MLPs, proposal grids 2^17, "
           "(256, 96) + 48 samples per ray; torch backend, camera optimiser off"
           if s["model_size"] == "nerfacto" else "the plugin's nerfacto-cpu preset")
        + f"), {runs['parameters'] / 1e6:.1f} M parameters ({runs['parameters_mib']:.0f} MiB of float32 weights, "
        f"checkpoint {runs['checkpoint_mib']:.0f} MiB). One run trained {s['train_steps']} step(s) on a generated "
        "capture (untrained weights: memory and render cost do not depend on them), copied N times (each copy its "
        "own run folder; checkpoints hard-linked), each loaded from its own config.yml and checkpoint.", "",
        f"**Layout**: NeRF k's transform a translation by k x {s['spacing']:g} along x (registration file and fusion "
        f"spec written by `write_minimal_registration` / `write_fusion_spec`); {s['views']} views of "
        f"{s['width']}x{s['height']} px ({s['fov_deg']:g} deg), {s['offset']:g} to the side of the line, looking along "
        "it, at the mid-points of equal steps from the first NeRF's origin to the last's; blend "
        f"{s['blend_method']}, gamma {s['gamma']:g}, tau {s['tau']}: each view passes the distance test of the "
        "number of NeRFs in the `NeRFs/view` column.", "",
        "**Path**: the `nerfuser` method's pipeline config (what `ns-render`/`ns-eval` load from a fused run's "
        "config.yml) with `max_resident_nerfs` set, `pipeline.setup(test_mode=\"inference\")` (datamanager, fusion "
        "spec, model; the fused checkpoint, which holds no sub-model weights, is not read), then "
        "`model.get_outputs_for_camera` per view. Each case in a fresh spawned process.", "",
        "**Memory**: `ru_maxrss` (exact peak RSS of the case process) and the peak PSS sampled by psutil every "
        f"{s['memory_interval_s']} s in a thread; baseline: PSS after the imports (torch, nerfstudio), before the "
        "fused model is built (the same in every case). Peaks per phase (setup, first view, later views) are in the "
        "JSON (`phase_peak_pss_mib`): the first view also pays the CPU fast path's one-off compile; the render's "
        "working set (4096-ray chunks through one or two sub-models) does not grow with N. Loads at setup: "
        "sub-models loaded by the model's setup (all of them without a limit); loads / evictions: the cache's "
        "counters.", "",
    ]  # fmt: skip
    for r in report["ratios"].values():
        if r["limit"] is None:
            lines.append(f"- no limit: `peak({r['n_max']})/peak({r['n_min']}) = {r['ru_maxrss_ratio']:.2f}` "
                         f"(ru_maxrss; sampled PSS {r['pss_ratio']:.2f}; PSS above the baseline "
                         f"{r['pss_above_baseline_ratio']:.2f})")  # fmt: skip
    lines += [
        "",
        "| N | limit | peak RSS MiB (ru_maxrss) | peak PSS MiB | baseline PSS MiB | PSS after setup MiB | setup s | "
        "render s | first view s | median view s | loaded at setup | loads | evictions | most resident | "
        "NeRFs/view (min-max) | max abs rgb diff vs all resident |",
        "|" + " ---: |" * 14 + " --- | ---: |",
    ]  # fmt: skip
    for r in report["cases"]:
        if r.get("status") != "ok":
            lines.append(f"| {r['nerfs']} | {_label(r['limit'])} | {r['status']}: {r.get('error', '')} |")
            continue
        per_view = r["nerfs_per_view"]
        lines.append(
            f"| {r['nerfs']} | {_label(r['limit'])} | {r['ru_maxrss_mib']:.0f} | {r['peak_pss_mib']:.0f} | "
            f"{r['baseline_pss_mib']:.0f} | {r['after_setup_pss_mib']:.0f} | {r['setup_s']:.1f} | "
            f"{r['render_s']:.1f} | {r['first_view_s']:.1f} | {r['median_view_s']:.2f} | {r['loaded_at_setup']} | "
            f"{_f(r['loads'], 'd')} | {_f(r['evictions'], 'd')} | {r['most_resident']} | "
            f"{min(per_view)}-{max(per_view)} | {_f(r.get('max_abs_rgb_diff_vs_all_resident'), '.2g')} |"
        )
    lines.append("")
    for label, r in report["ratios"].items():
        if r["limit"] is None:
            continue
        verdict = "meets" if r["meets"] else "misses"
        note = ""
        if (r["n_min"], r["n_max"]) != (4, 16):
            note = f" (the target is stated for 16/4; here {r['n_max']}/{r['n_min']})"
        lines.append(f"**Limit {label}: `peak({r['n_max']})/peak({r['n_min']}) = {r['ru_maxrss_ratio']:.2f}` "
                     f"(ru_maxrss; sampled PSS {r['pss_ratio']:.2f}): {verdict} the <= {TARGET_RATIO:g}x target**"
                     f"{note}. PSS above the baseline (the fused model's own memory, imports excluded): "
                     f"{r['pss_above_baseline_ratio']:.2f}x.")  # fmt: skip
    return "\n".join(lines) + "\n"


def write(cfg: BenchFusedMemory, results: list[dict], runs: dict, load: float) -> dict:
    order = {lim: k for k, lim in enumerate(cfg.limits)}
    results = sorted(results, key=lambda r: (r["nerfs"], order.get(r["limit"], 99)))
    pixel_differences(cfg, results)
    report = {
        "command": shlex.join(["python", "scripts/bench_fused_memory.py", *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS", "unset"),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "load_avg_at_start": round(load, 2),
        },
        "settings": cfg.settings(),
        "runs": {k: v for k, v in runs.items() if k != "runs"},
        "target_ratio": TARGET_RATIO,
        "ratios": ratios(results),
        "cases": results,
    }
    write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
    if cfg.report is not None:
        write_text_atomic(cfg.report, markdown(report))
    return report


def main(cfg: BenchFusedMemory) -> None:
    console = Console()
    if min(cfg.nerfs, default=0) < 2 or cfg.views < 1 or any(x is not None and x < 1 for x in cfg.limits):
        raise SystemExit("bench_fused_memory: --nerfs >= 2, --views >= 1, --limits >= 1 or None")
    try:
        torch.device(cfg.device)
        BlendSettings(method=cfg.blend_method, gamma=cfg.gamma, tau=cfg.tau).checked(2)
    except (RuntimeError, ValueError, TypeError) as e:
        raise SystemExit(f"bench_fused_memory: {e}") from None
    if torch.device(cfg.device).type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"bench_fused_memory: --device {cfg.device}, but torch sees no CUDA device")
    load = os.getloadavg()[0]
    t = time.perf_counter()
    console.rule(f"runs: {max(cfg.nerfs)} copies of one {cfg.model_size} run under {cfg.work_dir}")
    runs = in_fresh_process(build_runs, cfg, max(cfg.nerfs))
    console.print({k: v for k, v in runs.items() if k not in ("runs", "key")})
    results: list[dict] = []
    for n in sorted(set(cfg.nerfs)):
        spec = write_fusion(cfg, n)
        for limit in dict.fromkeys(cfg.limits):
            console.rule(f"{n} NeRFs, max_resident_nerfs {_label(limit)}")
            render_path = render_file(cfg, n, limit)
            render_path.parent.mkdir(parents=True, exist_ok=True)
            tc = time.perf_counter()
            try:
                result = in_fresh_process(_case, cfg, n, limit, str(spec), str(render_path))
            except BrokenProcessPool as e:  # killed (memory?) or crashed hard
                result = {"nerfs": n, "limit": limit, "status": "crash", "error": f"process died: {e}"}
            result["case_s"] = round(time.perf_counter() - tc, 1)
            brief = {k: result.get(k) for k in ("status", "error", "ru_maxrss_mib", "peak_pss_mib", "baseline_pss_mib",
                                                "setup_s", "render_s", "loads", "evictions", "most_resident",
                                                "case_s")}  # fmt: skip
            console.print({k: v for k, v in brief.items() if v is not None})
            if "traceback" in result:
                console.print(result["traceback"], markup=False, highlight=False)
            results.append(result)
            write(cfg, results, runs, load)
    report = write(cfg, results, runs, load)
    for label, r in report["ratios"].items():
        line = (f"limit {label}: peak({r['n_max']})/peak({r['n_min']}) = {r['ru_maxrss_ratio']:.2f} (ru_maxrss; "
                f"PSS {r['pss_ratio']:.2f})")  # fmt: skip
        if r["meets"] is not None:
            line += f": {'meets' if r['meets'] else 'misses'} the <= {TARGET_RATIO:g}x target"
        console.print(line)
    console.print(f"[bold green]wrote[/] {cfg.output}" + (f" and {cfg.report}" if cfg.report else "")
                  + f" in {time.perf_counter() - t:.0f} s")  # fmt: skip


def entrypoint() -> None:
    main(tyro.cli(BenchFusedMemory))


if __name__ == "__main__":
    entrypoint()
