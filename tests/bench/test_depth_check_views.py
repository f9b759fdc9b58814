"""The depth-check view study's scale errors (scripts/depth_check_views.py): a link off in scale by exactly the log
scale asked, about the NeRF's own origin, and a choice of views it does not know refused by the command line."""

from __future__ import annotations

import numpy as np
import pytest
import tyro

from nerfuser_ns import sim3


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("depth_check_views")


@pytest.mark.parametrize("log_scale", [0.1, -0.1, 0.02])
def test_a_scaled_link_is_off_by_that_log_scale_about_the_nerfs_origin(script, log_scale):
    rng = np.random.default_rng(3)
    T = sim3.make_sim3(sim3.so3_exp(rng.normal(size=3)), rng.normal(size=3), 1.7)
    moved = script.scaled(T, log_scale)
    e = sim3.sim3_errors(moved, T)
    assert (float(e.r_err_deg), float(e.s_err)) == pytest.approx((0.0, abs(log_scale)), abs=1e-9)
    assert float(sim3.decompose_sim3(moved)[2]) == pytest.approx(1.7 * np.exp(log_scale))
    assert np.allclose(sim3.transform_points(moved, np.zeros((1, 3))), T[:3, 3])  # the origin stays


def test_an_unknown_choice_of_views_is_refused(script, capsys):
    with pytest.raises(SystemExit) as exc:
        tyro.cli(script.DepthCheckViews, args=["--cases", "street:1=x", "--report", "r.md", "--choices", "middle"])
    assert exc.value.code != 0
