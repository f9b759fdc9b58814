"""Programmatic training and the per-capture run cache of generated scenes."""

from __future__ import annotations

import json

import pytest

from nerfuser_ns.bench import scenes, training

pytestmark = pytest.mark.slow


def test_train_captures_keeps_up_to_date_runs_and_retrains_on_new_inputs(tmp_path):
    layout = scenes.generate_scene(tmp_path / "scene", "object-centric", supersample=1, seed=3, num_views=12,
                                   num_test_views=1, width=32, height=24)  # fmt: skip
    gt = tmp_path / "scene" / "ground_truth.json"
    stamp = gt.stat().st_mtime_ns
    scenes.generate_scene(tmp_path / "scene", "object-centric", supersample=1, seed=3, num_views=12,
                          num_test_views=1, width=32, height=24)  # fmt: skip
    assert gt.stat().st_mtime_ns == stamp  # the same scene is not written again

    runs_dir, name = tmp_path / "runs", layout.captures[0].name
    lines: list[str] = []
    report = training.train_captures(tmp_path / "scene", runs_dir, [name], max_num_iterations=3, tiny=True,
                                     log=lines.append)  # fmt: skip
    entry = report["runs"][name]
    ckpt = next((runs_dir / name / "nerfacto-cpu" / "demo" / "nerfstudio_models").glob("step-*.ckpt"))
    assert entry["steps"] == 2 and len(entry["input_key"]) == 16 and entry["num_eval_images"] == 1
    assert json.loads((runs_dir / "train_report.json").read_text())["runs"][name] == entry
    first = ckpt.stat().st_mtime_ns

    training.train_captures(tmp_path / "scene", runs_dir, [name], max_num_iterations=3, tiny=True, log=lines.append)
    assert ckpt.stat().st_mtime_ns == first and "up to date" in lines[-1]

    # other inputs (here the step count) give another key: the run is trained again
    report = training.train_captures(tmp_path / "scene", runs_dir, [name], max_num_iterations=4, tiny=True,
                                     log=lines.append)  # fmt: skip
    assert report["runs"][name]["steps"] == 3 and report["runs"][name]["input_key"] != entry["input_key"]
    assert "optimizers" not in __import__("torch").load(
        next((runs_dir / name / "nerfacto-cpu" / "demo" / "nerfstudio_models").glob("step-*.ckpt")),
        weights_only=False,
    )  # slimmed for shipping
