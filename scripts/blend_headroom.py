"""How much a blend weight could still gain on a fused two-NeRF practitioner case, and one cue beyond the paper's.

A diagnostic (ours), not a method: it scores, on a case's test views (``scripts/bench_practitioner.py`` case
folders with their fused run),

* the fused model's own methods (IDW-2D, IDW-3D, IDW-Sample, coverage, coverage-3d) at the run's settings;
* the plain mean of the two NeRFs' renders (IDW at gamma 0);
* two ceilings no cue can pass: the best convex weight *per view* (fitted to the ground truth: the limit of any cue
  that is one number per camera, as IDW-2D's camera distance is) and the per-pixel oracle (the better NeRF per pixel);
* the depth-spread cue: per NeRF and ray, the spread of its termination distribution relative to its expected depth
  (``std(t) / E[t]`` under the ray's sample weights): a NeRF that ends a ray on one surface is confident, one whose
  weights spread over floaters and a surface is not. Its selection score (how often it picks the per-pixel better
  NeRF, :func:`nerfuser_ns.bench.metrics.selection_score`), and per-ray colour blends
  ``w_i ∝ spread_i^-g`` for ``g`` in ``--gammas``, alone and multiplied into IDW-2D's weights (same distance test).

The rule, fixed before any run: the cue becomes a candidate blend method only if, on the validation case, one of its
settings beats the best of IDW-2D / IDW-3D / IDW-Sample by at least 0.3 dB (issue target of the street and drive
scenes); that setting is then run once on the test cases. The ceilings say what any per-view cue could reach at most.

Example:
    python scripts/blend_headroom.py --cases outputs/practitioner/drive-14 --output reports/blend_headroom_drive14.json
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import tyro
from jaxtyping import Float
from rich.console import Console
from torch import Tensor

from nerfuser_ns import blending, runs
from nerfuser_ns.appearance import apply_colour_map
from nerfuser_ns.bench import metrics
from nerfuser_ns.bench.practitioner_cases import fused_config
from nerfuser_ns.files import write_text_atomic

MODEL_METHODS = ("nearest", "idw-2d", "idw-3d", "idw-sample", "coverage", "coverage-3d")
IDW_METHODS = ("idw-2d", "idw-3d", "idw-sample")
TARGET_DB = 0.3


@dataclass
class BlendHeadroom:
    """Score blend ceilings and the depth-spread cue on fused two-NeRF cases."""

    cases: list[Path]
    """Practitioner case folders, each with its fused run (the ``fuse`` stage) of exactly two NeRFs."""
    output: Path
    """JSON results (a markdown table is written beside it)."""
    gammas: list[float] = field(default_factory=lambda: [1.0, 2.0, 4.0])
    """Exponents of the spread cue's weights ``spread^-g``."""
    max_views: int | None = None
    """Score at most this many test views per case (evenly spaced); None: all."""


def relative_spread(
    weights: Float[Tensor, "*bs k"], starts: Float[Tensor, "*bs k"], ends: Float[Tensor, "*bs k"]
) -> Float[Tensor, " *bs"]:
    """``std(t) / E[t]`` of a ray's termination distribution (sample midpoints ``t`` under the normalised weights):
    0 for a ray ending on one sample, larger as the weights spread; rays with no mass get 1e6 (least confident).
    Scale-free, so a NeRF's own distances serve."""
    w = weights.clamp(min=0)
    acc = w.sum(-1)
    t = 0.5 * (starts + ends)
    wn = w / acc.clamp(min=1e-10)[..., None]
    mean = (wn * t).sum(-1)
    std = (wn * (t - mean[..., None]).square()).sum(-1).clamp(min=0).sqrt()
    return torch.where(acc > 1e-6, std / mean.clamp(min=1e-10), torch.full_like(std, 1e6)).clamp(min=1e-6)


