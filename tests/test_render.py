"""nerfstudio's ns-render spiral and interpolate, and ns-export pointcloud, on a fused run of the two shipped demo
NeRFs (demo/runs).

Both commands need cameras from the run's datamanager: the fusion spec's test views, else every NeRF's training
cameras (in the common frame), else they fail with one line naming what to use instead. Renders are a few frames of a
few pixels, written as images (no video encoding). ns-export tsdf and poisson mesh the fused scene.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
import yaml
from nerfstudio.scripts import exporter, render
from nerfstudio.utils import install_checks
from nerfstudio.utils.eval_utils import eval_setup
from PIL import Image

from nerfuser_ns import runs, sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.spec import write_fusion_spec

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEMO = {c: ROOT / "demo" / "runs" / c / "nerfacto-cpu" / "demo" for c in ("capture_a", "capture_b")}
# capture_b's frame in capture_a's, roughly as `make demo` registered it; the common frame is capture_a's, x1.5
A_TO_COMMON = sim3.make_sim3(np.eye(3), np.array([0.3, -0.2, 0.1]), 1.5)
B_TO_A = sim3.make_sim3(scenes.yaw_rotation(np.arctan2(-0.929, 0.369)), np.array([0.136, 1.088, 0.035]), 1.0)
W, H = 8, 6  # the cameras' size: every render is a few dozen rays


def ring(n: int, radius: float = 0.8, height: float = 0.4) -> np.ndarray:
    """OpenGL camera-to-world poses on a ring around the origin, looking at it."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        back = eye / np.linalg.norm(eye)  # OpenGL cameras look along -z
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        out.append(sim3.make_sim3(np.stack([right, np.cross(back, right), back], axis=1), eye, 1.0))
    return np.stack(out)


