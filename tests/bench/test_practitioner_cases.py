"""The practitioner benchmark's case folders (:mod:`nerfuser_ns.bench.practitioner_cases`): which ``ns-eval`` JSON
holds which appearance-matching setting."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from colmap_helpers import NUM_VIEWS, write_colmap_capture

import nerfuser_ns
from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import (
    appearance_evals,
    captures_from,
    captures_ready,
    case_layout,
    colmap_bend_deg,
    fused_appearance_matching,
    fused_config,
    library_commit,
    radial_transforms,
    reference_links,
    register_command,
    registration_with_transforms,
    rejected_registration,
    reposed_transforms,
    share_captures,
    tie_to_world,
    training_transforms,
)
from nerfuser_ns.registration.record import KIND, iter_registered_nerfs


def _fused(case, label, text):
    config = fused_config(case, label)
    config.parent.mkdir(parents=True)
    config.write_text(text)


def test_the_eval_of_each_appearance_setting(tmp_path):
    case = tmp_path / "street-9"
    assert fused_appearance_matching(case) is None and appearance_evals(case) == {}  # before the fuse stage
    _fused(case, None, "pipeline:\n  model:\n    appearance_matching: true\n    gamma: 5\n")
    assert fused_appearance_matching(case) is True
    assert appearance_evals(case) == {}  # fused, not yet scored
    (case / "eval.json").write_text("{}")
    (case / "eval_unmatched.json").write_text("{}")
    assert appearance_evals(case) == {True: case / "eval.json", False: case / "eval_unmatched.json"}
    (case / "eval_matched.json").write_text("{}")  # a forced setting's eval wins over the default's
    assert appearance_evals(case)[True] == case / "eval_matched.json"


def test_runs_fused_before_the_option_had_it_off(tmp_path):
    _fused(tmp_path / "old", None, "pipeline:\n  model:\n    gamma: 5\n")
    assert fused_appearance_matching(tmp_path / "old") is False
    _fused(tmp_path / "off", None, "pipeline:\n  model:\n    appearance_matching: false\n")
    (tmp_path / "off" / "eval.json").write_text("{}")
    assert appearance_evals(tmp_path / "off") == {False: tmp_path / "off" / "eval.json"}


def test_case_layouts_as_the_benchmark_renders_them():
    drive = case_layout("drive:4", num_captures=3)
    assert len(drive.captures) == 3 and all(c.num_views == 96 for c in drive.captures)
    assert len(case_layout("street:4", num_captures=3).captures) == 3
    oc = case_layout("object-centric:4", width=64, height=48)
    assert len(oc.captures) == 2 and all(c.num_views == 64 for c in oc.captures)


def test_the_register_command_names_every_capture_run_and_only_the_given_options(tmp_path):
    street = case_layout("street:4", num_captures=3)
    cmd = register_command(street, tmp_path, tmp_path / "r.json", "--no-model-check")
    assert Path(cmd[0]).name == "ns-nerfuser-register" and Path(cmd[0]).parent == Path(sys.executable).parent
    configs = cmd[cmd.index("--configs") + 1 : cmd.index("--output")]
    assert configs == [str(tmp_path / "runs" / c.name / "nerfacto" / "bench" / "config.yml") for c in street.captures]
    assert cmd[cmd.index("--output") + 1 :] == [str(tmp_path / "r.json"), "--no-model-check"]


def test_tie_to_world_recovers_a_capture_frame_and_measures_its_noise():
    rng = np.random.default_rng(0)
    true = sim3.make_sim3(sim3.random_rotation(rng, (20,)), rng.normal(size=(20, 3)) * 3.0)
    world_to_stored = sim3.random_sim3(rng)  # what COLMAP's own frame and scale make of the world
    stored = sim3.transform_poses(world_to_stored, true)
    T, rot_err, centre_err = tie_to_world(stored, true, world_scale=3.0)
    np.testing.assert_allclose(T, sim3.invert_sim3(world_to_stored), atol=1e-9)
    assert rot_err < 1e-6 and centre_err < 1e-9
    noisy = stored.copy()
    noisy[:, :3, 3] += rng.normal(size=(20, 3)) * 0.05 * sim3.decompose_sim3(world_to_stored)[2]  # 5 cm in the world
    _, _, centre_err = tie_to_world(noisy, true, world_scale=1.0)
    assert 0.02 < centre_err < 0.12  # reported in world units: about the noise put in


def test_colmap_bend_is_zero_for_a_rigid_reconstruction_and_sees_a_bent_one():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 10, 40)
    path = np.stack([t, np.sin(t), 0.3 * np.cos(2 * t)], -1)  # not a line: centres alone fix the frame
    true = sim3.make_sim3(np.broadcast_to(np.eye(3), (40, 3, 3)), path)
    idx = rng.permutation(40)  # COLMAP's frame order is not the capture's
    stored = sim3.transform_poses(sim3.random_sim3(rng), true[idx])
    assert colmap_bend_deg(stored, true[idx], idx, 5.0) < 1e-6
    bent = true.copy()  # the second half of the path turned by 3 deg about the half-way point
    turn = sim3.make_sim3(sim3.so3_exp(np.array([0.0, 0.0, np.radians(3.0)])))
    half = sim3.compose(sim3.make_sim3(np.eye(3), true[20, :3, 3]), turn,
                        sim3.make_sim3(np.eye(3), -true[20, :3, 3]))  # fmt: skip
    bent[20:] = sim3.transform_poses(half, true[20:])
    assert colmap_bend_deg(bent[idx], true[idx], idx, 5.0) == pytest.approx(3.0, abs=0.05)


def test_the_pose_tie_fixes_the_roll_of_a_near_collinear_capture():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 10, 48)
    path = np.stack([t, 0.1 * np.sin(t), 0.02 * np.cos(3 * t)], -1)  # a drive: centres near a line
    true = sim3.make_sim3(sim3.random_rotation(rng, (48,)), path)
    world_to_stored = sim3.random_sim3(rng)
    stored = sim3.transform_poses(world_to_stored, true)
    s = sim3.decompose_sim3(world_to_stored)[2]
    stored[:, :3, 3] += rng.normal(size=(48, 3)) * 0.03 * s  # COLMAP's centre noise, 3 cm in the world
    want = sim3.invert_sim3(world_to_stored)
    centres = tie_to_world(stored, true, 3.0)
    poses = tie_to_world(stored, true, 3.0, rotations=True)
    assert sim3.sim3_errors(centres[0], want).r_err_deg > 0.3  # the roll about the line follows the noise
    assert sim3.sim3_errors(poses[0], want).r_err_deg < 1e-6  # exact rotations fix it
    assert centres[1] > 0.3 and poses[1] < 1e-6  # and the residuals say which tie held


def test_reference_links_put_the_truths_in_the_registrations_reference_frame():
    rng = np.random.default_rng(5)
    to_world = sim3.random_sim3(rng, size=(3,))  # each NeRF frame -> the world
    gt = [{"nerf_to_world": T, "nerf_to_world_pose": T} for T in to_world]
    registered = sim3.to_reference_frame(to_world, 1)
    reg = {"reference": {"index": 1}, "nerfs": [{"T_to_reference": T.tolist()} for T in registered]}
    links = reference_links(reg, gt)
    assert set(links) == {"registered", "stored truth", "pose truth"}
    assert np.allclose(links["registered"], registered) and np.allclose(links["pose truth"], registered)
    assert np.allclose(links["stored truth"][1], np.eye(4))  # the reference NeRF maps to itself
    p = rng.normal(size=3)  # a point of NeRF 0 lands where the world puts it, seen from the reference
    want = sim3.transform_points(sim3.invert_sim3(to_world[1]), sim3.transform_points(to_world[0], p))
    assert np.allclose(sim3.transform_points(links["stored truth"][0], p), want)


def _captured(case, captures, times=None):
    for c in captures:
        (case / "images" / c).mkdir(parents=True)
        (case / "images" / c / "view_00000.png").write_bytes(b"png")
        (case / "images" / c / ".done").write_text("")
        (case / "datasets" / c).mkdir(parents=True)
        (case / "datasets" / c / "transforms.json").write_text('{"frames": []}')
        (case / f"colmap_{c}.log").write_text("colmap")
    (case / "test").mkdir()
    (case / "test" / "transforms.json").write_text("{}")
    (case / "times.json").write_text(json.dumps(times or {}))


def test_share_captures_copies_a_complete_sibling_once(tmp_path):
    caps = ["capture_0", "capture_1"]
    half, full, case = tmp_path / "street-5-half", tmp_path / "street-5-camopt-off", tmp_path / "street-5"
    _captured(full, caps, {"images capture_0": 80.0, "colmap capture_0": 120.0, "train capture_0": 450.0})
    _captured(half, caps)
    (half / "datasets" / "capture_1" / "transforms.json").unlink()  # COLMAP not done there: not a source
    assert not captures_ready(half, caps) and captures_ready(full, caps)
    case.mkdir()
    (case / "times.json").write_text(json.dumps({"register": 5.0}))
    assert share_captures(case, caps, [case, half, full]) == full
    assert captures_ready(case, caps) and captures_from(case) == "street-5-camopt-off"
    assert (case / "colmap_capture_1.log").read_text() == "colmap"
    # the shared stages' times come along, the training's do not, the case's own are kept
    assert json.loads((case / "times.json").read_text()) == {
        "images capture_0": 80.0, "colmap capture_0": 120.0, "register": 5.0}
    assert not list(case.glob(".*.partial"))
    # a case that has inputs of its own is never overwritten
    (case / "datasets" / "capture_0" / "transforms.json").write_text("mine")
    assert share_captures(case, caps, [full]) is None
    assert (case / "datasets" / "capture_0" / "transforms.json").read_text() == "mine"


def test_a_case_posed_by_another_matching_shares_the_images_alone(load_script, tmp_path):
    """``--matching-method sequential`` poses the same images again: images and test views are copied, COLMAP's
    datasets, logs and times are not; ``--check-captures`` trains the same datasets otherwise (all shared)."""
    bench = load_script("bench_practitioner")
    cfg = bench.BenchPractitioner(cases=["room:6"], root=tmp_path)
    seq = bench.replace(cfg, matching_method="sequential")
    checked = bench.replace(cfg, check_captures=True)
    assert [bench.case_folder("room:6", c) for c in (cfg, seq, checked)] == [
        "room-6", "room-6-sequential", "room-6-checked"]
    assert "room-6" in bench.training_siblings("room:6", checked)
    assert "room-6" in bench.image_siblings("room:6", seq) and "room-6" not in bench.training_siblings("room:6", seq)
    assert bench.case_options(seq) == ["--matching-method", "sequential"]
    one_focal = bench.replace(cfg, camera_type="simple_pinhole")  # ns-process-data --camera-type: posed again too
    assert bench.case_folder("room:6", one_focal) == "room-6-simple-pinhole"
    assert "room-6" in bench.image_siblings("room:6", one_focal)
    assert "room-6" not in bench.training_siblings("room:6", one_focal)
    assert bench.case_options(one_focal) == ["--camera-type", "simple_pinhole"]
    three = bench.replace(cfg, num_captures=3)  # other images: never a sibling of the two-capture case
    assert [bench.case_folder(c, three) for c in ("street:19", "drive:21", "room:6")] == [
        "street-19-3captures", "drive-21-3captures", "room-6"]
    assert "street-19" not in bench.image_siblings("street:19", three) + bench.training_siblings("street:19", three)
    assert bench.case_options(three) == ["--num-captures", "3"]
    caps = ["capture_a", "capture_b"]
    _captured(tmp_path / "room-6", caps, {"images capture_a": 80.0, "colmap capture_a": 120.0})
    case = tmp_path / "room-6-sequential"
    assert share_captures(case, caps, [tmp_path / "room-6"], parts=("images", "test")) == tmp_path / "room-6"
    assert (case / "images").is_dir() and (case / "test").is_dir() and not (case / "datasets").exists()
    assert not list(case.glob("colmap_*.log"))
    assert json.loads((case / "times.json").read_text()) == {"images capture_a": 80.0}


def test_share_captures_without_a_complete_sibling_does_nothing(tmp_path):
    case = tmp_path / "room-3"
    case.mkdir()
    assert share_captures(case, ["capture_a"], [tmp_path / "room-3-camopt-off"]) is None
    assert sorted(p.name for p in case.iterdir()) == [] and captures_from(case) is None


def test_registration_with_transforms_replaces_the_transforms_alone(tmp_path):
    """The ``truth`` stage's registration: each NeRF's transform replaced (both keys, as the fusion reads either),
    every other field kept, written beside the source so that relative run paths still resolve."""
    rng = np.random.default_rng(0)
    T_est, T_true = sim3.random_sim3(rng, size=(2,))
    nerfs = [{"name": "a", "config": "runs/a/config.yml", "T_to_reference": np.eye(4).tolist(),
              "transform": np.eye(4).tolist(), "colour_to_reference": None},
             {"name": "b", "config": "runs/b/config.yml", "T_to_reference": T_est.tolist(), "transform": T_est.tolist(),
              "colour_to_reference": [[0.9, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.1, 0]]}]  # fmt: skip
    source = tmp_path / "registration.json"
    source.write_text(json.dumps({"kind": KIND, "reference": {"index": 0}, "nerfs": nerfs, "pairs": [{"ncc": 0.9}]}))
    before = source.read_text()

    out = registration_with_transforms(source, [np.eye(4), T_true], "registration_truth.json")

    assert out == tmp_path / "registration_truth.json" and source.read_text() == before
    written = json.loads(out.read_text())
    for key in ("T_to_reference", "transform"):
        np.testing.assert_allclose(written["nerfs"][1][key], T_true)
        np.testing.assert_allclose(written["nerfs"][0][key], np.eye(4))
    assert written["nerfs"][1]["colour_to_reference"] == nerfs[1]["colour_to_reference"]
    assert written["pairs"] == [{"ncc": 0.9}] and written["reference"] == {"index": 0}
    read = list(iter_registered_nerfs(out))
    assert [n.name for n in read] == ["a", "b"]
    with pytest.raises(ValueError, match="2 NeRFs, 1 transforms"):
        registration_with_transforms(source, [T_true], "registration_bad.json")
    assert not (tmp_path / "registration_bad.json").exists()


def test_a_refused_registration_is_timed_and_keeps_this_runs_refused_solution(load_script, tmp_path, monkeypatch):
    bench = load_script("bench_practitioner")
    layout = case_layout("object-centric:1")
    work = tmp_path / "registration_work"
    work.mkdir()
    stale = work / "rejected_registration.json"
    stale.write_text('{"from": "an earlier run"}')
    os.utime(stale, (0, 0))

    def refused(cmd, log, cwd=None, solution=True):
        time.sleep(0.2)  # the attempt's own time, which the stage must record
        if solution:
            (work / "rejected_registration.json").write_text('{"from": "this run"}')
        raise RuntimeError("ns-nerfuser-register failed (exit 1)\nerror: self-check failed")

    monkeypatch.setattr(bench, "_run", refused)
    bench.stage_register(layout, tmp_path)
    assert json.loads((tmp_path / "times.json").read_text())["register"] >= 0.2
    assert json.loads(rejected_registration(tmp_path).read_text()) == {"from": "this run"}
    assert "self-check failed" in (tmp_path / "register_failed.txt").read_text()
    # a refusal that wrote no solution (e.g. too few views) leaves the earlier run's file where it is
    rejected_registration(tmp_path).unlink()
    os.utime(work / "rejected_registration.json", (0, 0))
    monkeypatch.setattr(bench, "_run", lambda cmd, log, cwd=None: refused(cmd, log, solution=False))
    bench.stage_register(layout, tmp_path)
    assert not rejected_registration(tmp_path).exists()


def test_each_refused_attempt_is_scored_against_the_truth(load_script):
    bench = load_script("bench_practitioner")
    rng = np.random.default_rng(3)
    A, B = (sim3.make_sim3(sim3.so3_exp(rng.normal(size=3)), rng.normal(size=3), 1.5) for _ in range(2))
    gt = [{"capture": "a", "nerf_to_world": A}, {"capture": "b", "nerf_to_world": B}]
    truth = sim3.compose(sim3.invert_sim3(A), B)  # b's frame -> a's (the reference)
    turn = sim3.make_sim3(sim3.so3_exp(np.deg2rad([0.0, 2.0, 0.0])), np.zeros(3), 1.0)
    choice = {"tried_before": [
        {"source": "training", "mode": "sfm", "error": "camera check", "refused_transforms": [np.eye(4).tolist(),
                                                                                             (turn @ truth).tolist()]},
        {"source": "both", "mode": "sfm", "error": "too few views"},
    ]}  # fmt: skip
    refused, failed = bench._attempts(choice, 0, gt)
    assert "refused_transforms" not in refused and refused["error"] == "camera check"
    (e,) = refused["errors"]
    assert e["nerf"] == "b" and e["r_err_deg"] == pytest.approx(2.0) and not e["failure"]
    assert failed["errors"] is None and bench._attempts(None, 0, gt) == []


def test_the_capture_check_line_says_which_check_found_the_fold(load_script):
    bench = load_script("bench_practitioner")
    order = {"checked": True, "folded": True, "suspect_views": 20, "num_views": 64}  # a record of before the matches
    assert bench._capture_check_cell(order) == (
        "folded by file order, 20 of 64 views suspect, trained on the larger side")
    unordered = {"checked": False, "folded": False, "suspect_views": 0, "num_views": 64}
    side = {"found_by": "matches", "dropped": [f"images/frame_{i:05d}.png" for i in range(24)]}
    assert bench._capture_check_cell({**unordered, "larger_side": side}) == (
        "folded (by the matches), 24 of 64 views dropped, trained on the larger side")
    folded = {"checked": True, "folded": True}
    assert bench._capture_check_cell({**unordered, "matches": folded, "larger_side": None}).endswith(
        "folded by the match check, no sides to train on: trained on every view")
    assert bench._capture_check_cell({**unordered, "matches": folded, "larger_side": None}, stopped=True).endswith(
        "folded by the match check, no sides to train on: the guide's path stops here")
    consistent = {"checked": True, "folded": False}
    assert bench._capture_check_cell({**unordered, "matches": consistent}) == (
        "not checked by file order (no sequence); the match check found it consistent")


def _posing_again(posed: list, seconds: float):
    """A stand-in for the benchmark's ``_process_data``: records each call in ``posed`` and writes a consistent
    COLMAP capture where ``ns-process-data`` would."""

    def process_data(images, out, matching_method, camera_type, log):
        posed.append((images, out, matching_method, camera_type))
        write_colmap_capture(out.parent, folded=False)
        return seconds

    return process_data


def test_the_guides_check_poses_a_capture_again_without_the_view_it_names(load_script, tmp_path, monkeypatch):
    """``--check-captures``: the real ``ns-nerfuser-check-capture`` names capture_1's one misposed view and copies the
    other images; ``ns-process-data`` (a stand-in here: a consistent reconstruction) poses them into
    ``capture_1_reposed``, whose frame names map to the first dataset's; capture_0, consistent, is left alone."""
    bench = load_script("bench_practitioner")
    layout = case_layout("street:1")
    for cap, twins in zip(layout.captures, ((), (5,)), strict=True):
        data = write_colmap_capture(tmp_path / "datasets" / cap.name, folded=bool(twins), twins=twins)
        (data / "images").mkdir()
        for i in range(NUM_VIEWS):
            (data / "images" / f"frame_{i + 1:05d}.png").write_bytes(bytes([i]))
    posed = []
    monkeypatch.setattr(bench, "_process_data", _posing_again(posed, seconds=1.5))
    bench.stage_check(layout, tmp_path, "sequential", "simple_pinhole")
    images = tmp_path / "datasets" / "capture_1" / "images_to_repose"
    reposed = reposed_transforms(tmp_path, "capture_1")
    assert posed == [(images, reposed, "sequential", "simple_pinhole")]
    assert sorted(p.name for p in images.iterdir()) == [f"frame_{i + 1:05d}.png" for i in range(NUM_VIEWS) if i != 5]
    names = json.loads((reposed.parent / "source_frames.json").read_text())
    assert names["frame_00005.png"] == "frame_00005.png" and names["frame_00006.png"] == "frame_00007.png"
    checks = json.loads((tmp_path / "capture_check.json").read_text())
    assert checks["capture_1"]["matches"]["repose_without"] == ["frame_00006.png"]
    assert checks["capture_1"]["reposed"]["matches"]["folded"] is False and "reposed" not in checks["capture_0"]
    assert json.loads((tmp_path / "times.json").read_text()) == {"colmap capture_1 reposed": 1.5}
    assert training_transforms(tmp_path, "capture_1") == reposed
    assert training_transforms(tmp_path, "capture_0") == tmp_path / "datasets" / "capture_0" / "transforms.json"
    assert "posed again without those views, then consistent" in bench._capture_check_cell(checks["capture_1"])
    # done once: a second call changes nothing
    bench.stage_check(layout, tmp_path)
    assert len(posed) == 1


