"""The rigid-set bundle adjustment of mode ``sfm`` (:mod:`nerfuser_ns.registration.refine`) on the object-centric
pair: more accurate than the camera estimator alone, and a start 40 deg off converges to the right answer (which the
camera check passes: the cameras agree with it)."""

from __future__ import annotations

import numpy as np
from registration_helpers import gt_of, perturb_second_estimate, small_config

from nerfuser_ns import registration as reg
from nerfuser_ns.bench.ground_truth import score_registration
from nerfuser_ns.registration.config import DirectConfig


def test_refinement_beats_the_camera_estimator(oc_layout, oc_renderers, oc_record, work):
    # Same renders and SfM (reused): only the solve differs (the direct alignment after it off in both).
    off = DirectConfig(enabled=False)
    plain = score_registration(reg.register(oc_renderers, small_config(refine=False, direct=off), work),
                               gt_of(oc_layout))  # fmt: skip
    assert plain["refinement"] is None and plain["nerfs"][1]["refinement_change"] is None
    assert plain["sfm"]["reused"]
    refined = score_registration(reg.register(oc_renderers, small_config(direct=off), work), gt_of(oc_layout))
    g0, g = plain["nerfs"][1]["ground_truth"], refined["nerfs"][1]["ground_truth"]
    assert g["r_err_deg"] < g0["r_err_deg"] and g["t_err"] < g0["t_err"] and g["s_err"] < g0["s_err"]


def test_refinement_corrects_a_wrong_start(oc_layout, oc_renderers, oc_record, work, monkeypatch):
    # The bundle adjustment fits the image evidence, so a start 40 deg off still converges to the right answer.
    perturb_second_estimate(monkeypatch)
    rec = score_registration(reg.register(oc_renderers, small_config(), work), gt_of(oc_layout))
    assert rec["refinement"]["change"][1]["r_deg"] > 39
    # the SfM's cameras agree with where it converged, so the camera check passes what moved that far
    assert rec["nerfs"][1]["residuals"]["rotation_deg_median"] < 0.5
    np.testing.assert_allclose(rec["nerfs"][1]["T_to_reference"], oc_record["nerfs"][1]["T_to_reference"], atol=1e-5)
