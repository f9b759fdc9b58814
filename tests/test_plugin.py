"""The plugin is discoverable by nerfstudio's own registry and commands."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest


def test_methods_registered_through_entry_points():
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    assert "nerfuser" in all_methods and "nerfacto-cpu" in all_methods
    assert "NeRFuser" in all_descriptions["nerfuser"]
    cpu = all_methods["nerfacto-cpu"]
    assert cpu.machine.device_type == "cpu"
    assert cpu.pipeline.model.implementation == "torch"


def _bin(name: str) -> str:
    path = Path(sys.executable).parent / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed next to {sys.executable}; install the package (pip install -e .)")
    return found


def test_ns_train_help_lists_methods():
    env = {**os.environ, "NERFUSER_CPU_FAST_PATH": "0"}
    out = subprocess.run([_bin("ns-train"), "--help"], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "nerfuser" in out.stdout and "nerfacto-cpu" in out.stdout


def test_register_command_installed():
    out = subprocess.run([_bin("ns-nerfuser-register"), "--help"], capture_output=True, text=True, timeout=300)
    assert "ns-nerfuser-register" in (out.stdout + out.stderr)


def test_stock_ns_train_and_ns_eval_work_offline(tmp_path):
    """With the plugin installed, stock ns-train trains and ns-eval loads (torch >= 2.6) with no network."""
    import json

    from nerfuser_ns.bench import scenes

    layout = scenes.make_layout("object-centric", seed=5, num_views=10, num_test_views=1, width=32, height=24)
    scenes.write_scene(layout, tmp_path / "scene", supersample=1)
    # any download attempt fails at once, even on a machine that has internet
    env = {
        **os.environ,
        "NERFUSER_CPU_FAST_PATH": "0",
        "HTTP_PROXY": "http://127.0.0.1:9",
        "HTTPS_PROXY": "http://127.0.0.1:9",
        "http_proxy": "http://127.0.0.1:9",
        "https_proxy": "http://127.0.0.1:9",
    }
    train_cmd = [
        _bin("ns-train"),
        "nerfacto-cpu",
        "--data",
        str(tmp_path / "scene" / "capture_a"),
        "--output-dir",
        str(tmp_path / "out"),
        "--experiment-name",
        "cli",
        "--timestamp",
        "t",
        "--max-num-iterations",
        "3",
        "--pipeline.datamanager.train-num-rays-per-batch",
        "128",
        "--pipeline.model.num-levels",
        "2",
        "--pipeline.model.log2-hashmap-size",
        "10",
        "--pipeline.model.num-nerf-samples-per-ray",
        "8",
        "--pipeline.model.num-proposal-samples-per-ray",
        "8",
        "8",
        "--pipeline.model.eval-num-rays-per-chunk",
        "512",
    ]
    out = subprocess.run(train_cmd, capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    config = tmp_path / "out" / "cli" / "nerfacto-cpu" / "t" / "config.yml"
    assert config.is_file()
    assert list((config.parent / "nerfstudio_models").glob("step-*.ckpt"))
    eval_cmd = [_bin("ns-eval"), "--load-config", str(config), "--output-path", str(tmp_path / "eval.json")]
    out = subprocess.run(eval_cmd, capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    results = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert results["psnr"] > 5