def test_the_guides_check_poses_a_drifted_capture_again_with_one_focal_length(load_script, tmp_path, monkeypatch):
    """``--check-captures``: a capture whose COLMAP camera drifted (fy/fx 1.2) is posed again from all its images with
    ``--camera-type simple_pinhole``, as the check advises, and trained on that; its views keep their numbers (no
    source map: nothing was left out). A capture already posed with one focal length is not posed again."""
    bench = load_script("bench_practitioner")
    layout = case_layout("street:1")
    for cap, aspect in zip(layout.captures, (1.2, 1.0), strict=True):
        data = write_colmap_capture(tmp_path / "datasets" / cap.name, folded=False)
        meta = json.loads((data / "transforms.json").read_text())
        (data / "transforms.json").write_text(json.dumps({**meta, "fl_y": meta["fl_x"] * aspect}))
        done = bench.images_done(tmp_path, cap.name)
        done.parent.mkdir(parents=True)
        for i in range(NUM_VIEWS):
            (done.parent / f"view_{i:05d}.png").write_bytes(bytes([i]))
        done.write_text("")
    posed = []
    monkeypatch.setattr(bench, "_process_data", _posing_again(posed, seconds=2.0))
    bench.stage_check(layout, tmp_path, "exhaustive", "perspective")
    reposed = reposed_transforms(tmp_path, "capture_0")
    assert posed == [(tmp_path / "images" / "capture_0", reposed, "exhaustive", "simple_pinhole")]
    assert not (reposed.parent / "source_frames.json").exists()
    checks = json.loads((tmp_path / "capture_check.json").read_text())
    assert checks["capture_0"]["camera"]["drifted"] and not checks["capture_1"]["camera"]["drifted"]
    again = checks["capture_0"]["reposed"]
    assert again["camera_type"] == "simple_pinhole" and again["for_drift"] and not again["without_views"]
    assert not again["camera"]["drifted"]
    assert training_transforms(tmp_path, "capture_0") == reposed and "reposed" not in checks["capture_1"]
    cell = bench._capture_check_cell(checks["capture_0"])
    assert "camera drifted (fy/fx 1.200): posed again with one focal length (--camera-type simple_pinhole), then "\
        "consistent by the match check" in cell
    assert "camera fy/fx 1.000" in bench._capture_check_cell(checks["capture_1"])
    # a case posed with one focal length from the start: its drifted-looking file is not posed again
    other = tmp_path / "one_focal"
    shutil.copytree(tmp_path / "datasets", other / "datasets", ignore=shutil.ignore_patterns("capture_0_reposed"))
    bench.stage_check(layout, other, "exhaustive", "simple_pinhole")
    assert len(posed) == 1


