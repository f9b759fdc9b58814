"""The cross-render self-check (:mod:`nerfuser_ns.registration.self_check`): NCC, a wrong transform rejected on the
object-centric pair, a wrong estimate (or refinement) failing the command with one line, and the failure messages
per mode and pose source."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from registration_helpers import assert_one_line_error, perturb_second_estimate, run_cli, small_config
from scipy.spatial.transform import Rotation

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.registration import pipeline as reg_pipeline
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.self_check import (
    depth_log_ratio,
    depth_views,
    failure_message,
    nearest_views,
    passed,
    view_nccs,
)
from nerfuser_ns.renderers import RenderBatch
from nerfuser_ns.spec import FusionSpecError, read_registered_nerfs


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
    # the SfM registration's own renders (stored with depth: these renderers give it)
    views = [reg.render_views_cached(r, config.sampling, work / "renders", depth=True) for r in oc_renderers]
    assert all(v.reused for v in views)
    T = np.stack([np.asarray(n["T_to_reference"]) for n in oc_record["nerfs"]])
    intr = config.sampling.intrinsics()
    good = reg.cross_render_check(oc_renderers, views, T, [(0, 1)], intr, config)[0]
    wrong = T.copy()
    wrong[1] = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 0.0, 25.0])), [0.1, 0.0, 0.0]) @ T[1]
    bad = reg.cross_render_check(oc_renderers, views, wrong, [(0, 1)], intr, config)[0]
    assert good.score > 0.9
    assert bad.score < config.ncc_threshold
    # These renderers give true depth: through the estimate, each NeRF's surfaces lie where the other has them.
    assert abs(good.depth_disagreement) < 0.01 and passed(good, config)


def test_the_depth_check_sees_a_scale_error_the_ncc_passes(oc_renderers, oc_record, work):
    config = small_config()
    views = [reg.render_views_cached(r, config.sampling, work / "renders", depth=True) for r in oc_renderers]
    T = np.stack([np.asarray(n["T_to_reference"]) for n in oc_record["nerfs"]])
    # The second NeRF scaled by 22% about its own cameras' centre: its views barely move, its surfaces do.
    centre = sim3.transform_points(T[1], views[1].c2w[:, :3, 3]).mean(axis=0)
    scaled = T.copy()
    scaled[1] = sim3.make_sim3(np.exp(0.2) * np.eye(3), centre - np.exp(0.2) * centre) @ T[1]
    intr = config.sampling.intrinsics()
    check = reg.cross_render_check(oc_renderers, views, scaled, [(0, 1)], intr, config)[0]
    assert check.score >= config.ncc_threshold  # the NCC passes it ...
    assert abs(check.depth_disagreement) > 2 * config.depth_threshold  # ... the depth does not
    assert not passed(check, config)
    message = failure_message([check], ["a", "b"], config)
    assert message.startswith("a and b: cross-render depth check failed") and "--depth-threshold 0" in message
    # 0 disables it; renders stored without depth measure nothing and pass as before
    assert passed(check, dataclasses.replace(config, depth_threshold=0.0))
    plain = [reg.render_views_cached(r, config.sampling, work / "renders") for r in oc_renderers]
    unmeasured = reg.cross_render_check(oc_renderers, plain, scaled, [(0, 1)], intr, config)[0]
    assert np.isnan(unmeasured.depth_disagreement) and passed(unmeasured, config)


def test_the_depth_is_compared_at_the_views_nearest_the_other_nerf(oc_renderers, oc_record, work):
    # Not at the views the NCC is given (in the registration, those sharing the most SfM points: the content the link
    # was fitted to, where a wrong link still agrees).
    config = small_config()
    views = [reg.render_views_cached(r, config.sampling, work / "renders", depth=True) for r in oc_renderers]
    T = np.stack([np.asarray(n["T_to_reference"]) for n in oc_record["nerfs"]])
    centre = sim3.transform_points(T[1], views[1].c2w[:, :3, 3]).mean(axis=0)
    T[1] = sim3.make_sim3(np.exp(0.2) * np.eye(3), centre - np.exp(0.2) * centre) @ T[1]
    T_01 = sim3.relative_sim3(T[1], T[0])
    near = depth_views(views[0], T_01, views[1])
    n = config.self_check_views
    intr = config.sampling.intrinsics()
    order = {(0, 1): near[::-1], (1, 0): depth_views(views[1], sim3.invert_sim3(T_01), views[0])[::-1]}
    check = reg.cross_render_check(oc_renderers, views, T, [(0, 1)], intr, config, view_order=order)[0]
    at_near: list = []
    view_nccs(views[0], oc_renderers[1], T_01, near[:n], intr, config, depths=at_near)
    at_far: list = []
    view_nccs(views[0], oc_renderers[1], T_01, near[::-1][:n], intr, config, depths=at_far)
    assert check.depth_i_in_j == pytest.approx(np.median(at_near))
    assert np.median(at_far) != pytest.approx(np.median(at_near), abs=1e-3)  # the choice of views matters here


def test_nearest_views_orders_by_the_mapped_centres_and_skips_dropped_views(tmp_path):
    def posed(centres):
        c2w = np.tile(np.eye(4), (len(centres), 1, 1))
        c2w[:, :3, 3] = centres
        return c2w

    mine = ViewSet("a", tmp_path, posed([[0, 0, 0], [5, 0, 0], [1, 0, 0], [2, 0, 0]]), ["hemisphere"] * 4,
                   np.ones(4), np.array([True, True, False, True]))  # fmt: skip
    other = ViewSet("b", tmp_path, posed([[10, 0, 0]]), ["hemisphere"], np.ones(1), np.ones(1, bool))
    # mapped by a scale of 2: centres at 0, 10, 2, 4; view 2 was dropped
    assert nearest_views(mine, sim3.make_sim3(np.eye(3), np.zeros(3), 2.0), other) == [1, 3, 0]


def test_depth_views_are_training_views_nearest_the_other_nerfs_training_views(tmp_path):
    def posed(xs):
        c2w = np.tile(np.eye(4), (len(xs), 1, 1))
        c2w[:, 0, 3] = xs
        return c2w

    sources = ["hemisphere", "hemisphere", "training", "training", "training"]
    mine = ViewSet("a", tmp_path, posed([9.0, 10.0, 0.0, 4.0, 6.0]), sources, np.ones(5),
                   np.array([True, True, True, True, False]))  # fmt: skip
    other = ViewSet("b", tmp_path, posed([10.0, 3.0]), ["hemisphere", "training"], np.ones(2), np.ones(2, bool))
    identity = np.eye(4)
    # every view, nearest any of the other's views: the hemisphere views by its hemisphere view come first
    assert nearest_views(mine, identity, other) == [1, 0, 3, 2]
    # the depth's: own training views only (view 4 dropped), nearest the other's training view at x=3
    assert depth_views(mine, identity, other) == [3, 2]
    # a side without training views falls back to all its views
    hemisphere_only = dataclasses.replace(other, sources=["hemisphere", "hemisphere"])
    assert depth_views(mine, identity, hemisphere_only) == [3, 2]  # by x=3: 4 (1 away), then 0 (3 away)
    # ... and the other side still measures to its training views
    assert depth_views(dataclasses.replace(mine, sources=["hemisphere"] * 5), identity, other) == [3, 2, 0, 1]
    # sources not recorded (an old render folder): every view
    assert depth_views(dataclasses.replace(mine, sources=[]), identity, other) == [3, 2, 0, 1]


def test_depth_log_ratio_is_the_links_scale_error():
    rng = np.random.default_rng(0)
    own = rng.uniform(1.0, 5.0, (20, 30))
    mask = np.ones(own.shape, bool)
    # the other NeRF at twice the units; a link that claims 2 * exp(0.1) is 0.1 too large in log scale
    assert depth_log_ratio(own, 2.0 * own, 2.0, mask) == pytest.approx(0.0, abs=1e-12)
    assert depth_log_ratio(own, 2.0 * own, 2.0 * np.exp(0.1), mask) == pytest.approx(-0.1)
    noisy = 2.0 * own * np.exp(rng.normal(0, 0.02, own.shape))
    noisy[:2] = 1e3  # a few outliers (floaters) do not move the median
    assert depth_log_ratio(own, noisy, 2.0, mask) == pytest.approx(0.0, abs=0.01)
    hidden = own.copy()
    hidden[mask] = 0.0  # nothing hit
    assert np.isnan(depth_log_ratio(own, hidden, 2.0, mask))
    assert np.isnan(depth_log_ratio(own, 2.0 * own, 2.0, np.zeros(own.shape, bool)))


class _Gained:
    """A renderer whose colours carry an exposure and white balance (linear-RGB gains), as another capture's would."""

    def __init__(self, renderer, gains: np.ndarray):
        self.renderer, self.gains, self.name = renderer, gains, renderer.name

    def cache_key(self) -> str:
        return f"{self.renderer.cache_key()}|gains {self.gains.tolist()}"

    def render(self, c2w, intrinsics) -> RenderBatch:
        out = self.renderer.render(c2w, intrinsics)
        return RenderBatch(scenes.apply_appearance(torch.from_numpy(out.rgb), self.gains).numpy(), out.accumulation)


