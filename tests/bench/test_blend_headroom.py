"""The blend-headroom diagnostic's math (scripts/blend_headroom.py): the spread cue and the per-view ceiling."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("blend_headroom")


def _edges(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    starts = torch.linspace(1.0, 10.0, n + 1)[:-1]
    return starts, starts + 9.0 / n


def test_a_ray_ending_on_one_sample_has_no_spread_and_a_split_one_does(script):
    starts, ends = _edges(10)
    one = torch.zeros(10)
    one[4] = 0.9
    split = torch.zeros(10)
    split[1], split[8] = 0.45, 0.45
    spread = script.relative_spread(torch.stack([one, split]), starts.expand(2, -1), ends.expand(2, -1))
    assert spread[0] == pytest.approx(1e-6)  # clamped zero
    mids = 0.5 * (starts + ends)
    expected = (0.5 * (mids[8] - mids[1])) / (0.5 * (mids[8] + mids[1]))  # two equal spikes: std = half the gap
    assert spread[1] == pytest.approx(float(expected), rel=1e-5)


def test_the_spread_ignores_the_nerf_scale_and_ranks_empty_rays_last(script):
    starts, ends = _edges(16)
    w = torch.rand(3, 16, generator=torch.Generator().manual_seed(0)) * 0.05
    w[2] = 0.0  # no mass
    base = script.relative_spread(w, starts.expand(3, -1), ends.expand(3, -1))
    scaled = script.relative_spread(w, 2.5 * starts.expand(3, -1), 2.5 * ends.expand(3, -1))
    assert torch.allclose(base[:2], scaled[:2], rtol=1e-5)
    assert base[2] == pytest.approx(1e6) and bool((base[:2] < 1.0).all())


def test_the_per_view_weight_recovers_a_known_mix_and_stays_convex(script):
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(3, 4, 5, 3, generator=g), torch.rand(3, 4, 5, 3, generator=g)
    alpha = torch.tensor([0.0, 0.3, 1.0])
    target = alpha[:, None, None, None] * a + (1 - alpha[:, None, None, None]) * b
    assert torch.allclose(script.best_view_weight(a, b, target), alpha, atol=1e-5)
    beyond = 2.0 * a - b  # alpha 2: outside the convex range, clamped to 1
    assert script.best_view_weight(a, b, beyond).tolist() == pytest.approx([1.0, 1.0, 1.0])


def test_the_per_view_table_states_each_view_and_the_sample_minus_nearest_gap(script):
    methods = script.PER_VIEW_COLUMNS
    case = {"case": "street-x", "view_ids": [3, 7], "camera_to_origin": [[0.5, 1.25], [1.0, 0.75]],
            "best_weight_nerf0": [0.8, 0.2],
            "per_view_psnr": {m: [20.0 + i, 21.0 + i] for i, m in enumerate(methods)}}  # fmt: skip
    case["per_view_psnr"]["nearest"], case["per_view_psnr"]["idw-sample"] = [24.0, 22.0], [23.5, 22.25]
    rows = [line for line in script._per_view_table(case) if line.startswith("| 3 ") or line.startswith("| 7 ")]
    assert len(rows) == 2
    assert rows[0].startswith("| 3 | 0.500 / 1.250 |") and rows[0].endswith("| -0.50 | 0.80 |")
    assert rows[1].endswith("| +0.25 | 0.20 |")
    assert script._per_view_table({"case": "old"}) == []  # results kept before the per-view figures: no table
