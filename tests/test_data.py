"""Fusion spec and registration reading/validation, and the nerfuser datamanager (no NeRF training needed)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from dataset_helpers import process_data_like_dataset, run_on
from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config
from nerfuser_ns.method_configs.nerfuser import nerfuser_config
from PIL import Image

from nerfuser_ns import data as fdata
from nerfuser_ns import registration, runs, sampling, sim3
from nerfuser_ns import spec as fspec
from nerfuser_ns.spec import FusionSpecError, NerfEntry, read_fusion_spec, read_registered_nerfs

T_B = sim3.make_sim3(np.eye(3)[[1, 0, 2]] * [[1], [-1], [1]], np.array([1.0, 2.0, 0.5]), 0.4)


def fake_run(root: Path, name: str, data: Path | None = None) -> Path:
    """A run folder that parses as a nerfstudio run (config.yml + a checkpoint file); nothing is trained."""
    config = nerfacto_cpu_config(10)
    config.experiment_name, config.timestamp, config.output_dir = name, "run", root
    config.pipeline.datamanager.data = data
    run_dir = root / name / "nerfacto-cpu" / "run"
    (run_dir / "nerfstudio_models").mkdir(parents=True)
    (run_dir / "config.yml").write_text(yaml.dump(config))
    (run_dir / "nerfstudio_models" / "step-000000009.ckpt").write_bytes(b"not loaded by these tests")
    return run_dir / "config.yml"


def with_checkpoint(config: Path) -> Path:
    """``config`` with a checkpoint file beside it, as fake_run's (not loaded by these tests)."""
    (config.parent / "nerfstudio_models").mkdir()
    (config.parent / "nerfstudio_models" / "step-000000009.ckpt").write_bytes(b"not loaded by these tests")
    return config


def write_dataset(folder: Path, c2ws: list[np.ndarray], w: int = 8, h: int = 6) -> Path:
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, c2w in enumerate(c2ws):
        Image.fromarray(np.full((h, w, 3), 40 * i, dtype=np.uint8)).save(folder / "images" / f"f{i}.png")
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": np.asarray(c2w).tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": w, "h": h, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


@pytest.fixture
def two_runs(tmp_path) -> tuple[Path, Path]:
    return fake_run(tmp_path / "outputs", "a"), fake_run(tmp_path / "outputs", "b")


def registration_file(path: Path, entries: list[dict]) -> Path:
    path.write_text(json.dumps({"nerfs": entries}))
    return path


def refused_before_writing(spec: Path, out: Path, pattern: str, **model_settings) -> None:
    """ns-train nerfuser's trainer config (with ``model_settings``) refuses ``spec`` with a SystemExit matching
    ``pattern`` before writing anything under ``out``."""
    config = nerfuser_config()
    config.data, config.output_dir = spec, out
    for key, value in model_settings.items():
        setattr(config.pipeline.model, key, value)
    config.set_timestamp()
    with pytest.raises(SystemExit, match=pattern):
        config.save_config()
    assert not out.exists()


def snapshot(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


# ----------------------------------------------------------------------------------------------------------------------
# Reading


def test_spec_with_minimal_registration(tmp_path, two_runs):
    a, b = two_runs
    registration_file(
        tmp_path / "reg.json",
        [
            {"name": "A", "config": str(a), "transform": np.eye(4).tolist()},
            {"name": "B", "config": str(b), "transform": T_B.tolist()},
        ],
    )
    # runs listed in the other order, relative paths, one renamed: the spec's order and names win
    spec_path = fspec.write_fusion_spec(
        tmp_path / "fusion.json",
        [b.relative_to(tmp_path), a.relative_to(tmp_path)],
        registration="reg.json",
        names=["bee", "A"],
    )
    spec = read_fusion_spec(spec_path)
    assert [n.name for n in spec.nerfs] == ["bee", "A"]
    assert spec.nerfs[0].config_path == b and spec.nerfs[1].config_path == a
    np.testing.assert_allclose(spec.nerfs[0].nerf_to_common, T_B)
    assert spec.nerfs[0].scale == pytest.approx(0.4)
    np.testing.assert_allclose(spec.origins[0], [1.0, 2.0, 0.5])
    assert spec.test_data is None and spec.registration_path == tmp_path / "reg.json"
    # a folder holding fusion.json, and the registration file itself, work as --data too
    assert [n.name for n in read_fusion_spec(tmp_path).nerfs] == ["bee", "A"]
    assert [n.name for n in read_fusion_spec(tmp_path / "reg.json").nerfs] == ["A", "B"]


def test_registration_record_of_ns_nerfuser_register(tmp_path, two_runs):
    """The record nerfuser_ns.registration writes: kind, T_to_reference (preferred over the 'transform' alias)."""
    a, b = two_runs
    record = {
        "format_version": 1,
        "kind": "nerfuser_registration",
        "reference": {"index": 0, "name": "a"},
        "nerfs": [
            {"name": "a", "config": str(a), "T_to_reference": np.eye(4).tolist(), "scale_to_reference": 1.0},
            {"name": "b", "config": str(b), "T_to_reference": T_B.tolist(), "transform": np.eye(4).tolist()},
        ],
        "pairs": [],
    }
    (tmp_path / "registration.json").write_text(json.dumps(record))
    entries = read_registered_nerfs(tmp_path / "registration.json")
    assert [e.name for e in entries] == ["a", "b"]
    np.testing.assert_allclose(entries[1].nerf_to_common, T_B)
    spec = read_fusion_spec(fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b]))  # default registration.json
    np.testing.assert_allclose(spec.transforms[1], T_B)