def test_the_guides_check_poses_a_capture_folded_with_one_focal_length_by_the_simple_radial_recipe(
    load_script, tmp_path, monkeypatch
):
    """``--check-captures`` follows the check's one-focal-length advice (drive-25): a drifted capture posed again with
    one focal length comes out folded with no side to train on, so it is posed once more by the guide's SIMPLE_RADIAL
    recipe from the same images, checked again and trained on; the case is not stopped. A capture folded with two
    focal lengths gets no such posing, and stays stuck."""
    bench = load_script("bench_practitioner")
    layout = case_layout("street:1")
    for cap, aspect in zip(layout.captures, (1.2, 1.002), strict=True):  # capture_1: two focal lengths, no drift
        data = write_colmap_capture(tmp_path / "datasets" / cap.name, folded=cap.name == "capture_1")
        meta = json.loads((data / "transforms.json").read_text())
        (data / "transforms.json").write_text(json.dumps({**meta, "fl_y": meta["fl_x"] * aspect}))
        done = bench.images_done(tmp_path, cap.name)
        done.parent.mkdir(parents=True)
        done.write_text("")

    def folded_again(images, out, matching_method, camera_type, log):
        write_colmap_capture(out.parent, folded=True)  # one focal length (fl_x = fl_y), folded, no side
        return 3.0

    radial = []

    def radial_recipe(images, out, matching_method, log):
        radial.append((images, out, matching_method))
        write_colmap_capture(out.parent, folded=False)
        return 4.0

    monkeypatch.setattr(bench, "_process_data", folded_again)
    monkeypatch.setattr(bench, "_process_data_radial", radial_recipe)
    bench.stage_check(layout, tmp_path, "sequential", "perspective")
    assert radial == [(tmp_path / "images" / "capture_0", radial_transforms(tmp_path, "capture_0"), "sequential")]
    checks = json.loads((tmp_path / "capture_check.json").read_text())
    assert checks["capture_0"]["reposed"]["matches"]["folded"] and checks["capture_0"]["reposed"]["larger_side"] is None
    assert not checks["capture_0"]["radial"]["matches"]["folded"] and "radial" not in checks["capture_1"]
    assert training_transforms(tmp_path, "capture_0") == radial_transforms(tmp_path, "capture_0")
    assert json.loads((tmp_path / "times.json").read_text())["colmap capture_0 radial"] == 4.0
    assert bench.unremedied_captures(tmp_path) == ["capture_1"]  # folded, not drifted, two focal lengths
    assert "posed once more by the SIMPLE_RADIAL recipe, then consistent by the match check" in \
        bench._capture_check_cell(checks["capture_0"])
    side = {"dropped": ["frame_00004.png", "frame_00009.png"]}
    folded_radial = {**checks["capture_0"]["radial"], "larger_side": side}
    assert "SIMPLE_RADIAL recipe, then consistent by the match check (0 of 57 pairs unexplained), 2 views dropped, " \
        "trained on the larger side" in bench._capture_check_cell({**checks["capture_0"], "radial": folded_radial})
    # done once, also when the case is checked again
    bench.stage_check(layout, tmp_path, "sequential", "perspective")
    assert len(radial) == 1