def test_colour_maps_recover_a_known_gain_from_the_cross_renders(oc_renderers, oc_record, work):
    config = small_config(colour_views=reg.RegistrationConfig.colour_views)
    gains = np.array([1.3, 1.0, 0.75])
    renderers = [oc_renderers[0], _Gained(oc_renderers[1], gains)]
    views = [reg.render_views_cached(r, config.sampling, work / "renders") for r in renderers]
    T = np.stack([np.asarray(n["T_to_reference"]) for n in oc_record["nerfs"]])
    check = reg.cross_render_check(renderers, views, T, [(0, 1)], config.sampling.intrinsics(), config)[0]
    assert check.colour_pixels > 10_000
    # exact renders: what is left is where the estimate and the PNGs' rounding put them
    np.testing.assert_allclose(np.diag(check.colour_j_to_i[:, :3]), 1 / gains, rtol=0.03)
    np.testing.assert_allclose(check.colour_j_to_i[:, :3] @ check.colour_i_to_j[:, :3], np.eye(3), atol=1e-9)
    off = reg.cross_render_check(renderers, views, T, [(0, 1)], config.sampling.intrinsics(),
                                 dataclasses.replace(config, colour_views=0))[0]  # fmt: skip
    assert off.colour_j_to_i is None and off.colour_pixels == 0 and off.score == pytest.approx(check.score)


