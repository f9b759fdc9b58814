"""The fold check of a capture's poses (nerfuser_ns.capture_check), its CLI ns-nerfuser-check-capture, and the
registration's warning: a room capture filmed in sequence, with a block of views posed by the room's half-turn twin."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console
from scipy.spatial.transform import Rotation

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import case_layout
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.capture_check import (
    LARGER_SIDE_NAME,
    MAX_ASPECT_DEVIATION,
    check_dataset,
    check_dataset_intrinsics,
    fold_check,
    intrinsics_check,
    neighbour_turns,
    process_data_command,
    simple_radial_recipe,
    write_larger_side,
)
from nerfuser_ns.registration.pipeline import check_captures
from nerfuser_ns.scripts import check_capture as cli

FOLDED = range(20, 40)
"""Views posed by the twin in the folded capture."""


@pytest.fixture(scope="module")
def room_poses() -> np.ndarray:
    """A room capture's true poses, filmed in sequence (64 views)."""
    return case_layout("room:3", width=64, height=48).captures[0].c2w_world.copy()


def _fold(poses: np.ndarray) -> np.ndarray:
    """The poses with :data:`FOLDED` moved by a half turn about the vertical through the capture's mean centre."""
    centre = poses[:, :3, 3].mean(0)
    R = sim3.so3_exp(np.radians([0.0, 0.0, 180.0]))
    half_turn = sim3.make_sim3(R, centre - R @ centre)
    out = poses.copy()
    out[list(FOLDED)] = sim3.transform_poses(half_turn, poses[list(FOLDED)])
    return out


def _names(n: int) -> list[str]:
    return [f"images/frame_{i + 1:05d}.png" for i in range(n)]


