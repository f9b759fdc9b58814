"""Tests for the ground-truth scene generator (nerfuser_ns.scenes): small images and few views to stay fast."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nerfuser_ns import sim3
from nerfuser_ns.bench import scenes as S
from nerfuser_ns.cameras import camera_rays

SMALL = dict(num_views=6, num_test_views=3, width=48, height=36, texels_per_metre=32.0)


@pytest.fixture(scope="module")
def room() -> S.SceneLayout:
    return S.make_layout("object-centric", seed=0, **SMALL)


@pytest.fixture(scope="module")
def room_dir(room: S.SceneLayout, tmp_path_factory) -> Path:
    return S.write_scene(room, tmp_path_factory.mktemp("scene") / "object-centric")


@pytest.fixture(scope="module")
def street() -> S.SceneLayout:
    return S.make_layout("street", seed=0, num_views=8, num_test_views=2, width=32, height=24, texels_per_metre=8.0)


@pytest.fixture(scope="module")
def drive() -> S.SceneLayout:
    return S.make_layout("drive", seed=0, num_views=32, num_test_views=6, width=32, height=24, texels_per_metre=8.0)


@pytest.fixture(scope="module")
def repeated_room() -> S.SceneLayout:
    return S.make_layout("room", seed=0, **SMALL)


def _file_digests(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# --------------------------------------------------------------------------------------------------------------
# Ground truth consistency
# --------------------------------------------------------------------------------------------------------------


def test_capture_frame_pose_maps_to_same_render(room: S.SceneLayout):
    """A view posed in the capture frame and mapped through capture_to_world renders exactly the world view."""
    for cap in room.captures:
        T = cap.capture_to_world
        s = float(sim3.decompose_sim3(T)[2])
        for i in (0, 3):
            world = S.render(room.scene, cap.c2w_world[i], cap.intrinsics)
            mapped_pose = sim3.transform_poses(T, cap.c2w_capture[i])
            mapped = S.render(room.scene, mapped_pose, cap.intrinsics)
            torch.testing.assert_close(mapped.rgb, world.rgb, atol=1e-5, rtol=0)
            assert torch.equal(mapped.mask, world.mask)
            # Depth in capture units (world / s) scaled back by s is the world depth.
            torch.testing.assert_close((mapped.depth / s) * s, world.depth, atol=1e-9, rtol=1e-9)
            # Same ray in the capture frame: its hit point maps to the world hit point.
            o, d = camera_rays(cap.c2w_capture[i], cap.intrinsics)
            p_cap = (o + (world.depth / s)[..., None, None] * d)[:, :, 0][world.mask].numpy()
            p_world = (p_cap * s) @ sim3.decompose_sim3(T)[0].T + T[:3, 3]
            o_w, d_w = camera_rays(cap.c2w_world[i], cap.intrinsics)
            expected = (o_w + world.depth[..., None, None] * d_w)[:, :, 0][world.mask].numpy()
            np.testing.assert_allclose(p_world, expected, atol=1e-9)


def test_capture_frame_normalisation(room: S.SceneLayout):
    for cap in room.captures:
        centres = cap.c2w_capture[:, :3, 3]
        np.testing.assert_allclose(centres.mean(0), 0.0, atol=1e-12)
        assert np.linalg.norm(centres, axis=-1).mean() == pytest.approx(1.0, abs=1e-12)
        R, t, s = sim3.decompose_sim3(cap.capture_to_world)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-12)  # yaw only: +z stays up
        assert np.linalg.det(R) == pytest.approx(1.0)
        # Camera rotations stay orthonormal in the capture frame.
        Rc = cap.c2w_capture[:, :3, :3]
        np.testing.assert_allclose(Rc @ np.swapaxes(Rc, 1, 2), np.broadcast_to(np.eye(3), Rc.shape), atol=1e-12)


def test_render_rays_matches_render(room: S.SceneLayout):
    cap = room.test
    out = S.render(room.scene, cap.c2w_world[0], cap.intrinsics, supersample=1)
    o, d = camera_rays(cap.c2w_world[0], cap.intrinsics)
    hits = S.render_rays(room.scene, o[:, :, 0], 3.0 * d[:, :, 0])  # non-unit directions: depth is the ray parameter
    torch.testing.assert_close(hits.rgb, out.rgb)
    torch.testing.assert_close(hits.depth * 3.0, out.depth)
    # Ray distance vs z-depth.
    z = S.ray_to_z_depth(out.depth, cap.intrinsics)
    cam = (o + out.depth[..., None, None] * d)[:, :, 0] - o[:, :, 0]
    z_expected = -(cam @ torch.as_tensor(cap.c2w_world[0][:3, :3]))[..., 2]
    torch.testing.assert_close(z, z_expected)


# --------------------------------------------------------------------------------------------------------------
# Dataset writer
# --------------------------------------------------------------------------------------------------------------


def test_dataset_roundtrip(room: S.SceneLayout, room_dir: Path):
    gt = json.loads((room_dir / "ground_truth.json").read_text())
    assert gt["format_version"] == S.FORMAT_VERSION and gt["layout"] == "object-centric" and gt["seed"] == 0
    assert [c["name"] for c in gt["captures"]] == ["capture_a", "capture_b"]
    assert gt["test"]["path"] == "test"
    for cap_gt, cap in zip(gt["captures"], room.captures, strict=True):
        T = np.array(cap_gt["capture_to_world"])
        np.testing.assert_allclose(
            T, sim3.make_sim3(cap_gt["rotation"], cap_gt["translation"], cap_gt["scale"]), atol=1e-11
        )
        tf = json.loads((room_dir / cap_gt["path"] / "transforms.json").read_text())
        assert tf["camera_model"] == "OPENCV" and (tf["w"], tf["h"]) == (48, 36)
        assert tf["depth_unit_scale_factor"] == 0.001
        poses = np.array([f["transform_matrix"] for f in tf["frames"]])
        np.testing.assert_allclose(sim3.transform_poses(T, poses), cap.c2w_world, atol=1e-9)
        for i in (0, len(tf["frames"]) - 1):
            frame = tf["frames"][i]
            out = S.render(room.scene, cap.c2w_world[i], cap.intrinsics)
            img = np.asarray(Image.open(room_dir / cap_gt["path"] / frame["file_path"]))
            np.testing.assert_array_equal(img, S.to_uint8(out.rgb))
            # Depth PNG: z-depth in capture units x 1000; times the capture scale it is the world z-depth.
            depth = np.asarray(Image.open(room_dir / cap_gt["path"] / frame["depth_file_path"])).astype(np.float64)
            z_world = S.ray_to_z_depth(out.depth, cap.intrinsics).numpy()
            np.testing.assert_allclose(depth * 0.001 * cap_gt["scale"], z_world, atol=0.0006 * cap_gt["scale"])
    # The test capture is posed in the world frame.
    tf = json.loads((room_dir / "test" / "transforms.json").read_text())
    np.testing.assert_allclose(np.array([f["transform_matrix"] for f in tf["frames"]]), room.test.c2w_world, atol=1e-9)
    # The layout can be regenerated from ground_truth.json alone.
    again = S.layout_from_ground_truth(room_dir)
    np.testing.assert_array_equal(again.captures[1].c2w_world, room.captures[1].c2w_world)


def test_write_is_deterministic_and_replaces_atomically(room: S.SceneLayout, room_dir: Path, tmp_path: Path):
    other = S.write_scene(S.make_layout("object-centric", seed=0, **SMALL), tmp_path / "again")
    assert _file_digests(other) == _file_digests(room_dir)
    S.write_scene(room, other)  # re-run over an existing scene
    assert _file_digests(other) == _file_digests(room_dir)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]  # no temporary folders left behind


def test_write_refuses_foreign_folder(room: S.SceneLayout, tmp_path: Path):
    (tmp_path / "precious.txt").write_text("keep me")
    with pytest.raises(ValueError, match="refusing"):
        S.write_scene(room, tmp_path)
    assert (tmp_path / "precious.txt").read_text() == "keep me"


# --------------------------------------------------------------------------------------------------------------
# Determinism, overlap, texture
# --------------------------------------------------------------------------------------------------------------


def test_seed_determinism(room: S.SceneLayout):
    same = S.make_layout("object-centric", seed=0, **SMALL)
    assert torch.equal(same.scene.texture_atlas, room.scene.texture_atlas)
    for a, b in zip(same.captures + [same.test], room.captures + [room.test], strict=True):
        np.testing.assert_array_equal(a.c2w_world, b.c2w_world)
        np.testing.assert_array_equal(a.capture_to_world, b.capture_to_world)
    other = S.make_layout("object-centric", seed=1, **SMALL)
    assert not np.allclose(other.captures[0].c2w_world, room.captures[0].c2w_world)
    assert not np.allclose(other.captures[0].capture_to_world, room.captures[0].capture_to_world)


def test_object_centric_captures_overlap():
    lay = S.make_layout(
        "object-centric", seed=0, num_views=12, num_test_views=4, width=40, height=30, texels_per_metre=16.0
    )
    ids = {name: lay.scene.object_index(name) for name in ("object1", "object2")}

    def fraction_seeing(cap, obj):
        seen = [
            (S.render(lay.scene, c2w, cap.intrinsics, supersample=1).object_id == ids[obj]).float().mean()
            for c2w in cap.c2w_world
        ]
        return torch.stack(seen)

    a_sees_1, a_sees_2 = fraction_seeing(lay.captures[0], "object1"), fraction_seeing(lay.captures[0], "object2")
    b_sees_1, b_sees_2 = fraction_seeing(lay.captures[1], "object1"), fraction_seeing(lay.captures[1], "object2")
    assert (a_sees_1 > 0.05).all() and (b_sees_2 > 0.05).all()  # every view shows its own object
    assert (a_sees_2 > 0.005).sum() >= 2 and (b_sees_1 > 0.005).sum() >= 2  # and some show the other one
    test_sees = fraction_seeing(lay.test, "object1") + fraction_seeing(lay.test, "object2")
    assert (test_sees > 0.01).all()


def _surface_points(lay: S.SceneLayout, cap: S.Capture, stride: int = 4) -> np.ndarray:
    pts = []
    for c2w in cap.c2w_world:
        out = S.render(lay.scene, c2w, cap.intrinsics, supersample=1)
        o, d = camera_rays(c2w, cap.intrinsics)
        p = (o + out.depth[..., None, None] * d)[::stride, ::stride, 0][out.mask[::stride, ::stride]]
        pts.append(p.numpy())
    return np.concatenate(pts)


def test_street_neighbouring_captures_overlap(street: S.SceneLayout):
    assert len(street.captures) == 3
    for a, b in zip(street.captures[:-1], street.captures[1:], strict=True):
        seen = S.visibility(street.scene, _surface_points(street, a), b.c2w_world, b.intrinsics)
        assert seen.any(dim=1).float().mean() > 0.2
    # Test views lie between the capture centres (along the street).
    xs = [cap.capture_to_world[0, 3] for cap in street.captures]
    tx = street.test.c2w_world[:, 0, 3]
    assert ((tx > min(xs)) & (tx < max(xs))).all()


def test_drive_is_a_surround_rig_along_the_lane(drive: S.SceneLayout):
    rig = S.DRIVE_RIG_CAMERAS
    for cap in drive.captures:
        centres = cap.c2w_world[:, :3, 3].reshape(-1, rig, 3)  # stop-major: one exposure of the rig per stop
        assert np.allclose(centres, centres[:, :1])  # the rig's cameras share the car's position
        assert np.all(np.abs(centres[..., 1] + 1.2) < 0.3) and np.all(np.abs(centres[..., 2] - 1.9) < 0.1)
        assert np.all(np.diff(centres[:, 0, 0]) > 0.3)  # driving along +x, about one step per stop
        forward = -cap.c2w_world[:, :3, 2].reshape(-1, rig, 3)
        yaw = np.arctan2(forward[..., 1], forward[..., 0])
        turn = np.exp(1j * (yaw - yaw[:, :1]))  # relative yaw as a unit complex number: no wrap-around at pi
        expected = np.exp(1j * 2 * np.pi * np.arange(rig) / rig)
        assert np.allclose(turn, expected, atol=1e-6)  # looking all around, one camera every 360 / rig deg
        assert np.all(np.abs(forward[..., 2]) < 0.2)  # level cameras


def test_drive_test_views_are_side_cameras_between_blocks(drive: S.SceneLayout):
    blocks = [(cap.c2w_world[:, 0, 3].min(), cap.c2w_world[:, 0, 3].max()) for cap in drive.captures]
    for (_, hi), (lo, _) in zip(blocks[:-1], blocks[1:], strict=True):
        assert lo - hi > S.DRIVE_STEP_M  # a left-out stop between neighbouring blocks
    tx = drive.test.c2w_world[:, 0, 3]
    in_gap = np.zeros(len(tx), dtype=bool)
    for (_, hi), (lo, _) in zip(blocks[:-1], blocks[1:], strict=True):
        in_gap |= (tx > hi + 0.2) & (tx < lo - 0.2)
        assert ((tx > hi) & (tx < lo)).sum() == len(tx) // (len(blocks) - 1)  # every gap gets its share
    assert in_gap.all()
    forward = -drive.test.c2w_world[:, :3, 2]
    assert np.all(np.abs(forward[:, 1]) > 0.95)  # side view
    assert (forward[:, 1] > 0).any() and (forward[:, 1] < 0).any()  # both sides
    # Neighbouring blocks see common ground: what one sees, the other sees too.
    for a, b in zip(drive.captures[:-1], drive.captures[1:], strict=True):
        seen = S.visibility(drive.scene, _surface_points(drive, a, stride=6), b.c2w_world, b.intrinsics)
        assert seen.any(dim=1).float().mean() > 0.2


def test_drive_shares_the_street(street: S.SceneLayout):
    # The benchmark's drive: 12 stops per block and 2 left out, so blocks 7 m apart as the street's captures are.
    params = S.benchmark_params("drive", 0) | dict(num_test_views=2, width=32, height=24, texels_per_metre=8.0)
    assert params["num_views"] == 12 * S.DRIVE_RIG_CAMERAS and params["num_captures"] == 3
    drive = S.make_layout("drive", **params)
    assert drive.scene.part_bounds == street.scene.part_bounds
    assert np.allclose(drive.test.c2w_world[:, 0, 3], [-3.5, 3.5], atol=0.4)  # between the 7 m apart blocks


def test_visibility_detects_occlusion(room: S.SceneLayout):
    cap = room.test
    lo, hi = (np.asarray(v) for v in room.scene.object_bounds["object2"])
    centre_inside = (lo + hi) / 2  # inside the sphere/pedestal: hidden from every camera
    surface = _surface_points(room, cap, stride=8)[:5]
    vis = S.visibility(room.scene, np.vstack([centre_inside, surface]), cap.c2w_world, cap.intrinsics)
    assert not vis[0].any()
    assert vis[1:].any(dim=1).all()


def test_images_are_textured(
    room: S.SceneLayout, street: S.SceneLayout, drive: S.SceneLayout, repeated_room: S.SceneLayout
):
    for lay in (room, street, drive, repeated_room):
        for cap in lay.captures + [lay.test]:
            for c2w in cap.c2w_world[:3]:
                out = S.render(lay.scene, c2w, cap.intrinsics)
                assert out.mask.float().mean() > 0.99  # nothing empty: the scenes are enclosed
                grey = out.rgb.mean(-1)
                assert grey.std() > 0.05
                grad = (grey[1:, :-1] - grey[:-1, :-1]).abs() + (grey[:-1, 1:] - grey[:-1, :-1]).abs()
                assert grad.mean() > 0.03
                assert (grad > 0.02).float().mean() > 0.3  # texture everywhere, not only at a few edges


# --------------------------------------------------------------------------------------------------------------
# The room: repeated structure, symmetric under a half turn about its vertical axis but for its door
# --------------------------------------------------------------------------------------------------------------

HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])  # (x, y, z) -> (-x, -y, z): 180 degrees about the room's vertical axis


def test_half_turn_symmetric_texture():
    tex = np.random.default_rng(0).random((7, 5, 3))
    out = S.half_turn_symmetric(tex)
    np.testing.assert_array_equal(out, out[::-1, ::-1])
    np.testing.assert_array_equal(out[:3], tex[:3])  # the first half is kept
    np.testing.assert_array_equal(out[3, :2], tex[3, :2])


def test_room_writes_and_regenerates(repeated_room: S.SceneLayout, tmp_path: Path):
    out = S.write_scene(repeated_room, tmp_path / "room")
    gt = json.loads((out / "ground_truth.json").read_text())
    assert gt["layout"] == "room" and gt["params"]["symmetric"] is False
    assert [c["name"] for c in gt["captures"]] == ["capture_a", "capture_b"]
    assert gt["render"]["light_dir"] == [0.0, 0.0, 1.0]  # light from straight above: shading keeps the symmetry
    assert set(gt["objects"]) == {"room", "shelves", "pillars", "crates", "door"}
    for cap in gt["captures"]:
        assert len(list((out / cap["path"] / "images").iterdir())) == SMALL["num_views"]
    again = S.layout_from_ground_truth(out)
    assert torch.equal(again.scene.texture_atlas, repeated_room.scene.texture_atlas)
    np.testing.assert_array_equal(again.captures[1].c2w_world, repeated_room.captures[1].c2w_world)


def test_room_captures_overlap(repeated_room: S.SceneLayout):
    a, b = repeated_room.captures
    assert (a.c2w_world[:, 0, 3] < 0).all() and (b.c2w_world[:, 0, 3] > 0).all()  # west half, east half
    for one, other in ((a, b), (b, a)):
        seen = S.visibility(repeated_room.scene, _surface_points(repeated_room, one), other.c2w_world,
                            other.intrinsics)
        assert 0.2 < seen.any(dim=1).float().mean() < 0.95  # overlapping, not the same
    assert (np.abs(repeated_room.test.c2w_world[:, 0, 3]) < 0.6).all()  # test views in the middle


def _half_turn_pairs(lay: S.SceneLayout):
    """(render of a view, render of the view turned by 180 degrees about the room's vertical axis) for every view."""
    for cap in lay.captures + [lay.test]:
        for c2w in cap.c2w_world:
            yield (S.render(lay.scene, c2w, cap.intrinsics, supersample=1),
                   S.render(lay.scene, HALF_TURN @ c2w, cap.intrinsics, supersample=1))


def test_symmetric_room_looks_the_same_after_a_half_turn(repeated_room: S.SceneLayout):
    sym = S.make_layout("room", seed=0, symmetric=True, **SMALL)
    assert "door" not in sym.scene.object_names
    # Only the door goes: same cameras, same textures for everything else.
    for c, d in zip(sym.captures + [sym.test], repeated_room.captures + [repeated_room.test], strict=True):
        np.testing.assert_array_equal(c.c2w_world, d.c2w_world)
    n = sym.scene.texture_atlas.shape[0]
    assert torch.equal(sym.scene.texture_atlas, repeated_room.scene.texture_atlas[:n])
    for view, turned in _half_turn_pairs(sym):
        torch.testing.assert_close(turned.rgb, view.rgb, atol=1e-5, rtol=0)
        torch.testing.assert_close(turned.depth, view.depth, atol=1e-9, rtol=1e-9)
        assert torch.equal(turned.object_id, view.object_id)


def test_room_door_breaks_the_symmetry(repeated_room: S.SceneLayout):
    door = repeated_room.scene.object_index("door")
    differs = []
    for view, turned in _half_turn_pairs(repeated_room):
        on_door = (view.object_id == door) | (turned.object_id == door)
        diff = (view.rgb - turned.rgb).abs().amax(-1)
        assert (diff[~on_door] < 1e-5).all()  # everything but the door has its twin
        differs.append(float((diff > 0.1).float().mean()))
    assert max(differs) > 0.02  # some view tells the room from its half turn


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(layout="nowhere"), "unknown layout"),
        (dict(width=-4), "width"),
        (dict(height=0), "height"),
        (dict(num_views=0), "num_views"),
        (dict(seed=-1), "seed"),
        (dict(hfov_deg=500.0), "hfov"),
        (dict(layout="street", num_captures=1), "num_captures"),
        (dict(layout="drive", num_views=12), "multiple of 8"),
        (dict(layout="room", symmetric="yes"), "symmetric"),
        (dict(colour="red"), "unknown layout parameters"),
    ],
)
def test_bad_layout_arguments(kwargs, match):
    kwargs = dict(kwargs)
    with pytest.raises(ValueError, match=match):
        S.make_layout(kwargs.pop("layout", "object-centric"), **kwargs)