def test_a_capture_the_registration_flagged_is_named_whenever_the_fusion_loads(tmp_path, two_runs, capsys):
    """The registration's capture checks found run b's capture folded: every load of the fused run (ns-train, ns-eval,
    the viewers build the datamanager) says so in one line naming the NeRF; run a, clean, is not named."""
    a, b = two_runs
    matches = {"folded": True, "pairs": 630, "unexplained_pairs": 32, "unexplained_share": 0.0508}
    record = {
        "format_version": 1, "kind": "nerfuser_registration", "reference": {"index": 0, "name": "a"},
        "nerfs": [{"name": "a", "config": str(a), "T_to_reference": np.eye(4).tolist()},
                  {"name": "b", "config": str(b), "T_to_reference": T_B.tolist()}],
        "pairs": [],
        "capture_checks": {"a": {"folded": False, "matches": {**matches, "folded": False}},
                           "b": {"folded": False, "matches": matches}},
    }  # fmt: skip
    (tmp_path / "registration.json").write_text(json.dumps(record))
    spec_path = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b])
    warnings = read_fusion_spec(spec_path).capture_warnings()
    assert len(warnings) == 1 and warnings[0].startswith("NeRF b's capture: folded by COLMAP")
    assert "32 of 630 verified image pairs (5.1%)" in warnings[0] and "ns-nerfuser-check-capture" in warnings[0]
    capsys.readouterr()
    fdata.NerfuserDataManagerConfig(data=spec_path).setup(device="cpu", test_mode="inference")
    said = " ".join(capsys.readouterr().out.split())
    assert "nerfuser: warning: NeRF b's capture: folded by COLMAP" in said and "NeRF a's" not in said
    # a minimal registration file records no checks: nothing to say
    entries = [{"name": "a", "config": str(a), "transform": np.eye(4).tolist()},
               {"name": "b", "config": str(b), "transform": T_B.tolist()}]  # fmt: skip
    registration_file(tmp_path / "registration.json", entries)
    assert read_fusion_spec(spec_path).capture_warnings() == []


def test_single_run_needs_no_registration(tmp_path, two_runs):
    spec = read_fusion_spec(fspec.write_fusion_spec(tmp_path / "fusion.json", [two_runs[0]]))
    assert len(spec.nerfs) == 1 and spec.registration_path is None
    np.testing.assert_array_equal(spec.nerfs[0].nerf_to_common, np.eye(4))


def test_missing_registration_runs_registration(tmp_path, two_runs, monkeypatch):
    """No registration file and several runs: nerfuser_ns.registration.register_runs is called and its file read."""


    calls, configs = [], []

    def fake_register_runs(config_paths, output, names=None, device="cpu", **kwargs):
        calls.append((list(config_paths), Path(output), list(names)))
        configs.append(kwargs.get("config"))
        entries = [NerfEntry(n, Path(c), np.eye(4)) for n, c in zip(names, config_paths, strict=True)]
        registration.write_minimal_registration(entries, output)
        return {}

    monkeypatch.setattr(registration, "register_runs", fake_register_runs)
    spec_path = fspec.write_fusion_spec(tmp_path / "fusion.json", list(two_runs))
    with pytest.raises(FusionSpecError, match="no registration file at .*run ns-nerfuser-register first"):
        read_fusion_spec(spec_path, register=False)
    assert not calls
    spec = read_fusion_spec(spec_path)
    assert calls == [(list(two_runs), tmp_path / "registration.json", ["nerf0", "nerf1"])]
    assert [n.config_path for n in spec.nerfs] == list(two_runs)
    assert configs == [registration.RegistrationConfig()]  # the registration's defaults
    # settings reach the registration (ns-train nerfuser: --pipeline.datamanager.registration.*)
    (tmp_path / "registration.json").unlink()
    settings = registration.RegistrationConfig(sampling=registration.PoseSamplingConfig(source="training"))
    read_fusion_spec(spec_path, registration_config=settings)
    assert configs[-1] is settings

    def failing(*args, **kwargs):
        raise registration.RegistrationError("nerf1: only 2 of 32 views registered")

    (tmp_path / "registration.json").unlink()
    monkeypatch.setattr(registration, "register_runs", failing)
    with pytest.raises(FusionSpecError, match="automatic registration failed: nerf1: only 2 of 32"):
        read_fusion_spec(spec_path)