SQUARE = {"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48}
"""ns-process-data's camera keys, square pixels."""


def _write_dataset(folder: Path, poses: np.ndarray, names: list[str], camera: dict = SQUARE) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    meta = {"camera_model": "OPENCV", "ply_file_path": "sparse_pc.ply", **camera,
            "frames": [{"file_path": n, "transform_matrix": p.tolist()} for n, p in zip(names, poses, strict=True)]}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_neighbour_turns_are_the_rotation_angles(room_poses):
    turns = neighbour_turns(room_poses)
    R = room_poses[:, :3, :3]
    ref = [np.degrees(Rotation.from_matrix(a.T @ b).magnitude()) for a, b in zip(R[:-1], R[1:], strict=True)]
    np.testing.assert_allclose(turns, ref, atol=1e-6)


def test_a_clean_sequence_is_checked_and_not_folded(room_poses):
    check = fold_check(room_poses, _names(64))
    assert check.checked and not check.folded and check.suspect == () and check.warning("x") is None
    assert check.median_turn_deg < 30


def test_the_folded_block_is_found_exactly_in_any_frame(room_poses):
    """Jumps out of and back into the block; the suspect views are exactly the block, whatever SIM(3) the capture's
    frame is in and whatever order the frames are stored in."""
    folded = _fold(room_poses)
    frame = sim3.make_sim3(sim3.so3_exp(np.array([0.3, -1.1, 0.7])), np.array([2.0, -1.0, 0.5]), 3.7)
    moved = sim3.transform_poses(frame, folded)
    names = _names(64)
    order = np.random.default_rng(0).permutation(64)
    check = fold_check(moved[order], [names[i] for i in order])
    assert check.folded and len(check.jumps) == 2
    assert set(check.suspect) == {names[i] for i in FOLDED}
    assert check.jumps[0][:2] == (names[19], names[20]) and check.jumps[0][2] > 120
    assert "20 of 64 views" in check.warning("capture_a")


def test_a_capture_not_filmed_in_file_order_is_not_checked(room_poses):
    """Poses shuffled against their names: the file order is no sequence, so nothing is claimed."""
    shuffled = _fold(room_poses)[np.random.default_rng(1).permutation(64)]
    check = fold_check(shuffled, _names(64))
    assert not check.checked and not check.folded and check.median_turn_deg > 30


@pytest.fixture(scope="module")
def rig_poses() -> np.ndarray:
    """A drive capture's true poses: an 8-camera roof rig, 12 exposures, stored exposure by exposure (96 views)."""
    return case_layout("drive:3", width=64, height=48).captures[0].c2w_world.copy()


def _half_turn(poses: np.ndarray, block: np.ndarray) -> np.ndarray:
    centre = poses[:, :3, 3].mean(0)
    R = sim3.so3_exp(np.radians([0.0, 0.0, 180.0]))
    out = poses.copy()
    out[block] = sim3.transform_poses(sim3.make_sim3(R, centre - R @ centre), poses[block])
    return out


def test_an_interleaved_rig_is_checked_camera_by_camera(rig_poses):
    """In file order the rig's cameras turn 45 deg apart (no sequence at lag 1); each camera's views are one."""
    assert np.median(neighbour_turns(rig_poses)) > 30
    check = fold_check(rig_poses, _names(96))
    assert check.checked and check.rig_cameras == 8 and not check.folded


def test_names_ending_in_timestamps_are_read_in_file_order(rig_poses):
    """Millisecond timestamps are no frame index (one would span 10^12 frames): the views are taken in file order."""
    names = [f"images/{1_700_000_000_000 + 33 * i}.png" for i in range(96)]
    check = fold_check(_half_turn(rig_poses, np.arange(30, 54)), names)
    assert check.checked and check.rig_cameras == 8
    assert set(check.suspect) == set(names[30:54])


def test_a_long_rig_video_is_checked_on_a_subsampled_mounting():
    """600 exposures of a 2-camera rig (90 deg apart), more than MEDOID_SAMPLES: the block is still found exactly."""
    mount = sim3.so3_exp(np.radians([0.0, 0.0, 90.0]))
    poses = np.tile(np.eye(4), (1200, 1, 1))
    for e in range(600):
        front = sim3.so3_exp(np.radians([0.0, 0.0, float(e)]))
        poses[2 * e, :3, :3], poses[2 * e + 1, :3, :3] = front, front @ mount
        poses[2 * e : 2 * e + 2, :3, 3] = [0.01 * e, 0.0, 0.0]
    names = _names(1200)
    check = fold_check(_half_turn(poses, np.arange(401, 701)), names)
    assert check.checked and check.rig_cameras == 2
    assert set(check.suspect) == set(names[401:701])


def test_cli_names_the_rig_it_checked(rig_poses, tmp_path, capsys):
    assert cli.run(cli.CheckCaptureCommand([_write_dataset(tmp_path / "rig", rig_poses, _names(96))])) == 0
    assert "not folded (96 views, each of 8 rig cameras" in capsys.readouterr().out


@pytest.mark.parametrize("start", [1, 21, 70])
def test_a_folded_block_of_a_rig_is_found_exactly(rig_poses, start):
    """A block of 24 views cut anywhere (mid-exposure too): one side for the whole rig, the block exactly."""
    block = np.arange(start, start + 24)
    names = _names(96)
    check = fold_check(_half_turn(rig_poses, block), names)
    assert check.folded and check.rig_cameras == 8
    assert set(check.suspect) == {names[i] for i in block}
    assert "each of 8 rig cameras" in check.warning("capture_0")


def test_a_rig_with_missing_views_keeps_one_side(rig_poses):
    """nerfstudio's split leaves out views; the block is still found exactly among those kept."""
    keep = np.setdiff1d(np.arange(96), np.arange(5, 96, 10))
    block = np.arange(40, 64)
    names = _names(96)
    check = fold_check(_half_turn(rig_poses, block)[keep], [names[i] for i in keep])
    assert check.folded and set(check.suspect) == {names[i] for i in np.intersect1d(block, keep)}


@pytest.mark.parametrize("seed", [101, 105])
def test_unordered_views_are_not_taken_for_a_rig(seed):
    """Views of a street in no filmed order show a small median turn at some lag by chance (a rule on the median alone
    took these captures for 10-camera rigs, and false alarms followed), but the turns do not repeat as a rig's do."""
    for cap in case_layout(f"street:{seed}", width=64, height=48).captures:
        check = fold_check(cap.c2w_world, _names(len(cap.c2w_world)))
        assert not check.checked and not check.folded


def test_larger_side_is_written_beside_and_never_over_the_dataset(room_poses, tmp_path):
    data = _write_dataset(tmp_path / "data", _fold(room_poses), _names(64))
    original = (data / "transforms.json").read_text()
    check = check_dataset(data)
    with pytest.raises(ValueError, match="own transforms.json"):
        write_larger_side(data, check.suspect, data / "transforms.json")
    out = write_larger_side(data, check.suspect, data / LARGER_SIDE_NAME)
    assert (data / "transforms.json").read_text() == original
    meta = json.loads(out.read_text())
    assert len(meta["frames"]) == 44 and "ply_file_path" not in meta
    assert not check_dataset(out).folded  # the larger side alone is a consistent sequence
    elsewhere = write_larger_side(data, check.suspect, tmp_path / "other" / "larger.json")
    assert Path(json.loads(elsewhere.read_text())["frames"][0]["file_path"]) == (data / "images/frame_00001.png")


def test_cli_reports_each_capture_and_exits_1_on_a_fold(room_poses, tmp_path, capsys):
    folded = _write_dataset(tmp_path / "east", _fold(room_poses), _names(64))
    clean = _write_dataset(tmp_path / "west", room_poses, _names(64))
    assert cli.run(cli.CheckCaptureCommand([clean])) == 0
    assert "not folded" in capsys.readouterr().out
    assert cli.run(cli.CheckCaptureCommand([clean, folded], write_larger_side=True)) == 1
    out = capsys.readouterr().out
    assert "looks folded" in out and "20 of 64 views" in out and "ns-train nerfacto --data" in out
    assert "  camera fy/fx 1.000 (square pixels)" in out  # the folded capture's camera verdict too
    drifted_fold = _write_dataset(tmp_path / "north", _fold(room_poses), _names(64), {**SQUARE, "fl_y": 60.0})
    assert cli.run(cli.CheckCaptureCommand([drifted_fold])) == 1
    out = capsys.readouterr().out
    assert "looks folded" in out and "camera looks drifted" in out and "  its camera drifted (fy/fx 1.200" in out
    assert (folded / LARGER_SIDE_NAME).is_file() and not (clean / LARGER_SIDE_NAME).exists()


def test_cli_bad_input_is_one_line_and_writes_nothing(room_poses, tmp_path, capsys):
    folded = _write_dataset(tmp_path / "east", _fold(room_poses), _names(64))
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "transforms.json").write_text("{not json")
    for bad, fragment in ((tmp_path / "missing", "no transforms.json"), (tmp_path / "broken", "not a nerfstudio")):
        assert cli.run(cli.CheckCaptureCommand([folded, bad], write_larger_side=True)) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and fragment in err and str(bad) in err
    assert not (folded / LARGER_SIDE_NAME).exists()  # every input is read before anything is written
    assert cli.run(cli.CheckCaptureCommand([])) == 1  # nothing to check is not "nothing folded"
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no dataset" in err


