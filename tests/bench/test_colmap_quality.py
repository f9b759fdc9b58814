"""COLMAP's own pose error per capture (scripts/colmap_quality.py,
:func:`nerfuser_ns.bench.practitioner_cases.colmap_tie`), read from a case folder without a trained run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import (
    SOURCE_FRAMES_NAME,
    case_layout,
    colmap_misposed,
    colmap_tie,
    reposed_transforms,
    source_frames,
    training_transforms,
)
from nerfuser_ns.capture_check import LARGER_SIDE_NAME, check_dataset, write_larger_side


@pytest.fixture(scope="module")
def quality(load_script):
    return load_script("colmap_quality")


def _write_dataset(case_dir, capture, poses, order, fl_y=50.0):
    """transforms.json as ns-process-data names the frames (frame_00001.png ... in the inputs' sorted order), its
    camera with a horizontal focal length of 50 px."""
    frames = [{"file_path": f"images/frame_{i + 1:05d}.png", "transform_matrix": poses[n].tolist()}
              for n, i in enumerate(order)]  # fmt: skip
    folder = case_dir / "datasets" / capture
    folder.mkdir(parents=True)
    camera = {"fl_x": 50.0, "fl_y": fl_y, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48}
    (folder / "transforms.json").write_text(json.dumps({**camera, "frames": frames}))


def test_exact_and_bent_reconstructions(quality, tmp_path):
    layout = case_layout("street:3", width=64, height=48)
    rng = np.random.default_rng(0)
    exact_cap, bent_cap = layout.captures[:2]
    order = rng.permutation(exact_cap.num_views)[:50]  # COLMAP posed 50 views, in its own order
    _write_dataset(tmp_path, exact_cap.name, sim3.transform_poses(sim3.random_sim3(rng), exact_cap.c2w_world[order]),
                   order)  # fmt: skip
    true = bent_cap.c2w_world.copy()  # the capture's second half turned by 4 deg about its middle camera
    middle = true[len(true) // 2, :3, 3]
    turn = sim3.compose(sim3.make_sim3(np.eye(3), middle), sim3.make_sim3(sim3.so3_exp(np.radians([0, 0, 4.0]))),
                        sim3.make_sim3(np.eye(3), -middle))  # fmt: skip
    true[len(true) // 2 :] = sim3.transform_poses(turn, true[len(true) // 2 :])
    _write_dataset(tmp_path, bent_cap.name, true, np.arange(len(true)), fl_y=55.0)  # its camera drifted too
    rows = quality.measure("street:3", tmp_path, 64, 48)
    exact, bent = rows
    assert (exact["posed"], exact["views"]) == (50, exact_cap.num_views) and exact["size"] == "64x48"
    assert exact["rot_err_deg"] < 1e-6 and exact["centre_err"] < 1e-6 and exact["bend_deg"] < 1e-6
    assert exact["pose_tie_rot_err_deg"] < 1e-6
    assert (exact["focal_ratio"], exact["camera_drifted"]) == (1.0, False) and bent["camera_drifted"]
    assert bent["bend_deg"] == pytest.approx(4.0, abs=0.3) and bent["rot_err_deg"] > 0.5
    assert bent["pose_tie_rot_err_deg"] > 0.5  # no tie of the views' rotations undoes a bend either
    assert exact["misposed"] == 0 and bent["misposed"] == 0  # a 4 deg bend splits the error, no view is 5 deg off
    out = tmp_path / "report" / "quality.md"
    out.parent.mkdir()
    quality.write_report(rows, out, "python scripts/colmap_quality.py ...")
    assert "| street:3 | 64x48 | exhaustive | perspective | capture_0 | 50/" in out.read_text()  # no colmap_camera.txt
    (tmp_path / "colmap_camera.txt").write_text("simple_pinhole\n")
    assert all(r["camera_type"] == "simple_pinhole" for r in quality.measure("street:3", tmp_path, 64, 48))
    assert "| 1.100 drifted |" in out.read_text()
    assert json.loads(out.with_suffix(".json").read_text()) == rows


def test_views_posed_by_the_wrong_copy_are_counted(quality, tmp_path):
    """A room capture whose views 0-19 COLMAP posed by the half-turn twin of the room (turned about its vertical axis):
    the misposed count finds exactly those views, the other capture none."""
    layout = case_layout("room:3", width=64, height=48)
    cap = layout.captures[0]
    poses = cap.c2w_world.copy()
    half_turn = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 0.0, 180.0])))
    poses[:20] = sim3.transform_poses(half_turn, poses[:20])
    _write_dataset(tmp_path, cap.name, poses, np.arange(len(poses)))
    _write_dataset(tmp_path, layout.captures[1].name, layout.captures[1].c2w_world, np.arange(64))
    folded, clean = quality.measure("room:3", tmp_path, 64, 48)
    assert folded["misposed"] == 20 and clean["misposed"] == 0
    assert folded["check"] == 20 and folded["check_misposed"] == 20 and clean["check"] == 0  # the check, no truth
    assert folded["rot_err_deg"] < 90  # what the centres' tie shows of it


def test_a_run_trained_on_the_larger_side_is_tied_by_the_views_it_trained_on(tmp_path):
    """After ``ns-nerfuser-check-capture --write-larger-side``: COLMAP's record still counts the whole capture (20
    misposed of 64 posed), the ties use the 44 views the run trained on (no misposed view left to bend them)."""
    layout = case_layout("room:3", width=64, height=48)
    cap = layout.captures[0]
    poses = cap.c2w_world.copy()
    centre = poses[:, :3, 3].mean(0)
    R = sim3.so3_exp(np.radians([0.0, 0.0, 180.0]))
    poses[20:40] = sim3.transform_poses(sim3.make_sim3(R, centre - R @ centre), poses[20:40])
    _write_dataset(tmp_path, cap.name, poses, np.arange(64))
    folded = colmap_tie(cap, tmp_path)[0]
    data = tmp_path / "datasets" / cap.name
    write_larger_side(data, check_dataset(data).suspect, data / LARGER_SIDE_NAME)
    assert training_transforms(tmp_path, cap.name) == data / LARGER_SIDE_NAME
    record = colmap_tie(cap, tmp_path)[0]
    assert record["posed_by_colmap"] == 64 and record["pose_tie_misposed_views"] == 20 and record["trained_views"] == 44
    assert record["colmap_centre_err_median"] < 1e-6 < folded["colmap_centre_err_median"]  # the centres' tie was bent
    misposed = colmap_misposed(cap, tmp_path)  # per view, over the whole capture
    assert [f for f, wrong in misposed.items() if wrong] == [f"images/frame_{i + 1:05d}.png" for i in range(20, 40)]


def test_a_capture_posed_again_without_its_misposed_view_is_tied_through_the_first_datasets_names(tmp_path):
    """After ``--write-images-to-repose`` and ``ns-process-data`` on the other 63 images: the re-posed dataset's frames
    are numbered afresh (frame_00011.png is the first dataset's frame_00012.png); through ``source_frames.json`` the
    run's views are tied to their true poses exactly, the first dataset's record still counts its misposed view."""
    layout = case_layout("street:3", width=64, height=48)
    cap = layout.captures[0]
    poses = cap.c2w_world.copy()
    poses[10] = sim3.transform_poses(sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 30.0, 0.0]))), poses[10:11])[0]
    _write_dataset(tmp_path, cap.name, poses, np.arange(cap.num_views))
    kept = [i for i in range(cap.num_views) if i != 10]
    rng = np.random.default_rng(1)
    reposed = reposed_transforms(tmp_path, cap.name)
    _write_dataset(tmp_path, reposed.parent.name, sim3.transform_poses(sim3.random_sim3(rng), cap.c2w_world[kept]),
                   np.arange(len(kept)))  # fmt: skip
    assert training_transforms(tmp_path, cap.name) == reposed
    shifted = colmap_tie(cap, tmp_path)[0]  # without the names, every view after the dropped one is tied one off
    # the images posed again: the first dataset's, frame_00011.png left out (and a file nerfstudio does not list)
    images = tmp_path / "datasets" / cap.name / "images_to_repose"
    images.mkdir()
    for i in kept:
        (images / f"frame_{i + 1:05d}.png").write_bytes(b"")
    (images / "notes.txt").write_text("")
    names = source_frames(images)
    assert len(names) == len(kept) and names["frame_00010.png"] == "frame_00010.png"
    assert names["frame_00011.png"] == "frame_00012.png" and names["frame_00063.png"] == "frame_00064.png"
    (reposed.parent / SOURCE_FRAMES_NAME).write_text(json.dumps(names))
    record = colmap_tie(cap, tmp_path)[0]
    assert (record["posed_by_colmap"], record["pose_tie_misposed_views"]) == (cap.num_views, 1)
    assert (record["reposed_posed_by_colmap"], record["reposed_misposed_views"], record["trained_views"]) == (
        len(kept), 0, len(kept))
    assert record["colmap_rot_err_deg_median"] < 1e-6 and record["colmap_centre_err_median"] < 1e-6
    assert record["colmap_bend_deg"] < 1e-6 < shifted["colmap_centre_err_median"]


def test_bad_cases_say_what_is_expected(quality, tmp_path):
    with pytest.raises(ValueError, match="LAYOUT:SEED=CASE_DIR@WIDTHxHEIGHT"):
        quality.parse_case("drive:6=outputs/practitioner/drive-6")
    assert quality.parse_case("drive:6=a/b@640x480") == ("drive:6", Path("a/b"), 640, 480)
    with pytest.raises(SystemExit, match="no datasets/"):
        quality.measure("drive:6", tmp_path, 64, 48)
