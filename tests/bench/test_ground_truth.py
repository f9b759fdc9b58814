"""Ground truth and scoring of the benchmark kit (:mod:`nerfuser_ns.bench.ground_truth`): a hand-written
registration scored against 3x4 and 4x4 truth, ground_truth.json captures checked, and 3x4 / 4x4 transform files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench.ground_truth import ScoreCommand, load_ground_truth_captures, read_gt_transforms


def test_scoring_a_hand_written_registration_with_mixed_3x4_and_4x4_truth(tmp_path):
    """The minimal registration a user writes (no "reference": the identity entry is it) against a 3x4 and a 4x4
    ground-truth file: both shapes are SIM(3)s, and the scores are right."""
    W_b = sim3.make_sim3(sim3.so3_exp(np.array([0.0, 0.0, 0.4])), np.array([1.0, 2.0, 3.0]), 1.5)
    W_a = sim3.make_sim3(np.eye(3), np.array([0.0, 1.0, 0.0]), 2.0)
    nerfs = [{"name": "b", "config": "b/config.yml", "T_to_reference": (np.linalg.inv(W_a) @ W_b).tolist()},
             {"name": "a", "config": "a/config.yml", "T_to_reference": np.eye(4).tolist()}]  # fmt: skip
    path = tmp_path / "hand.json"
    path.write_text(json.dumps({"kind": "nerfuser_registration", "nerfs": nerfs}))
    gt = [tmp_path / "b.json", tmp_path / "a.json"]
    gt[0].write_text(json.dumps({"nerf_to_world": W_b[:3].tolist()}))  # 3x4
    gt[1].write_text(json.dumps(W_a.tolist()))  # 4x4, bare
    console = Console(record=True, width=200)
    scored = ScoreCommand(path, gt_transforms=gt).main(console)
    assert "in the frame of a" in console.export_text()
    g = scored["nerfs"][0]["ground_truth"]
    assert g["r_err_deg"] < 1e-6 and g["t_err"] < 1e-9 and g["s_err"] < 1e-9 and not scored["ground_truth"]["failure"]


def test_ground_truth_inputs_are_checked(tmp_path):
    gt = tmp_path / "ground_truth.json"
    gt.write_text(json.dumps({"captures": [{"name": "capture_a", "capture_to_world": np.eye(4).tolist()}]}))
    assert np.allclose(load_ground_truth_captures(gt, ["capture_a"])[0], np.eye(4))
    with pytest.raises(reg.RegistrationError, match="no capture named 'capture_z'"):
        load_ground_truth_captures(gt, ["capture_z"])
    with pytest.raises(reg.RegistrationError, match="not a readable ground_truth.json"):
        load_ground_truth_captures(tmp_path / "nope.json", ["capture_a"])


def test_mixed_3x4_and_4x4_ground_truth_transforms(tmp_path):
    T = sim3.make_sim3(np.eye(3), np.array([1.0, 2.0, 3.0]), 2.0)
    (tmp_path / "a.json").write_text(json.dumps(T[:3].tolist()))
    (tmp_path / "b.json").write_text(json.dumps({"nerf_to_world": T.tolist()}))
    gt = read_gt_transforms([tmp_path / "a.json", tmp_path / "b.json"])
    assert [g.shape for g in gt] == [(4, 4), (4, 4)]
    np.testing.assert_array_equal(gt[0], gt[1])
    sheared = T.copy()
    sheared[0, 1] = 0.5
    (tmp_path / "b.json").write_text(json.dumps(sheared.tolist()))
    with pytest.raises(reg.RegistrationError, match="b.json: nerf_to_world: the 3x3 block is not a scaled rotation"):
        read_gt_transforms([tmp_path / "a.json", tmp_path / "b.json"])