class _TrainedRun:
    def __init__(self, name: str, poses: np.ndarray):
        self.name, self._poses = name, poses

    def training_poses(self) -> np.ndarray:
        return self._poses

    def training_image_files(self) -> list[Path]:
        return [Path("/data") / n for n in _names(len(self._poses))]


def test_registration_warns_about_a_run_trained_on_a_folded_capture(room_poses):
    console = Console(record=True, width=400)
    checks = check_captures([_TrainedRun("east", _fold(room_poses)), _TrainedRun("west", room_poses)], console)
    text = console.export_text()
    assert "NeRF east" in text and "looks folded" in text and "NeRF west" not in text
    assert checks["east"]["folded"] and checks["east"]["suspect_views"] == 20 and not checks["west"]["folded"]


class _RunWithDataset(_TrainedRun):
    def __init__(self, name: str, poses: np.ndarray, dataset: Path):
        super().__init__(name, poses)
        self._dataset = dataset

    def dataset_path(self) -> Path:
        return self._dataset


def test_registration_checks_the_file_the_run_was_given_as_the_cli_does(room_poses, tmp_path):
    """The dataset's frames in file order decide, not the training cameras (nerfstudio's held-out frames leave gaps
    in them); runs without a readable dataset file fall back to their training cameras."""
    console = Console(record=True, width=400)
    folded = _write_dataset(tmp_path / "folded", _fold(room_poses), _names(64))
    clean = _write_dataset(tmp_path / "clean", room_poses, _names(64))
    runs = [_RunWithDataset("a", room_poses, folded), _RunWithDataset("b", _fold(room_poses), clean),
            _RunWithDataset("c", _fold(room_poses), tmp_path / "gone")]  # fmt: skip
    checks = check_captures(runs, console)
    assert checks["a"]["folded"] and checks["a"]["suspect_views"] == 20
    assert not checks["b"]["folded"]
    assert checks["c"]["folded"]  # no dataset file: the training cameras
    text = console.export_text()
    assert "NeRF a" in text and "NeRF b" not in text and "NeRF c" in text