# ----------------------------------------------------------------------------------------------------------------------
# Bad specs: one clear line, nothing written


def _bad_cases(tmp_path: Path, a: Path, b: Path) -> list[tuple[str, dict | str, dict | None]]:
    other = fake_run(tmp_path / "elsewhere", "c")
    eye = np.eye(4).tolist()
    shear = np.eye(4)
    shear[0, 1] = 0.3
    nan = np.eye(4)
    nan[1, 3] = np.nan
    reflect = np.diag([1.0, 1.0, -1.0, 1.0])

    def reg(t_b, b_path=b) -> dict:
        return {
            "nerfs": [
                {"name": "a", "config": str(a), "transform": eye},
                {"name": "b", "config": str(b_path), "transform": t_b},
            ]
        }

    spec = {"runs": [str(a), str(b)], "registration": "reg.json"}
    return [
        ("missing.*config.yml: no such file", {"runs": [str(a), str(tmp_path / "missing" / "config.yml")]}, None),
        ("not in the registration", spec, reg(eye, b_path=other)),
        ("also registers runs the spec does not list", {"runs": [str(a)], "registration": "reg.json"}, reg(eye)),
        (r"transform: expected a 4x4 \(or 3x4\) matrix, got shape \(3, 3\)", spec, reg(np.eye(3).tolist())),
        ("transform: has non-finite values", spec, reg(json.loads(json.dumps(nan.tolist())))),
        ("not a scaled rotation", spec, reg(shear.tolist())),
        ("not a similarity", spec, reg(reflect.tolist())),
        ("last row must be", spec, reg([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]])),
        ("not a numeric 4x4 matrix", spec, reg("identity")),
        ("missing transform", spec, {"nerfs": [{"name": "a", "config": str(a)}]}),
        ("unknown keys", {"runs": [str(a)], "regsitration": "reg.json"}, None),
        ("not a readable JSON fusion spec", "{not json", None),
        ("no registration file at", {"runs": [str(a), str(b)]}, None),
        ("test_data .* is not a nerfstudio dataset", {"runs": [str(a)], "test_data": str(tmp_path)}, None),
        ("test_to_common: has non-finite values", {"runs": [str(a)], "test_to_common": nan.tolist()}, None),
        ("test_run 'c' names no run; the runs are", {"runs": [str(a)], "test_run": "c"}, None),
        ("test_run 3 is not an index of the 1 runs", {"runs": [str(a)], "test_run": 3}, None),
        ("test_run must be a run's name", {"runs": [str(a)], "test_run": 1.5}, None),
        ("drop test_data / test_to_common or test_run", {"runs": [str(a)], "test_run": 0, "test_to_common": eye}, None),
        (
            "duplicate NeRF names",
            spec,
            {
                "nerfs": [
                    {"name": "x", "config": str(a), "transform": eye},
                    {"name": "x", "config": str(b), "transform": eye},
                ]
            },
        ),
    ]


def test_bad_specs_give_one_clear_line_and_write_nothing(tmp_path, two_runs):
    a, b = two_runs
    cases = _bad_cases(tmp_path, a, b)
    for i, (pattern, spec, reg) in enumerate(cases):
        folder = tmp_path / f"case{i}"
        folder.mkdir()
        (folder / "fusion.json").write_text(spec if isinstance(spec, str) else json.dumps(spec))
        if reg is not None:
            (folder / "reg.json").write_text(json.dumps(reg))
        before = snapshot(tmp_path)
        with pytest.raises(FusionSpecError, match=pattern) as info:
            read_fusion_spec(folder / "fusion.json", register=False)
        message = str(info.value)
        assert "\n" not in message, message
        assert str(folder) in message, message
        assert snapshot(tmp_path) == before, pattern


def test_ns_train_with_a_bad_spec_writes_no_run(tmp_path, two_runs):
    a, b = two_runs
    reg = {
        "nerfs": [
            {"name": "a", "config": str(a), "transform": np.eye(4).tolist()},
            {"name": "b", "config": str(b), "transform": [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]},
        ]
    }
    (tmp_path / "reg.json").write_text(json.dumps(reg))
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], registration="reg.json")
    # the trainer config refuses before writing config.yml
    refused_before_writing(spec, tmp_path / "out", r"^nerfuser: .*reg\.json: nerfs\[1\]\.transform: expected a 4x4")
    # and so does the real command
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "ns-train"),
            "nerfuser",
            "--data",
            str(spec),
            "--output-dir",
            str(tmp_path / "out"),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ},
    )
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("nerfuser: ") and "expected a 4x4 (or 3x4) matrix" in last, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------------------------------
# Datamanager


