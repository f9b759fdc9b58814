"""The model-check study (scripts/model_check_cases.py): which refusals it registers again, and how it judges a check
against the truth. The links it reads per SfM model are :func:`nerfuser_ns.registration.self_check.model_links`
(tests/registration/test_self_check.py)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("model_check_cases")


def test_only_the_model_checks_refusals_are_registered_again(script):
    model = ("capture_1/nerfacto/bench: another SfM model (31 views) links it to capture_0/nerfacto/bench 13.4 deg, "
             "0.647 reference units and 2.132 in log scale away from the registration's link")  # fmt: skip
    camera = "capture_0/nerfacto/bench: its SfM cameras disagree with its registered transform by 26.6 deg"
    depth = "capture_0 and capture_1: cross-render depth check: another SfM model was not involved"
    record = {"sampling_choice": {"tried_before": [
        {"source": "training", "mode": "sfm", "error": model},
        {"source": "both", "mode": "sfm", "error": camera},
        {"source": "hemisphere", "mode": "sfm", "error": depth},
    ]}}  # fmt: skip
    assert [t["source"] for t in script.model_check_refusals(record)] == ["training"]
    assert script.model_check_refusals({"sampling_choice": {"tried_before": []}}) == []
    assert script.model_check_refusals({}) == []  # registered with an explicit source: nothing was tried before
    settings = {"sampling": {"source": "training"}, "mode": "sfm"}
    refused = script.model_check_refusals({"refused": model, "settings": settings})  # refused with one pose source
    assert refused == [{"source": "training", "mode": "sfm", "error": model}]
    auto = f"no pose source registered the runs, 4 tried: training (sfm): {model}"  # its attempts are tried_before's
    assert script.model_check_refusals({"refused": auto, "settings": settings}) == []
    assert script.model_check_refusals({"refused": camera, "settings": settings}) == []


@pytest.mark.parametrize(
    ("failure", "refused", "right"),
    [(True, True, True), (False, True, False), (True, False, False), (False, False, True)],
)
def test_a_check_is_right_when_it_refuses_exactly_the_failures(script, failure, refused, right):
    assert script.verdict(failure, refused).startswith("right" if right else "wrong")
