"""Registration end to end (:mod:`nerfuser_ns.registration.pipeline` and ``ns-nerfuser-register``), through
pycolmap (CPU): the object-centric pair against ground truth, re-runs and options, the command's file and summary,
the automatic choice of pose sampling, one-line errors on bad inputs, and the real command on tiny trained nerfacto
checkpoints.

The "NeRFs" are mostly ground-truth scene renderers seen through their capture frames (exact, fast); the tiny-run
tests train real ones. Renders and SfM results are cached in the work folder the registration tests share
(``conftest.py``), so tests that reuse a NeRF's views do not render them again.
"""

from __future__ import annotations

import copy
import json
import shutil
import sys
from pathlib import Path, PurePath
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from registration_helpers import FakeRenderer, W, assert_one_line_error, gt_of, run_cli, small_config
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns import runs, sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.bench.ground_truth import ScoreCommand, score_registration
from nerfuser_ns.bench.scene_renderer import SceneFrameRenderer
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration import pipeline as reg_pipeline
from nerfuser_ns.registration.reference_colour import reference_colour
from nerfuser_ns.renderers import NerfstudioRenderer, RenderBatch
from nerfuser_ns.scripts import register as cli


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


# ---------------------------------------------------------------------------------------------------------------------
# End to end on ground-truth renderers


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
    assert set(rec["timings_s"]) == {"render", "features", "matching", "mapping", "solve", "model_check", "direct",
                                     "self_check"}  # fmt: skip
    assert "model_check" not in rec  # no other SfM model disagreed: nothing cross-rendered, nothing recorded
    assert rec["settings"]["sampling"]["num_poses"] == 20


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
    assert f"next: ns-train nerfuser --data {out} (then ns-viewer)" in printed  # what to run with the file
    # the kit scores the file afterwards, into a copy
    console = Console(record=True, width=200)
    scored = ScoreCommand(out, gt_transforms=gt).main(console)
    assert scored["nerfs"][1]["ground_truth"]["r_err_deg"] < 0.15 and "r_err" in console.export_text()
    assert reg.read_registration(out.with_name(out.stem + "_scored.json"))["ground_truth"]["failure"] is False
    assert "ground_truth" not in json.loads(out.read_text())  # the input is untouched
    with pytest.raises(reg.RegistrationError, match="is the input registration file"):
        ScoreCommand(out, gt_transforms=gt, output=out).main(console)


def test_cli_writes_a_fusion_spec_beside_and_never_over_another(oc_renderers, work, tmp_path, capsys):
    """--fusion-spec: the spec ns-train nerfuser and ns-eval take (the registration file, relative to the spec, and
    the reference run's held-out images); a spec already there is replaced only where it is the same, checked before
    anything is rendered; the registration file itself is refused as the spec."""
    spec = tmp_path / "specs" / "fusion.json"
    rc, out, _ = run_cli(tmp_path, oc_renderers, None, work_dir=work, fusion_spec=spec)
    printed = capsys.readouterr()
    assert rc == 0, printed.err
    assert json.loads(spec.read_text()) == {"registration": "../registration.json", "test_run": "capture_a"}
    assert f"next: ns-train nerfuser --data {spec}" in printed.out
    rc, out, err = run_cli(tmp_path, oc_renderers, capsys, work_dir=work, fusion_spec=spec)  # the same spec again
    assert rc == 0, err
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "fusion.json").write_text('{"registration": "../registration.json", "test_data": "test"}\n')
    rc, out, err = run_cli(mine, oc_renderers, capsys, work_dir=work, fusion_spec=mine / "fusion.json")
    assert_one_line_error(rc, out, err, "exists and holds another spec")
    assert json.loads((mine / "fusion.json").read_text())["test_data"] == "test"  # the user's spec untouched
    rc, out, err = run_cli(mine, oc_renderers, capsys, work_dir=work, fusion_spec=mine / "registration.json")
    assert_one_line_error(rc, out, err, "is the registration file")
    # datasets moved (--data): the held-out images cannot be found through the runs' configs, so no test_run
    moved = cli.RegisterCommand(output=tmp_path / "registration.json", fusion_spec=tmp_path / "fusion.json",
                                data=[tmp_path / "a", tmp_path / "b"])  # fmt: skip
    assert json.loads(moved._spec_text("capture_a")) == {"registration": "registration.json"}


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