def test_bad_render_arguments(room: S.SceneLayout):
    k = room.test.intrinsics
    with pytest.raises(ValueError, match="c2w"):
        S.render(room.scene, np.eye(3), k)
    with pytest.raises(ValueError, match="width"):
        S.render(room.scene, np.eye(4), dataclasses.replace(k, width=0))
    with pytest.raises(ValueError, match="supersample"):
        S.render(room.scene, np.eye(4), k, supersample=0)


def test_script_reports_bad_values(tmp_path: Path):
    script = Path(__file__).resolve().parents[2] / "scripts" / "make_scene.py"
    res = subprocess.run(
        [sys.executable, str(script), "--width", "-5", "--output-dir", str(tmp_path / "x")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2
    assert "width must be an integer" in res.stderr
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------------------------------------------
# Row houses: the street with one house repeated along it
# --------------------------------------------------------------------------------------------------------------


def test_row_houses_repeat_along_the_street():
    lay = S.make_layout("row-houses", seed=0, num_views=8, num_test_views=2, width=32, height=24,
                        texels_per_metre=8.0)  # fmt: skip
    assert lay.layout == "row-houses" and len(lay.captures) == 3
    buildings = lay.scene.object_index("buildings")
    shift = np.eye(4)
    shift[0, 3] = 2 * S.ROW_HOUSE_PERIOD_M  # the distance between neighbouring captures: two houses
    same, differs = [], []
    for c2w in lay.captures[1].c2w_world:
        view = S.render(lay.scene, c2w, lay.captures[1].intrinsics, supersample=1)
        moved = S.render(lay.scene, shift @ c2w, lay.captures[1].intrinsics, supersample=1)
        both = (view.object_id == buildings) & (moved.object_id == buildings)
        twin = both & ((view.depth - moved.depth).abs() < 1e-6)
        diff = (view.rgb - moved.rgb).abs().amax(-1)
        assert (diff[twin] < 1e-5).all()  # the same wall at the same place looks the same two houses along
        same.append(float(twin.sum()) / max(1, int((view.object_id == buildings).sum())))
        differs.append(float((diff > 0.1).float().mean()))
    assert np.median(same) > 0.8  # most of what a view sees of the houses has its twin
    assert max(differs) > 0.02  # the road and the street furniture tell the two places apart
