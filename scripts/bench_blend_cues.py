"""Which cue tells the better NeRF apart, pixel by pixel: the camera's distance or the surface's?

IDW-2D and Nearest weight NeRFs by the distance from the CAMERA to each NeRF's origin; IDW-3D and IDW-Sample by the
distance from the SURFACE (samples near it) to each origin. Which one wins depends on which cue predicts where a NeRF
renders well. This script measures that directly on generated scenes: every test view is rendered by each NeRF alone;
between the two NeRFs nearest the camera, the per-pixel better one (lower squared error against the ground truth)
is compared with the choice of each cue taken to its limit (gamma -> inf):

* camera cue: the NeRF whose origin is nearest the camera (Nearest; IDW-2D's favourite);
* surface cue: the NeRF whose own expected surface point is nearest its origin (IDW-3D; IDW-Sample near the surface).

Each cue gets :func:`nerfuser_ns.bench.metrics.selection_score` (1: always the better NeRF, 0.5: a coin flip, 0:
always the worse; pixels count by how much the choice matters there) and the PSNR of its hard per-pixel selection,
beside the per-pixel oracle's PSNR.

The premise of the surface cue is tested on its own too: each pixel's ground-truth surface point (from the test
capture's depth files) is placed along the axis from the camera's NeRF origin (u = 0) to the other NeRF's (u = 1),
and both NeRFs' PSNR is pooled per band of u. Where each NeRF renders its own side of the scene better, the camera's
NeRF wins the bands below 0.5 and the other NeRF those above.

Example:
    python scripts/bench_blend_cues.py --scenes \\
        oc1=outputs/bench/scenes/object-centric-1:outputs/bench/runs-6000/object-centric-1 \\
        street0=outputs/bench/scenes/street-0:outputs/bench/runs-6000/street-0 --output outputs/bench/blend_cues.json
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import tyro

if TYPE_CHECKING:
    from jaxtyping import Float
    from torch import Tensor

BANDS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Default band edges of u, the surface point's position between the two NeRF origins."""


@dataclass
class BenchBlendCuesConfig:
    """Score the camera and surface cues of the blend methods against the per-pixel better NeRF."""

    scenes: list[str] = field(default_factory=lambda: ["demo=demo/scene:demo/runs"])
    """Scenes as NAME=SCENE_DIR:RUNS_DIR (runs at RUNS_DIR/<capture>/nerfacto-cpu/demo/config.yml)."""
    max_test_views: int = 12
    """Test views per scene."""
    bands: tuple[float, ...] = BANDS
    """Edges of the bands of u (surface point along the axis between the two NeRF origins) the PSNR is pooled in;
    the first and last band also take everything beyond them."""
    output: Path = Path("outputs/bench/blend_cues.json")
    """JSON results (a markdown summary is written beside it)."""


def _psnr(err_mean: float) -> float:
    return -10.0 * math.log10(max(err_mean, 1e-12))


def axis_position(
    points: Float[Tensor, "p 3"], origin_a: Float[Tensor, "3"], origin_b: Float[Tensor, "3"]
) -> Float[Tensor, " p"]:
    """Where each point lies along the axis from ``origin_a`` (0) to ``origin_b`` (1): the projection's fraction."""
    axis = origin_b - origin_a
    return (points - origin_a) @ axis / axis.dot(axis)


def band_profile(err: Float[Tensor, "2 p"], u: Float[Tensor, " p"], edges: tuple[float, ...]) -> list[dict]:
    """Per band of ``u`` (the outer bands open-ended; NaN ``u`` left out): its share of the pixels with a ``u`` and
    the PSNR of each of the two NeRFs over its pixels."""
    import torch

    band = torch.bucketize(u, torch.as_tensor(edges[1:-1], dtype=u.dtype), right=True)
    ok = ~torch.isnan(u)
    total = max(1, int(ok.sum()))
    out = []
    for b, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=False)):
        m = ok & (band == b)
        n = max(1, int(m.sum()))
        out.append({"u": [lo, hi], "pixel_share": int(m.sum()) / total,
                    "psnr_camera_nerf": _psnr(float(err[0][m].sum()) / n),
                    "psnr_other_nerf": _psnr(float(err[1][m].sum()) / n)})  # fmt: skip
    return out