def test_datamanager_poses_test_images_in_the_common_frame(tmp_path, two_runs):
    a, b = two_runs
    registration_file(
        tmp_path / "registration.json",
        [{"config": str(a), "transform": np.eye(4).tolist()}, {"config": str(b), "transform": T_B.tolist()}],
    )
    c2ws = [sim3.make_sim3(np.eye(3), np.array([0.1 * i, 0.0, 2.0]), 1.0) for i in range(3)]
    write_dataset(tmp_path / "test", c2ws)
    world_to_common = sim3.make_sim3(scene_yaw(0.3), np.array([0.5, -0.1, 0.2]), 2.5)
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], test_data="test", test_to_common=world_to_common)
    dm = fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="test")
    assert len(dm.train_dataset) == 3 and len(dm.eval_dataset) == 3
    expected = sim3.transform_poses(world_to_common, np.stack(c2ws))[:, :3, :4]
    np.testing.assert_allclose(dm.eval_dataset.cameras.camera_to_worlds.numpy(), expected, atol=1e-5)
    # camera rotations stay orthonormal (the scale went into the positions only)
    R = dm.eval_dataset.cameras.camera_to_worlds[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-5, rtol=0)
    assert dm.train_dataset.metadata[fspec.METADATA_KEY].nerfs[1].name == "nerf1"
    cams = list(dm.fixed_indices_eval_dataloader)
    assert len(cams) == 3 and cams[2][1]["image"].shape == (6, 8, 3)
    camera, batch = dm.next_eval_image(0)
    assert batch["image"].shape == (6, 8, 3)
    # the scene box holds both NeRFs' [-1, 1] cubes
    aabb = dm.train_dataset.scene_box.aabb
    assert torch.all(aabb[0] <= torch.tensor([-1.0, -1.0, -1.0])) and torch.all(aabb[1] >= torch.tensor(1.0))


def test_export_rays_are_every_nerfs_training_camera_rays_in_the_common_frame(tmp_path):
    """``ns-export pointcloud`` turns the datamanager's "training" rays into points: random rays of every fused NeRF's
    training cameras (the registration file's, else the run's dataset's), in the common frame, the same every run."""
    a_poses = [sim3.make_sim3(scene_yaw(0.3 * i), np.array([0.2 * i, 0.0, 1.5]), 1.0) for i in range(4)]
    a = fake_run(tmp_path / "outputs", "a", write_dataset(tmp_path / "data_a", a_poses))
    b = fake_run(tmp_path / "outputs", "b")  # no dataset: its cameras come from the registration file
    b_c2w = np.stack([sim3.make_sim3(scene_yaw(-0.2 * i), np.array([0.0, 0.3 * i, 2.0]), 1.0) for i in range(3)])
    b_intr = np.array([[5.0, 6.0, 3.0, 2.5, 6, 5]] * 3)
    registration_file(tmp_path / "registration.json", [
        {"config": str(a), "transform": np.eye(4).tolist()},
        {"config": str(b), "transform": T_B.tolist(),
         "training_cameras": {"c2w": b_c2w[:, :3].tolist(), "intrinsics": b_intr.tolist()}}])  # fmt: skip
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], registration="registration.json")

    def rays(n: int) -> tuple:
        dm = fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="inference")
        dm.train_pixel_sampler.num_rays_per_batch = n  # as ns-export sets it
        assert dm.get_train_rays_per_batch() == n
        return dm.next_train(0)

    bundle, batch = rays(600)
    assert bundle.shape == (600,) and batch["indices"].shape == (600, 3)
    a_cams = runs.training_cameras(a)  # run a's dataset, in its NeRF frame (the common frame: identity)
    a_c2w = a_cams.camera_to_worlds.double().numpy()
    cam_c2w = np.concatenate([a_c2w, sim3.transform_poses(T_B, b_c2w)[:, :3]])  # scale 0.4 into the positions
    a_intr = torch.cat([a_cams.fx, a_cams.fy, a_cams.cx, a_cams.cy, a_cams.width, a_cams.height], -1).double().numpy()
    intr = np.concatenate([a_intr, b_intr])
    cam, row, col = (batch["indices"][:, i].numpy() for i in range(3))
    assert set(np.unique(cam)) == set(range(7))  # every camera of both NeRFs
    o, d = bundle.origins.double().numpy(), bundle.directions.double().numpy()
    np.testing.assert_allclose(o, cam_c2w[cam, :, 3], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    # each ray passes through the pixel it names, in the camera it names (OpenGL axes: the camera looks along -z)
    p = np.einsum("nji,nj->ni", cam_c2w[cam, :, :3], d)
    fx, fy, cx, cy = (intr[cam, i] for i in range(4))
    u, v = cx + fx * p[:, 0] / -p[:, 2], cy - fy * p[:, 1] / -p[:, 2]
    assert (p[:, 2] < 0).all()
    np.testing.assert_array_equal(np.floor(u + 1e-4), col)  # the drawn point lies inside the named pixel
    np.testing.assert_array_equal(np.floor(v + 1e-4), row)
    assert (col < intr[cam, 4]).all() and (row < intr[cam, 5]).all()
    again, _ = rays(600)  # seeded once per datamanager: the same rays
    torch.testing.assert_close(again.directions, bundle.directions)


def test_export_cameras_name_the_nerfs_without_any_and_refuse_when_none_has(tmp_path):
    a_poses = [sim3.make_sim3(scene_yaw(0.3 * i), np.array([0.2 * i, 0.0, 1.5]), 1.0) for i in range(3)]
    a = fake_run(tmp_path / "outputs", "a", write_dataset(tmp_path / "data_a", a_poses))
    gone = fake_run(tmp_path / "outputs", "gone", tmp_path / "no_such_dataset")
    also_gone = fake_run(tmp_path / "outputs", "also_gone", tmp_path / "no_such_dataset")
    entries = [{"name": n, "config": str(c), "transform": np.eye(4).tolist()} for n, c in (("a", a), ("g", gone))]
    registration_file(tmp_path / "registration.json", entries)
    spec = read_fusion_spec(fspec.write_fusion_spec(tmp_path / "fusion.json", [a, gone], "registration.json"))
    cameras, missing = fdata.export_cameras(spec)
    assert len(cameras) == 3 and missing == ["g"]
    entries = [{"name": n, "config": str(c), "transform": np.eye(4).tolist()} for n, c in (("g", gone),
                                                                                            ("h", also_gone))]
    registration_file(tmp_path / "none.json", entries)
    spec = read_fusion_spec(fspec.write_fusion_spec(tmp_path / "none_fusion.json", [gone, also_gone], "none.json"))
    with pytest.raises(FusionSpecError, match="no fused NeRF has training cameras") as e:
        fdata.export_cameras(spec)
    assert "\n" not in str(e.value)


def test_ns_train_nerfuser_refuses_iterations_before_writing(tmp_path, two_runs):
    a, b = two_runs
    registration_file(tmp_path / "registration.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                       {"config": str(b), "transform": T_B.tolist()}])  # fmt: skip
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], registration="registration.json")
    config = nerfuser_config()
    config.data, config.output_dir, config.max_num_iterations = spec, tmp_path / "out", 5
    config.set_timestamp()
    with pytest.raises(SystemExit, match="nothing to train .* not 5"):
        config.save_config()
    assert not (tmp_path / "out").exists()