# ---------------------------------------------------------------------------------------------------------------------
# Automatic pose sampling


def test_automatic_sampling_uses_training_poses_when_datasets_are_readable(oc_layout, oc_renderers):
    choices = reg.resolve_sampling(oc_renderers, reg.RegistrationConfig())
    assert [c.config.sampling.source for c in choices] == ["training", "both", "hemisphere", "both"]
    # SfM first with every source, known geometry last
    assert [c.config.mode for c in choices] == ["sfm"] * 3 + ["known-geometry"]
    assert "SfM registered with no pose source" in choices[-1].reason
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
    assert [(c.config.sampling.source, c.config.mode) for c in choices] == [("hemisphere", "sfm")]  # no depth either
    assert "training poses unavailable" in choices[0].reason
    sc = choices[0].config.sampling
    assert (sc.width, sc.height, sc.fov_deg) == reg.DEFAULT_RENDER_SIZE
    # one run without its dataset is enough to need the hemisphere for all
    mixed = reg.resolve_sampling([oc_renderers[0], blind[1]], reg.RegistrationConfig())
    assert [c.config.sampling.source for c in mixed] == ["hemisphere"]
    # runs that render depth but lost their datasets: known geometry on the hemisphere last
    datasetless = [SimpleNamespace(name=r.name, render=r.render, training_poses=lambda: None) for r in oc_renderers]
    choices = reg.resolve_sampling(datasetless, reg.RegistrationConfig())
    assert [(c.config.sampling.source, c.config.mode) for c in choices] == [("hemisphere", "sfm"),
                                                                            ("hemisphere", "known-geometry")]
    # a mode given explicitly keeps to itself
    kg = reg.resolve_sampling(oc_renderers, reg.RegistrationConfig(mode="known-geometry"))
    assert [(c.config.sampling.source, c.config.mode) for c in kg] == [
        ("training", "known-geometry"), ("both", "known-geometry"), ("hemisphere", "known-geometry")]


class DepthCountingRenderer:
    """A renderer that gives depth and counts the views it renders."""

    def __init__(self, inner):
        self.inner, self.name, self.rendered = inner, inner.name, 0

    def cache_key(self):
        return self.inner.cache_key()

    def training_poses(self):
        return self.inner.training_poses()

    def render(self, c2w, intrinsics, depth: bool = False):
        self.rendered += len(c2w)
        return self.inner.render(c2w, intrinsics, depth=depth)


def test_sfm_renders_keep_depth_for_known_geometry(oc_renderers, tmp_path, monkeypatch):
    # the SfM mode stores depth where every renderer gives it: known geometry, the automatic choice's last step, lifts
    # those views instead of rendering them again
    def no_sfm(*args):
        raise reg.RegistrationError("a: its views form a separate SfM model")

    monkeypatch.setattr(reg_pipeline, "run_sfm", no_sfm)
    counting = [DepthCountingRenderer(r) for r in oc_renderers]
    config = small_config(num_poses=4)
    with pytest.raises(reg.RegistrationError, match="separate SfM model"):
        reg_pipeline.register_once(counting, config, tmp_path, Console(quiet=True))
    assert [c.rendered for c in counting] == [4, 4]
    again = [reg.render_views_cached(c, config.sampling, tmp_path / "renders", Console(quiet=True), depth=True)
             for c in counting]  # fmt: skip
    assert all(v.reused and v.has_depth for v in again) and [c.rendered for c in counting] == [4, 4]
    direct = oc_renderers[0].render(again[0].c2w[:1], config.sampling.intrinsics(), depth=True).depth[0]
    np.testing.assert_allclose(again[0].load_depth()[0], direct, rtol=1e-6)
    # a renderer without depth: the SfM mode renders images alone, as before
    plain = [SimpleNamespace(name=r.name, cache_key=r.cache_key, training_poses=r.training_poses,
                             render=lambda c2w, k, r=r: r.render(c2w, k)) for r in oc_renderers]  # fmt: skip
    with pytest.raises(reg.RegistrationError, match="separate SfM model"):
        reg_pipeline.register_once(plain, config, tmp_path / "plain", Console(quiet=True))
    assert not any((f / "depth.npz").exists() for f in (tmp_path / "plain" / "renders").iterdir())