def scene_cues(
    scene,  # noqa: ANN001 - SceneRuns
    max_test_views: int,
    description: str,
    bands: tuple[float, ...] = BANDS,
) -> dict:
    """Per-view and pooled cue scores for one scene (ground-truth transforms), and both NeRFs' errors pooled per
    band of the surface's position between their origins."""
    import torch
    from rich.progress import track

    from nerfuser_ns import blending, runs
    from nerfuser_ns.bench import evaluation
    from nerfuser_ns.bench.metrics import selection_score

    models = [(n, runs.load_run(p).model) for n, p in zip(scene.captures, scene.configs, strict=True)]
    cams, target = scene.test_views(max_views=max_test_views)
    surface = scene.test_surface_points(max_views=max_test_views).reshape(len(cams), -1, 3)
    model = evaluation.fused(models, scene.nerf_to_common(), blend_method="nerf", share_outputs=False)
    origins = model.nerf_origins
    chunk = model.config.eval_num_rays_per_chunk
    views, pooled = [], {"err": [], "camera": [], "surface": [], "u": []}
    with torch.no_grad():
        for v in track(range(len(cams)), description=description, transient=True):
            rays = cams.generate_rays(camera_indices=v, keep_shape=True).flatten()
            rgb, depth = [[] for _ in models], [[] for _ in models]
            for start in range(0, len(rays), chunk):
                part = rays[start : start + chunk]
                per_nerf = model.nerf_samples(part)
                for i in range(len(models)):
                    model.set_blend(reference_nerf=i)
                    out = model.blend_samples(part, per_nerf)
                    rgb[i].append(out["rgb"])
                    depth[i].append(out["expected_depth"][..., 0])
            rgb_t = torch.stack([torch.cat(x) for x in rgb])  # [N, P, 3]
            depth_t = torch.stack([torch.cat(x) for x in depth])  # [N, P]
            err = (rgb_t - target[v].reshape(1, -1, 3)).square().mean(-1)  # [N, P]
            cam_d = blending.camera_to_origin_distances(rays.origins[0], origins)  # [N]
            two = torch.argsort(cam_d)[:2]
            surf_d = torch.linalg.vector_norm(
                blending.expected_points(rays.origins, rays.directions, depth_t) - origins[:, None, :], dim=-1
            )
            e2 = err[two]
            camera_pick = torch.zeros(e2.shape[1], dtype=torch.long)  # two[0] is the camera-nearest
            surface_pick = torch.argmin(surf_d[two], dim=0)
            views.append({
                "view": v,
                "nerfs": [int(i) for i in two],
                "distance_ratio": float(blending.distance_ratio(cam_d)),
                "psnr_nerfs": [_psnr(float(e.mean())) for e in e2],
                "psnr_oracle": _psnr(float(e2.min(0).values.mean())),
                "psnr_camera": _psnr(float(e2[0].mean())),
                "psnr_surface": _psnr(float(e2.gather(0, surface_pick[None]).mean())),
                "score_camera": selection_score(e2, camera_pick),
                "score_surface": selection_score(e2, surface_pick),
                "surface_agrees_with_camera": float((surface_pick == camera_pick).float().mean()),
            })  # fmt: skip
            pooled["err"].append(e2)
            pooled["camera"].append(camera_pick)
            pooled["surface"].append(surface_pick)
            pooled["u"].append(axis_position(surface[v].to(origins.dtype), origins[two[0]], origins[two[1]]))
    err_all = torch.cat(pooled["err"], dim=1)
    return {
        "name": scene.name,
        "layout": scene.ground_truth["layout"],
        "test_views": len(cams),
        "score_camera": selection_score(err_all, torch.cat(pooled["camera"])),
        "score_surface": selection_score(err_all, torch.cat(pooled["surface"])),
        "bands": band_profile(err_all, torch.cat(pooled["u"]), bands),
        "views": views,
    }