def test_test_images_with_applied_transform_keep_their_stored_poses(tmp_path, two_runs):
    """A test capture made by ns-process-data carries applied_transform / applied_scale: its stored poses are what
    test_to_common maps, and nerfstudio's report of those keys must not move them again."""
    a, b = two_runs
    registration_file(tmp_path / "registration.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                       {"config": str(b), "transform": T_B.tolist()}])  # fmt: skip
    c2ws = [sim3.make_sim3(scene_yaw(0.4 * i), np.array([0.1 * i, 0.3, 2.0]), 1.0) for i in range(3)]
    write_dataset(tmp_path / "test", c2ws)
    meta = json.loads((tmp_path / "test" / "transforms.json").read_text())
    meta.update(applied_transform=[[0, 1, 0, 0.5], [1, 0, 0, 0], [0, 0, -1, 0.2]], applied_scale=3.0)
    (tmp_path / "test" / "transforms.json").write_text(json.dumps(meta))
    test_to_common = sim3.make_sim3(scene_yaw(-0.2), np.array([0.3, 0.1, -0.4]), 0.7)
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], test_data="test", test_to_common=test_to_common)
    dm = fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="test")
    expected = sim3.transform_poses(test_to_common, np.stack(c2ws))[:, :3, :4]
    np.testing.assert_allclose(dm.eval_dataset.cameras.camera_to_worlds.numpy(), expected, atol=1e-5)


def spec_with_test_run(tmp_path: Path) -> tuple[Path, Path, Path, Path]:
    """A spec fusing run a (no dataset) and run b (20 views of a dataset as ns-process-data writes it, registered
    under T_B) whose test images are b's held-out ones; returns the spec, b's dataset and the two configs."""
    eyes = np.array([[3 * np.cos(t), 3 * np.sin(t), 1.0 + 0.1 * np.sin(3 * t)] for t in np.linspace(0, 5, 20)])
    data, _ = process_data_like_dataset(tmp_path / "data_b", sampling.look_at(eyes, np.zeros(3)), 2.5)
    a, b = fake_run(tmp_path / "outputs", "a"), with_checkpoint(run_on(tmp_path / "outputs", data, name="b"))
    registration_file(tmp_path / "registration.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                       {"config": str(b), "transform": T_B.tolist()}])  # fmt: skip
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b], names=["a", "b"], test_run="b")
    return spec, data, a, b