def best_view_weight(
    a: Float[Tensor, "v h w 3"], b: Float[Tensor, "v h w 3"], target: Float[Tensor, "v h w 3"]
) -> Float[Tensor, " v"]:
    """Per view, the ``alpha`` in [0, 1] minimising ``|alpha a + (1 - alpha) b - target|^2`` (closed form)."""
    diff = (a - b).flatten(1)
    alpha = ((target - b).flatten(1) * diff).sum(1) / diff.square().sum(1).clamp(min=1e-12)
    return alpha.clamp(0, 1)


def _own_renders(model, per_nerf) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: ANN001 - fused model, its samples
    """Each NeRF's own colour (with the model's colour maps) and relative depth spread per ray: ``[2, R, 3]``,
    ``[2, R]``."""
    rgbs, spreads = [], []
    for i, q in enumerate(per_nerf):
        s = q.samples
        w = s.weights.clamp(min=0)
        c = s.rgbs
        bg = s.background_rgb
        if model.blend_settings.appearance_matching and model._colour_mapped[i]:
            c, bg = apply_colour_map(c, model.colour_maps[i]), apply_colour_map(bg, model.colour_maps[i])
        acc = w.sum(-1)
        rgbs.append((w[..., None] * c).sum(-2) + (1 - acc).clamp(min=0)[..., None] * bg)
        spreads.append(relative_spread(w, s.starts, s.ends))
    return torch.stack(rgbs), torch.stack(spreads)


