"""Registration from re-rendering, end to end through pycolmap (CPU).

The "NeRFs" are mostly ground-truth scene renderers seen through their capture frames (exact, fast); one test runs
the real command on tiny trained nerfacto checkpoints. Renders and SfM results are cached in a module-wide work
folder, so tests that reuse a NeRF's views do not render them again.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import runs, sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.ground_truth import (
    ScoreCommand,
    load_ground_truth_captures,
    read_gt_transforms,
    score_registration,
)
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration import estimate as reg_estimate
from nerfuser_ns.registration import pipeline as reg_pipeline
from nerfuser_ns.registration import sfm as reg_sfm
from nerfuser_ns.renderers import RenderBatch, Renderer
from nerfuser_ns.sampling import sample_hemisphere_poses
from nerfuser_ns.scripts import register as cli

W, H = 240, 180  # smallest size at which SIFT finds enough on these scenes (160x120: nothing reconstructs)


def small_config(**kw) -> reg.RegistrationConfig:
    # the paper's hemisphere at a fixed camera (the automatic choice has tests of its own)
    sampling_kw = {"source": "hemisphere", "fov_deg": 60.0, **kw.pop("sampling", {})}
    sampling = reg.PoseSamplingConfig(num_poses=kw.pop("num_poses", 20), width=W, height=H, **sampling_kw)
    return reg.RegistrationConfig(sampling=sampling, self_check_views=kw.pop("self_check_views", 2), **kw)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("register_work")


@pytest.fixture(scope="module")
def oc_layout():
    return scenes.make_layout("object-centric", seed=0, num_views=16, num_test_views=1, width=W, height=H)


@pytest.fixture(scope="module")
def oc_renderers(oc_layout) -> list[SceneFrameRenderer]:
    return [SceneFrameRenderer.from_layout(oc_layout, c) for c in ("capture_a", "capture_b")]


def gt_of(layout, names=None) -> list[np.ndarray]:
    caps = {c.name: c for c in layout.captures}
    return [caps[n].capture_to_world for n in (names or [c.name for c in layout.captures])]


@pytest.fixture(scope="module")
def oc_record(oc_layout, oc_renderers, work) -> dict:
    return score_registration(reg.register(oc_renderers, small_config(), work), gt_of(oc_layout))


# ---------------------------------------------------------------------------------------------------------------------
# Fakes for bad inputs


class FakeRenderer:
    """Noise, blank or NaN images: nothing SfM can use."""

    def __init__(self, name: str, kind: str):
        self.name, self.kind = name, kind

    def cache_key(self) -> str:
        return f"fake:{self.name}:{self.kind}"

    def render(self, c2w, intrinsics) -> RenderBatch:
        n, h, w = len(c2w), intrinsics.height, intrinsics.width
        if self.kind == "noise":
            rng = np.random.default_rng(zlib.crc32(np.asarray(c2w).tobytes()))
            return RenderBatch(rng.random((n, h, w, 3), dtype=np.float32), None)
        if self.kind == "blank":
            return RenderBatch(np.zeros((n, h, w, 3), np.float32), np.zeros((n, h, w), np.float32))
        return RenderBatch(np.full((n, h, w, 3), np.nan, np.float32), np.ones((n, h, w), np.float32))

    def training_poses(self):
        return None


class MirroredRenderer:
    """A scene renderer whose images are flipped left-right: a consistent (mirror) world SIFT cannot match to the
    original, so its views form an SfM model of their own (no overlap)."""

    def __init__(self, inner: SceneFrameRenderer):
        self.inner, self.name = inner, f"mirrored_{inner.name}"

    def cache_key(self) -> str:
        return "mirror:" + self.inner.cache_key()

    def render(self, c2w, intrinsics) -> RenderBatch:
        out = self.inner.render(c2w, intrinsics)
        return RenderBatch(out.rgb[:, :, ::-1].copy(), out.accumulation[:, :, ::-1].copy())

    def training_poses(self):
        return None


def run_cli(tmp_path: Path, renderers=None, capsys=None, **kw) -> tuple[int, Path, str]:
    out = tmp_path / "registration.json"
    cmd = cli.RegisterCommand(**{**vars(small_config()), "output": out, **kw})
    rc = cli.run(cmd, renderers)
    err = capsys.readouterr().err if capsys is not None else ""
    return rc, out, err


def assert_one_line_error(rc: int, out: Path, err: str, *fragments: str) -> None:
    assert rc == 1
    assert not out.exists(), "no registration file may be written on error"
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error:")
    for f in fragments:
        assert f in lines[0], (f, lines[0])


# ---------------------------------------------------------------------------------------------------------------------
# End to end on ground-truth renderers


def test_renderer_protocol(oc_renderers):
    assert all(isinstance(r, Renderer) for r in oc_renderers)
    assert isinstance(FakeRenderer("x", "noise"), Renderer)
    train = oc_renderers[0].training_poses()
    assert train.shape == (16, 4, 4)
    # capture frames are normalised: unit mean camera distance to the origin
    assert np.isclose(np.linalg.norm(train[:, :3, 3], axis=-1).mean(), 1.0)


def test_training_pose_subsets(oc_renderers):
    train = oc_renderers[0].training_poses()
    pick = lambda seed: reg.sample_poses(oc_renderers[0], reg.PoseSamplingConfig(  # noqa: E731
        source="training", max_training_poses=5, seed=seed))[0]  # fmt: skip
    even = pick(0)
    np.testing.assert_array_equal(even, train[[0, 4, 8, 11, 15]])  # evenly spaced, first and last included
    a, b, c = pick(3), pick(3), pick(4)
    np.testing.assert_array_equal(a, b)  # deterministic by seed
    assert not np.array_equal(a, c) and not np.array_equal(a, even)
    idx = [int(np.flatnonzero((train == p).all(axis=(1, 2)))[0]) for p in a]
    assert idx == sorted(set(idx)) and len(idx) == 5  # distinct training poses, in capture order


def test_object_centric_two_nerfs_recovers_ground_truth(oc_record):
    rec = oc_record
    a, b = rec["nerfs"]
    assert rec["reference"] == {"index": 0, "name": "capture_a"}
    np.testing.assert_allclose(a["T_to_reference"], np.eye(4), atol=1e-12)
    for n in rec["nerfs"]:
        assert n["views"]["rendered"] == 20 and n["views"]["registered"] >= 18
        assert n["estimator"] == "weiszfeld"
        assert n["scale_spread"] < 0.01
    g = b["ground_truth"]
    # measured (240x180, 20 views each, refined): r 0.026 deg, t 0.00084, s 0.00098
    assert g["r_err_deg"] < 0.06 and g["t_err"] < 0.003 and g["s_err"] < 0.003 and not g["failure"]
    ref = rec["refinement"]
    assert ref["used"] and ref["points"] > 50 and ref["rms_px_after"] <= ref["rms_px_before"]
    assert b["refinement_change"]["r_deg"] > 0 and a["refinement_change"] == {"r_deg": 0.0, "t": 0.0, "s": 0.0}
    # The SfM's own cameras agree with the refined transform to a fraction of a degree.
    assert b["residuals"]["rotation_deg_median"] < 0.3 and b["residuals"]["centre_median"] < 0.01
    assert rec["ground_truth"]["failure"] is False
    (pair,) = rec["pairs"]
    np.testing.assert_allclose(pair["T_j_to_i"], b["T_to_reference"], atol=1e-9)
    assert pair["covisible_points"] > 50
    assert pair["self_check"]["passed"] and pair["self_check"]["ncc"] > 0.9
    assert rec["sfm"]["matching"] == "exhaustive" and sum(rec["sfm"]["models"][0]) >= 36
    assert set(rec["timings_s"]) == {"render", "features", "matching", "mapping", "solve", "self_check"}
    assert rec["settings"]["sampling"]["num_poses"] == 20


def test_refinement_beats_the_camera_estimator(oc_layout, oc_renderers, oc_record, work):
    # Same renders and SfM (reused): only the solve differs.
    plain = score_registration(reg.register(oc_renderers, small_config(refine=False), work), gt_of(oc_layout))
    assert plain["refinement"] is None and plain["nerfs"][1]["refinement_change"] is None
    assert plain["sfm"]["reused"]
    g0, g = plain["nerfs"][1]["ground_truth"], oc_record["nerfs"][1]["ground_truth"]
    assert g["r_err_deg"] < g0["r_err_deg"] and g["t_err"] < g0["t_err"] and g["s_err"] < g0["s_err"]


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


PREVIOUS_FORMAT = Path(__file__).parent / "data" / "registration_format1.json"
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


def test_cli_success_writes_the_file_and_prints_a_summary(oc_layout, oc_renderers, oc_record, work, tmp_path, capsys):
    gt = []
    for i, T in enumerate(gt_of(oc_layout)):
        (tmp_path / f"gt{i}.json").write_text(json.dumps({"nerf_to_world": T.tolist()}))
        gt.append(tmp_path / f"gt{i}.json")
    rc, out, err = run_cli(tmp_path, oc_renderers, None, work_dir=work)
    printed = capsys.readouterr().out
    assert rc == 0, err
    rec = reg.read_registration(out)
    np.testing.assert_allclose(rec["nerfs"][1]["T_to_reference"], oc_record["nerfs"][1]["T_to_reference"])
    np.testing.assert_array_equal(rec["nerfs"][1]["transform"], rec["nerfs"][1]["T_to_reference"])  # fusion reader
    assert "ground_truth" not in rec and "ground_truth" not in rec["nerfs"][1]  # registration never sees the truth
    assert "capture_b" in printed and "passed" in printed
    # the kit scores the file afterwards, into a copy
    console = Console(record=True, width=200)
    scored = ScoreCommand(out, gt_transforms=gt).main(console)
    assert scored["nerfs"][1]["ground_truth"]["r_err_deg"] < 0.15 and "r_err" in console.export_text()
    assert reg.read_registration(out.with_name(out.stem + "_scored.json"))["ground_truth"]["failure"] is False
    assert "ground_truth" not in json.loads(out.read_text())  # the input is untouched
    with pytest.raises(reg.RegistrationError, match="is the input registration file"):
        ScoreCommand(out, gt_transforms=gt, output=out).main(console)


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


def test_rerun_reuses_renders_and_sfm(oc_layout, oc_renderers, oc_record, work):
    rec = score_registration(reg.register(oc_renderers, small_config(), work), gt_of(oc_layout))
    assert all(n["renders_reused"] for n in rec["nerfs"]) and rec["sfm"]["reused"]
    assert rec["timings_s"]["features"] == 0.0 and rec["timings_s"]["render"] < 1.0
    # what the cached steps cost when they were made is still reported, equal to the first run's
    for step in ("render", "features", "matching", "mapping"):
        assert rec["compute_timings_s"][step] == oc_record["compute_timings_s"][step] > 0
    assert rec["reused"] == {"renders": [True, True], "sfm": True}
    np.testing.assert_allclose(rec["nerfs"][1]["T_to_reference"], oc_record["nerfs"][1]["T_to_reference"])


def test_umeyama_and_reference_options(oc_layout, oc_renderers, oc_record, work):
    rec = reg.register(oc_renderers, small_config(estimator="umeyama-ransac", reference=1), work)
    rec = score_registration(rec, gt_of(oc_layout))
    assert rec["sfm"]["reused"]  # same renders, same SfM: only the solve differs
    assert rec["reference"]["index"] == 1
    np.testing.assert_allclose(rec["nerfs"][1]["T_to_reference"], np.eye(4), atol=1e-12)
    assert rec["nerfs"][0]["estimator"] == "umeyama_ransac"
    g = rec["nerfs"][0]["ground_truth"]
    assert g["r_err_deg"] < 0.5 and g["t_err"] < 0.02 and g["s_err"] < 0.01
    # the two reference choices agree: T_a->b = inv(T_b->a)
    T_ba = np.asarray(oc_record["nerfs"][1]["T_to_reference"])
    T_ab = np.asarray(rec["nerfs"][0]["T_to_reference"])
    assert sim3.sim3_errors(T_ab, sim3.invert_sim3(T_ba)).r_err_deg < 0.5


@pytest.mark.slow
def test_street_three_nerfs(work):
    """Three street segments from their training poses (12 per capture leaves one segment unconnected)."""
    layout = scenes.make_layout("street", seed=1, num_views=16, num_test_views=1, num_captures=3, width=W, height=H)
    renderers = [SceneFrameRenderer.from_layout(layout, c.name) for c in layout.captures]
    # 48 images over the exhaustive limit: exercises the pose-guided pair list
    config = small_config(sampling={"source": "training"}, sfm=reg.SfMConfig(exhaustive_max_images=40))
    rec = score_registration(reg.register(renderers, config, work), gt_of(layout))
    assert rec["sfm"]["matching"] == "pose-guided pairs"
    assert len(rec["pairs"]) == 3
    checked = [p for p in rec["pairs"] if p["self_check"] is not None]
    assert len(checked) == 2 and all(p["self_check"]["passed"] for p in checked)  # spanning tree of 3 NeRFs
    for n in rec["nerfs"][1:]:
        g = n["ground_truth"]
        # measured: capture_2 (14 m from the reference capture) r 0.096 deg, t 0.011, s 0.0076 -- t is in the
        # reference's units (~2.5 m), so the lever arm turns a 0.1 deg rotation error into ~0.01 of translation
        assert g["r_err_deg"] < 0.4 and g["t_err"] < 0.04 and g["s_err"] < 0.03, (n["name"], g)


def test_pose_guided_pairs_are_linear_in_the_image_count(tmp_path):
    def viewset(name, n):
        c2w = sample_hemisphere_poses(n)
        return reg.ViewSet(name, tmp_path / name, c2w, ["hemisphere"] * n, np.ones(n), np.ones(n, bool))

    cfg = reg.SfMConfig(own_neighbors=4, cross_views=6)
    views = [viewset("a", 40), viewset("b", 40), viewset("c", 40)]
    pairs = reg_sfm._cheap_pairs(views, [v.image_names for v in views], cfg)
    assert len(pairs) == len(set(pairs)) and all(a < b for a, b in pairs)
    assert len(pairs) <= 120 * (4 + 2 * 6)
    n_ab = sum(a.startswith("a/") and b.startswith("b/") for a, b in pairs)
    assert n_ab >= 40 * 6  # every image of a meets 6 views of b (and vice versa)


# ---------------------------------------------------------------------------------------------------------------------
# Self-check


def test_automatic_sampling_uses_training_poses_when_datasets_are_readable(oc_layout, oc_renderers):
    choices = reg.resolve_sampling(oc_renderers, reg.RegistrationConfig())
    assert [c.config.sampling.source for c in choices] == ["training", "both", "hemisphere"]
    # the render camera is the training cameras' (field of view, aspect), the longer side `size` pixels
    intr = oc_layout.captures[0].intrinsics  # 240x180 at 65 deg
    sc = choices[0].config.sampling
    assert (sc.width, sc.height) == (400, 300)
    assert sc.fov_deg == pytest.approx(65.0, abs=1e-6)
    small = reg.resolve_sampling(oc_renderers, reg.RegistrationConfig(sampling=reg.PoseSamplingConfig(size=120)))
    assert (small[0].config.sampling.width, small[0].config.sampling.height) == (120, 90)
    assert small[0].config.sampling.intrinsics().fx == pytest.approx(intr.fx / 2)
    # an explicit choice is kept as given
    given = reg.resolve_sampling(oc_renderers, small_config())
    assert len(given) == 1 and given[0].config.sampling.source == "hemisphere"
    assert (given[0].config.sampling.width, given[0].config.sampling.fov_deg) == (W, 60.0)


def test_automatic_sampling_without_datasets_uses_the_hemisphere(oc_renderers):
    blind = [MirroredRenderer(r) for r in oc_renderers]  # no training poses, no training cameras
    choices = reg.resolve_sampling(blind, reg.RegistrationConfig())
    assert [c.config.sampling.source for c in choices] == ["hemisphere"]
    assert "training poses unavailable" in choices[0].reason
    sc = choices[0].config.sampling
    assert (sc.width, sc.height, sc.fov_deg) == reg.DEFAULT_RENDER_SIZE
    # one run without its dataset is enough to need the hemisphere for all
    mixed = reg.resolve_sampling([oc_renderers[0], blind[1]], reg.RegistrationConfig())
    assert [c.config.sampling.source for c in mixed] == ["hemisphere"]


def test_automatic_sampling_falls_back_and_says_so(oc_renderers, work, monkeypatch):
    tried = []

    def once(renderers, config, work_dir, console):
        tried.append(config.sampling.source)
        if config.sampling.source == "training":
            raise reg.RegistrationError("a: its views form a separate SfM model")
        return {"nerfs": []}

    monkeypatch.setattr(reg_pipeline, "register_once", once)
    console = Console(record=True, width=200)
    record = reg.register(oc_renderers, reg.RegistrationConfig(), work, console=console)
    assert tried == ["training", "both"]
    assert record["sampling_choice"]["source"] == "both"
    assert record["sampling_choice"]["tried_before"] == [
        {"source": "training", "error": "a: its views form a separate SfM model"}]
    text = console.export_text()
    for line in ("pose sampling: training", "training poses did not register", "pose sampling: both"):
        assert line in text, line
    # every choice failing: the last error is the one raised
    monkeypatch.setattr(reg_pipeline, "register_once", lambda *a: (_ for _ in ()).throw(reg.RegistrationError("no")))
    with pytest.raises(reg.RegistrationError, match="no"):
        reg.register(oc_renderers, reg.RegistrationConfig(), work, console=Console(quiet=True))


def test_ncc_basics():
    rng = np.random.default_rng(0)
    a = rng.random((32, 48, 3)).astype(np.float32)
    assert reg.ncc(a, a) == pytest.approx(1.0)
    assert reg.ncc(a, 0.5 * a + 0.2) == pytest.approx(1.0)  # gain and offset invariant
    assert reg.ncc(a, 1 - a) == pytest.approx(-1.0)
    assert abs(reg.ncc(a, rng.random((32, 48, 3)).astype(np.float32))) < 0.1
    assert np.isnan(reg.ncc(a, a, mask=np.zeros((32, 48), bool)))


def test_self_check_rejects_a_wrong_transform(oc_layout, oc_renderers, oc_record, work):
    config = small_config()
    views = [reg.render_views_cached(r, config.sampling, work / "renders") for r in oc_renderers]
    assert all(v.reused for v in views)
    T = np.stack([np.asarray(n["T_to_reference"]) for n in oc_record["nerfs"]])
    intr = config.sampling.intrinsics()
    good = reg.cross_render_check(oc_renderers, views, T, [(0, 1)], intr, config)[0]
    wrong = T.copy()
    wrong[1] = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 0.0, 25.0])), [0.1, 0.0, 0.0]) @ T[1]
    bad = reg.cross_render_check(oc_renderers, views, wrong, [(0, 1)], intr, config)[0]
    assert good.score > 0.9
    assert bad.score < config.ncc_threshold


WRONG = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 40.0, 0.0])))  # 40 deg about the frame's origin


def perturb_second_estimate(monkeypatch) -> None:
    """The paper's estimator returns NeRF B's transform rotated by ``WRONG``."""
    real = sim3.estimate_sim3_from_poses
    calls = []

    def perturbed(G_nerf, G_sfm, **kw):
        est = real(G_nerf, G_sfm, **kw)
        calls.append(est)
        return dataclasses.replace(est, T=WRONG @ est.T) if len(calls) == 2 else est

    monkeypatch.setattr(reg_estimate.sim3, "estimate_sim3_from_poses", perturbed)


@pytest.mark.parametrize("refine", [False, True])
def test_register_fails_when_the_estimate_is_wrong(
    oc_renderers, oc_record, work, monkeypatch, tmp_path, capsys, refine
):
    if refine:  # the refinement would correct a wrong start (next test): break its output instead
        real_refine = reg.refine_transforms

        def perturbed_refine(*args, **kw):
            T, summary = real_refine(*args, **kw)
            T = T.copy()
            T[1] = WRONG @ T[1]
            return T, summary

        monkeypatch.setattr(reg_pipeline, "refine_transforms", perturbed_refine)
    else:
        perturb_second_estimate(monkeypatch)
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work, refine=refine)
    assert_one_line_error(rc, out, err, "capture_a and capture_b", "self-check failed")
    rejected = json.loads((work / "rejected_registration.json").read_text())
    assert rejected["pairs"][0]["self_check"]["passed"] is False


def test_refinement_corrects_a_wrong_start(oc_layout, oc_renderers, oc_record, work, monkeypatch):
    # The bundle adjustment fits the image evidence, so a start 40 deg off still converges to the right answer.
    perturb_second_estimate(monkeypatch)
    rec = score_registration(reg.register(oc_renderers, small_config(), work), gt_of(oc_layout))
    assert rec["refinement"]["change"][1]["r_deg"] > 39
    np.testing.assert_allclose(rec["nerfs"][1]["T_to_reference"], oc_record["nerfs"][1]["T_to_reference"], atol=1e-5)


# ---------------------------------------------------------------------------------------------------------------------
# Bad inputs: one red line naming the NeRF, exit 1, no file


@pytest.mark.parametrize(
    ("kind", "fragments"),
    [
        ("noise", ("noise_b", "views registered", "--sampling.num-poses")),
        ("blank", ("blank_b", "see enough", "--sampling.radius")),
        ("nan", ("nan_b", "NaN")),
    ],
)
def test_bad_renders_fail_clearly(oc_renderers, work, tmp_path, capsys, kind, fragments):
    renderers = [oc_renderers[0], FakeRenderer(f"{kind}_b", kind)]
    rc, out, err = run_cli(tmp_path, renderers, capsys, work_dir=work, sfm=reg.SfMConfig(max_num_features=2048))
    assert_one_line_error(rc, out, err, *fragments)


def test_no_overlap_gives_separate_models(oc_renderers, work, tmp_path, capsys):
    renderers = [oc_renderers[0], MirroredRenderer(oc_renderers[1])]
    rc, out, err = run_cli(tmp_path, renderers, capsys, work_dir=work)
    assert_one_line_error(rc, out, err, "separate SfM model")
    assert "capture_a" in err and "mirrored_capture_b" in err


def test_same_run_twice_and_too_few_runs(oc_renderers, work, tmp_path, capsys):
    rc, out, err = run_cli(tmp_path, [oc_renderers[0], oc_renderers[0]], capsys, work_dir=work)
    assert_one_line_error(rc, out, err, "passed twice")
    rc, out, err = run_cli(tmp_path, None, capsys, configs=[tmp_path / "only.yml"])
    assert_one_line_error(rc, out, err, "at least 2 runs")


def test_missing_and_unreadable_configs(tmp_path, capsys):
    bad = tmp_path / "bad.yml"
    bad.write_text("pipeline: [unclosed\n")
    rc, out, err = run_cli(tmp_path, None, capsys, configs=[tmp_path / "missing.yml", bad])
    assert_one_line_error(rc, out, err, "missing.yml", "no such file")
    rc, out, err = run_cli(tmp_path, None, capsys, configs=[bad, bad])
    assert_one_line_error(rc, out, err, "bad.yml", "not a readable nerfstudio config")


def test_ground_truth_inputs_are_checked(tmp_path):
    gt = tmp_path / "ground_truth.json"
    gt.write_text(json.dumps({"captures": [{"name": "capture_a", "capture_to_world": np.eye(4).tolist()}]}))
    assert np.allclose(load_ground_truth_captures(gt, ["capture_a"])[0], np.eye(4))
    with pytest.raises(reg.RegistrationError, match="no capture named 'capture_z'"):
        load_ground_truth_captures(gt, ["capture_z"])
    with pytest.raises(reg.RegistrationError, match="not a readable ground_truth.json"):
        load_ground_truth_captures(tmp_path / "nope.json", ["capture_a"])


# ---------------------------------------------------------------------------------------------------------------------
# The real command on tiny trained nerfacto runs


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    """One tiny nerfacto-cpu run (seconds of training) on capture_a of a tiny scene, and a copy of it elsewhere."""
    from nerfuser_ns.bench.training import train

    layout = scenes.make_layout("object-centric", seed=3, num_views=12, num_test_views=2, width=40, height=30)
    root = tmp_path_factory.mktemp("tiny")
    scenes.write_scene(layout, root / "scene", supersample=1)
    result = train(data=root / "scene" / "capture_a", output_dir=root / "outputs", experiment_name="tiny",
                   max_num_iterations=6, seed=0, tiny=True)
    first = result.config_path
    second = root / "copy" / "tiny" / first.parent.parent.name / first.parent.name / "config.yml"
    shutil.copytree(first.parent, second.parent)
    return root, first, second


def test_real_command_on_tiny_nerfacto_runs(tiny_runs, tmp_path, monkeypatch, capsys):
    root, first, second = tiny_runs
    out = tmp_path / "registration.json"
    argv = ["ns-nerfuser-register", "--configs", str(first), str(second), "--output", str(out),
            "--sampling.num-poses", "6", "--sampling.width", "64", "--sampling.height", "48"]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exit_info:
        cli.entrypoint()
    err = capsys.readouterr().err
    # Runs trained for 6 steps render blurry blobs: SfM may not register them. Then the documented one-line error;
    # otherwise a complete registration file.
    if exit_info.value.code == 0:
        rec = reg.read_registration(out)
        assert len(rec["nerfs"]) == 2 and rec["nerfs"][0]["config"] == str(first)
        scored = ScoreCommand(out, ground_truth=root / "scene", gt_captures=["capture_a", "capture_a"]).main()
        assert scored["nerfs"][1]["ground_truth"] is not None
        assert rec["nerfs"][0]["checkpoint"] == runs.checkpoint_identity(first)  # which weights were registered
    else:
        assert_one_line_error(exit_info.value.code, out, err)
        assert any(s in err for s in ("views registered", "reconstructed nothing", "see enough", "self-check")), err
        assert str(first) in err or str(second) in err or "reconstructed nothing" in err
    # the renders are kept for a re-run (one folder per NeRF and pose source the automatic choice tried)
    assert len(list((tmp_path / "registration_work" / "renders").glob("*/poses.json"))) in (2, 4, 6)


def test_run_without_checkpoints(tiny_runs, tmp_path, capsys):
    _, first, _ = tiny_runs
    no_ckpt = tmp_path / "o" / "tiny" / "nerfacto-cpu" / "run"
    shutil.copytree(first.parent, no_ckpt)
    shutil.rmtree(no_ckpt / "nerfstudio_models")
    rc, out, err = run_cli(tmp_path, None, capsys, configs=[first, no_ckpt / "config.yml"])
    assert_one_line_error(rc, out, err, str(no_ckpt / "config.yml"), "has no checkpoint")


def test_moved_dataset_needs_and_takes_data(tiny_runs, tmp_path, capsys):
    """Training poses come from the run's dataset: a moved dataset is a one-line error naming --data, and --data
    points the run at it."""
    root, first, _ = tiny_runs
    moved = tmp_path / "o" / "tiny" / "nerfacto-cpu" / "run"
    shutil.copytree(first.parent, moved)
    config = runs.read_config(moved / "config.yml")
    config.pipeline.datamanager.data = tmp_path / "gone"
    (moved / "config.yml").write_text(yaml.dump(config))
    kw = dict(configs=[first, moved / "config.yml"], sampling=reg.PoseSamplingConfig(
        source="training", max_training_poses=4, width=64, height=48))  # fmt: skip
    rc, out, err = run_cli(tmp_path, None, capsys, **kw)
    assert_one_line_error(rc, out, err, str(moved / "config.yml"), "is missing", "--data")
    rc, out, err = run_cli(tmp_path, None, capsys, **kw, data=[root / "scene" / "capture_a"] * 2)
    assert "is missing" not in err  # now the poses load; tiny runs may still fail to register (another error)
    rc, out, err = run_cli(tmp_path, None, capsys, **kw, data=[root / "scene" / "capture_a"])
    assert_one_line_error(rc, out, err, "--data names 1 dataset folders for 2 runs")


class MustNotRender(FakeRenderer):
    """A run whose rendering would be the mistake: output checks must come first."""

    def __init__(self, name: str, config_path: Path):
        super().__init__(name, "noise")
        self.config_path = config_path

    def render(self, c2w, intrinsics) -> RenderBatch:
        raise AssertionError("rendered before the output path was checked")


def test_output_paths_are_checked_before_any_rendering(tmp_path, capsys):
    run_dir = tmp_path / "outputs" / "a" / "nerfacto" / "run"
    run_dir.mkdir(parents=True)
    config = run_dir / "config.yml"
    config.write_text("the run's config\n")
    renderers = [MustNotRender("a", config), MustNotRender("b", tmp_path / "b" / "config.yml")]
    for output, fragment in ((config, "inside the run folder"), (run_dir / "reg.json", "inside the run folder"),
                             (tmp_path, "is a folder"), (tmp_path / "file.txt" / "reg.json", "is not a folder")):
        if output.name == "reg.json" and output.parent.name == "file.txt":
            output.parent.write_text("a file, not a folder\n")
        cmd = cli.RegisterCommand(**{**vars(small_config()), "output": output})
        rc = cli.run(cmd, renderers)
        err = capsys.readouterr().err
        assert rc == 1 and fragment in err, (output, err)
    assert config.read_text() == "the run's config\n"  # the input is untouched


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


def test_non_finite_sampling_settings_are_refused_before_rendering(tmp_path, capsys):
    renderers = [MustNotRender("a", tmp_path / "a" / "config.yml"), MustNotRender("b", tmp_path / "b" / "config.yml")]
    for sampling, fragment in (({"center": (0.0, float("nan"), 0.0)}, "--sampling.center (0.0, nan, 0.0): must be"),
                               ({"radius": float("inf")}, "--sampling.radius inf: must be finite")):  # fmt: skip
        cmd = cli.RegisterCommand(**{**vars(small_config(sampling=sampling)), "output": tmp_path / "r.json",
                                     "work_dir": tmp_path / "work"})  # fmt: skip
        rc = cli.run(cmd, renderers)
        err = capsys.readouterr().err
        assert rc == 1 and fragment in err, err
        assert not (tmp_path / "work").exists()  # nothing cached


def test_ctrl_c_is_one_line(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "register", interrupted)
    rc = cli.run(cli.RegisterCommand(**{**vars(small_config()), "output": tmp_path / "r.json"}),
                 [FakeRenderer("a", "noise"), FakeRenderer("b", "noise")])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 130 and err.strip().startswith("interrupted: nothing written") and "Traceback" not in err
    assert not (tmp_path / "r.json").exists()


def test_damaged_caches_are_rebuilt_or_named(tmp_path):
    sampling = reg.PoseSamplingConfig(source="hemisphere", num_poses=4, width=16, height=12)
    renderer = FakeRenderer("noise", "noise")
    first = reg.render_views_cached(renderer, sampling, tmp_path / "renders", Console(quiet=True))
    assert not first.reused
    assert reg.render_views_cached(renderer, sampling, tmp_path / "renders", Console(quiet=True)).reused
    image = first.folder / "images" / "00002.png"
    good = image.read_bytes()
    image.write_bytes(good[: len(good) // 2])  # truncated
    console = Console(record=True, width=200)
    again = reg.render_views_cached(renderer, sampling, tmp_path / "renders", console)
    assert not again.reused and image.read_bytes() == good  # rendered again, identically
    text = console.export_text()
    assert "images/00002.png" in text and "rendering again" in text
    (tmp_path / "sfm").mkdir()
    (tmp_path / "sfm" / "observations.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(reg.RegistrationError, match=r"observations.npz: damaged SfM cache .*delete"):
        reg.load_observations(SimpleNamespace(folder=str(tmp_path / "sfm")))


def test_an_implausible_scale_is_warned_about(oc_renderers, oc_record, tmp_path, capsys, monkeypatch):
    record = copy.deepcopy(oc_record)
    record["nerfs"][1]["scale_to_reference"] = 1e-6
    monkeypatch.setattr(cli, "register", lambda *args, **kwargs: record)
    rc, out, _ = run_cli(tmp_path, oc_renderers, None, work_dir=tmp_path / "work")
    printed = " ".join(capsys.readouterr().out.split())
    assert rc == 0 and out.is_file()
    assert "implausible scale to the reference for capture_b" in printed and "same place" in printed


@pytest.mark.parametrize("mode", ["sfm", "known-geometry", "graph"])
def test_a_failed_self_check_names_the_likely_cause_of_its_mode(mode):
    from nerfuser_ns.registration.self_check import CrossRenderCheck, failure_message

    config = reg.RegistrationConfig(mode=mode)
    good, bad = CrossRenderCheck(0, 1, 0.9, 0.8, 4), CrossRenderCheck(1, 2, 0.1, 0.2, 4)
    assert failure_message([good], ["a", "b", "c"], config) is None
    message = failure_message([good, bad], ["a", "b", "c"], config)
    assert message.startswith("b and c: cross-render self-check failed (NCC 0.10 < ")  # the worse direction
    assert ("SfM" in message) == (mode == "sfm") and ("pose graph" in message) == (mode == "graph")


@pytest.mark.parametrize("source", ["hemisphere", "training", "both"])
def test_a_failed_self_check_suggests_what_fits_its_pose_source(source):
    """The advice names options of the poses that failed: no hemisphere radius for training poses, no training
    poses for a run that already rendered them."""
    from nerfuser_ns.registration.self_check import CrossRenderCheck, failure_message

    config = reg.RegistrationConfig(sampling=reg.PoseSamplingConfig(source=source))
    message = failure_message([CrossRenderCheck(0, 1, 0.1, 0.2, 4)], ["a", "b"], config)
    assert ("--sampling.radius" in message) == (source == "hemisphere")
    assert ("--sampling.max-training-poses" in message) == (source != "hemisphere")
    assert ("--mode known-geometry" in message) == (source != "hemisphere")