# ---------------------------------------------------------------------------------------------------------------------
# The camera check: COLMAP's vertical focal length drifted from the horizontal one


def test_square_pixels_pass_and_a_drifted_focal_ratio_is_reported():
    square = intrinsics_check(Intrinsics(250.0, 251.0, 160.0, 120.0, 320, 240))
    assert not square.drifted and square.warning("data/a") is None and square.aspect == pytest.approx(1.004)
    drifted = intrinsics_check(Intrinsics(250.5, 352.9, 160.2, 102.9, 320, 240))  # COLMAP on a drive capture
    warning = drifted.warning("data/b")
    assert drifted.drifted and warning.startswith("data/b: ") and "1.409" in warning and "102.9" in warning
    edge = 1 + MAX_ASPECT_DEVIATION
    assert not intrinsics_check(Intrinsics(100.0, 100.0 * edge - 1e-6, 50, 50, 100, 100)).drifted
    assert intrinsics_check(Intrinsics(100.0, 100.0 / (edge + 1e-3), 50, 50, 100, 100)).drifted  # either way
    assert drifted.to_record()["drifted"] and drifted.to_record()["aspect"] == pytest.approx(352.9 / 250.5, abs=1e-4)
    # one focal length means a model with one (fy = fx exactly), not square pixels measured by a model with two
    assert intrinsics_check(Intrinsics(251.2, 251.2, 160.0, 120.0, 320, 240)).one_focal_length
    assert not square.one_focal_length
    assert not intrinsics_check(Intrinsics(250.0, 250.0 + 1e-9, 0, 0, 1, 1)).one_focal_length
    with pytest.raises(ValueError, match="must be positive"):
        intrinsics_check(Intrinsics(0.0, 1.0, 0, 0, 1, 1))


def test_the_process_data_command_names_only_what_differs_from_its_defaults():
    """ns-process-data's command as the check prints it and the benchmark runs it: the stock call carries no option
    but the folders; each asked-for option appears once, with its value."""
    images, out = Path("data/east/images"), Path("data/east_reposed")
    assert process_data_command(images, out) == ["ns-process-data", "images", "--data", str(images), "--output-dir",
                                                 str(out)]  # fmt: skip
    cmd = process_data_command(images, out, "simple_pinhole", "sequential", use_gpu=False, ns_process_data="/v/ns",
                               num_downscales=0, skip_colmap=True)  # fmt: skip
    assert cmd[0] == "/v/ns" and cmd[cmd.index("--camera-type") + 1] == "simple_pinhole"
    assert cmd[cmd.index("--matching-method") + 1] == "sequential" and cmd[cmd.index("--num-downscales") + 1] == "0"
    assert "--no-gpu" in cmd and "--skip-colmap" in cmd and len(cmd) == 14


def test_the_simple_radial_recipe_poses_every_image_with_one_distorted_camera():
    """The check's SIMPLE_RADIAL posing: one SIMPLE_RADIAL camera shared by every image, matcher and mapper into the new
    dataset's colmap folder, then ns-process-data writing the dataset from that model; CPU SIFT only when asked."""
    images, out = Path("data/east/images"), Path("data/east_radial")
    steps = simple_radial_recipe(images, out)
    assert list(steps) == ["features", "matches", "mapper", "process_data"]
    features, matcher, mapper, process = steps.values()
    assert features[:2] == ["colmap", "feature_extractor"] and matcher[:2] == ["colmap", "exhaustive_matcher"]
    assert features[features.index("--ImageReader.camera_model") + 1] == "SIMPLE_RADIAL"
    assert features[features.index("--ImageReader.single_camera") + 1] == "1"
    assert features[features.index("--image_path") + 1] == mapper[mapper.index("--image_path") + 1] == str(images)
    database = str(out / "colmap" / "database.db")
    assert {cmd[cmd.index("--database_path") + 1] for cmd in (features, matcher, mapper)} == {database}
    assert mapper[mapper.index("--output_path") + 1] == str(out / "colmap" / "sparse")
    assert process[:2] == ["ns-process-data", "images"] and "--skip-colmap" in process
    assert process[process.index("--output-dir") + 1] == str(out) and "--num-downscales" not in process
    assert not any("use_gpu" in arg for cmd in steps.values() for arg in cmd)  # COLMAP's default: its GPU
    cpu = simple_radial_recipe(images, out, "sequential", use_gpu=False, ns_process_data="/venv/bin/ns-process-data",
                               num_downscales=0)  # fmt: skip
    assert cpu["features"][-2:] == ["--SiftExtraction.use_gpu", "0"] and cpu["matches"][1] == "sequential_matcher"
    assert cpu["matches"][-2:] == ["--SiftMatching.use_gpu", "0"]
    assert cpu["process_data"][0] == "/venv/bin/ns-process-data"
    assert cpu["process_data"][cpu["process_data"].index("--num-downscales") + 1] == "0"