def write_dataset(folder: Path, c2w: np.ndarray) -> Path:
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, pose in enumerate(c2w):
        Image.fromarray(np.full((H, W, 3), 30 * i, np.uint8)).save(folder / "images" / f"{i}.png")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": pose.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 7.0, "fl_y": 7.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H}
    (folder / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    return folder


def copy_run(demo_run: Path, dest: Path, data: Path) -> Path:
    """A copy of a demo run whose config.yml records ``data`` as its dataset."""
    shutil.copytree(demo_run, dest)
    config = runs.read_config(dest / "config.yml")
    config.pipeline.datamanager.data = data
    (dest / "config.yml").write_text(yaml.dump(config))
    return dest / "config.yml"


@pytest.fixture(scope="module")
def fusion(tmp_path_factory) -> dict:
    """The demo NeRFs fused by ns-train nerfuser; the spec file is rewritten by each test (the run reads it again)."""
    root = tmp_path_factory.mktemp("render")
    a = copy_run(DEMO["capture_a"], root / "runs" / "a", write_dataset(root / "capture_a", ring(6)))
    a_gone = copy_run(DEMO["capture_a"], root / "runs" / "a_gone", root / "no_such_dataset")
    b = copy_run(DEMO["capture_b"], root / "runs" / "b", root / "no_such_dataset")
    transforms = [A_TO_COMMON, A_TO_COMMON @ B_TO_A]
    for name, configs in (("registration.json", (a, b)), ("registration_gone.json", (a_gone, b))):
        nerfs = [
            {"name": n, "config": str(c), "transform": T.tolist()}
            for n, c, T in zip("ab", configs, transforms, strict=True)
        ]
        (root / name).write_text(json.dumps({"nerfs": nerfs}))
    # test views: a ring in capture_a's frame, mapped into the common frame
    test_data = write_dataset(root / "test", sim3.transform_poses(A_TO_COMMON, ring(3, radius=0.9)))
    spec = write_fusion_spec(root / "fusion.json", [a, b], registration="registration.json", test_data=test_data)
    proc = subprocess.run(
        [str(BIN / "ns-train"), "nerfuser", "--data", str(spec), "--output-dir", str(root / "outputs")]
        + ["--experiment-name", "fused", "--timestamp", "run"],
        cwd=root,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {"root": root, "spec": spec, "config": root / "outputs" / "fused" / "nerfuser" / "run" / "config.yml",
            "a": a, "a_gone": a_gone, "b": b, "test_data": test_data}  # fmt: skip


@pytest.fixture(autouse=True)
def no_ffmpeg_needed(monkeypatch):
    """Images need no ffmpeg, but nerfstudio checks for it first."""
    monkeypatch.setattr(install_checks, "check_ffmpeg_installed", lambda: None)


def frames(folder: Path) -> list[np.ndarray]:
    return [np.asarray(Image.open(p)) for p in sorted(folder.glob("*.png"))]


def spiral(fusion: dict, out: Path) -> render.SpiralRender:
    return render.SpiralRender(load_config=fusion["config"], output_path=out / "spiral.mp4", output_format="images",
                               image_format="png", seconds=1.0, frame_rate=4)  # fmt: skip


def interpolate(fusion: dict, out: Path) -> render.RenderInterpolated:
    return render.RenderInterpolated(load_config=fusion["config"], output_path=out / "interp.mp4",
                                     output_format="images", image_format="png", interpolation_steps=2)  # fmt: skip


def test_spiral_and_interpolate_along_the_test_views(fusion, tmp_path):
    write_fusion_spec(fusion["spec"], [fusion["a"], fusion["b"]], registration="registration.json",
                      test_data=fusion["test_data"])  # fmt: skip
    spiral(fusion, tmp_path).main()
    shots = frames(tmp_path / "spiral")
    assert len(shots) == 4 and all(s.shape == (H, W, 3) for s in shots)
    assert len({s.tobytes() for s in shots}) > 1  # the camera moves
    interpolate(fusion, tmp_path).main()
    assert len(frames(tmp_path / "interp")) >= 4  # 3 test views, 2 steps between each


def test_without_test_views_the_training_cameras_are_used(fusion, tmp_path):
    write_fusion_spec(fusion["spec"], [fusion["a"], fusion["b"]], registration="registration.json")
    spiral(fusion, tmp_path).main()
    assert len(shots := frames(tmp_path / "spiral")) == 4 and shots[0].shape == (H, W, 3)
    interpolate(fusion, tmp_path).main()
    assert len(frames(tmp_path / "interp")) >= 4


def test_without_any_cameras_spiral_names_what_to_use(fusion, tmp_path):
    """No test views and no readable dataset: one line naming ns-render camera-path, not a bare AssertionError."""
    write_fusion_spec(fusion["spec"], [fusion["a_gone"], fusion["b"]], registration="registration_gone.json")
    with pytest.raises(SystemExit) as exit_info:
        spiral(fusion, tmp_path).main()
    message = str(exit_info.value.code)
    assert "\n" not in message and "no cameras to render a spiral" in message, message
    assert "ns-render camera-path" in message and "ns-render dataset" in message
    assert not (tmp_path / "spiral").exists()


def test_ns_export_pointcloud_exports_the_fused_scene_from_every_nerfs_cameras(fusion, tmp_path, capsys):
    """nerfstudio's own ``ns-export pointcloud`` on a fused run: points of rays from every NeRF's training cameras
    (capture_a's from its dataset, capture_b's from the registration file), in the common frame."""
    reg = json.loads((fusion["root"] / "registration.json").read_text())
    reg["nerfs"][1]["training_cameras"] = {"c2w": ring(4, radius=0.9)[:, :3].tolist(),
                                           "intrinsics": [[7.0, 7.0, W / 2, H / 2, W, H]] * 4}  # fmt: skip
    (fusion["root"] / "registration_cams.json").write_text(json.dumps(reg))
    write_fusion_spec(fusion["spec"], [fusion["a"], fusion["b"]], registration="registration_cams.json")
    export = exporter.ExportPointCloud(load_config=fusion["config"], output_dir=tmp_path / "export", num_points=300,
                                       remove_outliers=False, normal_method="open3d", num_rays_per_batch=128)
    export.main()
    assert "no training cameras" not in capsys.readouterr().out  # both NeRFs have cameras
    cloud = o3d.io.read_point_cloud(str(tmp_path / "export" / "point_cloud.ply"))
    points, colours = np.asarray(cloud.points), np.asarray(cloud.colors)
    assert len(points) >= 300 and np.isfinite(points).all() and colours.std(axis=0).max() > 0.01
    # the first points are the fused depth along the datamanager's first rays (their geometry: tests/test_data.py),
    # kept where the blend's accumulation passes 0.5
    _, pipeline, _, _ = eval_setup(fusion["config"], test_mode="inference")
    pipeline.datamanager.train_pixel_sampler.num_rays_per_batch = 128
    bundle, _ = pipeline.datamanager.next_train(0)
    with torch.no_grad():
        outputs = pipeline.model(bundle)
    alpha = pipeline.model.get_rgba_image(outputs)[:, 3]
    torch.testing.assert_close(alpha, outputs["accumulation"][:, 0])  # not nerfstudio's alpha of 1 everywhere
    keep = alpha > 0.5
    with pytest.raises(NotImplementedError, match="accumulation_idw_sample"):  # an output without its own alpha
        pipeline.model.get_rgba_image({**outputs, "rgb_idw_sample": outputs["rgb"]}, "rgb_idw_sample")
    expected = (bundle.origins + bundle.directions * outputs["depth"])[keep].double().numpy()
    np.testing.assert_allclose(points[: len(expected)], expected, atol=1e-4)
    # ns-export's default --normal-method model_output probes the model with one ray and stops with its own advice
    # (a fused run has no normals, as stock nerfacto has none): that probe must reach the advice, not a traceback
    with pytest.raises(SystemExit):
        exporter.validate_pipeline("model_output", "normals", pipeline)
    assert "--normal-method" in capsys.readouterr().out
    # without the training cameras of capture_b, its rays are left out and said so
    write_fusion_spec(fusion["spec"], [fusion["a"], fusion["b"]], registration="registration.json")
    export.output_dir = tmp_path / "export_a"
    export.main()
    assert "no training cameras for b" in " ".join(capsys.readouterr().out.split())
    assert (tmp_path / "export_a" / "point_cloud.ply").is_file()


def test_ns_export_tsdf_and_poisson_mesh_the_fused_scene(fusion, tmp_path):
    """nerfstudio's own ``ns-export tsdf`` (textured by the fused model) and ``poisson`` on a fused run: the TSDF
    integrates the blend's depth from the run's cameras (here the test views) inside the fused scene box, so its
    surface passes through the fused depth points."""
    write_fusion_spec(fusion["spec"], [fusion["a"], fusion["b"]], registration="registration.json",
                      test_data=fusion["test_data"])  # fmt: skip
    exporter.ExportTSDFMesh(load_config=fusion["config"], output_dir=tmp_path / "tsdf", resolution=16,
                            downscale_factor=1, use_bounding_box=False, num_pixels_per_side=64,
                            target_num_faces=500).main()  # fmt: skip
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "tsdf" / "tsdf_mesh.ply"))
    vertices = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 0 and (tmp_path / "tsdf" / "mesh.obj").is_file()  # textured through the model
    _, pipeline, _, _ = eval_setup(fusion["config"], test_mode="inference")
    box = pipeline.datamanager.train_dataset.scene_box.aabb.double().numpy()  # every NeRF's [-1, 1] cube
    assert (vertices >= box[0] - 1e-4).all() and (vertices <= box[1] + 1e-4).all()
    cameras = pipeline.datamanager.train_dataset.cameras
    points = []
    for i in range(len(cameras)):
        with torch.no_grad():
            outputs = pipeline.model.get_outputs_for_camera(cameras[i : i + 1])
        rays = cameras[i : i + 1].generate_rays(camera_indices=0)
        surface = outputs["accumulation"][..., 0] > 0.5
        points.append((rays.origins + rays.directions * outputs["depth"])[surface].double().numpy())
    points = np.concatenate(points)
    points = points[((points > box[0]) & (points < box[1])).all(-1)]
    voxel = (box[1] - box[0]).max() / 16
    nearest = np.linalg.norm(points[:, None] - vertices[None], axis=-1).min(axis=1)
    assert len(points) > 20 and np.median(nearest) < voxel, (np.median(nearest), voxel)
    exporter.ExportPoissonMesh(load_config=fusion["config"], output_dir=tmp_path / "poisson", num_points=300,
                               remove_outliers=False, normal_method="open3d", num_rays_per_batch=128,
                               texture_method="point_cloud").main()  # fmt: skip
    poisson = o3d.io.read_triangle_mesh(str(tmp_path / "poisson" / "poisson_mesh.ply"))
    assert len(poisson.triangles) > 0 and np.isfinite(np.asarray(poisson.vertices)).all()
