"""Evaluation building blocks on a tiny generated scene with two tiny trained runs, and the blending benchmark."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro

from nerfuser_ns import runs, sim3
from nerfuser_ns.appearance import IDENTITY
from nerfuser_ns.bench import evaluation, metrics, scenes
from nerfuser_ns.bench.evaluation import EvaluationError, SceneRuns
from nerfuser_ns.bench.training import train
from nerfuser_ns.blending import BLEND_METHODS, PAPER_BLEND_METHODS
from nerfuser_ns.cameras import camera_rays
from nerfuser_ns.coverage import CoverageParams
from nerfuser_ns.registration import NerfEntry, write_minimal_registration

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny(tiny_scene, tmp_path_factory) -> SceneRuns:
    """The tiny object-centric scene and one tiny nerfacto-cpu run per capture, laid out as build_demo.py does."""
    root = tmp_path_factory.mktemp("eval")
    for capture in ("capture_a", "capture_b"):
        train(data=tiny_scene / capture, output_dir=root / "runs", experiment_name=capture,
              max_num_iterations=30, seed=0, timestamp="demo", tiny=True)  # fmt: skip
    return SceneRuns.from_dirs("tiny", tiny_scene, root / "runs")


@pytest.fixture(scope="module")
def models(tiny):
    return [(n, runs.load_run(p).model) for n, p in zip(tiny.captures, tiny.configs, strict=True)]


def test_scene_runs_bad_input_names_the_file(tiny, tmp_path):
    with pytest.raises(EvaluationError, match=r"ground_truth.json: no ground truth"):
        SceneRuns.from_dirs("x", tmp_path, tiny.configs[0].parents[3])
    runs_dir = tmp_path / "runs"
    shutil.copytree(tiny.configs[0].parents[3], runs_dir)
    shutil.rmtree(runs_dir / "capture_b")
    with pytest.raises(EvaluationError, match=r"capture_b/nerfacto-cpu/demo/config.yml: no trained run.*build_demo"):
        SceneRuns.from_dirs("x", tiny.scene_dir, runs_dir)
    with pytest.raises(EvaluationError, match="NAME=SCENE_DIR:RUNS_DIR"):
        SceneRuns.parse("no-equals-sign")


def test_ground_truth_transforms_are_consistent(tiny):
    to_world = tiny.nerf_to_world()
    to_common = tiny.nerf_to_common(reference=1)
    np.testing.assert_allclose(to_common[1], np.eye(4), atol=1e-9)
    # a point of NeRF 0 reaches the world the same way directly and through the common frame
    p = np.array([0.1, -0.2, 0.3, 1.0])
    np.testing.assert_allclose(to_world[1] @ to_common[0] @ p, to_world[0] @ p, atol=1e-6)  # float32 json
    # the test cameras, posed in the common frame, are the world test cameras
    cams, target = tiny.test_views(reference=1)
    meta = json.loads((tiny.scene_dir / "test" / "transforms.json").read_text())
    world = np.stack([np.asarray(f["transform_matrix"]) for f in meta["frames"]])
    back = sim3.transform_poses(
        to_world[1],
        np.concatenate([cams.camera_to_worlds.double().numpy(), np.tile([[[0, 0, 0, 1.0]]], (len(cams), 1, 1))], 1),
    )
    np.testing.assert_allclose(back[:, :3, 3], world[:, :3, 3], atol=1e-5)
    assert target.shape == (len(world), meta["h"], meta["w"], 3) and 0 <= target.min() and target.max() <= 1


def test_registered_transforms_follow_capture_order(tiny, tmp_path):
    T = tiny.nerf_to_common()
    entries = [NerfEntry(n, c, t) for n, c, t in zip(tiny.captures, tiny.configs, T, strict=True)]
    path = write_minimal_registration(entries[::-1], tmp_path / "reg.json")
    got = evaluation.registered_transforms(path, tiny)
    for a, b in zip(got, T, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    other = write_minimal_registration([NerfEntry("zzz", tiny.configs[0], np.eye(4))], tmp_path / "other.json")
    with pytest.raises(EvaluationError, match="no NeRF named 'capture_a'"):
        evaluation.registered_transforms(other, tiny)


def test_blend_metrics_nerf_method_is_the_reference_alone(tiny, models):
    cams, target = tiny.test_views()
    T = tiny.nerf_to_common()
    scores = evaluation.blend_metrics(models, T, cams, target, methods=("nerf", "nearest", "idw-sample"))
    assert set(scores) == {"nerf", "nearest", "idw-sample"}
    alone = runs.render_views(models[0][1], cams, outputs=("rgb",), progress=False)["rgb"]
    expected = metrics.image_metrics(alone.clamp(0, 1), target)
    assert scores["nerf"]["psnr"] == pytest.approx(expected["psnr"], abs=1e-3)
    # the other methods really blend: with two different NeRFs they do not reproduce the reference alone
    assert scores["idw-sample"]["psnr"] != pytest.approx(expected["psnr"], abs=1e-3)
    with pytest.raises(EvaluationError, match="2 models but 1 transforms"):
        evaluation.blend_metrics(models, T[:1], cams, target)


def test_blend_metrics_apply_the_colour_maps_given(tiny, models):
    """Identity maps score as no maps; a gain on the second NeRF leaves the reference alone and changes the blends."""
    cams, target = tiny.test_views(max_views=1)
    T = tiny.nerf_to_common()
    methods = ("nerf", "idw-sample")
    plain = evaluation.blend_metrics(models, T, cams, target, methods=methods)
    identity = evaluation.blend_metrics(models, T, cams, target, methods=methods, colour_maps=[None, IDENTITY])
    brighter = np.hstack([np.diag([2.0, 2.0, 2.0]), np.zeros((3, 1))])
    gained = evaluation.blend_metrics(models, T, cams, target, methods=methods, colour_maps=[None, brighter])
    for m in methods:
        assert identity[m]["psnr"] == pytest.approx(plain[m]["psnr"], abs=1e-5)
    assert gained["nerf"]["psnr"] == pytest.approx(plain["nerf"]["psnr"], abs=1e-5)
    assert abs(gained["idw-sample"]["psnr"] - plain["idw-sample"]["psnr"]) > 0.05


def test_coverage_is_scored_with_the_runs_training_cameras(tiny, models):
    """The kit scores ours (coverage) only with the runs' cameras, read as a registration records them."""
    cams, target = tiny.test_views()
    T = tiny.nerf_to_common()
    nerf_cameras = evaluation.training_cameras(tiny, models)
    for (_, model), tc, config, capture in zip(models, nerf_cameras, tiny.configs, tiny.capture_dirs(), strict=True):
        parsed = runs.training_cameras(config, data_override=capture)
        assert len(tc.c2w) == len(parsed) == model.num_train_data
        np.testing.assert_allclose(tc.intrinsics[:, 0], parsed.fx[:, 0].numpy(), rtol=1e-6)
    with pytest.raises(EvaluationError, match="needs the runs' training cameras"):
        evaluation.blend_metrics(models, T, cams, target, methods=("idw-sample", "coverage"))
    # no distance test: with tau 1.8 every test ray of this scene keeps one NeRF, and one NeRF blends alike
    scores = evaluation.blend_metrics(models, T, cams, target, tau=None, methods=("idw-sample", "coverage"),
                                      nerf_cameras=nerf_cameras)  # fmt: skip
    assert set(scores) == {"idw-sample", "coverage"} and np.isfinite(scores["coverage"]["psnr"])
    # the cameras change the weights: not IDW-Sample's fallback
    assert scores["coverage"]["psnr"] != pytest.approx(scores["idw-sample"]["psnr"], abs=1e-4)