def test_the_benchmark_poses_a_capture_with_ns_process_data_on_cpu_sift(load_script, tmp_path, monkeypatch):
    """The benchmark's posing: ``ns-process-data images`` with CPU SIFT, the case's matcher, no downscaled copies,
    and ``--camera-type`` only where it is not the default; an error when nothing was posed."""
    bench = load_script("bench_practitioner")
    calls = []

    def run(cmd, log, cwd=None):
        calls.append(cmd)
        (Path(cmd[cmd.index("--output-dir") + 1]) / "transforms.json").write_text("{}")
        return 2.0

    monkeypatch.setattr(bench, "_run", run)
    out = tmp_path / "capture_0" / "transforms.json"
    out.parent.mkdir()
    assert bench._process_data(tmp_path / "images", out, "sequential", "perspective", tmp_path / "c.log") == 2.0
    assert bench._process_data(tmp_path / "images", out, "exhaustive", "simple_pinhole", tmp_path / "c.log") == 2.0
    first, second = calls
    assert Path(first[0]).name == "ns-process-data" and first[first.index("--data") + 1] == str(tmp_path / "images")
    assert "--no-gpu" in first and first[first.index("--num-downscales") + 1] == "0"
    assert first[first.index("--matching-method") + 1] == "sequential" and "--camera-type" not in first
    assert second[second.index("--camera-type") + 1] == "simple_pinhole"
    monkeypatch.setattr(bench, "_run", lambda cmd, log, cwd=None: 1.0)
    with pytest.raises(RuntimeError, match="COLMAP posed nothing"):
        bench._process_data(tmp_path / "images", tmp_path / "other" / "transforms.json", "exhaustive", "perspective",
                            tmp_path / "c.log")  # fmt: skip


