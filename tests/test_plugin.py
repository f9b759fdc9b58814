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
