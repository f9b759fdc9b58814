"""The registration file (:mod:`nerfuser_ns.registration.record`): written and read back, a file of the previous
format, the typed result, the minimal hand-written form, the optional training cameras and colour maps, the work
folder and render poses, and the one-line layout of matrix rows and camera lists."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from registration_helpers import FakeRenderer
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.capture_check import FoldCheck, IntrinsicsCheck
from nerfuser_ns.match_check import MatchCheck


def test_registration_file_round_trip(oc_record, tmp_path):
    path = reg.write_registration(oc_record, tmp_path / "sub" / "registration.json")
    assert [p.name for p in path.parent.iterdir()] == ["registration.json"]  # no temp file left behind
    back = reg.read_registration(path)
    np.testing.assert_allclose(back["nerfs"][1]["T_to_reference"], oc_record["nerfs"][1]["T_to_reference"])
    T = back["nerfs"][1]["T_to_reference"]
    R, _, s = sim3.decompose_sim3(T)
    assert s > 0 and np.isclose(np.linalg.det(R), 1.0)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(reg.RegistrationError, match="not a readable registration file"):
        reg.read_registration(tmp_path / "bad.json")


PREVIOUS_FORMAT = Path(__file__).parents[1] / "data" / "registration_format1.json"
"""Written by ``registration.register`` + ``write_registration`` before registration became a package (e8e5829):
oc_layout, small_config(), work folder ``registration_work``."""


def test_a_file_of_the_previous_format_reads_back_unchanged(tmp_path):
    text = PREVIOUS_FORMAT.read_text()
    old = json.loads(text)
    back = reg.read_registration(PREVIOUS_FORMAT)
    assert all(isinstance(n["T_to_reference"], np.ndarray) for n in back["nerfs"])
    as_json = json.loads(json.dumps(back, default=lambda a: a.tolist()))
    assert as_json == old and list(back) == list(old)
    # typed and back: the same record, key order included (a rewrite holds the same JSON, in the compact layout)
    result = reg.RegistrationResult.from_record(back)
    assert result.reference == 0 and [n.name for n in result.nerfs] == ["capture_a", "capture_b"]
    np.testing.assert_array_equal(result.nerfs[1].T_to_reference, old["nerfs"][1]["transform"])
    assert result.pairs[0].self_check.passed and result.sfm.reused is False and result.extra == {}
    assert result.to_record() == old
    again = reg.write_registration(result.to_record(), tmp_path / "again.json").read_text()
    assert json.loads(again) == old and list(json.loads(again)) == list(old)
    retyped = reg.RegistrationResult.from_record(reg.read_registration(tmp_path / "again.json")).to_record()
    assert reg.write_registration(retyped, tmp_path / "twice.json").read_text() == again  # byte-identical from now on
    # keys a later reader adds (the kit's scores) are kept
    scored = score_registration(back, [np.eye(4), np.eye(4)])
    assert reg.RegistrationResult.from_record(scored).to_record() == scored
    with pytest.raises(reg.RegistrationError, match="not a registration record"):
        reg.RegistrationResult.from_record({**old, "kind": "something else"})
    # the fusion's view of it: the record's T_to_reference (not its alias), the render folders beside it
    items = list(reg.iter_registered_nerfs(PREVIOUS_FORMAT))
    assert [(i.name, i.config, i.transform_key) for i in items] == [("capture_a", None, "T_to_reference"),
                                                                     ("capture_b", None, "T_to_reference")]
    assert [f.folder for f in reg.render_folders(PREVIOUS_FORMAT)] == [
        PREVIOUS_FORMAT.parent / n["render_folder"] for n in old["nerfs"]]  # fmt: skip


def test_the_typed_result_is_the_record(oc_record):
    result = reg.RegistrationResult.from_record(oc_record)
    assert result.to_record() == oc_record
    assert set(result.nerfs[1].extra) == {"ground_truth"} and set(result.extra) == {"ground_truth"}
    assert json.dumps(result.to_record(), indent=2) == json.dumps(oc_record, indent=2)  # key order too


def test_capture_checks_are_a_typed_field_of_the_record(oc_record):
    """The registration's fold checks of each run's training cameras read back as the typed field, not as extra."""
    checks = {"a": {"num_views": 58, "checked": True, "folded": True, "suspect_views": 20, "jumps": [["x", "y", 170]]}}
    result = reg.RegistrationResult.from_record({**oc_record, "capture_checks": checks})
    assert result.capture_checks == checks and "capture_checks" not in result.extra
    assert result.to_record()["capture_checks"] == checks
    assert "capture_checks" not in reg.RegistrationResult.from_record(oc_record).to_record()


def flagged_capture_checks() -> dict:
    """Capture-check records as the registration writes them: capture "b" folded (by file order and by its matches)
    with a drifted camera, capture "a" clean."""
    square, stretched = (Intrinsics(fx=300, fy=f, cx=160, cy=120, width=320, height=240) for f in (300.0, 360.0))
    suspect = tuple(f"f{i}" for i in range(11, 20))
    folded = FoldCheck(40, 9.0, True, (("f10", "f11", 175.0), ("f19", "f20", 176.0)), suspect).to_record()
    clean = FoldCheck(40, 9.0, True, (), ()).to_record()
    unexplained = [(f"a{i}", f"b{i}") for i in range(10)]
    explained = [(f"{s}{i}", f"{s}{i + 1}") for s in "ab" for i in range(95)]
    return {
        "a": {**clean, "matches": MatchCheck(True, 190, [], explained).to_record(),
              "camera": IntrinsicsCheck(square).to_record()},
        "b": {**folded, "matches": MatchCheck(True, 200, unexplained, explained).to_record(),
              "camera": IntrinsicsCheck(stretched).to_record()},
    }  # fmt: skip


def test_capture_findings_name_what_the_checks_found_wrong():
    checks = flagged_capture_checks()
    assert reg.capture_findings(checks["a"]) == ()
    found = reg.capture_findings(checks["b"])
    assert len(found) == 3
    assert "folded by COLMAP in file order (9 of 40 views" in found[0]
    assert "does not explain 10 of 200 verified image pairs (5.0%)" in found[1]
    assert found[2] == "its camera drifted (fy/fx 1.200)"
    # a record written before the match and camera checks, or none at all
    assert reg.capture_findings({k: v for k, v in checks["b"].items() if k not in ("matches", "camera")}) == found[:1]
    assert reg.capture_findings(None) == () and reg.capture_findings("folded") == ()


def test_capture_findings_travel_with_each_registered_nerf(oc_record, tmp_path):
    record = {**oc_record, "capture_checks": flagged_capture_checks()}
    names = [n["name"] for n in record["nerfs"]]
    record["capture_checks"] = dict(zip(names, record["capture_checks"].values(), strict=False))
    path = tmp_path / "registration.json"
    path.write_text(json.dumps(record))
    found = [item.capture_findings for item in reg.iter_registered_nerfs(path)]
    assert found[0] == () and len(found[1]) == 3
    path.write_text(json.dumps(oc_record))  # no checks recorded: nothing found
    assert all(item.capture_findings == () for item in reg.iter_registered_nerfs(path))


def test_minimal_form(tmp_path):
    entries = [reg.NerfEntry("a", tmp_path / "a.yml", np.eye(4)),
               reg.NerfEntry("b", tmp_path / "b.yml", sim3.make_sim3(np.eye(3), [1.0, 0.0, 0.0], 2.0))]  # fmt: skip
    path = reg.write_minimal_registration(entries, tmp_path / "sub" / "reg.json")
    assert [p.name for p in path.parent.iterdir()] == ["reg.json"]
    items = list(reg.iter_registered_nerfs(path))
    assert [(i.name, i.config, i.transform_key) for i in items] == [("a", str(tmp_path / "a.yml"), "transform"),
                                                                     ("b", str(tmp_path / "b.yml"), "transform")]
    np.testing.assert_array_equal(items[1].transform, entries[1].nerf_to_common)
    assert reg.render_folders(path) == [("a", tmp_path / "a.yml", None), ("b", tmp_path / "b.yml", None)]
    with pytest.raises(reg.RegistrationFileError, match="nerfs.1.: missing config"):
        path.write_text(json.dumps({"nerfs": [{"config": "a.yml", "transform": []}, {"transform": []}]}))
        list(reg.iter_registered_nerfs(path))


def test_training_cameras_and_colour_maps_travel_with_the_file(tmp_path):
    """Optional per-NeRF fields: written when known, read back checked, absent meaning unknown."""
    from nerfuser_ns.registration.record import TrainingCameras, colour_maps_to_reference, training_cameras_of
    from nerfuser_ns.spec import read_registered_nerfs

    c2w = np.stack([np.eye(4), sim3.make_sim3(np.eye(3), [0.0, 0.0, 2.0], 1.0)])
    cams = TrainingCameras(c2w, np.array([[30.0, 30.0, 16.0, 12.0, 32.0, 24.0]] * 2))
    colour = np.hstack([np.diag([1.2, 1.0, 0.8]), np.full((3, 1), 0.01)])
    entries = [reg.NerfEntry("a", tmp_path / "a.yml", np.eye(4)),
               reg.NerfEntry("b", tmp_path / "b.yml", np.eye(4), training_cameras=cams, colour_to_reference=colour)]
    path = reg.write_minimal_registration(entries, tmp_path / "reg.json")
    assert "training_cameras" not in json.loads(path.read_text())["nerfs"][0]  # unknown: no key
    a, b = read_registered_nerfs(path, check_runs=False)
    assert a.training_cameras is None and a.colour_to_reference is None
    np.testing.assert_allclose(b.training_cameras.c2w, c2w, atol=1e-6)
    np.testing.assert_allclose(b.training_cameras.intrinsics, cams.intrinsics)
    np.testing.assert_allclose(b.colour_to_reference, colour)
    data = json.loads(path.read_text())
    data["nerfs"][1]["training_cameras"]["intrinsics"] = [[30.0, 30.0, 16.0, 12.0, 32.0]]
    path.write_text(json.dumps(data))
    with pytest.raises(reg.RegistrationFileError, match=r"nerfs\[1\]: training_cameras must hold"):
        list(reg.iter_registered_nerfs(path))
    data["nerfs"][1]["training_cameras"] = None
    data["nerfs"][1]["colour_to_reference"] = [[1.0, 0.0]]
    path.write_text(json.dumps(data))
    with pytest.raises(reg.RegistrationFileError, match="colour_to_reference must be a finite 3x4"):
        list(reg.iter_registered_nerfs(path))

    # A renderer's cameras: its training poses with its intrinsics; None when it has none.
    class WithPoses:
        def training_poses(self):
            return c2w

        def training_intrinsics(self):
            return Intrinsics(30.0, 30.0, 16.0, 12.0, 32, 24)

    got = training_cameras_of(WithPoses())
    np.testing.assert_array_equal(got.c2w, c2w) and np.testing.assert_array_equal(got.intrinsics, cams.intrinsics)
    assert training_cameras_of(FakeRenderer("x", "blank")) is None

    # Colour maps chain along the checked pairs to the reference: 2 -> 1 -> 0.
    half = np.hstack([0.5 * np.eye(3), np.zeros((3, 1))])
    checks = [reg.CrossRenderCheck(0, 1, 0.9, 0.9, 2, colour_j_to_i=half, colour_i_to_j=4 * half),
              reg.CrossRenderCheck(1, 2, 0.9, 0.9, 2, colour_j_to_i=half, colour_i_to_j=4 * half)]  # fmt: skip
    maps = colour_maps_to_reference(3, 0, checks)
    np.testing.assert_allclose(maps[2][:, :3], 0.25 * np.eye(3))
    np.testing.assert_allclose(colour_maps_to_reference(3, 2, checks)[0][:, :3], 4 * np.eye(3))
    assert colour_maps_to_reference(3, 0, checks[:1])[2] is None


def test_work_folder_and_render_poses(tmp_path):
    """The work folder is <output stem>_work beside the output; render folders moved with it are found there."""
    assert reg.work_dir_for(tmp_path / "out" / "registration.json") == tmp_path / "out" / "registration_work"
    sampling = reg.PoseSamplingConfig(source="hemisphere", num_poses=4, width=16, height=12)
    views = reg.render_views_cached(FakeRenderer("a", "blank"), sampling, tmp_path / "old_work" / "renders",
                                    Console(quiet=True))  # fmt: skip
    output = tmp_path / "moved" / "registration.json"
    output.parent.mkdir()
    output.write_text(json.dumps({"kind": "nerfuser_registration",
                                  "nerfs": [{"name": "a", "config": None, "render_folder": str(views.folder)}]}))
    shutil.move(views.folder.parent.parent, reg.work_dir_for(output))
    (entry,) = reg.render_folders(output)
    assert entry.folder == reg.work_dir_for(output) / "renders" / views.folder.name and entry.config is None
    poses = reg.read_render_poses(entry.folder)
    np.testing.assert_array_equal(poses.c2w, views.c2w)
    assert not poses.kept.any() and poses.intrinsics["width"] == 16  # blank views see nothing: left out of the SfM
    with pytest.raises(FileNotFoundError):
        reg.read_render_poses(views.folder)


def test_the_file_keeps_matrix_rows_and_camera_lists_on_one_line(tmp_path):
    """Hundreds of training cameras stay readable: lists of plain values are one line each; the JSON is unchanged."""
    record = {"kind": "nerfuser_registration", "nerfs": [{"name": "a", "T_to_reference": np.eye(4).tolist(),
              "training_cameras": {"c2w": np.zeros((300, 3, 4)).tolist(), "intrinsics": np.ones((300, 6)).tolist()},
              "note": None, "empty": [], "nested": {}}]}  # fmt: skip
    path = reg.write_registration(record, tmp_path / "r.json")
    text = path.read_text()
    assert json.loads(text) == record
    assert "        [1.0, 0.0, 0.0, 0.0],\n" in text and "[1.0, 1.0, 1.0, 1.0, 1.0, 1.0]" in text
    assert len(text.splitlines()) < 300 * 6 + 50  # 3 rows + 2 brackets per c2w, 1 line per intrinsics