def test_test_run_scores_the_runs_held_out_images_in_the_common_frame(tmp_path):
    """``test_run``: the images run b kept out of its training, posed as its NeRF saw them and moved by its registered
    transform. The same images given the other way (test_data, with test_to_common = T_b @ data_to_nerf of b, from a
    dataset that carries applied_transform / applied_scale) land on the same poses."""
    spec, data, a, b = spec_with_test_run(tmp_path)
    dm = fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="test")
    held = dm.eval_dataset
    train_names = {p.name for p in runs.training_views(b).image_filenames}
    held_names = [p.name for p in held.image_filenames]
    # nerfstudio's default split keeps 2 of 20 images out of training: those, and none of the others
    assert len(held_names) == 2 and not set(held_names) & train_names and len(train_names) == 18
    other = fspec.write_fusion_spec(tmp_path / "other.json", [a, b], names=["a", "b"], test_data="data_b",
                                    test_to_common=T_B @ runs.read_dataparser_transform(b))  # fmt: skip
    every = fdata.NerfuserDataManagerConfig(data=other).setup(device="cpu", test_mode="test").eval_dataset
    pick = [[p.name for p in every.image_filenames].index(n) for n in held_names]
    np.testing.assert_allclose(held.cameras.camera_to_worlds.numpy(), every.cameras.camera_to_worlds[pick].numpy(),
                               atol=1e-5)  # fmt: skip
    assert [c[1]["image"].shape for c in dm.fixed_indices_eval_dataloader] == [(6, 8, 3)] * 2
    # the spec ns-nerfuser-register --fusion-spec writes: no runs (the registration file's), the run by its name
    name = read_registered_nerfs(tmp_path / "registration.json")[1].name
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({"registration": "registration.json", "test_run": name}))
    same = fdata.NerfuserDataManagerConfig(data=bare).setup(device="cpu", test_mode="test").eval_dataset
    assert [p.name for p in same.image_filenames] == held_names
    np.testing.assert_allclose(same.cameras.camera_to_worlds.numpy(), held.cameras.camera_to_worlds.numpy())


def test_a_test_run_whose_dataset_is_gone_is_one_line_before_ns_train_writes(tmp_path):
    spec, data, _, _ = spec_with_test_run(tmp_path)
    data.rename(tmp_path / "moved")
    with pytest.raises(FusionSpecError, match=r"fusion.json: test_run 'b': .*data_b is missing; put it back") as info:
        fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="test")
    assert "\n" not in str(info.value)
    refused_before_writing(spec, tmp_path / "out", r"^nerfuser: .*test_run 'b': .*is missing")


def test_datamanager_without_test_images(tmp_path, two_runs):
    registration_file(
        tmp_path / "registration.json",
        [
            {"config": str(two_runs[0]), "transform": np.eye(4).tolist()},
            {"config": str(two_runs[1]), "transform": T_B.tolist()},
        ],
    )
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", list(two_runs))
    dm = fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="inference")
    assert dm.eval_dataset is None
    assert len(dm.train_dataset) == 2  # placeholder cameras at the NeRF origins, for the viewer
    np.testing.assert_allclose(dm.train_dataset.cameras.camera_to_worlds[1, :, 3].numpy(), T_B[:3, 3], atol=1e-6)
    assert dm.train_dataset[1]["image"].shape == (48, 64, 3)
    with pytest.raises(RuntimeError, match="has no test images; add 'test_data'"):
        dm.fixed_indices_eval_dataloader  # noqa: B018
    # nothing to start ns-render spiral from (the runs' datasets are gone): one line naming what to use instead
    with pytest.raises(SystemExit, match=r"fusion.json: no cameras to render a spiral .*ns-render camera-path"):
        dm.eval_dataloader  # noqa: B018