def test_dataset_camera_per_frame_overrides_the_file(room_poses, tmp_path):
    folder = _write_dataset(tmp_path / "d", room_poses[:5], _names(5), {**SQUARE, "fl_y": 60.0})
    meta = json.loads((folder / "transforms.json").read_text())
    for f in meta["frames"][:3]:  # three of five frames carry their own (square) camera: the median is theirs
        f.update(fl_x=40.0, fl_y=40.0)
    (folder / "transforms.json").write_text(json.dumps(meta))
    check = check_dataset_intrinsics(folder)
    assert (check.intrinsics.fx, check.intrinsics.fy, check.intrinsics.width) == (40.0, 40.0, 64) and not check.drifted
    stretched = _write_dataset(tmp_path / "e", room_poses[:5], _names(5), {**SQUARE, "fl_y": 60.0})
    assert check_dataset_intrinsics(stretched).drifted
    missing = _write_dataset(tmp_path / "f", room_poses[:5], _names(5), {"fl_x": 50.0})
    with pytest.raises(ValueError, match="no camera intrinsics") as e:
        check_dataset_intrinsics(missing)
    assert str(missing / "transforms.json") in str(e.value) and len(str(e.value).splitlines()) == 1


def test_cli_reports_a_drifted_camera_with_what_to_run(room_poses, tmp_path, capsys):
    clean = _write_dataset(tmp_path / "west", room_poses, _names(64))
    drifted = _write_dataset(tmp_path / "east", room_poses, _names(64), {**SQUARE, "fl_y": 60.0, "cy": 20.0})
    assert cli.run(cli.CheckCaptureCommand([clean])) == 0
    capsys.readouterr()
    assert cli.run(cli.CheckCaptureCommand([clean, drifted])) == 1
    out = capsys.readouterr().out
    assert f"{drifted}: COLMAP's camera looks drifted" in out and "--camera-type simple_pinhole" in out
    assert f"{clean}: COLMAP's camera" not in out and "not folded" in out  # the fold check still runs on both
    lines = {line.split(":")[0]: line for line in out.splitlines() if "not folded" in line}
    assert "fy/fx 1.000 (square pixels)" in lines[str(clean)]
    assert "but its camera drifted (fy/fx 1.200" in lines[str(drifted)]
    # what to run for this capture, to copy: its images posed again with one focal length beside it, then checked
    reposed = tmp_path / "east_reposed"
    commands = [line.strip() for line in out.splitlines() if line.startswith("    ")]
    pose_again = f"ns-process-data images --data {drifted / 'images'} --output-dir {reposed} --camera-type "
    pose_again += "simple_pinhole"
    assert commands == [pose_again, f"ns-nerfuser-check-capture {reposed}"]
    reposed.mkdir()  # never a folder that exists
    assert cli.one_focal_lines(drifted)[-1] == f"ns-nerfuser-check-capture {tmp_path / 'east_reposed_2'}"


class _TrainedRunWithCamera(_TrainedRun):
    def __init__(self, name: str, poses: np.ndarray, camera: Intrinsics):
        super().__init__(name, poses)
        self._camera = camera

    def training_intrinsics(self) -> Intrinsics:
        return self._camera


def test_registration_warns_about_a_run_trained_on_a_drifted_camera(room_poses):
    console = Console(record=True, width=400)
    square, stretched = Intrinsics(50.0, 50.0, 32, 24, 64, 48), Intrinsics(50.0, 58.0, 32, 20, 64, 48)
    runs = [_TrainedRunWithCamera("east", room_poses, stretched), _TrainedRunWithCamera("west", room_poses, square),
            _TrainedRun("north", room_poses)]  # fmt: skip
    checks = check_captures(runs, console)
    text = console.export_text()
    assert "NeRF east: COLMAP's camera looks drifted" in text and "NeRF west" not in text and "simple_pinhole" in text
    assert checks["east"]["camera"]["drifted"] and not checks["west"]["camera"]["drifted"]
    assert "camera" not in checks["north"] and not checks["east"]["folded"]  # a renderer without its camera: no check
