"""A run's rendered depth over the true depth (scripts/depth_vs_truth.py): the ratio table on synthetic depth maps."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("depth_vs_truth")


def test_a_content_at_the_wrong_scale_shows_in_the_ratio(script):
    rng = np.random.default_rng(0)
    true = [rng.uniform(1.0, 10.0, (12, 16)) for _ in range(3)]
    acc = [np.ones((12, 16)) for _ in range(3)]
    exact = script.depth_ratios([t.copy() for t in true], true, acc, 0.95)
    assert exact["median"] == pytest.approx(1.0) and exact["pixels"] == 3 * 12 * 16
    assert all(b["median"] == pytest.approx(1.0) for b in exact["by_true_depth"])
    # far surfaces pulled in by 20%: the far quarter says so, the near one does not
    pulled = [np.where(t > 7.0, 0.8 * t, t) for t in true]
    table = script.depth_ratios(pulled, true, acc, 0.95)
    assert table["by_true_depth"][-1]["median"] == pytest.approx(0.8)
    assert table["by_true_depth"][0]["median"] == pytest.approx(1.0)
    # transparent NeRF pixels and pixels without a scene surface are left out
    acc[0][:6] = 0.5
    true[1][0, 0] = np.inf
    assert script.depth_ratios(true, true, acc, 0.95)["pixels"] == 3 * 12 * 16 - 6 * 16 - 1
    with pytest.raises(ValueError, match="no pixel is opaque"):
        script.depth_ratios(true, true, [np.zeros((12, 16))] * 3, 0.95)