def test_measure_render_cost(tiny, models):
    cams, _ = tiny.test_views()
    cost = evaluation.measure_render_cost(models, tiny.nerf_to_common(), cams, num_rays=256, repeats=5)
    assert cost.num_rays == 256 and cost.repeats == 5 and len(cost.sub_s) == 2 == len(cost.sub_peak_mib)
    assert cost.fused_s > 0 and all(t > 0 for t in cost.sub_s)
    q1, q3 = cost.ratio_quartiles
    assert 0 < q1 <= cost.ratio <= q3  # the median per-repeat ratio lies within its quartiles
    u1, u3 = cost.ratio_used_quartiles
    assert 0 < u1 <= cost.ratio_used <= u3
    # No bound ties the paired ratio to the ratio of the median times: with another test process on the cores, 5
    # repeats gave 1.31 against 0.35 (CI), so only properties that hold by construction are checked here.
    # Every ray is rendered by one NeRF at least. In this scene the distance test gives each ray to one NeRF alone
    # (139 + 117 of 256 seen), so the fused pass may cost less than a sub-model's full pass; what it cannot undercut
    # is a sub-model's pass on the rays the fused model queries it on. Compared on each pass's fastest repeat: with
    # another test process on the same cores, medians of 5 passes of ~10 ms swung 3x apart (fused 0.05 s, one
    # sub-model 0.14 s). Even the fastest repeats tie within noise (CI: fused 0.195 s against 0.197 s), so the bound
    # is half: it still fails a fused pass that renders far fewer samples than the sub-models do on its rays.
    assert len(cost.used_rays) == 2 and sum(cost.used_rays) >= cost.num_rays
    assert cost.fused_min_s > 0.5 * max(cost.sub_used_min_s)
    assert cost.fused_min_s <= cost.fused_s
    assert all(m <= t for m, t in zip(cost.sub_used_min_s, cost.sub_used_s, strict=True))
    assert cost.fused_peak_mib >= 0 and set(cost.as_dict()) >= {"ratio", "fused_s", "sub_s", "fused_peak_mib"}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator (the memory sampler's setting)")
def test_peak_memory_sees_reused_heap():
    # Free space inside the heap (what earlier rendering leaves behind) must not hide new allocations from RSS.
    blocks = [np.ones(4096) for _ in range(3200)]  # 100 MiB in 32 KiB blocks, below the mmap threshold
    top = np.ones(4096)  # keeps the freed blocks below the top of the heap, out of reach of the automatic trim
    del blocks
    with evaluation._PeakRSS() as mem:
        again = [np.ones(4096) for _ in range(1600)]  # 50 MiB
    # without the trim the reused heap hides nearly all of it (~0 MiB); the allocator keeps some pages resident in a
    # process that has run other tests (39 MiB seen under pytest-xdist), so the bound is half the allocation
    assert 25 < mem.added_mib < 80, mem.added_mib
    del again, top


def test_geometric_gammas():
    g = evaluation.geometric_gammas(1e-2, 1e3, 6)
    assert g[0] == pytest.approx(1e-2) and g[-1] == pytest.approx(1e3)
    assert np.allclose(np.diff(np.log10(g)), 1.0)


def test_bench_blending_script(tiny, tmp_path):
    reg = write_minimal_registration([
        NerfEntry(n, c, T) for n, c, T in zip(tiny.captures, tiny.configs, tiny.nerf_to_common(), strict=True)
    ], tmp_path / "reg.json")  # fmt: skip
    runs_dir = tiny.configs[0].parents[3]
    out = tmp_path / "bench" / "blending.json"
    cmd = [
        sys.executable,
        str(ROOT / "scripts/bench_blending.py"),
        "--scenes",
        f"tiny={tiny.scene_dir}:{runs_dir}",
        "--registrations",
        f"tiny={reg}",
        "--timing-rays",
        "128",
        "--timing-repeats",
        "1",
        "--cost-methods",
        "idw-sample",
        "coverage",
        "--device",
        "cpu",
        "--gammas",
        "5",
        "1000",
        "--output",
        str(out),
    ]
    result = subprocess.run(
        cmd, capture_output=True, text=True, cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(out.read_text())
    (scene,) = report["scenes"]
    assert scene["gamma"] == 5.0 and scene["tau"] == 1.8  # the paper's object-centric setting
    q = scene["quality"]
    assert set(q) == {"ground-truth", "estimated"} and set(q["estimated"]) == set(BLEND_METHODS)
    for m in BLEND_METHODS:  # the "estimated" transforms are the ground truth here
        assert q["estimated"][m]["psnr"] == pytest.approx(q["ground-truth"][m]["psnr"], abs=1e-4)
    assert report["machine"]["device"] == "cpu" and report["machine"]["gpu"] is None
    assert list(scene["costs"]) == ["idw-sample", "coverage"]
    assert [c["method"] for c in scene["costs"].values()] == ["idw-sample", "coverage"]
    cost = scene["cost"]
    assert cost == scene["costs"]["idw-sample"] and cost["num_rays"] == 128
    # the nearest NeRF of each ray is always queried, never more rays than the chunk holds
    assert sum(cost["used_rays"]) >= 128 and all(0 <= r <= 128 for r in cost["used_rays"])
    assert len(cost["sub_used_s"]) == len(cost["sub_s"]) and cost["ratio_used"] > 0
    # the sweep re-blends the same samples: at the scene's own gamma it scores what the quality pass scored
    sweep = scene["gamma_sweep"]
    assert set(sweep) == {"5.0", "1000.0"}
    for m in PAPER_BLEND_METHODS:  # the sweep re-blends the paper's methods
        assert sweep["5.0"][m]["psnr"] == pytest.approx(q["ground-truth"][m]["psnr"], abs=1e-4)
    for m in ("nerf", "nearest"):  # no gamma in them
        assert sweep["1000.0"][m]["psnr"] == pytest.approx(sweep["5.0"][m]["psnr"], abs=1e-6)
    md = out.with_suffix(".md").read_text()
    assert "IDW-Sample - Nearest" in md and "| 1000 |" in md
    assert "median fused idw-sample" in md and "median fused coverage" in md
    assert not list(out.parent.glob("*.tmp"))
    bad = subprocess.run(cmd[:3] + ["nope=/nonexistent:/nonexistent"], capture_output=True, text=True)
    assert bad.returncode != 0 and "ground_truth.json: no ground truth" in bad.stderr
    for args, message in ((["--cost-methods", "idw"], "unknown blend method 'idw'"),
                          (["--cost-methods", "coverage", "--no-coverage"], "drop --no-coverage")):  # fmt: skip
        bad = subprocess.run(cmd + args, capture_output=True, text=True, cwd=tmp_path)
        assert bad.returncode != 0 and message in bad.stderr and "Traceback" not in bad.stderr


def test_test_surface_points_are_where_the_test_rays_hit(tiny):
    layout = scenes.layout_from_ground_truth(tiny.scene_dir)
    to_world = tiny.nerf_to_world()[1]
    points = tiny.test_surface_points(reference=1).double().numpy()
    k = layout.test.intrinsics
    assert points.shape == (layout.test.num_views, k.height, k.width, 3)
    for v, c2w in enumerate(layout.test.c2w_world):
        hit = scenes.render(layout.scene, c2w, k, supersample=1)
        origins, directions = camera_rays(c2w, k)
        expected = (origins + directions * hit.depth[..., None, None])[:, :, 0].numpy()
        world = points[v] @ to_world[:3, :3].T + to_world[:3, 3]  # back from the common frame
        mask = hit.mask.numpy()
        assert mask.any() and np.isnan(world[~mask]).all() and not np.isnan(world[mask]).any()
        # depth files hold z-depth in millimetres (half a millimetre of rounding)
        np.testing.assert_allclose(world[mask], expected[mask], atol=2e-3)


def test_test_surface_points_need_depth_files(tiny, tmp_path):
    shutil.copytree(tiny.scene_dir / "test", tmp_path / "test")
    meta = json.loads((tmp_path / "test" / "transforms.json").read_text())
    for f in meta["frames"]:
        del f["depth_file_path"]
    (tmp_path / "test" / "transforms.json").write_text(json.dumps(meta))
    scene = SceneRuns("x", tmp_path, tiny.configs, tiny.ground_truth)
    with pytest.raises(EvaluationError, match=r"test/transforms.json: test frames without depth_file_path"):
        scene.test_surface_points()


def test_bench_blend_cues_script(tiny, tmp_path):
    runs_dir = tiny.configs[0].parents[3]
    out = tmp_path / "cues.json"
    cmd = [sys.executable, str(ROOT / "scripts/bench_blend_cues.py"), "--scenes", f"tiny={tiny.scene_dir}:{runs_dir}",
           "--output", str(out)]  # fmt: skip
    result = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr[-2000:]
    (scene,) = json.loads(out.read_text())["scenes"]
    assert scene["test_views"] == len(scene["views"]) == 2
    assert 0.0 <= scene["score_camera"] <= 1.0 and 0.0 <= scene["score_surface"] <= 1.0
    for v in scene["views"]:
        # the per-pixel oracle is at least as good as any per-pixel choice; the camera cue is the nearer NeRF
        assert v["psnr_oracle"] >= max(v["psnr_camera"], v["psnr_surface"]) - 1e-9
        assert v["psnr_camera"] == pytest.approx(v["psnr_nerfs"][0])
        assert min(v["psnr_nerfs"]) - 1e-9 <= v["psnr_surface"] <= v["psnr_oracle"] + 1e-9
        assert v["distance_ratio"] >= 1.0
    # the bands partition the test pixels (a closed room: every ray hits) and pool the camera NeRF's error
    bands = scene["bands"]
    assert [b["u"] for b in bands] == [[0.0, 0.25], [0.25, 0.5], [0.5, 0.75], [0.75, 1.0]]
    assert sum(b["pixel_share"] for b in bands) == pytest.approx(1.0)
    pooled_mse = sum(b["pixel_share"] * 10 ** (-b["psnr_camera_nerf"] / 10) for b in bands)
    per_view_mse = np.mean([10 ** (-v["psnr_nerfs"][0] / 10) for v in scene["views"]])
    assert pooled_mse == pytest.approx(per_view_mse, rel=1e-4)
    md = out.with_suffix(".md").read_text()
    assert "score surface cue" in md and "| tiny | 0.25 - 0.5 |" in md
    bad = subprocess.run(cmd[:3] + ["nope=/nonexistent:/nonexistent"], capture_output=True, text=True)
    assert bad.returncode != 0 and "ground_truth.json: no ground truth" in bad.stderr
    bad = subprocess.run(cmd + ["--bands", "0.5", "0.2"], capture_output=True, text=True)
    assert bad.returncode != 0 and "--bands must be at least two increasing edges" in bad.stderr


def test_gamma_sweep_matches_separate_renders(tiny, models):
    cams, target = tiny.test_views(max_views=1)
    T = tiny.nerf_to_common()
    # no distance test: it would make every method the nearest NeRF on this view
    sweep = evaluation.gamma_sweep(
        models, T, cams, target, gammas=[0.5, 20.0], tau=None, methods=("nearest", "idw-sample")
    )
    assert set(sweep) == {0.5, 20.0}
    for g in (0.5, 20.0):
        one = evaluation.blend_metrics(models, T, cams, target, gamma=g, tau=None, methods=("nearest", "idw-sample"))
        for m in ("nearest", "idw-sample"):
            assert sweep[g][m]["psnr"] == pytest.approx(one[m]["psnr"], abs=1e-3)
    assert sweep[0.5]["nearest"]["psnr"] == pytest.approx(sweep[20.0]["nearest"]["psnr"], abs=1e-6)  # no gamma
    assert sweep[0.5]["idw-sample"]["psnr"] != pytest.approx(sweep[20.0]["idw-sample"]["psnr"], abs=1e-4)


def test_blend_sweep_over_coverage_constants_matches_separate_renders(tiny, models):
    """A sweep over coverage constants (what the validation script tunes) scores what separate fused models with
    those constants score, and leaves the model's own settings as they were."""
    cams, target = tiny.test_views(max_views=1)
    T = tiny.nerf_to_common()
    nerf_cameras = evaluation.training_cameras(tiny, models)
    methods = ("idw-sample", "coverage")
    model = evaluation.fused(models, T, nerf_cameras, tau=None, render_all_methods=True, share_outputs=False)
    before = model.blend_settings
    settings = [{"coverage": CoverageParams(sigma_deg=5.0, k=1, candidates=4)},
                {"coverage": CoverageParams(sigma_deg=60.0, k=2, candidates=8), "gamma": 1.0}]
    sweep = evaluation.blend_sweep(model, cams, target, settings, methods)
    assert model.blend_settings == before
    for changes, result in zip(settings, sweep, strict=True):
        one = evaluation.fused(models, T, nerf_cameras, tau=None, render_all_methods=True, share_outputs=False,
                               coverage=changes["coverage"], gamma=changes.get("gamma", before.gamma))
        with torch.no_grad():
            image = runs.render_views(one, cams, outputs=("rgb_coverage",), progress=False)["rgb_coverage"]
        assert result["coverage"]["psnr"] == pytest.approx(metrics.image_metrics(image, target)["psnr"], abs=1e-3)
    assert sweep[0]["coverage"]["psnr"] != pytest.approx(sweep[1]["coverage"]["psnr"], abs=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cost_and_gamma_sweep_on_cuda_models(tiny, models):
    """The kit's measurements follow the models' device: rays and cameras are moved there, CUDA memory is the
    allocator's peak, and the sweep scores what the CPU scores."""
    cams, target = tiny.test_views(max_views=1)
    T = tiny.nerf_to_common()
    on_cuda = [(n, runs.load_run(p, device="cuda").model) for n, p in zip(tiny.captures, tiny.configs, strict=True)]
    cost = evaluation.measure_render_cost(on_cuda, T, cams, num_rays=256, repeats=3)
    assert cost.fused_s > 0 and cost.fused_peak_mib > 0 and sum(cost.used_rays) >= 256
    kwargs = {"gammas": [5.0], "tau": None, "methods": ("nearest", "idw-sample")}
    gpu = evaluation.gamma_sweep(on_cuda, T, cams, target, **kwargs)
    cpu = evaluation.gamma_sweep(models, T, cams, target, **kwargs)
    for m in kwargs["methods"]:
        assert gpu[5.0][m]["psnr"] == pytest.approx(cpu[5.0][m]["psnr"], abs=0.05)


def test_demo_script_scores_a_given_registration(tiny, tmp_path, monkeypatch, load_script):
    """scripts/demo.py on the tiny runs, blending with a registration file given (the ground truth): the estimated
    column equals the ground-truth one and the registration errors are zero."""
    demo = load_script("demo")
    runs_dir = tiny.configs[0].parents[3]
    reg = write_minimal_registration([
        NerfEntry(n, c, T) for n, c, T in zip(tiny.captures, tiny.configs, tiny.nerf_to_common(), strict=True)
    ], tmp_path / "reg.json")  # fmt: skip
    out = tmp_path / "demo"
    args = ["--scene-dir", str(tiny.scene_dir), "--runs-dir", str(runs_dir), "--output-dir", str(out),
            "--max-test-views", "2"]  # fmt: skip
    demo.main(tyro.cli(demo.DemoConfig, args=[*args, "--registration", str(reg)]))
    summary = json.loads((out / "summary.json").read_text())
    errors = summary["registration"]["errors"]
    assert errors["capture_b"]["r_err_deg"] < 1e-6 and errors["capture_b"]["t_err"] < 1e-6
    blend = summary["blending"]
    assert set(blend) == {"ground truth", "estimated"}
    for method in PAPER_BLEND_METHODS:
        assert blend["estimated"]["methods"][method]["psnr"] == pytest.approx(
            blend["ground truth"]["methods"][method]["psnr"], abs=1e-4
        )
        assert len(list((out / "fused" / "estimated" / method).glob("test_*.png"))) == 2
    # the registration the demo runs is ns-nerfuser-register's command line with its defaults but size, poses and
    # the device (the demo's own default: the same as the command's)
    command = demo.register_command(tiny.configs, tmp_path / "r.json", tmp_path / "w", 192, 24, "cpu")
    parsed = tyro.cli(demo.register.RegisterCommand, args=command[1:])
    assert command[0] == "ns-nerfuser-register" and parsed.configs == list(tiny.configs)
    assert (parsed.sampling.size, parsed.sampling.max_training_poses, parsed.sampling.source) == (192, 24, "auto")
    assert parsed.device == "cpu" and demo.DemoConfig().device == demo.register.RegisterCommand().device
    # a device this machine lacks is refused with one line before any work
    monkeypatch.setattr(sys, "argv", ["demo.py", *args, "--device", "cuda:7", "--output-dir", str(tmp_path / "none")])
    with pytest.raises(SystemExit, match=r"^demo: --device 'cuda:7' is not on this machine"):
        demo.entrypoint()
    assert not (tmp_path / "none").exists()
    # a file in another NeRF's frame is refused with one line naming it
    shifted = write_minimal_registration([
        NerfEntry(n, c, T) for n, c, T in zip(tiny.captures, tiny.configs, tiny.nerf_to_common(1), strict=True)
    ], tmp_path / "reg_b.json")  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["demo.py", *args, "--registration", str(shifted)])
    with pytest.raises(SystemExit, match="reg_b.json: not in capture_a's frame"):
        demo.entrypoint()


@pytest.mark.parametrize(
    "script, config", [("evaluate", "EvaluateConfig"), ("bench_baselines", "BenchBaselinesConfig")]
)
def test_scripts_needing_open3d_say_so_before_any_work(script, config, tmp_path, monkeypatch, load_script):
    """Open3D is the optional ``baselines`` extra: without it, one line naming it and the install command, nothing
    written."""
    module = load_script(script)
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d raises ImportError
    out = tmp_path / "out"
    args = ["--output-dir", str(out)] if script == "evaluate" else ["--output", str(out / "baselines.json")]
    cfg = tyro.cli(getattr(module, config), args=args)
    line = f'{script}: the point-cloud baselines need Open3D: pip install "nerfuser_ns[baselines]"'
    with pytest.raises(SystemExit, match=f"^{re.escape(line)}$"):
        module.main(cfg)
    assert not out.exists()