def _refinement_turned(monkeypatch, degrees: float) -> None:
    """The bundle adjustment's result for NeRF B turned by ``degrees``: a refinement that followed wrong points."""
    real_refine = reg.refine_transforms
    turn = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, degrees, 0.0])))

    def turned(*args, **kw):
        T, summary = real_refine(*args, **kw)
        T = T.copy()
        T[1] = turn @ T[1]
        return T, summary

    monkeypatch.setattr(reg_pipeline, "refine_transforms", turned)


@pytest.mark.parametrize("refine", [False, True])
def test_register_fails_when_the_estimate_is_wrong(
    oc_renderers, oc_record, work, monkeypatch, tmp_path, capsys, refine
):
    if refine:  # the refinement would correct a wrong start (test_refine.py): break its output instead
        _refinement_turned(monkeypatch, 40.0)
    else:
        perturb_second_estimate(monkeypatch)
    # (the camera check would refuse it first: its own test follows)
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work, refine=refine, camera_check=False)
    assert_one_line_error(rc, out, err, "capture_a and capture_b", "self-check failed")
    rejected = json.loads((work / "rejected_registration.json").read_text())
    assert rejected["pairs"][0]["self_check"]["passed"] is False
    # marked with the refusal: the fusion refuses the file (one line naming it) until a user removes the mark
    assert "self-check failed" in rejected["refused"]
    with pytest.raises(FusionSpecError, match=r"rejected_registration.json: a solution the registration's "
                                              r"checks refused.*remove its \"refused\" key"):
        read_registered_nerfs(work / "rejected_registration.json", check_runs=False)
    del rejected["refused"]
    (work / "kept.json").write_text(json.dumps(rejected))
    assert [n.name for n in reg.iter_registered_nerfs(work / "kept.json")] == ["capture_a", "capture_b"]


