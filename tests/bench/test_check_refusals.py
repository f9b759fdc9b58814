"""The study of the render-free checks' refusals (scripts/check_refusals.py): which refusals it registers again, and
how it judges a check against the truth. The links it reads per SfM model are
:func:`nerfuser_ns.registration.self_check.model_links` (tests/registration/test_self_check.py)."""

from __future__ import annotations

import pytest

MODEL = ("capture_1/nerfacto/bench: another SfM model (31 views) links it to capture_0/nerfacto/bench 13.4 deg, 0.647 "
         "reference units and 2.132 in log scale away from the registration's link")  # fmt: skip
CAMERA = ("capture_0/nerfacto/bench: its SfM cameras disagree with its registered transform by 26.6 deg and 1.149 "
          "reference units (median; the paper's failure rule: 5 deg, 0.2)")  # fmt: skip
DEPTH = ("capture_0 and capture_1: cross-render depth check: median log depth ratio +0.081, beyond 0.07 (not "
         "another SfM model ( nor its SfM cameras disagree with its registered transform)")  # fmt: skip
SETTINGS = {"sampling": {"source": "training"}, "mode": "sfm"}


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("check_refusals")


def test_the_render_free_checks_refusals_are_registered_again(script):
    record = {"sampling_choice": {"tried_before": [
        {"source": "training", "mode": "sfm", "error": MODEL, "seconds": 1.0},
        {"source": "both", "mode": "sfm", "error": CAMERA},
        {"source": "hemisphere", "mode": "sfm", "error": DEPTH},
    ]}}  # fmt: skip
    assert script.refusals(record) == [
        {"check": "model", "source": "training", "mode": "sfm", "error": MODEL},
        {"check": "camera", "source": "both", "mode": "sfm", "error": CAMERA},
    ]
    assert script.refusals({"sampling_choice": {"tried_before": []}}) == []
    assert script.refusals({}) == []  # registered with an explicit source: nothing was tried before


def test_a_solution_refused_with_one_pose_source_is_its_own_refusal(script):
    assert script.refusals({"refused": MODEL, "settings": SETTINGS}) == [
        {"check": "model", "source": "training", "mode": "sfm", "error": MODEL}
    ]
    assert script.refusals({"refused": CAMERA, "settings": SETTINGS})[0]["check"] == "camera"
    assert script.refusals({"refused": DEPTH, "settings": SETTINGS}) == []
    auto = f"no pose source registered the runs, 4 tried: training (sfm): {MODEL}"  # its attempts are tried_before's
    assert script.refusals({"refused": auto, "settings": SETTINGS}) == []


def test_a_refusal_line_names_its_check(script):
    assert script.refused_by(MODEL) == "model"
    assert script.refused_by(CAMERA) == "camera"
    assert script.refused_by(DEPTH) is None
    assert script.refused_by("passed") is None
    assert script.refused_by(f"no pose source registered the runs, 4 tried: training (sfm): {MODEL}") is None


@pytest.mark.parametrize(
    ("failure", "refused", "right"),
    [(True, True, True), (False, True, False), (True, False, False), (False, False, True)],
)
def test_a_check_is_right_when_it_refuses_exactly_the_failures(script, failure, refused, right):
    assert script.verdict(failure, refused).startswith("right" if right else "wrong")