def test_automatic_sampling_falls_back_and_says_so(oc_renderers, work, monkeypatch):
    tried = []

    def once(renderers, config, work_dir, console):
        tried.append(config.sampling.source)
        if config.sampling.source == "training":
            raise reg.RegistrationError("a: its views form a separate SfM model")
        # register() records its choice, and the reference NeRF's colour map (or why not), on the result
        return SimpleNamespace(sampling_choice=None, reference=0, nerfs=[], reference_colour=None)

    monkeypatch.setattr(reg_pipeline, "register_once", once)
    console = Console(record=True, width=200)
    record = reg.register(oc_renderers, reg.RegistrationConfig(), work, console=console)
    assert tried == ["training", "both"]
    assert record.sampling_choice["source"] == "both"
    (before,) = record.sampling_choice["tried_before"]
    assert before.pop("seconds") >= 0  # the failed attempt's own time: its renders stay in the work folder
    assert before == {"source": "training", "mode": "sfm", "error": "a: its views form a separate SfM model"}
    text = console.export_text()
    for line in ("automatic pose sampling: tries training (sfm), both (sfm), hemisphere (sfm), both (known-geometry) "
                 "in turn", "pose sampling: training", "training poses did not register (sfm, 0 s)",
                 "trying next (2 of 4): both (sfm)", "pose sampling: both",
                 "appearance: the colour maps stay relative to the reference NeRF"):
        assert line in text, line
    assert "no training images" in record.reference_colour["skipped"]  # ground-truth renderers have none
    # SfM failing with every source: known geometry last, said so
    tried.clear()

    def sfm_fails(renderers, config, work_dir, console):
        tried.append((config.sampling.source, config.mode))
        if config.mode == "sfm":
            raise reg.RegistrationError("b: its SfM cameras disagree with its registered transform")
        return SimpleNamespace(sampling_choice=None, reference=0, nerfs=[], reference_colour=None)

    monkeypatch.setattr(reg_pipeline, "register_once", sfm_fails)
    console = Console(record=True, width=200)
    record = reg.register(oc_renderers, reg.RegistrationConfig(), work, console=console)
    assert tried == [("training", "sfm"), ("both", "sfm"), ("hemisphere", "sfm"), ("both", "known-geometry")]
    assert (record.sampling_choice["source"], record.sampling_choice["mode"]) == ("both", "known-geometry")
    text = console.export_text()
    assert "pose sampling: both, mode known-geometry (SfM registered with no pose source" in text
    assert "trying next (4 of 4): both (known-geometry)" in text
    # every choice failing: one line with what each try found (its advice dropped) and the causes left
    def every_one_fails(renderers, config, work_dir, console):
        raise reg.RegistrationError(f"{config.sampling.source}: depth check failed (ratio 0.84; beyond 0.07); render "
                                    "more poses")  # fmt: skip

    monkeypatch.setattr(reg_pipeline, "register_once", every_one_fails)
    with pytest.raises(reg.RegistrationError) as failed:
        reg.register(oc_renderers, reg.RegistrationConfig(), work, console=Console(quiet=True))
    message = str(failed.value)
    assert "\n" not in message and message.startswith("no pose source registered the runs, 4 tried: training (sfm): "
                                                      "training: depth check failed (ratio 0.84; beyond 0.07); both")
    assert "both (known-geometry): both: depth check failed (ratio 0.84; beyond 0.07). Either" in message
    assert "render more poses" not in message and "ns-nerfuser-check-capture" in message and str(work) in message
    # a run whose capture check found a fold is named as the cause
    text = reg_pipeline.every_choice_failed(
        [{"source": "training", "mode": "sfm", "error": "b: separate SfM model; render more"}], work,
        {"a": {"folded": False, "matches": {"folded": False}}, "b": {"folded": False, "matches": {"folded": True}}})
    assert "training (sfm): b: separate SfM model. The capture check found b trained on folded COLMAP poses" in text
    assert "Either the runs" not in text and "render more" not in text
    # every run's poses vouched for by the checks (matched exhaustively, every match explained): no fold to blame
    clean = {"folded": False, "matches": {"checked": True, "folded": False, "compared_pairs": 66, "possible_pairs": 66}}
    attempt = [{"source": "training", "mode": "sfm", "error": "depth check failed"}]
    text = reg_pipeline.every_choice_failed(attempt, work, {"a": clean, "b": clean}, num_runs=2)
    assert "found every run's COLMAP poses consistent" in text and "or a check refused a right link" in text
    assert "repeated structure" not in text
    sequential = {**clean, "matches": {**clean["matches"], "compared_pairs": 21}}  # the check's blind spot
    for checks, count in (({"a": clean}, 2), ({"a": clean, "b": sequential}, 2), ({"a": clean, "b": clean}, None)):
        assert "repeated structure can fold" in reg_pipeline.every_choice_failed(attempt, work, checks, num_runs=count)
    # one pose source as given: its own error, unchanged
    with pytest.raises(reg.RegistrationError, match="^hemisphere: depth check failed .*render more poses$"):
        reg.register(oc_renderers, reg.RegistrationConfig(sampling=reg.PoseSamplingConfig(source="hemisphere")), work,
                     console=Console(quiet=True))  # fmt: skip
    # every choice refused by a check: the refused solution (kept as rejected_registration.json) says what ran before it
    def refused(renderers, config, work_dir, console):
        turn = sim3.make_sim3(sim3.so3_exp(np.array([0.0, 0.0, len(config.sampling.source) / 100])), np.zeros(3), 1.0)
        rejected = SimpleNamespace(sampling_choice=None, nerfs=[SimpleNamespace(T_to_reference=np.eye(4)),
                                                                SimpleNamespace(T_to_reference=turn)])
        raise reg.RegistrationFailed(f"{config.sampling.source}/{config.mode}: self-check failed", rejected)

    monkeypatch.setattr(reg_pipeline, "register_once", refused)
    last = "both \\(known-geometry\\): both/known-geometry: self-check failed"
    with pytest.raises(reg.RegistrationFailed, match=last) as failed:
        reg.register(oc_renderers, reg.RegistrationConfig(), work, console=Console(quiet=True))
    choice = failed.value.result.sampling_choice
    assert (choice["source"], choice["mode"]) == ("both", "known-geometry")
    assert [(t["source"], t["mode"]) for t in choice["tried_before"]] == [("training", "sfm"), ("both", "sfm"),
                                                                          ("hemisphere", "sfm")]
    assert choice["tried_before"][0]["error"] == "training/sfm: self-check failed"
    # each refused attempt keeps its solution (JSON lists), so the checks can be judged against a truth afterwards
    turned = [np.asarray(t["refused_transforms"][1]) for t in choice["tried_before"]]
    assert [float(sim3.rotation_angle_deg(T[:3, :3])) for T in turned] == pytest.approx(
        [np.rad2deg(len(s) / 100) for s in ("training", "both", "hemisphere")])
    assert all(t["refused_transforms"][0] == np.eye(4).tolist() for t in choice["tried_before"])
    # an attempt that raised a plain error (no solution) keeps none
    monkeypatch.setattr(reg_pipeline, "register_once", sfm_fails)
    record = reg.register(oc_renderers, reg.RegistrationConfig(), work, console=Console(quiet=True))
    assert all("refused_transforms" not in t for t in record.sampling_choice["tried_before"])


