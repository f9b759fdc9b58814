"""The fused model on tiny CPU-trained nerfacto runs: exactness properties, limits, and the nerfstudio commands."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox

from nerfuser_ns import runs, sim3
from nerfuser_ns.appearance import IDENTITY, apply_colour_map
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.training import train
from nerfuser_ns.blending import BLEND_METHODS, render_samples
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.coverage import CameraIndex
from nerfuser_ns.model import NerfuserModel, NerfuserModelConfig, fuse_models, map_rays
from nerfuser_ns.registration import NerfEntry, write_minimal_registration
from nerfuser_ns.sampling import look_at
from nerfuser_ns.spec import write_fusion_spec

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent
OUTPUTS = ("rgb", "depth", "accumulation")
# A camera in the NeRF's own frame, looking at the scene centre along -z.
C2W = np.array([[1.0, 0, 0, 0.05], [0, 1, 0, -0.02], [0, 0, 1, 0.6], [0, 0, 0, 1]])
INTR = Intrinsics(fx=20, fy=20, cx=10, cy=8, width=20, height=16)
# A SIM(3) far from the identity: scale 3.7, a generic rotation, a translation.
T_FAR = sim3.make_sim3(
    scenes.yaw_rotation(0.7) @ np.array([[1, 0, 0], [0, np.cos(0.4), -np.sin(0.4)], [0, np.sin(0.4), np.cos(0.4)]]),
    np.array([0.4, -1.2, 2.0]),
    3.7,
)


def cams(c2w: np.ndarray):
    return runs.make_cameras(np.asarray(c2w)[None], INTR)


def render(model, c2w: np.ndarray, outputs=OUTPUTS) -> dict[str, torch.Tensor]:
    return runs.render_views(model, cams(c2w), outputs=outputs, progress=False)


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("outputs")
    result = train(
        data=tiny_scene / "capture_a", output_dir=out, experiment_name="tiny", max_num_iterations=60, seed=0, tiny=True
    )
    return runs.load_run(result.config_path)


@pytest.fixture(scope="module")
def ref(trained) -> dict[str, torch.Tensor]:
    """The NeRF's own render (nerfacto's get_outputs_for_camera) from C2W in its frame."""
    return render(trained.model, C2W)


def close(a: torch.Tensor, b: torch.Tensor, atol: float) -> None:
    torch.testing.assert_close(a, b, rtol=0, atol=atol)


# ----------------------------------------------------------------------------------------------------------------------
# Exactness


def test_one_nerf_identity_equals_its_own_render(trained, ref):
    for method in BLEND_METHODS:
        fused = fuse_models([("a", trained.model, np.eye(4))], blend_method=method)
        out = render(fused, C2W, OUTPUTS + ("expected_depth", "share_0", "nerf_share"))
        assert out["rgb"].shape == (1, 16, 20, 3) and out["depth"].shape == (1, 16, 20, 1)
        close(out["rgb"], ref["rgb"], 1e-6)
        close(out["accumulation"], ref["accumulation"], 1e-6)
        close(out["depth"], ref["depth"], 1e-5)
        close(out["share_0"], torch.ones_like(out["share_0"]), 1e-6)


def test_two_identity_copies_equal_the_single_render_for_any_gamma(trained, ref):
    fused = fuse_models([("a", trained.model, np.eye(4)), ("b", trained.model, np.eye(4))])
    for gamma in (0.0, 0.3, 5.0, 80.0, float("inf")):
        for method in BLEND_METHODS:
            fused.gamma, fused.blend_method = gamma, method
            out = render(fused, C2W, OUTPUTS + ("share_0", "share_1"))
            close(out["rgb"], ref["rgb"], 1e-5)
            close(out["accumulation"], ref["accumulation"], 1e-5)
            close(out["depth"], ref["depth"], 1e-4)
            close(out["share_0"] + out["share_1"], torch.ones_like(out["share_0"]), 1e-5)


def test_copy_under_a_far_sim3_renders_like_the_original(trained, ref):
    """NeRF frame -> common frame by T (scale 3.7): the world camera T G S^-1 sees what the original sees from G."""
    fused = fuse_models([("copy", trained.model, T_FAR)])
    world_c2w = sim3.transform_poses(T_FAR, C2W)
    out = render(fused, world_c2w, OUTPUTS + ("expected_depth",))
    close(out["rgb"], ref["rgb"], 2e-4)
    close(out["accumulation"], ref["accumulation"], 2e-4)
    # depths are common-frame lengths: 3.7 x the NeRF's own
    torch.testing.assert_close(out["depth"], 3.7 * ref["depth"], rtol=1e-4, atol=1e-4)


def test_map_rays_scales_distances_and_keeps_points():
    T = torch.tensor(T_FAR, dtype=torch.float32)
    o = torch.tensor([[0.3, -0.2, 1.0], [2.0, 0.5, -1.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.1, 0.2, -1.0], [-1.0, 0.3, 0.2]]), dim=-1)
    bundle = RayBundle(
        origins=o,
        directions=d,
        pixel_area=torch.full((2, 1), 1e-3),
        nears=torch.full((2, 1), 0.5),
        fars=torch.full((2, 1), 4.0),
        camera_indices=torch.tensor([[7], [0]]),
    )
    mapped, k = map_rays(bundle, torch.linalg.inv(T), num_train_data=5)
    torch.testing.assert_close(k, torch.full_like(k, 1 / 3.7))
    t = 1.7
    p_common = o + t * d
    p_nerf = (p_common - T[:3, 3]) @ torch.linalg.inv(T[:3, :3]).T
    torch.testing.assert_close(mapped.origins + (t * k) * mapped.directions, p_nerf, atol=1e-5, rtol=0)
    torch.testing.assert_close(mapped.directions.norm(dim=-1), torch.ones(2))
    torch.testing.assert_close(mapped.nears, 0.5 * k)
    torch.testing.assert_close(mapped.fars, 4.0 * k)
    assert mapped.camera_indices.tolist() == [[4], [0]]  # clamped into the sub-model's range
    torch.testing.assert_close(mapped.pixel_area, bundle.pixel_area)  # a solid angle: similarity-invariant


# ----------------------------------------------------------------------------------------------------------------------
# Blending limits through the model


@pytest.fixture(scope="module")
def pair(trained):
    """NeRF A at the identity; B: A with its colour head perturbed (another NeRF), moved by a small translation."""
    model_b = copy.deepcopy(trained.model)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in model_b.field.mlp_head.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=gen))
    T_b = sim3.make_sim3(np.eye(3), np.array([0.25, 0.0, 0.0]), 1.0)
    renders = {
        "a": render(fuse_models([("a", trained.model, np.eye(4))]), C2W),
        "b": render(fuse_models([("b", model_b, T_b)]), C2W),
    }
    fused = fuse_models([("a", trained.model, np.eye(4)), ("b", model_b, T_b)], tau=None)
    return fused, renders


def test_gamma_zero_is_the_mean_and_shares_are_normalised(pair):
    fused, single = pair
    mean = 0.5 * (single["a"]["rgb"] + single["b"]["rgb"])
    for method in ("idw-sample", "idw-2d", "idw-3d"):
        fused.blend_method, fused.gamma = method, 0.0
        out = render(fused, C2W, OUTPUTS + ("share_0", "share_1"))
        close(out["rgb"], mean, 1e-5)
        close(out["share_0"], torch.full_like(out["share_0"], 0.5), 1e-5)
    assert (single["a"]["rgb"] - single["b"]["rgb"]).abs().mean() > 0.02  # the check is not vacuous
    for method in BLEND_METHODS:
        for gamma in (1.0, 5.0, float("inf")):
            fused.blend_method, fused.gamma = method, gamma
            out = render(fused, C2W, ("share_0", "share_1", "accumulation"))
            close(out["share_0"] + out["share_1"], torch.ones_like(out["share_0"]), 1e-5)
            assert out["accumulation"].min() >= 0 and out["accumulation"].max() <= 1 + 1e-5


def test_gamma_infinity_is_nearest_and_large_gamma_converges(pair):
    fused, single = pair
    c2w = C2W.copy()
    c2w[:3, 3] = [-0.3, 0.0, 0.6]  # nearer to A's origin (0) than to B's (0.25, 0, 0)
    a_here = render(fuse_models([("a", fused.nerfs.models[0], np.eye(4))]), c2w)
    fused.gamma = float("inf")
    fused.blend_method = "idw-2d"
    close(render(fused, c2w)["rgb"], a_here["rgb"], 1e-6)
    fused.blend_method = "idw-sample"
    inf = render(fused, c2w, ("rgb", "share_0"))
    # far samples (up to nerfacto's far plane, 1000) are almost equidistant from both origins (relative difference
    # ~2.5e-4), so the limit is reached only for gamma >> 1e4
    fused.gamma = 1e7
    big = render(fused, c2w, ("rgb", "share_0"))
    close(big["rgb"], inf["rgb"], 1e-4)
    # the distance test (any ratio > 1 fails it) falls back to the camera's nearest NeRF: exactly A's render
    fused.gamma, fused.tau = 5.0, 1.0
    close(render(fused, c2w)["rgb"], a_here["rgb"], 1e-5)
    fused.tau = None


# ----------------------------------------------------------------------------------------------------------------------
# Ours: coverage blending and appearance matching


def _cameras(*c2w: np.ndarray) -> CameraIndex:
    return CameraIndex.from_cameras(np.stack(c2w), [INTR.fx, INTR.fy, INTR.cx, INTR.cy, INTR.width, INTR.height])


# The scene seen from the other side: C2W turned half a turn about x (looks along +z) and moved behind the scene.
C2W_BEHIND = np.diag([1.0, -1.0, -1.0, 1.0]) @ C2W


@pytest.mark.parametrize("method", ["coverage", "coverage-3d"])
def test_coverage_gives_the_weight_to_the_nerf_whose_cameras_saw_the_view(pair, method):
    """Each NeRF's cameras in its own frame: one NeRF saw the scene from the query camera, the other only from
    behind. The one that saw it takes the pixel; IDW-Sample would share it."""
    fused, _ = pair
    (a, b), T_b = fused.nerfs.models, fused.nerf_to_common[1].double().numpy()
    to_b = sim3.invert_sim3(T_b)
    seen = [_cameras(C2W), _cameras(sim3.transform_poses(to_b, C2W))]
    behind = [_cameras(C2W_BEHIND), _cameras(sim3.transform_poses(to_b, C2W_BEHIND))]
    idw = render(fuse_models([("a", a, np.eye(4)), ("b", b, T_b)], tau=None), C2W, ("share_0",))["share_0"]
    assert 0.05 < float(idw.mean()) < 0.95  # IDW-Sample shares the pixels: the check below is not vacuous
    for who in (0, 1):
        cams_a, cams_b = (seen[0], behind[1]) if who == 0 else (behind[0], seen[1])
        two = fuse_models([("a", a, np.eye(4), cams_a), ("b", b, T_b, cams_b)], tau=None, blend_method=method)
        out = render(two, C2W, ("rgb", "share_0", "share_1"))
        assert float(out[f"share_{who}"].min()) > 0.95, who
        close(out["share_0"] + out["share_1"], torch.ones_like(out["share_0"]), 1e-5)


def test_coverage_without_cameras_is_idw_sample_with_one_warning(pair):
    fused, _ = pair
    (a, b), T_b = fused.nerfs.models, fused.nerf_to_common[1].double().numpy()
    # One NeRF without cameras is enough: scores of some NeRFs only cannot be compared.
    two = fuse_models([("a", a, np.eye(4), _cameras(C2W)), ("b", b, T_b)], tau=None, blend_method="coverage")
    with pytest.warns(UserWarning, match=r"coverage.*\['b'\] have none.*IDW-Sample and IDW-2D are used instead"):
        got = render(two, C2W, OUTPUTS + ("share_0",))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render(two, C2W, ("rgb",))
    assert not [w for w in caught if "coverage" in str(w.message)]  # one warning per model, not one per batch
    two.blend_method = "idw-sample"
    want = render(two, C2W, OUTPUTS + ("share_0",))
    for key in want:
        assert torch.equal(got[key], want[key]), key
    # coverage-3d falls back to the image-level IDW-2D
    two.blend_method = "coverage-3d"
    got = render(two, C2W, OUTPUTS + ("share_0",))
    two.blend_method = "idw-2d"
    want = render(two, C2W, OUTPUTS + ("share_0",))
    for key in want:
        assert torch.equal(got[key], want[key]), key


def test_auto_renders_idw_sample_around_the_scene_idw_2d_for_a_rig_and_coverage_along_a_path(pair):
    fused, _ = pair
    (a, b), T_b = fused.nerfs.models, fused.nerf_to_common[1].double().numpy()
    to_b = sim3.invert_sim3(T_b)
    az = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    around = look_at(np.stack([0.6 * np.cos(az), 0.6 * np.sin(az), np.full(12, 0.3)], axis=-1), np.zeros(3))
    walk = np.stack([np.linspace(-1.0, 1.0, 12), np.full(12, -0.6), np.full(12, 0.1)], axis=-1)
    along = look_at(walk, walk + np.array([0.0, 1.0, 0.0]))  # a walk past a facade
    stops = np.repeat(np.stack([np.linspace(-1.0, 1.0, 4), np.full(4, -0.6), np.full(4, 0.1)], axis=-1), 6, axis=0)
    yaw = np.tile(np.linspace(0, 2 * np.pi, 6, endpoint=False), 4)
    rig = look_at(stops, stops + np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=-1))  # 6 cameras
    for cameras, want in ((around, "idw-sample"), (rig, "idw-2d"), (along, "coverage")):
        nerfs = [("a", a, np.eye(4), _cameras(*cameras)), ("b", b, T_b, _cameras(*sim3.transform_poses(to_b, cameras)))]
        auto = fuse_models(nerfs, tau=None)  # the default
        assert (auto.blend_method, auto.active_method) == ("auto", want)
        assert want in auto.auto_reason and want in auto.viewer_scene.controls["blend_method"].hint
        explicit = fuse_models(nerfs, tau=None, blend_method=want)
        got, expected = render(auto, C2W, OUTPUTS + ("share_0",)), render(explicit, C2W, OUTPUTS + ("share_0",))
        for key in expected:
            assert torch.equal(got[key], expected[key]), (want, key)
        auto.blend_method = "nearest"  # a method set live is rendered as it is; auto again resolves as before
        assert auto.active_method == "nearest"
        auto.blend_method = "auto"
        assert auto.active_method == want
    assert "auto" in auto.viewer_scene.controls["blend_method"].options


def test_colour_maps_are_applied_to_each_nerfs_colours_and_can_be_switched_off(trained, monkeypatch):
    colour = np.hstack([np.diag([0.6, 1.0, 1.4]), np.full((3, 1), 0.02)])
    plain = render(fuse_models([("a", trained.model, np.eye(4))]), C2W)["rgb"]
    mapped = fuse_models([("a", trained.model, np.eye(4), None, colour)])  # the default: on
    assert mapped.config.appearance_matching
    got = render(mapped, C2W)["rgb"]
    assert (got - plain).abs().mean() > 0.02
    # The twin: the map on every sample colour and the background, then nerfstudio's volume rendering.
    bundle = cams(C2W).generate_rays(torch.arange(1)[:, None], keep_shape=False)
    with torch.no_grad():
        s = mapped.nerf_samples(bundle)[0].samples
        m = torch.tensor(colour, dtype=torch.float32)
        want = render_samples(s.weights, apply_colour_map(s.rgbs, m), apply_colour_map(s.background_rgb, m))
    close(got.reshape(-1, 3), want.clamp(0, 1), 1e-5)
    off = fuse_models([("a", trained.model, np.eye(4), None, colour)], appearance_matching=False)
    assert torch.equal(render(off, C2W)["rgb"], plain)
    off.appearance_matching = True  # through set_blend, like the viewer and ns-nerfuser-view
    assert off.blend_settings.appearance_matching and torch.equal(render(off, C2W)["rgb"], got)
    monkeypatch.setenv("NERFUSER_APPEARANCE_MATCHING", "0")  # what ns-render / ns-eval read at load
    assert torch.equal(render(fuse_models([("a", trained.model, np.eye(4), None, colour)]), C2W)["rgb"], plain)
    monkeypatch.delenv("NERFUSER_APPEARANCE_MATCHING")
    # the viewer's checkbox switches it for the next frame, both ways
    checkbox = mapped.viewer_scene.controls["appearance_matching"]
    assert checkbox.value is True
    checkbox.value = False
    checkbox.cb_hook(checkbox)
    assert mapped.blend_settings.appearance_matching is False
    assert torch.equal(render(mapped, C2W)["rgb"], plain)
    checkbox.value = True
    checkbox.cb_hook(checkbox)
    assert torch.equal(render(mapped, C2W)["rgb"], got)
    identity = fuse_models([("a", trained.model, np.eye(4), None, IDENTITY)], appearance_matching=True)
    assert torch.equal(render(identity, C2W)["rgb"], plain)


# ----------------------------------------------------------------------------------------------------------------------
# Only the NeRFs a ray can use are queried


def _spy_queries(model: NerfuserModel, monkeypatch) -> list[list[int]]:
    """Records, per NeRF, the number of rays of each query of its adapter."""
    calls: list[list[int]] = [[] for _ in model.adapters]
    for adapter, record in zip(model.adapters, calls, strict=True):

        def spy(bundle, original=adapter.samples, record=record):  # noqa: ANN001, ANN202
            record.append(len(bundle))
            return original(bundle)

        monkeypatch.setattr(adapter, "samples", spy)
    return calls


def test_a_nerf_failing_the_distance_test_is_not_queried_and_changes_nothing(pair, monkeypatch):
    (a, b), T_b = pair[0].nerfs.models, pair[0].nerf_to_common[1].numpy()
    far = sim3.make_sim3(np.eye(3), np.array([30.0, 0.0, 0.0]), 1.0)  # 50x farther from the camera than A and B
    nerfs = [("a", a, np.eye(4)), ("b", b, T_b), ("c", a, far)]
    for method in BLEND_METHODS:
        two = fuse_models(nerfs[:2], blend_method=method, tau=1.8)
        three = fuse_models(nerfs, blend_method=method, tau=1.8)
        calls = _spy_queries(three, monkeypatch)
        want = render(two, C2W, OUTPUTS + ("share_0", "share_1"))
        got = render(three, C2W, OUTPUTS + ("share_0", "share_1", "share_2"))
        assert calls[2] == [] and calls[0], method
        for key in want:
            close(got[key], want[key], 1e-6)
        assert got["share_2"].abs().max() == 0


def test_each_ray_uses_only_its_own_nerfs_in_any_batch(pair, monkeypatch):
    """Two cameras in one batch: C2W blends A and B, the other sits by C, where A and B fail the distance test.
    Each NeRF is queried only on the rays that use it, and every ray renders as it does alone."""
    (a, b), T_b = pair[0].nerfs.models, pair[0].nerf_to_common[1].numpy()
    T_c = sim3.make_sim3(np.eye(3), np.array([1.5, 0.0, 0.0]), 1.0)
    c2w_c = C2W.copy()
    c2w_c[:3, 3] += [1.5, 0.0, 0.0]  # sees C as C2W sees A
    nerfs = [("a", a, np.eye(4)), ("b", b, T_b), ("c", b, T_c)]
    bundle = runs.make_cameras(np.stack([C2W, c2w_c]), INTR).generate_rays(
        torch.arange(2)[:, None], keep_shape=False
    )
    at_c = bundle.camera_indices[:, 0] == 1  # the cameras' rays interleave
    half = int(at_c.sum())
    alone_c = render(fuse_models([("c", b, T_c)]), c2w_c)["rgb"].reshape(-1, 3)
    alone_ab = render(fuse_models(nerfs[:2], tau=1.8), C2W)["rgb"].reshape(-1, 3)

    three = fuse_models(nerfs, tau=1.8)
    calls = _spy_queries(three, monkeypatch)
    with torch.no_grad():
        mixed = three(bundle)
    assert calls == [[half], [half], [half]]
    close(mixed["rgb"][~at_c], alone_ab, 1e-5)
    close(mixed["rgb"][at_c], alone_c, 1e-5)

    # Every method at once, C the `nerf` method's NeRF: C is queried on every ray, but on C2W's rays, where it fails
    # the distance test, it must not even split A's and B's samples: IDW-Sample there is still their blend alone.
    # (A high gamma flips the weights sharply between A and B, so a split shows: 2e-5 if C's samples took part.)
    sharp_ab = render(fuse_models(nerfs[:2], tau=1.8, gamma=1e3), C2W)["rgb"].reshape(-1, 3)
    three = fuse_models(nerfs, tau=1.8, gamma=1e3, render_all_methods=True, reference_nerf=2)
    calls = _spy_queries(three, monkeypatch)
    with torch.no_grad():
        mixed = three(bundle)
        apart = [three(bundle[~at_c]), three(bundle[at_c])]
    assert calls == [[half, half], [half, half], [2 * half, half, half]]
    for key in mixed:
        close(mixed[key][~at_c], apart[0][key], 1e-5)
        close(mixed[key][at_c], apart[1][key], 1e-5)
    close(mixed["rgb_idw_sample"][~at_c], sharp_ab, 1e-6)
    close(mixed["rgb_idw_sample"][at_c], alone_c, 1e-5)
    close(mixed["rgb_nerf"][at_c], alone_c, 1e-5)
    close(mixed["share_2"][at_c], torch.ones_like(mixed["share_2"][at_c]), 1e-6)


# ----------------------------------------------------------------------------------------------------------------------
# Bounded memory (ours): sub-models loaded on first use, at most max_resident_nerfs resident


@pytest.fixture(scope="module")
def three_runs_spec(trained, tmp_path_factory) -> Path:
    """A fusion spec of three copies of the run: A (identity), B (moved 0.25) and C (moved 1.5, away from C2W)."""
    root = tmp_path_factory.mktemp("lru")
    configs = [trained.config_path]
    for name in ("b", "c"):
        run_dir = root / "runs" / name / "nerfacto-cpu" / "run"
        shutil.copytree(trained.config_path.parent, run_dir)
        configs.append(run_dir / "config.yml")
    transforms = [np.eye(4)] + [sim3.make_sim3(np.eye(3), np.array([x, 0.0, 0.0]), 1.0) for x in (0.25, 1.5)]
    entries = [NerfEntry(n, c, t) for n, c, t in zip("abc", configs, transforms, strict=True)]
    write_minimal_registration(entries, root / "registration.json")
    return write_fusion_spec(root / "fusion.json", configs, registration="registration.json", names=list("abc"))


def _from_spec(spec: Path, **overrides) -> NerfuserModel:  # noqa: ANN003
    config = NerfuserModelConfig(fusion_spec=spec, tau=1.8, **overrides)
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=1, metadata={})
    return model.eval()


def test_one_resident_nerf_renders_what_all_resident_render(three_runs_spec):
    """max_resident_nerfs=1 over three NeRFs: the same pixels as with all three resident, never more than one in
    memory (A and B are both needed by C2W's rays: the batch takes them one at a time), and a NeRF is loaded only
    for rays that pass its distance test (C2W never loads C; a camera by C loads C alone)."""
    c2w_c = C2W.copy()
    c2w_c[:3, 3] += [1.5, 0.0, 0.0]  # sees C as C2W sees A; A and B fail the distance test there
    full = _from_spec(three_runs_spec)
    assert full.nerf_cache is None and len(full.nerfs) == 3  # the default: all loaded at setup, as before
    want = [render(full, c, OUTPUTS + ("share_0", "share_1", "share_2")) for c in (C2W, c2w_c)]

    lazy = _from_spec(three_runs_spec, max_resident_nerfs=1)
    cache = lazy.nerf_cache
    assert lazy.nerfs is None and cache.resident() == [] and cache.loads == 0  # nothing loaded at setup
    loaded: list[int] = []
    most: list[int] = []
    load = cache.loader

    def spy(i: int):  # noqa: ANN202
        loaded.append(i)
        most.append(len(cache.resident()) + 1)  # resident once this one is in
        return load(i)

    cache.loader = spy
    got = render(lazy, C2W, OUTPUTS + ("share_0", "share_1", "share_2"))
    assert loaded == [0, 1] and max(most) == 1 and cache.resident() == [1]
    got_c = render(lazy, c2w_c, OUTPUTS + ("share_0", "share_1", "share_2"))
    assert loaded == [0, 1, 2] and max(most) == 1 and cache.resident() == [2]
    assert (cache.loads, cache.evictions) == (3, 2)
    again = render(lazy, C2W, OUTPUTS)  # A and B reloaded after their eviction: still the same pixels
    assert loaded == [0, 1, 2, 0, 1] and (cache.loads, cache.evictions) == (5, 4)
    for out, ref_out in ((got, want[0]), (got_c, want[1]), (again, want[0])):
        for key in out:
            close(out[key], ref_out[key], 1e-6)

    fresh = _from_spec(three_runs_spec, max_resident_nerfs=1)
    render(fresh, c2w_c)
    assert fresh.nerf_cache.resident() == [2] and fresh.nerf_cache.loads == 1  # C's rays need C alone


def test_model_is_frozen_and_its_checkpoint_holds_no_sub_model(trained):
    fused = fuse_models([("a", trained.model, np.eye(4)), ("b", trained.model, T_FAR)])
    assert fused.get_param_groups() == {}
    assert sum(p.numel() for p in fused.parameters()) == 0  # only nerfstudio's empty device indicator
    keys = list(fused.state_dict())
    assert not any(k.startswith("nerfs") or "field." in k for k in keys), keys
    fused.train()
    assert not fused.nerfs.models[0].training  # sub-models stay in eval mode


def test_render_time_settings_from_the_environment(trained, monkeypatch):
    monkeypatch.setenv("NERFUSER_BLEND_METHOD", "nearest")
    monkeypatch.setenv("NERFUSER_GAMMA", "2.5")
    monkeypatch.setenv("NERFUSER_TAU", "none")
    fused = fuse_models([("a", trained.model, np.eye(4))])
    assert (fused.blend_method, fused.gamma, fused.tau) == ("nearest", 2.5, None)
    monkeypatch.setenv("NERFUSER_BLEND_METHOD", "idw-4d")
    with pytest.raises(ValueError, match="unknown blend method 'idw-4d'"):
        fuse_models([("a", trained.model, np.eye(4))])


# ----------------------------------------------------------------------------------------------------------------------
# ns-train / ns-eval / ns-render


def _run(cmd: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    full_env = {**os.environ, **(env or {})}
    proc = subprocess.run(cmd, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{cmd[0]} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def fused_run(trained, tiny_scene, tmp_path_factory) -> Path:
    """Two runs (A, and a copy B of it registered under T_FAR) fused by ns-train, with the scene's test images."""
    root = tmp_path_factory.mktemp("fusion")
    b_dir = root / "runs" / "b" / "nerfacto-cpu" / "run"
    shutil.copytree(trained.config_path.parent, b_dir)
    gt = json.loads((tiny_scene / "ground_truth.json").read_text())
    capture_to_world = np.array(gt["captures"][0]["capture_to_world"])
    world_to_common = trained.data_to_nerf @ np.linalg.inv(capture_to_world)  # the test capture is world-posed
    write_minimal_registration(
        [NerfEntry("a", trained.config_path, np.eye(4)), NerfEntry("b", b_dir / "config.yml", T_FAR)],
        root / "registration.json",
    )
    spec = write_fusion_spec(
        root / "fusion.json",
        [trained.config_path, b_dir / "config.yml"],
        registration="registration.json",
        test_data=tiny_scene / "test",
        test_to_common=world_to_common,
    )
    _run(
        [
            str(BIN / "ns-train"),
            "nerfuser",
            "--data",
            str(spec),
            "--output-dir",
            str(root / "outputs"),
            "--experiment-name",
            "fused",
            "--timestamp",
            "run",
            "--pipeline.model.render-all-methods",
            "True",
        ],
        cwd=root,
    )
    config = root / "outputs" / "fused" / "nerfuser" / "run" / "config.yml"
    assert config.is_file()
    return config


def test_ns_train_writes_a_normal_run(fused_run):
    run_dir = fused_run.parent
    ckpts = list((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    assert len(ckpts) == 1 and ckpts[0].stat().st_size < 100_000  # no sub-model weights inside
    assert (run_dir / "dataparser_transforms.json").is_file()
    config = yaml.load(fused_run.read_text(), Loader=yaml.Loader)
    assert config.method_name == "nerfuser" and config.pipeline.model.blend_method == "auto"
    loaded = runs.load_run(fused_run)  # the fused run loads like any other
    assert isinstance(loaded.model, NerfuserModel) and loaded.model.num_nerfs == 2


def test_ns_eval_reports_every_method(fused_run, tmp_path):
    out = tmp_path / "eval.json"
    _run(
        [str(BIN / "ns-eval"), "--load-config", str(fused_run), "--output-path", str(out)],
        cwd=tmp_path,
        env={"NERFUSER_BLEND_METHOD": "idw-2d"},
    )
    results = json.loads(out.read_text())["results"]
    for method in BLEND_METHODS:
        key = method.replace("-", "_")
        assert np.isfinite(results[f"psnr_{key}"]) and np.isfinite(results[f"ssim_{key}"]), results
    assert results["psnr"] == pytest.approx(results["psnr_idw_2d"])  # the environment chose the main method
    assert results["psnr_nerf"] > 12  # the registered test views see the scene, not noise


def test_ns_render_renders_every_method(fused_run, tmp_path):
    names = ["rgb", "depth", "nerf_share", "share_1"] + [f"rgb_{m.replace('-', '_')}" for m in BLEND_METHODS]
    _run(
        [
            str(BIN / "ns-render"),
            "dataset",
            "--load-config",
            str(fused_run),
            "--output-path",
            str(tmp_path / "r"),
            "--split",
            "test",
            "--rendered-output-names",
            *names,
        ],
        cwd=tmp_path,
    )
    for name in names:
        files = sorted((tmp_path / "r" / "test" / name).glob("*"))
        assert len(files) == 2, name


def test_ns_eval_on_a_runs_held_out_images_scores_its_nerf_as_nerfstudio_does(fused_run, trained, tmp_path):
    """``"test_run": 0``: the fused run scored on the images run a kept out of its training. Its reference NeRF
    alone (method ``nerf``: run a, registered at the identity) must score what nerfstudio's own ns-eval of run a
    scores on the same images; a pose off by a pixel would not."""
    spec = write_fusion_spec(tmp_path / "fusion.json", [trained.config_path, fused_run.parents[4] / "runs" / "b" /
                             "nerfacto-cpu" / "run" / "config.yml"], registration=fused_run.parents[4] /
                             "registration.json", test_run=0)  # fmt: skip
    _run([str(BIN / "ns-train"), "nerfuser", "--data", str(spec), "--output-dir", str(tmp_path / "outputs"),
          "--experiment-name", "held", "--timestamp", "out", "--pipeline.model.render-all-methods", "True"],
         cwd=tmp_path)  # fmt: skip
    config = tmp_path / "outputs" / "held" / "nerfuser" / "out" / "config.yml"
    _run([str(BIN / "ns-eval"), "--load-config", str(config), "--output-path", str(tmp_path / "fused.json")],
         cwd=tmp_path)  # fmt: skip
    _run([str(BIN / "ns-eval"), "--load-config", str(trained.config_path), "--output-path", str(tmp_path / "own.json")],
         cwd=tmp_path)  # fmt: skip
    fused, own = (json.loads((tmp_path / f).read_text())["results"] for f in ("fused.json", "own.json"))
    assert own["psnr"] > 12
    assert fused["psnr_nerf"] == pytest.approx(own["psnr"], abs=0.05)


def test_a_run_whose_samples_cannot_be_merged_is_named(trained):
    """A method without a NeRF adapter (e.g. an instant-ngp run beside a nerfacto one): one error naming the run."""

    class OtherModel(torch.nn.Module):
        pass

    with pytest.raises(TypeError, match="run 'ngp': nerfuser: no adapter for OtherModel") as e:
        fuse_models([("a", trained.model, np.eye(4)), ("ngp", OtherModel(), np.eye(4))])
    assert "nerfuser_ns.adapters.ADAPTERS" in str(e.value)  # where the list it names lives


ALIKE_KEYS = ("rgb", "accumulation", "expected_depth", "depth")
"""What must agree on every pixel between renders that differ by float noise. No ray of the 60-step NeRF reaches an
accumulated weight of 0.5, so the median depth is everywhere the convention for that case
(:func:`nerfuser_ns.merging.furthest_last_mids`), which must be as stable as the rest."""


def assert_renders_alike(out: dict[str, torch.Tensor], ref: dict[str, torch.Tensor], method: str) -> None:
    for key in ALIKE_KEYS:
        torch.testing.assert_close(out[key].cpu(), ref[key], atol=2e-3, rtol=1e-3,
                                   msg=lambda m, k=key: f"{method} {k}: {m}")  # fmt: skip


def test_every_blend_method_is_stable_under_float_level_changes(pair):
    """A 1e-5 relative change to the NeRFs' parameters (this machine's stand-in for another device's arithmetic)
    changes no blend beyond float noise (IDW-Sample's median depth did, by 6 of 34 units on 4 pixels, when it took
    the last merged interval's midpoint: the CPU-CUDA difference seen on an H100)."""
    fused, _ = pair
    nudged = copy.deepcopy(fused)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in (p for model in nudged.nerfs.models for p in model.parameters()):
            p.mul_(1 + 1e-5 * torch.randn(p.shape, generator=gen))
    original = fused.blend_method
    try:
        for method in BLEND_METHODS:
            fused.blend_method = nudged.blend_method = method
            assert_renders_alike(render(nudged, C2W, ALIKE_KEYS), render(fused, C2W, ALIKE_KEYS), method)
    finally:
        fused.blend_method = original


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_every_blend_method_renders_alike_on_cuda(pair):
    """Device-clean: the fused model moved to the GPU renders what it renders on the CPU."""
    fused, _ = pair
    original, on_cpu = fused.blend_method, {}
    for method in BLEND_METHODS:
        fused.blend_method = method
        on_cpu[method] = render(fused, C2W, ALIKE_KEYS)
    gpu = copy.deepcopy(fused).to("cuda")
    try:
        for method in BLEND_METHODS:
            gpu.blend_method = method
            assert_renders_alike(render(gpu, C2W, ALIKE_KEYS), on_cpu[method], method)
    finally:
        fused.blend_method = original