def test_the_simple_radial_recipe_runs_the_guides_commands(load_script, tmp_path, monkeypatch):
    """The benchmark's SIMPLE_RADIAL posing is the guide's recipe: COLMAP's feature extractor with one SIMPLE_RADIAL
    camera, the case's matcher and the mapper on CPU SIFT, then ``ns-process-data --skip-colmap`` into the same folder;
    each step logged on its own, and an error when nothing was posed."""
    bench = load_script("bench_practitioner")
    calls = []

    def run(cmd, log, cwd=None):
        calls.append((cmd, log.name))
        if cmd[1] == "images":  # ns-process-data writes the dataset
            (Path(cmd[cmd.index("--output-dir") + 1]) / "transforms.json").write_text("{}")
        return 1.0

    monkeypatch.setattr(bench, "_run", run)
    out = tmp_path / "capture_0_radial" / "transforms.json"
    assert bench._process_data_radial(tmp_path / "images", out, "sequential", tmp_path / "colmap_radial.log") == 4.0
    tools = [" ".join(cmd[:2]) if cmd[0] == "colmap" else Path(cmd[0]).name for cmd, _ in calls]
    assert tools == ["colmap feature_extractor", "colmap sequential_matcher", "colmap mapper", "ns-process-data"]
    features, matcher, mapper, process = (cmd for cmd, _ in calls)
    assert features[features.index("--ImageReader.camera_model") + 1] == "SIMPLE_RADIAL"
    assert features[features.index("--ImageReader.single_camera") + 1] == "1"
    assert features[features.index("--SiftExtraction.use_gpu") + 1] == "0"
    assert matcher[-2:] == ["--SiftMatching.use_gpu", "0"]
    assert mapper[mapper.index("--output_path") + 1] == str(out.parent / "colmap" / "sparse")
    assert "--skip-colmap" in process and process[process.index("--output-dir") + 1] == str(out.parent)
    assert len({log for _, log in calls}) == 4
    monkeypatch.setattr(bench, "_run", lambda cmd, log, cwd=None: 1.0)  # COLMAP posed nothing: no dataset
    with pytest.raises(RuntimeError, match="COLMAP posed nothing"):
        bench._process_data_radial(tmp_path / "images", tmp_path / "other" / "transforms.json", "exhaustive",
                                   tmp_path / "colmap_other.log")  # fmt: skip