def test_without_test_images_every_nerfs_training_cameras_are_rendered(tmp_path):
    """ns-render spiral/interpolate/dataset and ns-export tsdf need cameras: every fused NeRF's training cameras
    (the registration file's, else the run's dataset's), in the common frame, in the spec's order."""
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager

    from nerfuser_ns.runs import training_cameras, training_views

    ring = [sim3.make_sim3(scene_yaw(0.5 * i), np.array([2 * np.sin(0.5 * i), 0.3 * i, 2.0]), 1.0) for i in range(5)]
    a = fake_run(tmp_path / "outputs", "a", data=write_dataset(tmp_path / "capture_a", ring))
    b = fake_run(tmp_path / "outputs", "b")  # its dataset is gone
    T_A = sim3.make_sim3(scene_yaw(0.3), np.array([0.5, -0.1, 0.2]), 1.5)
    b_c2w = np.stack([sim3.make_sim3(scene_yaw(-0.2 * i), np.array([0.0, 0.3 * i, 2.0]), 1.0) for i in range(3)])
    b_cameras = {"c2w": b_c2w[:, :3].tolist(), "intrinsics": [[5.0, 6.0, 3.0, 2.5, 6, 5]] * 3}
    own = training_cameras(a)
    views = training_views(a)  # the same cameras, with the images they belong to in the same order
    assert torch.equal(views.cameras.camera_to_worlds, own.camera_to_worlds)
    assert [Path(f).name for f in views.image_filenames] == [f"f{i}.png" for i in range(5)]
    a_expected = sim3.transform_poses(T_A, own.camera_to_worlds.double().numpy())

    def datamanager(b_entry: dict) -> fdata.NerfuserDataManager:
        registration_file(tmp_path / "registration.json", [{"config": str(b), "transform": T_B.tolist(), **b_entry},
                                                           {"config": str(a), "transform": T_A.tolist()}])  # fmt: skip
        spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [b, a])
        return fdata.NerfuserDataManagerConfig(data=spec).setup(device="cpu", test_mode="test")

    # the first NeRF has neither a dataset nor recorded cameras: the other's cameras alone
    dm = datamanager({})
    assert isinstance(dm, VanillaDataManager)  # ns-render spiral asserts it
    assert len(dm.train_dataset) == len(own) == 5 and dm.eval_dataset is dm.train_dataset
    np.testing.assert_allclose(dm.train_dataset.cameras.camera_to_worlds.numpy(), a_expected, atol=1e-5)
    torch.testing.assert_close(dm.train_dataset.cameras.fx, own.fx)
    # with its training cameras in the registration file, both NeRFs' cameras, the first NeRF's first (named as the
    # spec names them)
    dm = datamanager({"training_cameras": b_cameras})
    b_expected = sim3.transform_poses(T_B, b_c2w)[:, :3]
    np.testing.assert_allclose(dm.train_dataset.cameras.camera_to_worlds.numpy(),
                               np.concatenate([b_expected, a_expected]), atol=1e-5)  # fmt: skip
    names = [f.as_posix() for f in dm.train_dataset.image_filenames]
    assert names[2:4] == ["<nerf0>/train_00002", "<nerf1>/train_00000"]
    assert dm.train_dataset.cameras.width[:, 0].tolist() == [6] * 3 + [8] * 5
    camera, batch = dm.eval_dataloader.get_camera(image_idx=3)
    np.testing.assert_allclose(camera.camera_to_worlds[0].numpy(), a_expected[0], atol=1e-5)
    assert batch["image"].shape == (6, 8, 3)  # no image: a grey stand-in
    # they are not test images: ns-eval still refuses
    with pytest.raises(RuntimeError, match="has no test images; add 'test_data'"):
        dm.fixed_indices_eval_dataloader  # noqa: B018
    with pytest.raises(RuntimeError, match="no test images"):
        dm.next_eval_image(0)


def scene_yaw(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_a_run_retrained_after_registration_is_refused(tmp_path, two_runs):
    from nerfuser_ns.runs import checkpoint_identity

    a, b = two_runs
    entries = [{"config": str(a), "transform": np.eye(4).tolist(), "checkpoint": checkpoint_identity(a)},
               {"config": str(b), "transform": T_B.tolist(), "checkpoint": checkpoint_identity(b)}]  # fmt: skip
    reg = registration_file(tmp_path / "registration.json", entries)
    assert [e.name for e in read_registered_nerfs(reg)] == ["nerf0", "nerf1"]
    assert entries[1]["checkpoint"]["step"] == 9 and len(entries[1]["checkpoint"]["sha256"]) == 64
    # b trained further: a newer checkpoint
    (b.parent / "nerfstudio_models" / "step-000000019.ckpt").write_bytes(b"other weights")
    with pytest.raises(FusionSpecError, match=r"changed since it was registered \(registered step 9, now step 19"):
        read_registered_nerfs(reg)
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b])
    with pytest.raises(FusionSpecError, match="re-run ns-nerfuser-register"):
        read_fusion_spec(spec, register=False)
    # same step, other content (a checkpoint overwritten in place) is refused too
    (b.parent / "nerfstudio_models" / "step-000000019.ckpt").unlink()
    (b.parent / "nerfstudio_models" / "step-000000009.ckpt").write_bytes(b"overwritten")
    with pytest.raises(FusionSpecError, match="registered step 9, now step 9"):
        read_registered_nerfs(reg)
    # hand-written registrations without the record still load
    registration_file(reg, [{k: v for k, v in e.items() if k != "checkpoint"} for e in entries])
    assert len(read_registered_nerfs(reg)) == 2