def score_case(case_dir: Path, gammas: list[float], max_views: int | None, console: Console) -> dict:
    loaded = runs.load_run(fused_config(case_dir, None), device=runs.default_device(), with_data=True,
                           test_mode="test")  # fmt: skip
    model = loaded.pipeline.model  # type: ignore[union-attr]
    if model.num_nerfs != 2:
        raise SystemExit(f"blend_headroom: {case_dir}: {model.num_nerfs} NeRFs; this diagnostic takes two")
    model.config.render_all_methods = True
    settings = model.blend_settings
    dataset = loaded.pipeline.datamanager.eval_dataset  # type: ignore[union-attr]
    ids = np.arange(len(dataset))
    if max_views is not None and len(ids) > max_views:
        ids = np.unique(np.linspace(0, len(ids) - 1, max_views).round().astype(int))
    cameras = dataset.cameras[torch.from_numpy(ids)].to(model.device)
    target = torch.stack([dataset.get_image_float32(int(i))[..., :3] for i in ids])
    keys = [f"rgb_{m.replace('-', '_')}" for m in MODEL_METHODS]
    own_all, spread_all, cam_w_all, model_all = [], [], [], {k: [] for k in keys}
    start = time.perf_counter()
    with torch.no_grad():
        for c in range(len(cameras)):
            bundle = cameras.generate_rays(camera_indices=c, keep_shape=True)
            h, w = bundle.origins.shape[:2]
            flat = bundle.flatten()
            parts: dict[str, list[torch.Tensor]] = {k: [] for k in [*keys, "own", "spread", "cam_w"]}
            for s in range(0, len(flat), model.config.eval_num_rays_per_chunk):
                rays = flat[s : s + model.config.eval_num_rays_per_chunk]
                per_nerf = model.nerf_samples(rays)  # both NeRFs on every ray
                out = model.blend_samples(rays, per_nerf)
                for k in keys:
                    parts[k].append(out[k])
                own, spread = _own_renders(model, per_nerf)
                parts["own"].append(own)
                parts["spread"].append(spread)
                cam_d = blending.camera_to_origin_distances(rays.origins, model.nerf_origins.to(rays.origins))
                parts["cam_w"].append(blending.idw_2d_weights(cam_d, settings.gamma, settings.tau))
            for k in keys:
                model_all[k].append(torch.cat(parts[k]).reshape(h, w, 3).cpu())
            own_all.append(torch.cat(parts["own"], dim=1).reshape(2, h, w, 3).cpu())
            spread_all.append(torch.cat(parts["spread"], dim=1).reshape(2, h, w).cpu())
            cam_w_all.append(torch.cat(parts["cam_w"], dim=1).reshape(2, h, w).cpu())
    seconds = time.perf_counter() - start
    own = torch.stack(own_all, dim=1)  # [2, V, H, W, 3]
    spread = torch.stack(spread_all, dim=1)  # [2, V, H, W]
    cam_w = torch.stack(cam_w_all, dim=1)

    def score(pred: torch.Tensor) -> dict:
        return metrics.image_metrics(pred.clamp(0, 1), target, lpips=False)

    rows = {m: score(torch.stack(model_all[k])) for m, k in zip(MODEL_METHODS, keys, strict=True)}
    rows["nerf 0 alone"], rows["nerf 1 alone"] = score(own[0]), score(own[1])
    rows["mean (gamma 0)"] = score(own.mean(0))
    # Best convex weight per view: min over a in [0, 1] of |a A + (1 - a) B - T|^2, closed form.
    a = best_view_weight(own[0], own[1], target)[:, None, None, None]
    rows["ceiling: best weight per view"] = score(a * own[0] + (1 - a) * own[1])
    errors = (own - target[None]).square().mean(-1)  # [2, V, H, W]
    best = errors.argmin(0)
    rows["ceiling: per-pixel oracle"] = score(torch.where((best == 0)[..., None], own[0], own[1]))
    per_view = {m: metrics.per_image_psnr(torch.stack(model_all[k]), target).tolist()
                for m, k in zip(MODEL_METHODS, keys, strict=True)}  # fmt: skip
    per_view["nerf 0 alone"], per_view["nerf 1 alone"] = (metrics.per_image_psnr(o, target).tolist() for o in own)
    per_view["ceiling: best weight per view"] = metrics.per_image_psnr(a * own[0] + (1 - a) * own[1], target).tolist()
    centres = cameras.camera_to_worlds[:, :3, 3]
    camera_distances = (centres[:, None] - model.nerf_origins.to(centres)[None]).norm(dim=-1)  # [V, 2]
    cues = {"spread": spread.argmin(0), "camera": cam_w.argmax(0)}
    selection = {name: metrics.selection_score(errors, choice) for name, choice in cues.items()}
    for g in gammas:
        ws = spread.pow(-g)
        ws = ws / ws.sum(0, keepdim=True)
        rows[f"spread g={g:g}"] = score((ws[..., None] * own).sum(0))
        wc = ws * cam_w
        wc = wc / wc.sum(0, keepdim=True).clamp(min=1e-12)
        rows[f"IDW-2D x spread g={g:g}"] = score((wc[..., None] * own).sum(0))
    best_idw = max(rows[m]["psnr"] for m in IDW_METHODS)
    spread_rows = [k for k in rows if "spread g=" in k]
    best_spread = max(spread_rows, key=lambda k: rows[k]["psnr"])
    console.print(f"{case_dir.name}: {len(ids)} views in {seconds:.0f} s; best IDW {best_idw:.2f} dB, best spread "
                  f"setting {best_spread} {rows[best_spread]['psnr']:.2f} dB")  # fmt: skip
    return {"case": case_dir.name, "views": len(ids), "seconds": round(seconds, 1),
            "settings": {"gamma": settings.gamma, "tau": settings.tau,
                         "appearance_matching": settings.appearance_matching},
            "rows": rows, "selection_score": selection, "best_idw_psnr": best_idw, "best_spread": best_spread,
            "view_ids": ids.tolist(), "per_view_psnr": per_view, "camera_to_origin": camera_distances.tolist(),
            "best_weight_nerf0": a.flatten().tolist(),
            "best_spread_minus_best_idw_db": rows[best_spread]["psnr"] - best_idw,
            "candidate": rows[best_spread]["psnr"] - best_idw >= TARGET_DB}  # fmt: skip


PER_VIEW_COLUMNS = ("nerf 0 alone", "nerf 1 alone", "nearest", "idw-2d", "idw-3d", "idw-sample", "coverage")