def test_a_checked_case_stops_at_a_fold_the_check_cannot_mend(load_script, tmp_path):
    """--check-captures trains a folded capture's larger side, or its re-posed dataset; a capture folded with neither
    stops the case before training (street-20's capture_0: 5.1% of its pairs unexplained, no side, no views to drop)."""
    bench = load_script("bench_practitioner")

    def found(folded=False, matches_folded=False, larger_side=None):
        return {"folded": folded, "matches": {"folded": matches_folded}, "larger_side": larger_side}

    checks = {
        "consistent": found(),
        "folded_with_side": found(folded=True, larger_side=[0, 1, 2]),
        "matches_folded": found(matches_folded=True),
        "reposed_clean": {**found(matches_folded=True), "reposed": found()},
        "reposed_still_folded": {**found(), "reposed": found(folded=True)},
        "radial_clean": {**found(), "reposed": found(folded=True), "radial": found()},
        "radial_still_folded": {**found(matches_folded=True), "radial": found(matches_folded=True)},
    }
    (tmp_path / "capture_check.json").write_text(json.dumps(checks))
    assert bench.unremedied_captures(tmp_path) == ["matches_folded", "reposed_still_folded", "radial_still_folded"]


def test_a_case_stopped_at_the_check_is_reported_and_tallied_as_a_failure(load_script, tmp_path):
    """A case the check stops before training is still a case of the guide's path: its record says so, with what
    COLMAP made of each capture, the report shows it, and the tally counts it as a failed link."""
    bench, tally = load_script("bench_practitioner"), load_script("tally_practitioner")
    layout = case_layout("street:1")
    for cap, folded in zip(layout.captures, (False, True), strict=True):
        data = write_colmap_capture(tmp_path / "datasets" / cap.name, folded=folded)
        transforms = data / "transforms.json"
        meta = json.loads(transforms.read_text())
        for i, frame in enumerate(meta["frames"]):  # posed at the truth: the tie itself is not under test
            frame["transform_matrix"] = cap.c2w_world[i].tolist()
        transforms.write_text(json.dumps(meta))
    (tmp_path / "check_commit.txt").write_text("abc1234\n")
    record = bench.stopped_record(layout, tmp_path, "street:1", ["capture_1"])
    assert record["registration"]["errors"] is None and "capture_1 folded" in record["registration"]["stopped"]
    assert record["registered_at_commit"] == "abc1234"
    assert [c["match_check_folded"] for c in record["captures"]] == [False, True]
    report = tmp_path / "report.md"
    bench.write_report([record], report, bench.BenchPractitioner(cases=["street:1"], root=tmp_path))
    text = report.read_text()
    assert f"| {tmp_path.name} | - | stopped before training | | | FAIL |" in text
    assert "nothing registered (ns-nerfuser-check-capture found capture_1 folded" in text
    assert "success rate 0.00" in text
    tallied = tmp_path / "tally.md"
    tally.write_tally(tally.collect([report.with_suffix(".json")]), tallied)
    assert f"| {tmp_path.name} | stopped before training | | | FAIL |" in tallied.read_text()


def test_library_commit_names_the_checkout_the_library_came_from_whatever_the_current_folder(tmp_path, monkeypatch):
    root = Path(nerfuser_ns.__file__).resolve().parent.parent
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    monkeypatch.chdir(tmp_path)  # not a checkout: the cwd's HEAD would be none (or another checkout's)
    got = library_commit()
    if head.returncode != 0:  # an installed copy outside git
        assert got == "unknown"
    else:
        assert got.removesuffix("-dirty") == head.stdout.strip()