@pytest.mark.parametrize(
    ("settings", "env", "message"),
    [
        ({"gamma": -1.0}, {}, "gamma must be >= 0, got -1.0"),
        ({"gamma": float("nan")}, {}, "gamma must be >= 0, got nan"),
        ({"tau": 0.5}, {}, "tau must be >= 1"),
        ({}, {"NERFUSER_TAU": "banana"}, "NERFUSER_TAU must be a number, got 'banana'"),
        ({}, {"NERFUSER_BLEND_METHOD": "idw-4d"}, "unknown blend method 'idw-4d'"),
    ],
)
def test_ns_train_with_bad_blend_settings_writes_no_run(tmp_path, two_runs, monkeypatch, settings, env, message):
    a, b = two_runs
    registration_file(tmp_path / "registration.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                       {"config": str(b), "transform": T_B.tolist()}])  # fmt: skip
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b])
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    refused_before_writing(spec, tmp_path / "out", r"^nerfuser: " + message.replace("(", r"\("), **settings)


def test_a_failed_automatic_registration_leaves_no_run(tmp_path, two_runs, monkeypatch):
    a, b = two_runs

    def fail(*args, **kwargs):
        raise FusionSpecError("registration.json: automatic registration failed: no overlap (run ns-nerfuser-register)")

    monkeypatch.setattr(fspec, "run_registration", fail)
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, b])
    refused_before_writing(spec, tmp_path / "out", "^nerfuser: registration.json: automatic registration failed")


def test_the_automatic_registration_says_what_it_runs_before_it_starts(tmp_path, two_runs, monkeypatch, capsys):
    a, b = two_runs
    calls = []

    def register_runs(config_paths, output, config=None, names=None, device="cpu"):
        calls.append(capsys.readouterr().out)  # what was printed before the work started
        entries = [NerfEntry(n, Path(c), np.eye(4)) for n, c in zip(names, config_paths, strict=True)]
        registration.write_minimal_registration(entries, output)

    monkeypatch.setattr(fspec.registration, "register_runs", register_runs)
    folder = tmp_path / "fused[v2]"  # printed as written, not read as console markup
    folder.mkdir()
    spec = read_fusion_spec(fspec.write_fusion_spec(folder / "fusion.json", [a, b]))
    assert len(calls) == 1 and len(spec.nerfs) == 2
    said = "".join(calls[0].split())  # the console wraps long lines anywhere
    assert f"noregistrationfileat{folder / 'registration.json'}".replace(" ", "") in said
    said = " ".join(calls[0].split())
    assert "registering 2 runs now" in said
    assert "pose source auto" in said and "estimator nerfuser" in said and "device" in said


@pytest.mark.parametrize("method", ["splatfacto", "instant-ngp"])
def test_ns_train_nerfuser_names_a_run_whose_samples_cannot_be_merged_before_writing(tmp_path, method):
    """A splatfacto or instant-ngp run beside a nerfacto one registers, but its samples cannot be blended: ns-train
    nerfuser says which run and why in one line before the run folder exists (not a traceback after it)."""
    from nerfstudio.configs.method_configs import method_configs

    a = fake_run(tmp_path / "outputs", "a")
    other = fake_run(tmp_path / "outputs", "other")
    config = method_configs[method]
    config.experiment_name, config.timestamp, config.output_dir = "other", "run", tmp_path / "outputs"
    other.write_text(yaml.dump(config))
    registration_file(tmp_path / "registration.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                       {"config": str(other), "transform": T_B.tolist()}])  # fmt: skip
    spec = fspec.write_fusion_spec(tmp_path / "fusion.json", [a, other], registration="registration.json")
    model = config.pipeline.model._target.__name__
    refused_before_writing(spec, tmp_path / "out", rf"^nerfuser: run 'nerf1' was trained with {method} \({model}\)")
    if method == "splatfacto":  # the viewer checks the same before loading any run
        proc = subprocess.run([str(Path(sys.executable).parent / "ns-nerfuser-view"), str(spec), "--device", "cpu"],
                              capture_output=True, text=True, timeout=300, cwd=tmp_path)  # fmt: skip
        assert proc.returncode == 1, proc.stderr[-2000:]
        assert "run 'nerf1' was trained with splatfacto" in proc.stderr and "Traceback" not in proc.stderr
    # the nerfacto family passes the same check
    ok_spec = fspec.write_fusion_spec(tmp_path / "ok.json", [a, a], registration="registration_ok.json")
    registration_file(tmp_path / "registration_ok.json", [{"config": str(a), "transform": np.eye(4).tolist()},
                                                          {"config": str(a), "transform": T_B.tolist()}])  # fmt: skip
    trainer = nerfuser_config()
    trainer.data, trainer.output_dir = ok_spec, tmp_path / "ok_out"
    trainer.set_timestamp()
    trainer.save_config()
    assert (tmp_path / "ok_out").is_dir()