def _markdown(report: dict) -> str:
    lines = [
        f"# Blend cues ({report['date']})",
        "",
        f"`{report['command']}` on {report['machine']['platform']}, {report['machine']['cpus']} CPUs.",
        "",
        "Between the two NeRFs nearest each test camera: how well each cue picks the per-pixel better rendering",
        "(selection score: 1 always the better NeRF, 0.5 a coin flip, 0 always the worse; pixels weighted by how much",
        "the choice matters), and the mean PSNR of each cue's hard per-pixel selection. Camera cue: the NeRF nearest",
        "the camera (Nearest, IDW-2D). Surface cue: the NeRF whose expected surface point is nearest its origin",
        "(IDW-3D; IDW-Sample near the surface).",
        "",
        "| scene | layout | views | score camera cue | score surface cue | PSNR camera | PSNR surface | PSNR oracle |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in report["scenes"]:
        v = s["views"]

        def mean(key: str, views: list = v) -> float:
            return sum(x[key] for x in views) / len(views)

        lines.append(
            f"| {s['name']} | {s['layout']} | {s['test_views']} | {s['score_camera']:.3f} | {s['score_surface']:.3f} "
            f"| {mean('psnr_camera'):.2f} | {mean('psnr_surface'):.2f} | {mean('psnr_oracle'):.2f} |"
        )
    lines += [
        "",
        "Does each NeRF render its own side better? Each pixel's ground-truth surface point at u along the axis from",
        "the camera's NeRF origin (u = 0) to the other NeRF's (u = 1); PSNR of each NeRF over the pixels of each band",
        "(all views pooled; the outer bands take everything beyond). The surface cue's premise: the camera's NeRF",
        "better below u = 0.5, the other above.",
        "",
        "| scene | band of u | pixel share | PSNR camera's NeRF | PSNR other NeRF | camera's - other |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for s in report["scenes"]:
        for b in s["bands"]:
            lo, hi = b["u"]
            lines.append(
                f"| {s['name']} | {lo:g} - {hi:g} | {b['pixel_share']:.2f} | {b['psnr_camera_nerf']:.2f} "
                f"| {b['psnr_other_nerf']:.2f} | {b['psnr_camera_nerf'] - b['psnr_other_nerf']:+.2f} |"
            )
    for s in report["scenes"]:
        lines += [
            "",
            f"## {s['name']}",
            "",
            "| view | NeRFs | distance ratio | score camera | score surface | PSNR camera / surface / oracle |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for x in s["views"]:
            lines.append(
                f"| {x['view']} | {x['nerfs'][0]}, {x['nerfs'][1]} | {x['distance_ratio']:.2f} "
                f"| {x['score_camera']:.2f} | {x['score_surface']:.2f} "
                f"| {x['psnr_camera']:.2f} / {x['psnr_surface']:.2f} / {x['psnr_oracle']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def main(cfg: BenchBlendCuesConfig) -> None:
    if len(cfg.bands) < 2 or any(b >= c for b, c in zip(cfg.bands, cfg.bands[1:], strict=False)):
        raise SystemExit(f"bench_blend_cues: --bands must be at least two increasing edges, got {cfg.bands}")
    import torch
    from rich.console import Console

    from nerfuser_ns.bench import evaluation
    from nerfuser_ns.bench.evaluation import SceneRuns
    from nerfuser_ns.files import write_text_atomic

    console = Console()
    try:
        scenes = [SceneRuns.parse(s) for s in cfg.scenes]
    except evaluation.EvaluationError as e:
        raise SystemExit(f"bench_blend_cues: {e}") from None
    report = {
        "command": "python scripts/bench_blend_cues.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "scenes": [],
    }
    for scene in scenes:
        try:
            res = scene_cues(scene, cfg.max_test_views, description=scene.name, bands=cfg.bands)
        except evaluation.EvaluationError as e:
            raise SystemExit(f"bench_blend_cues: {e}") from None
        console.print(f"{scene.name}: camera cue {res['score_camera']:.3f}, surface cue {res['score_surface']:.3f}")
        report["scenes"].append(res)
        write_text_atomic(cfg.output, json.dumps(report, indent=2) + "\n")
        write_text_atomic(cfg.output.with_suffix(".md"), _markdown(report))
    console.print(f"wrote {cfg.output} and {cfg.output.with_suffix('.md')}")


def entrypoint() -> None:
    main(tyro.cli(BenchBlendCuesConfig))


if __name__ == "__main__":
    entrypoint()