def test_a_twin_refusal_goes_to_known_geometry_on_the_same_renders(oc_renderers, work, monkeypatch):
    tried = []

    def twin_then_kg(renderers, config, work_dir, console):
        tried.append((config.sampling.source, config.mode))
        if config.mode == "sfm":
            rejected = SimpleNamespace(sampling_choice=None, nerfs=[SimpleNamespace(T_to_reference=np.eye(4))] * 2)
            raise reg.TwinLinked("twin check: a / b: another transform renders better", rejected)
        return SimpleNamespace(sampling_choice=None, reference=0, nerfs=[], reference_colour=None)

    monkeypatch.setattr(reg_pipeline, "register_once", twin_then_kg)
    console = Console(record=True, width=200)
    record = reg.register(oc_renderers, reg.RegistrationConfig(), work, console=console)
    # no further SfM over the same repeated structure: known geometry on the training renders, right away
    assert tried == [("training", "sfm"), ("training", "known-geometry")]
    assert record.sampling_choice["reason"].startswith("the twin check refused the SfM's link")
    assert "trying next (2 of 3): training (known-geometry)" in console.export_text()
    # known geometry failing there too: then on the most views, as the automatic choice's last step
    tried.clear()

    def twin_then_fail(renderers, config, work_dir, console):
        twin_then_kg(renderers, config, work_dir, console)
        if config.sampling.source == "training":
            raise reg.RegistrationError("a and b: ambiguous")
        return SimpleNamespace(sampling_choice=None, reference=0, nerfs=[], reference_colour=None)

    monkeypatch.setattr(reg_pipeline, "register_once", twin_then_fail)
    reg.register(oc_renderers, reg.RegistrationConfig(), work, console=Console(quiet=True))
    assert tried == [("training", "sfm"), ("training", "known-geometry"), ("both", "known-geometry")]
    # an explicit pose source tries that source in that mode only: the refusal is the error
    tried.clear()
    config = reg.RegistrationConfig(sampling=reg.PoseSamplingConfig(source="training"))
    with pytest.raises(reg.TwinLinked, match="twin check"):
        reg.register(oc_renderers, config, work, console=Console(quiet=True))
    assert tried == [("training", "sfm")]


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
        # named by the folders that tell them apart (both are tiny/<method>/<timestamp>), not by whole paths
        assert [n["name"] for n in rec["nerfs"]] == [str(PurePath(*p.parts[-5:-1])) for p in (first, second)]
        scored = ScoreCommand(out, ground_truth=root / "scene", gt_captures=["capture_a", "capture_a"]).main()
        assert scored["nerfs"][1]["ground_truth"] is not None
        assert rec["nerfs"][0]["checkpoint"] == runs.checkpoint_identity(first)  # which weights were registered
    else:
        assert_one_line_error(exit_info.value.code, out, err)
        # the last word is known geometry's when SfM registered from no pose source
        assert any(s in err for s in ("views registered", "reconstructed nothing", "see enough", "self-check",
                                      "reliable, multi-view", "inlier 3D matches")), err
        names = runs.run_names([first, second])
        assert names == [str(PurePath(*p.parts[-5:-1])) for p in (first, second)]
        assert any(n in err for n in names) or "reconstructed nothing" in err
        assert str(root) not in err, "runs are named by their distinguishing folders, not whole paths"
    # the renders are kept for a re-run (one folder per NeRF and pose source the automatic choice tried; known
    # geometry's, with depth, are folders of their own)
    assert len(list((tmp_path / "registration_work" / "renders").glob("*/poses.json"))) in (2, 4, 6, 8)


