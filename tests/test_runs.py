"""Train a tiny nerfacto offline on CPU, then load it back from config.yml and render it from arbitrary poses."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from dataset_helpers import process_data_like_dataset, run_on

from nerfuser_ns import runs, runtime
from nerfuser_ns.bench.training import train
from nerfuser_ns.cameras import Intrinsics


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
    """A nerfacto-cpu run trained for a few steps with every socket connection refused."""
    mp = pytest.MonkeyPatch()

    def no_network(*args, **kwargs):
        raise OSError("network access attempted during offline training")

    mp.setattr(socket.socket, "connect", no_network)
    try:
        out = tmp_path_factory.mktemp("outputs")
        result = train(
            data=tiny_scene / "capture_a", output_dir=out, experiment_name="tiny", max_num_iterations=6, seed=0,
            tiny=True,
        )
    finally:
        mp.undo()
    return result


def test_offline_training_writes_a_normal_run(trained):
    config_path = trained.config_path
    assert config_path.name == "config.yml" and config_path.is_file()
    assert (config_path.parent / "dataparser_transforms.json").is_file()
    ckpts = list((config_path.parent / "nerfstudio_models").glob("step-*.ckpt"))
    assert len(ckpts) == 1
    assert np.isfinite(trained.final_loss)


def test_checkpoint_round_trip_matches_in_memory_render(trained):
    loaded = runs.load_run(trained.config_path)
    assert loaded.step == trained.step
    c2w = torch.tensor([[1.0, 0, 0, 0.05], [0, 1, 0, -0.02], [0, 0, 1, 0.6]])
    cams = runs.make_cameras(c2w[None], Intrinsics(20, 20, 10, 8, 20, 16))
    ours = runs.render_views(loaded.model, cams, progress=False)
    ref = runs.render_views(trained.model, cams, progress=False)
    assert ours["rgb"].shape == (1, 16, 20, 3)
    # same weights, same rays: equal up to float reassociation in the compiled kernels
    torch.testing.assert_close(ours["rgb"], ref["rgb"], rtol=0, atol=5e-4)
    assert (ours["rgb"] - ref["rgb"]).abs().mean() < 1e-5
    torch.testing.assert_close(ours["depth"], ref["depth"], rtol=1e-3, atol=1e-3)


def test_load_with_relative_output_dir_from_another_cwd_and_missing_dataset(trained, tmp_path, monkeypatch):
    """A run copied elsewhere, its dataset gone, loaded from an unrelated working directory."""
    import shutil

    run_dir = trained.config_path.parent
    moved = tmp_path / "elsewhere" / "tiny" / "nerfacto-cpu" / run_dir.name
    shutil.copytree(run_dir, moved)
    cfg = yaml.load((moved / "config.yml").read_text(), Loader=yaml.Loader)
    cfg.output_dir = Path("relative/outputs")
    cfg.pipeline.datamanager.data = Path("/nonexistent/dataset")
    (moved / "config.yml").write_text(yaml.dump(cfg))
    monkeypatch.chdir(tmp_path)
    loaded = runs.load_run(moved / "config.yml")
    assert loaded.checkpoint_path.parent == moved / "nerfstudio_models"
    # the dataset frame needs the dataset (its applied_transform lives there): a clear error, only when asked for
    with pytest.raises(runs.RunLoadError, match="cannot read the run's dataset"):
        loaded.data_to_nerf  # noqa: B018
    with pytest.raises(runs.RunLoadError, match="dataset /nonexistent/dataset is missing"):
        runs.load_run(moved / "config.yml", with_data=True)


def test_load_with_data_gives_training_cameras(trained, tiny_scene):
    loaded = runs.load_run(trained.config_path, with_data=True, data_override=tiny_scene / "capture_a")
    cams = loaded.pipeline.datamanager.train_dataset.cameras
    assert len(cams) >= 10
    # both load paths replay the step-driven state (nerfacto's proposal anneal), so they render alike
    alone = runs.load_run(trained.config_path)
    view = cams[0:1]
    a = runs.render_views(loaded.model, view, outputs=("rgb", "depth"), progress=False)
    b = runs.render_views(alone.model, view, outputs=("rgb", "depth"), progress=False)
    torch.testing.assert_close(a["rgb"], b["rgb"], atol=1e-5, rtol=0)
    torch.testing.assert_close(a["depth"], b["depth"], atol=1e-4, rtol=1e-4)


def test_unregistered_method_name_still_loads(trained, tmp_path):
    import shutil

    moved = tmp_path / "o" / "tiny" / "my-own-method" / "run"
    shutil.copytree(trained.config_path.parent, moved)
    text = (moved / "config.yml").read_text().replace("method_name: nerfacto-cpu", "method_name: not-registered")
    (moved / "config.yml").write_text(text)
    loaded = runs.load_run(moved / "config.yml")
    assert loaded.config.method_name == "not-registered"


def test_bad_config_paths_give_clear_errors(tmp_path, trained):
    with pytest.raises(runs.RunLoadError, match=r"missing\.yml: no such file"):
        runs.load_run(tmp_path / "missing.yml")
    bad = tmp_path / "bad.yml"
    bad.write_text("pipeline: [unclosed\n")
    with pytest.raises(runs.RunLoadError, match=r"bad\.yml: not a readable nerfstudio config"):
        runs.load_run(bad)
    other = tmp_path / "other.yml"
    other.write_text("a: 1\n")
    with pytest.raises(runs.RunLoadError, match=r"other\.yml: not a nerfstudio run config"):
        runs.load_run(other)
    with pytest.raises(runs.RunLoadError, match="without config.yml"):
        runs.load_run(tmp_path)
    # a run whose checkpoints are gone
    import shutil

    no_ckpt = tmp_path / "o" / "tiny" / "nerfacto-cpu" / "run"
    shutil.copytree(trained.config_path.parent, no_ckpt)
    shutil.rmtree(no_ckpt / "nerfstudio_models")
    with pytest.raises(runs.RunLoadError, match="has no checkpoint"):
        runs.load_run(no_ckpt / "config.yml")
    # every message is one line
    try:
        runs.load_run(bad)
    except runs.RunLoadError as e:
        assert "\n" not in str(e)


def test_render_views_rejects_bad_cameras():
    with pytest.raises(ValueError, match="camera_to_worlds"):
        runs.make_cameras(np.zeros((2, 2, 4)), Intrinsics(10, 10, 5, 5, 10, 10))
    with pytest.raises(ValueError, match="positive"):
        runs.make_cameras(np.zeros((1, 3, 4)), Intrinsics(10, 10, 5, 5, 0, 10))


def test_runtime_installed_by_loading():
    runs.load_run  # noqa: B018 - importing runs is enough
    runtime.install()
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    assert LearnedPerceptualImagePatchSimilarity is runtime.LazyLPIPS


# ----------------------------------------------------------------------------------------------------------------------
# Frames of datasets made by ns-process-data (applied_transform / applied_scale)

@pytest.mark.parametrize("applied_scale", [1.0, 2.5])
def test_dataset_frame_with_applied_transform_lands_where_the_ground_truth_says(tmp_path, applied_scale):
    from nerfuser_ns import sampling, sim3

    eyes = np.array([[np.cos(a) * 3, np.sin(a) * 3, 1.0 + 0.2 * (a % 1)] for a in np.linspace(0, 5, 9)])
    world = sampling.look_at(eyes, np.zeros(3))
    data, stored_to_world = process_data_like_dataset(tmp_path / "data", world, applied_scale)
    config = run_on(tmp_path / "outputs", data)
    data_to_nerf = runs.read_dataparser_transform(config)
    nerf_cams = runs.training_cameras(config).camera_to_worlds.double().numpy()
    stored = np.array([f["transform_matrix"] for f in json.loads((data / "transforms.json").read_text())["frames"]])
    # the dataparser_transforms.json alone (what nerfstudio reports) does not map the stored poses onto them
    meta = json.loads((config.parent / "dataparser_transforms.json").read_text())
    naive = sim3.to_homogeneous(np.asarray(meta["transform"])) * np.array([meta["scale"]] * 3 + [1.0])[:, None]
    assert not np.allclose(sim3.transform_poses(naive, stored)[:, :3, 3], nerf_cams[:, :3, 3], atol=1e-2)
    # the stored poses, mapped by data_to_nerf, are the cameras the run trained with
    np.testing.assert_allclose(sim3.transform_poses(data_to_nerf, stored)[:, :3, :4], nerf_cams, atol=1e-5)
    # and through the ground truth, every NeRF-frame camera lands on its true world pose
    nerf_to_world = stored_to_world @ sim3.invert_sim3(data_to_nerf)
    np.testing.assert_allclose(sim3.transform_points(nerf_to_world, nerf_cams[:, :3, 3]), eyes, atol=1e-5)
    R, _, s = sim3.decompose_sim3(data_to_nerf)
    assert np.linalg.det(R) > 0 and s > 0


def test_dataset_frame_needs_the_dataset(tmp_path):
    from nerfuser_ns import sampling

    world = sampling.look_at(np.array([[3.0, 0, 1], [0, 3.0, 1], [-3.0, 0, 1]]), np.zeros(3))
    data, _ = process_data_like_dataset(tmp_path / "data", world, 1.0)
    config = run_on(tmp_path / "outputs", data)
    moved = tmp_path / "moved"
    data.rename(moved)
    with pytest.raises(runs.RunLoadError, match="cannot read the run's dataset"):
        runs.read_dataparser_transform(config)
    assert runs.read_dataparser_transform(config, data_override=moved).shape == (4, 4)
    with pytest.raises(runs.RunLoadError, match="is missing"):
        runs.training_cameras(config)
    assert len(runs.training_cameras(config, data_override=moved)) >= 2


def test_optimized_poses_match_nerfstudios_camera_optimizer():
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
    from nerfstudio.cameras.cameras import Cameras

    n = 4
    optimizer = CameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=n, device="cpu")
    with torch.no_grad():
        optimizer.pose_adjustment.copy_(torch.randn(n, 6, generator=torch.Generator().manual_seed(0)) * 0.05)
    model = torch.nn.Module()
    model.camera_optimizer = optimizer
    c2w = runs.make_cameras(np.tile(np.eye(4)[:3], (n, 1, 1)) + 0.1, Intrinsics(10, 10, 5, 5, 10, 10)).camera_to_worlds
    ours = runs.optimized_poses(model, c2w)
    for i in range(n):
        cam = Cameras(camera_to_worlds=c2w[i : i + 1], fx=10.0, fy=10.0, cx=5.0, cy=5.0, metadata={"cam_idx": i})
        torch.testing.assert_close(ours[i : i + 1], optimizer.apply_to_camera(cam), atol=1e-6, rtol=0)
    assert not torch.allclose(ours, c2w)
    optimizer.config.mode = "off"
    assert torch.equal(runs.optimized_poses(model, c2w), c2w)


def test_default_device_follows_torch(monkeypatch):
    from nerfuser_ns.scripts.register import RegisterCommand
    from nerfuser_ns.scripts.view import ViewCommand

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert runs.default_device() == "cpu" and RegisterCommand().device == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert runs.default_device() == "cuda"
    assert RegisterCommand().device == "cuda" and ViewCommand(path=Path("x")).device == "cuda"


def test_relative_dataset_path_resolves_from_another_working_directory(tmp_path, monkeypatch):
    """ns-train stores --data as given (relative to where it ran), beside a relative output_dir: recovered from
    any working directory."""
    from nerfuser_ns import sampling

    world = sampling.look_at(np.array([[3.0, 0, 1], [0, 3.0, 1], [-3.0, 0, 1]]), np.zeros(3))
    work = tmp_path / "work"
    process_data_like_dataset(work / "data" / "part_a", world, 1.0)
    config_path = run_on(work / "outputs", work / "data" / "part_a")
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    config.output_dir, config.pipeline.datamanager.data = Path("outputs"), Path("data/part_a")
    config_path.write_text(yaml.dump(config))
    monkeypatch.chdir(tmp_path)  # not where it was trained
    assert runs.read_config(config_path).pipeline.datamanager.data == work / "data" / "part_a"
    assert runs.read_dataparser_transform(config_path).shape == (4, 4)
    assert len(runs.training_cameras(config_path)) == 3


def test_devices_that_do_not_exist_are_one_line(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert runs.check_device("cpu") == torch.device("cpu")
    with pytest.raises(runs.RunLoadError, match=r"--device 'banana' is not a torch device; this machine has: cpu$"):
        runs.check_device("banana")
    with pytest.raises(runs.RunLoadError, match=r"--device 'cuda' is not on this machine; it has: cpu$"):
        runs.check_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert runs.check_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(runs.RunLoadError, match="it has: cpu, cuda:0, cuda:1"):
        runs.check_device("cuda:2")


@pytest.mark.parametrize(
    "payload",
    [
        "!!python/object/apply:os.system ['touch {marker}']",
        "!!python/object/apply:subprocess.check_call [['touch', '{marker}']]",
        "!!python/object/apply:nerfstudio.utils.scripts.run_command ['touch {marker}']",  # a function, not a class
        "!!python/object/new:subprocess.Popen [['touch', '{marker}']]",
        "!!python/name:os.system",
        "!!python/module:os",
    ],
)
def test_a_config_that_would_run_code_is_refused(tmp_path, payload):
    marker = tmp_path / "ran"
    run_dir = tmp_path / "outputs" / "x" / "nerfacto" / "run"
    run_dir.mkdir(parents=True)
    (run_dir / "config.yml").write_text(f"method_name: nerfacto\nexploit: {payload.format(marker=marker)}\n")
    with pytest.raises(runs.UnsafeConfigError, match=r"config.yml: refusing !!python/") as info:
        runs.read_config(run_dir / "config.yml")
    assert f"refusing {payload.split()[0]}" in str(info.value)  # the tag as written
    assert not marker.exists()  # nothing ran


def test_every_kind_of_real_config_still_loads(tmp_path):
    from nerfstudio.configs.method_configs import method_configs
    from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config
    from nerfuser_ns.method_configs.nerfuser import nerfuser_config

    configs = {"nerfacto": method_configs["nerfacto"], "instant-ngp": method_configs["instant-ngp"],
               "nerfacto-cpu": nerfacto_cpu_config(), "nerfuser": nerfuser_config()}  # fmt: skip
    for name, config in configs.items():
        run_dir = tmp_path / "outputs" / name / name / "run"
        run_dir.mkdir(parents=True)
        config.experiment_name, config.timestamp = name, "run"
        (run_dir / "config.yml").write_text(yaml.dump(config))
        loaded = runs.read_config(run_dir / "config.yml")
        assert type(loaded) is type(config) and loaded.method_name == config.method_name
        assert type(loaded.pipeline.model) is type(config.pipeline.model)
        # stock nerfacto trains with its camera optimiser on; our CPU preset with it off; some models have none
        expected_mode = {"nerfacto": "SO3xR3", "instant-ngp": None, "nerfacto-cpu": "off", "nerfuser": None}[name]
        assert runs.camera_optimizer_mode(loaded) == expected_mode


def test_run_names_are_the_folders_that_tell_runs_apart():
    a, b = "/home/me/out/part_a/nerfacto/2026-11-27_101500/config.yml", "/home/me/out/part_b/nerfacto/2026-11-27_101500"
    assert runs.run_names([a, b]) == ["part_a/nerfacto/2026-11-27_101500", "part_b/nerfacto/2026-11-27_101500"]
    # the same experiment/method/timestamp under two output folders: one folder more
    c = "/data/copy/part_a/nerfacto/2026-11-27_101500/config.yml"
    assert runs.run_names([a, c]) == ["out/part_a/nerfacto/2026-11-27_101500", "copy/part_a/nerfacto/2026-11-27_101500"]
    assert runs.run_names(["a/config.yml", "b/config.yml"]) == ["a", "b"]
    assert runs.run_names([a, a]) == [a, a]  # never distinct: the paths as given
    assert runs.run_names([]) == []