def test_cameras_that_contradict_the_refined_transform_are_refused(oc_renderers, oc_record, work, monkeypatch,
                                                                     tmp_path, capsys):
    # The pair of benchmarks that passed the self-check 13 deg wrong had its refinement 9.2 deg from its cameras.
    assert max(n["residuals"]["rotation_deg_median"] for n in oc_record["nerfs"]) < 0.5  # the correct pair: passes
    _refinement_turned(monkeypatch, 9.0)
    # every default: the check refuses the link before the direct alignment (which would pull a turned transform back
    # a little, to 8.8 deg) and before the cross-renders, so a refused link costs no renders
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work)
    assert_one_line_error(rc, out, err, "capture_b: its SfM cameras disagree with its registered transform by 9.0 deg",
                          "--no-camera-check")
    assert "the bundle adjustment followed points" in err  # its cameras fit the estimator's own transform
    rejected = json.loads((work / "rejected_registration.json").read_text())
    assert rejected["nerfs"][1]["residuals"]["rotation_deg_median"] == pytest.approx(9.0, abs=0.3)
    assert "direct" not in rejected and rejected["pairs"][0]["self_check"] is None
    # 4 deg is within the paper's failure rule: the camera check passes it (the cross-render check judges it)
    _refinement_turned(monkeypatch, 4.0)
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work, self_check_views=0)
    assert rc == 0, err


@pytest.mark.parametrize(("rotation", "centre", "scale", "fails"),
                         [(0.3, 0.01, 1.0, False), (5.5, 0.01, 1.0, True), (0.3, 0.3, 1.0, True),
                          (0.3, 0.3, 0.5, False), (None, None, 1.0, False)])
def test_the_camera_check_applies_the_failure_rule_in_reference_units(rotation, centre, scale, fails):
    from nerfuser_ns.registration.self_check import camera_failure

    # NeRF "a" passes; "b" has the residual medians of the case
    message = camera_failure(["a", "b"], [1.0, scale], [0.1, rotation], [0.0, centre], reg.RegistrationConfig())
    assert (message is not None) == fails
    if fails:
        assert message.startswith("b: its SfM cameras disagree")
        assert "bundle adjustment" in message  # the likely cause: without refinement, cameras among themselves
        alone = camera_failure(["b"], [scale], [rotation], [centre], reg.RegistrationConfig(refine=False))
        assert "among themselves" in alone
        # cameras that fit their own best SIM(3) no better: the SfM itself is distorted, not the bundle adjustment
        distorted = camera_failure(["b"], [scale], [rotation], [centre], reg.RegistrationConfig(),
                                   [(rotation, centre)])  # fmt: skip
        assert "fit no one SIM(3) of its known poses" in distorted and "bundle adjustment" not in distorted
        fits = camera_failure(["b"], [scale], [rotation], [centre], reg.RegistrationConfig(), [(0.1, 0.001)])
        assert "bundle adjustment" in fits
        assert distorted.count("\n") == fits.count("\n") == 0


@pytest.mark.parametrize("mode", ["sfm", "known-geometry", "graph"])
def test_a_failed_self_check_names_the_likely_cause_of_its_mode(mode):
    from nerfuser_ns.registration.self_check import CrossRenderCheck, failure_message

    config = reg.RegistrationConfig(mode=mode, sampling=reg.PoseSamplingConfig(source="training"))
    good, bad = CrossRenderCheck(0, 1, 0.9, 0.8, 4), CrossRenderCheck(1, 2, 0.1, 0.2, 4)
    assert failure_message([good], ["a", "b", "c"], config) is None
    message = failure_message([good, bad], ["a", "b", "c"], config)
    assert message.startswith("b and c: cross-render self-check failed (NCC 0.10 < ")  # the worse direction
    assert ("SfM" in message) == (mode == "sfm") and ("pose graph" in message) == (mode == "graph")
    # known geometry is offered to the SfM mode only (the other modes already register on it)
    assert ("--mode known-geometry" in message) == (mode == "sfm")
    assert "--sampling.max-training-poses" in message


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