def _per_view_table(case: dict) -> list[str]:
    """One row per test view: each NeRF's distance from the camera, PSNR alone and per method, the fitted weight."""
    if "per_view_psnr" not in case:  # results written before the per-view figures were kept
        return []
    pv = case["per_view_psnr"]
    lines = [f"Per view, {case['case']} (PSNR dB; camera to each NeRF's origin in the common frame; the per-view "
             "best weight of NeRF 0 fitted to the ground truth):", "",
             "| view | camera-origin 0 / 1 | " + " | ".join(PER_VIEW_COLUMNS)
             + " | IDW-Sample - Nearest | best weight 0 |",
             "| --- | --- | " + " | ".join("---:" for _ in PER_VIEW_COLUMNS) + " | ---: | ---: |"]  # fmt: skip
    for j, view in enumerate(case["view_ids"]):
        d, gap = case["camera_to_origin"][j], pv["idw-sample"][j] - pv["nearest"][j]
        lines.append(f"| {view} | {d[0]:.3f} / {d[1]:.3f} | "
                     + " | ".join(f"{pv[m][j]:.2f}" for m in PER_VIEW_COLUMNS)
                     + f" | {gap:+.2f} | {case['best_weight_nerf0'][j]:.2f} |")  # fmt: skip
    return [*lines, ""]


def _markdown(cases: list[dict], command: str) -> str:
    names = list(cases[0]["rows"])
    lines = ["# Blend headroom on fused two-NeRF cases (ours, a diagnostic)", "", f"`{command}`", "",
             "PSNR (dB) / SSIM on each case's test views (the fused run's settings: "
             + "; ".join(f"{c['case']}: gamma {c['settings']['gamma']:g}, tau {c['settings']['tau']}, appearance "
                         f"matching {c['settings']['appearance_matching']}" for c in cases) + "). Ceilings are fitted "
             "to the ground truth: no cue reaches them.", "",
             "| setting | " + " | ".join(c["case"] for c in cases) + " |",
             "| --- | " + " | ".join("---:" for _ in cases) + " |"]  # fmt: skip
    for name in names:
        lines.append(f"| {name} | " + " | ".join(f"{c['rows'][name]['psnr']:.2f} / {c['rows'][name]['ssim']:.3f}"
                                                  for c in cases) + " |")  # fmt: skip
    lines += ["", "Selection scores (1: always the per-pixel better NeRF, 0.5: a coin flip): "
              + "; ".join(f"{c['case']}: " + ", ".join(f"{k} {v:.3f}" for k, v in c["selection_score"].items())
                          for c in cases) + ".", ""]  # fmt: skip
    for c in cases:
        lines += _per_view_table(c)
    for c in cases:
        per_view = c["rows"]["ceiling: best weight per view"]["psnr"] - c["best_idw_psnr"]
        lines.append(f"- {c['case']}: best spread setting ({c['best_spread']}) - best IDW = "
                     f"{c['best_spread_minus_best_idw_db']:+.2f} dB; per-view ceiling - best IDW = {per_view:+.2f} dB; "
                     f"candidate by the rule (>= +{TARGET_DB} dB): {'yes' if c['candidate'] else 'no'}")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(cfg: BlendHeadroom) -> None:
    console = Console()
    for case in cfg.cases:
        if not fused_config(case, None).is_file():
            raise SystemExit(f"blend_headroom: {case} has no fused run ({fused_config(case, None)}); run "
                             "scripts/bench_practitioner.py's fuse stage on it first")  # fmt: skip
    if not cfg.cases or any(g <= 0 for g in cfg.gammas):
        raise SystemExit("blend_headroom: name at least one case (--cases) and positive --gammas")
    cases = [score_case(case, cfg.gammas, cfg.max_views, console) for case in cfg.cases]
    command = (f"python scripts/blend_headroom.py --cases {' '.join(map(str, cfg.cases))} --output {cfg.output} "
               f"--gammas {' '.join(f'{g:g}' for g in cfg.gammas)}"
               + ("" if cfg.max_views is None else f" --max-views {cfg.max_views}"))  # fmt: skip
    write_text_atomic(cfg.output, json.dumps({"command": command, "cases": cases}, indent=2) + "\n")
    write_text_atomic(cfg.output.with_suffix(".md"), _markdown(cases, command))
    console.print(f"wrote {cfg.output} and {cfg.output.with_suffix('.md')}")


if __name__ == "__main__":
    main(tyro.cli(BlendHeadroom))