def test_training_views_render_as_the_pinhole_path(tiny_runs):
    """A run's training cameras rendered by camera (its own intrinsics and distortion) equal the pinhole render at
    the same pose when the cameras have no distortion; the reference NeRF's colour map comes from them."""
    renderer = NerfstudioRenderer(tiny_runs[1])
    (batch,) = renderer.render_training_views([3], 2)
    assert batch.rgb.shape == (1, 15, 20, 3) and batch.accumulation.shape == (1, 15, 20)
    k = renderer.training_intrinsics()
    half = Intrinsics(k.fx / 2, k.fy / 2, k.cx / 2, k.cy / 2, 20, 15)
    pinhole = renderer.render(renderer.training_poses()[3:4], half)
    np.testing.assert_allclose(batch.rgb, pinhole.rgb, atol=1e-5)
    assert len(renderer.training_image_files()) == len(renderer.training_poses())
    root = tiny_runs[0]
    assert renderer.dataset_path().resolve() == (root / "scene" / "capture_a").resolve()  # the match check reads it
    assert NerfstudioRenderer(tiny_runs[1], data_override=root / "gone").dataset_path() is None
    transforms = root / "scene" / "capture_a" / "transforms.json"  # a run trained on one transforms file: that file
    assert NerfstudioRenderer(tiny_runs[1], data_override=transforms).dataset_path() == transforms
    rc = reference_colour(renderer, 3)
    assert (rc.colour_map is not None and rc.views == 3) or "too few" in rc.skipped


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


# ---------------------------------------------------------------------------------------------------------------------
# Checked before any rendering; interrupted; warned about


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


def test_an_implausible_scale_is_warned_about(oc_renderers, oc_record, tmp_path, capsys, monkeypatch):
    record = copy.deepcopy(oc_record)
    record["nerfs"][1]["scale_to_reference"] = 1e-6
    monkeypatch.setattr(cli, "register", lambda *args, **kwargs: reg.RegistrationResult.from_record(record))
    rc, out, _ = run_cli(tmp_path, oc_renderers, None, work_dir=tmp_path / "work")
    printed = " ".join(capsys.readouterr().out.split())
    assert rc == 0 and out.is_file()
    assert "implausible scale to the reference for capture_b" in printed and "same place" in printed