def _posed(T: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Camera poses moved by a SIM(3) (rigid poses out: the scale moves the centres only)."""
    R, t, s = sim3.decompose_sim3(T)
    out = c2w.copy()
    out[:, :3, :3] = R @ c2w[:, :3, :3]
    out[:, :3, 3] = s * c2w[:, :3, 3] @ R.T + t
    return out


@pytest.mark.parametrize(("offset_deg", "views_b", "fails"),
                         [(0.0, 8, False), (1.0, 8, False), (10.0, 8, True), (10.0, 3, False)])  # fmt: skip
def test_the_model_check_refuses_sfm_models_that_link_the_nerfs_otherwise(tmp_path, offset_deg, views_b, fails):
    from nerfuser_ns.registration.self_check import model_disagreements, model_failure_line, model_links

    rng = np.random.default_rng(3)
    views = []
    for name in ("a", "b"):
        c2w = sim3.make_sim3(sim3.random_rotation(rng, (8,)), rng.normal(size=(8, 3)))
        views.append(reg.ViewSet(name, tmp_path / name, c2w, ["training"] * 8, np.ones(8), np.ones(8, bool)))
    T_to_ref = np.stack([np.eye(4), sim3.random_sim3(rng, (0.5, 2.0))])
    S = sim3.random_sim3(rng, (0.1, 10.0))  # the other model's frame
    axis = np.array([0.0, 0.0, np.deg2rad(offset_deg)])
    wrong = sim3.make_sim3(Rotation.from_rotvec(axis).as_matrix())
    poses = {}
    for i, vs in enumerate(views):
        G = _posed(S @ (wrong if i == 1 else np.eye(4)) @ T_to_ref[i], vs.c2w)
        for k in range(8 if i == 0 else views_b):
            poses[vs.image_names[k]] = G[k]
    sfm = reg.SfMResult({}, [], {}, 0, 0.0, 0, "exhaustive")
    (links,) = model_links(views, sfm, reg.RegistrationConfig(), [poses])
    assert links.num_views == 8 + views_b and links.views_per_nerf == [8, views_b]
    assert sorted(links.T_to_model) == ([0, 1] if views_b >= 4 else [0])  # 3 views of b: too few to link it
    if offset_deg == 0.0 and views_b >= 4:  # the same link as the registration's, in the model's own frame
        relative = sim3.invert_sim3(links.T_to_model[0]) @ links.T_to_model[1]
        np.testing.assert_allclose(relative, T_to_ref[1], atol=1e-6)
    found = model_disagreements(views, sfm, T_to_ref, reg.RegistrationConfig(), models=[poses])
    assert len(found) == fails
    if fails:  # the other model's link, as transforms the cross-render check scores: a's kept, b's turned
        (d,) = found
        np.testing.assert_allclose(d.T_to_ref[0], T_to_ref[0], atol=1e-9)
        np.testing.assert_allclose(sim3.invert_sim3(d.T_to_ref[0]) @ d.T_to_ref[1],
                                   wrong @ T_to_ref[1], atol=1e-6)  # fmt: skip
        assert d.r_err_deg == pytest.approx(10.0, abs=1e-6) and d.s_err == pytest.approx(0.0, abs=1e-9)
    if fails:
        message = model_failure_line(found[0], ["a", "b"], reg.RegistrationConfig())
        assert message.startswith("b: another SfM model (16 views) links it to a 10.0 deg")
        assert "--no-model-check" in message and "cross-rendered" not in message  # unscored
    assert model_disagreements(views, sfm, T_to_ref, reg.RegistrationConfig(), models=[]) == []


def _other_model_turning(folder: str, T: np.ndarray):
    """``sfm.other_models`` giving one more model: the same views, those of ``folder`` moved by ``T``."""

    def other_models(sfm):
        poses = {n: np.asarray(c, dtype=np.float64) for n, c in sfm.c2w.items()}
        return [{n: _posed(T, G[None])[0] if n.startswith(folder) else G for n, G in poses.items()}]

    return other_models


def test_register_keeps_its_link_when_the_other_models_link_renders_worse(oc_renderers, oc_record, work, monkeypatch,
                                                                          tmp_path, capsys):
    from pathlib import Path

    from nerfuser_ns.registration import self_check

    folder_b = Path(oc_record["nerfs"][1]["render_folder"]).name
    turned = sim3.make_sim3(Rotation.from_rotvec(np.radians([0.0, 10.0, 0.0])).as_matrix())
    monkeypatch.setattr(self_check, "other_models", _other_model_turning(folder_b, turned))
    rc, out, _ = run_cli(tmp_path, oc_renderers, work_dir=work)
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    said = " ".join(captured.out.split())  # rich wraps the console's lines
    assert "but under its link the cross-render self-check failed (NCC" in said and "link kept" in said
    (contest,) = json.loads(out.read_text())["model_check"]["contests"]
    assert contest["nerfs"] == ["capture_a", "capture_b"] and contest["r_err_deg"] == pytest.approx(10.0, abs=0.5)
    assert contest["verdict"] == "kept the registration's link"
    assert contest["registration_ncc"] > contest["model_ncc"] + 0.05  # the turned link renders worse


def test_register_refuses_a_link_that_another_model_links_as_well_or_better(oc_renderers, oc_record, work,
                                                                            monkeypatch, tmp_path, capsys):
    # the registration's link turned 40 deg (refinement and camera check off, so it stays wrong) and another model
    # holding the SfM's own poses, which link the pair right
    from nerfuser_ns.registration import self_check

    perturb_second_estimate(monkeypatch)
    monkeypatch.setattr(self_check, "other_models", lambda sfm: [dict(sfm.c2w)])
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work, refine=False, camera_check=False)
    assert_one_line_error(rc, out, err, "capture_b: another SfM model", "40.0 deg",
                          "cross-rendered on the same views its link scores NCC", "--no-model-check")  # fmt: skip
    rejected = json.loads((work / "rejected_registration.json").read_text())
    (contest,) = rejected["model_check"]["contests"]
    assert contest["verdict"] == "refused" and contest["model_ncc"] > contest["registration_ncc"]
    assert rejected["pairs"][0]["self_check"] is None  # refused before the self-check's own renders
    assert "direct" not in rejected  # ... and before the direct alignment's


@pytest.mark.parametrize(("registration", "model", "depth", "refuses"), [
    (0.80, 0.30, 0.0, False),  # the other link fails the self-check's NCC threshold
    (0.80, 0.70, 0.0, False),  # ... or scores clearly worse (by more than the 0.05 margin)
    (0.80, 0.76, 0.0, True),  # within the margin: ambiguous
    (0.50, 0.70, 0.0, True),  # the other link renders better
    (float("nan"), 0.60, 0.0, True),  # the registration's link saw nothing in common
    (0.50, 0.70, 0.5, False),  # the other link fails the depth check
])  # fmt: skip
def test_model_contest_keeps_the_registration_only_when_the_other_link_renders_clearly_worse(registration, model,
                                                                                             depth, refuses):
    from nerfuser_ns.registration.self_check import CrossRenderCheck, model_contest

    config = reg.RegistrationConfig()
    mine = CrossRenderCheck(0, 1, registration, registration, 4)
    theirs = CrossRenderCheck(0, 1, model, model, 4, depth_i_in_j=depth, depth_j_in_i=0.0)
    assert model_contest(mine, theirs, config) is refuses


def test_tree_edges_run_breadth_first_from_the_reference():
    from nerfuser_ns.registration.self_check import tree_edges

    assert tree_edges([(0, 1), (1, 2), (1, 3)], ref=2) == [(2, 1), (1, 0), (1, 3)]
    assert tree_edges([(0, 1)], ref=0) == [(0, 1)]
