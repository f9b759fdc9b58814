"""Train a tiny nerfacto offline on CPU, then load it back from config.yml and render it from arbitrary poses."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from nerfuser_ns import runs, runtime, scenes
from nerfuser_ns.training import train


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    layout = scenes.make_layout("object-centric", seed=3, num_views=12, num_test_views=2, width=40, height=30)
    out = tmp_path_factory.mktemp("scene") / "scene"
    scenes.write_scene(layout, out, supersample=1)
    return out


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
    cams = runs.make_cameras(c2w[None], fx=20, fy=20, cx=10, cy=8, width=20, height=16)
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
    assert loaded.data_to_nerf is not None and loaded.data_to_nerf.shape == (4, 4)
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
        runs.make_cameras(np.zeros((2, 2, 4)), 10, 10, 5, 5, 10, 10)
    with pytest.raises(ValueError, match="positive"):
        runs.make_cameras(np.zeros((1, 3, 4)), 10, 10, 5, 5, 0, 10)


def test_runtime_installed_by_loading():
    runs.load_run  # noqa: B018 - importing runs is enough
    runtime.install()
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    assert LearnedPerceptualImagePatchSimilarity is runtime.LazyLPIPS
