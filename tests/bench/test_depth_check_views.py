"""The depth-check view study's command line (scripts/depth_check_views.py): a choice of views it does not know is
refused. Its scale errors are :func:`nerfuser_ns.sim3.rescaled_about_origin` (tests/test_sim3.py)."""

from __future__ import annotations

import pytest
import tyro


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("depth_check_views")


def test_an_unknown_choice_of_views_is_refused(script, capsys):
    with pytest.raises(SystemExit) as exc:
        tyro.cli(script.DepthCheckViews, args=["--cases", "street:1=x", "--report", "r.md", "--choices", "middle"])
    assert exc.value.code != 0
