"""Appearance matching (ours): the colour-map estimate, its algebra, and the generator's per-capture appearance."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerfuser_ns.appearance import (
    IDENTITY,
    apply_colour_map,
    chain_to_reference,
    compose,
    fit_colour_map,
    fit_colour_map_directions,
    linear_to_srgb,
    srgb_to_linear,
)
from nerfuser_ns.bench import scenes

KNOWN = np.array([[0.8, 0.05, 0.0, 0.01], [0.02, 1.1, 0.03, -0.01], [0.0, 0.1, 0.7, 0.02]])
GAINS = np.array([0.8, 1.3, 0.6])  # an exposure and white-balance difference: per-channel gains on linear RGB


def test_the_estimate_recovers_known_gains():
    rng = np.random.default_rng(0)
    src = rng.uniform(0.05, 0.95, size=(2000, 3))
    gain_map = np.hstack([np.diag(GAINS), np.zeros((3, 1))])
    dst = apply_colour_map(torch.from_numpy(src), torch.from_numpy(gain_map)).numpy()
    np.testing.assert_allclose(fit_colour_map(src, dst), gain_map, atol=1e-9)  # green's clipped pixels left out
    # Saturated pixels (a clipped sky in one render) are left out, not fitted.
    src[:300] = 1.0
    dst[300:600] = 1.0
    np.testing.assert_allclose(fit_colour_map(src, dst), gain_map, atol=1e-9)
    assert fit_colour_map(src[:40], dst[:40]) is None  # too few pixels
    assert fit_colour_map(src, np.full_like(dst, 0.001)) is None  # a 'gain' of 1/1000: no match, not an exposure


def test_each_nerfs_advantage_on_its_own_views_cancels_between_the_directions():
    # Each NeRF renders its own views brighter than the other renders them (the source's own views in the first
    # direction, the target's in the second): one direction alone is off by that factor, pooling the pixels weights
    # the directions by their brightness, the geometric mean of the two directions' gains is exact.
    rng = np.random.default_rng(2)
    gain_map = np.hstack([np.diag(GAINS), np.zeros((3, 1))])
    advantage = np.hstack([np.diag([1.25, 1.2, 1.15]), np.zeros((3, 1))])
    as_map = lambda c, m: apply_colour_map(torch.from_numpy(c), torch.from_numpy(m)).numpy()  # noqa: E731
    dark, bright = rng.uniform(0.02, 0.3, size=(500, 3)), rng.uniform(0.2, 0.6, size=(3000, 3))
    own_source = (as_map(dark, advantage), as_map(dark, gain_map))  # the source at its own views
    own_target = (bright, as_map(as_map(bright, gain_map), advantage))  # the target at its own views
    np.testing.assert_allclose(fit_colour_map_directions([own_source, own_target]), gain_map, atol=1e-9)
    one = np.diag(fit_colour_map(*own_source)[:, :3])
    np.testing.assert_allclose(one, GAINS / [1.25, 1.2, 1.15], rtol=1e-9)
    pooled = np.diag(fit_colour_map(np.concatenate([own_source[0], own_target[0]]),
                                    np.concatenate([own_source[1], own_target[1]]))[:, :3])  # fmt: skip
    assert np.abs(np.log(pooled / GAINS)).max() > 0.05
    # a direction with too few pixels is left out; none left: no map
    few = (dark[:10], dark[:10])
    np.testing.assert_allclose(fit_colour_map_directions([own_source, few]), fit_colour_map(*own_source))
    assert fit_colour_map_directions([few]) is None


def test_misaligned_renders_of_the_same_colours_give_the_identity():
    # Two renders of one textured surface a few pixels apart (registration error, each NeRF's blur), no colour
    # difference: a per-pixel regression of one on the other would shrink the map towards 0; the gains stay 1.
    rng = np.random.default_rng(1)
    texture = rng.uniform(0.05, 0.95, size=(96, 104, 3))
    src, dst = texture[:, :96], texture[:, 6:102]
    np.testing.assert_allclose(fit_colour_map(src, dst), IDENTITY, atol=0.03)


def test_transfer_functions_and_map_algebra():
    x = torch.linspace(0, 1, 1001, dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(x)), x)
    rgb = torch.rand(10, 3, dtype=torch.float64)
    torch.testing.assert_close(apply_colour_map(rgb, torch.from_numpy(IDENTITY)), rgb)
    inner = np.hstack([0.9 * np.eye(3), np.full((3, 1), 0.01)])
    both = apply_colour_map(apply_colour_map(rgb * 0.5, torch.from_numpy(inner)), torch.from_numpy(KNOWN))
    torch.testing.assert_close(apply_colour_map(rgb * 0.5, torch.from_numpy(compose(KNOWN, inner))), both)
    maps = chain_to_reference(3, 1, {(1, 0): KNOWN, (0, 2): inner, (2, 0): None})
    np.testing.assert_allclose(maps[1], IDENTITY)
    np.testing.assert_allclose(maps[0], KNOWN)
    np.testing.assert_allclose(maps[2], compose(KNOWN, inner))
    assert chain_to_reference(2, 0, {(1, 0): KNOWN})[1] is None  # only 0 -> 1 known: 1 is unreached


def test_generated_captures_get_their_own_exposure_and_white_balance(tmp_path):
    small = {"num_views": 4, "num_test_views": 1, "width": 24, "height": 18, "texels_per_metre": 8.0}
    plain = scenes.make_layout("object-centric", seed=2, **small)
    assert "appearance_jitter" not in plain.params  # the default leaves ground_truth.json as it was
    assert all(c.appearance_gains is None for c in plain.captures)
    jittered = scenes.make_layout("object-centric", seed=2, appearance_jitter=0.5, **small)
    again = scenes.make_layout("object-centric", seed=2, appearance_jitter=0.5, **small)
    gains = [c.appearance_gains for c in jittered.captures]
    assert all(g is not None for g in gains) and not np.allclose(gains[0], gains[1])
    np.testing.assert_array_equal(gains, [c.appearance_gains for c in again.captures])  # seeded
    assert jittered.test.appearance_gains is None  # the test views show the scene as it is
    for g in gains:
        assert 2**-0.5 - 1e-9 <= g[1] <= 2**0.5 + 1e-9  # green carries the exposure alone
    np.testing.assert_array_equal(jittered.captures[0].c2w_world, plain.captures[0].c2w_world)  # same cameras
    with pytest.raises(ValueError, match="appearance_jitter"):
        scenes.make_layout("object-centric", seed=2, appearance_jitter=-1.0, **small)
    # bracketed: the two captures at the ends of the range, opposite white balance; no jitter is an error
    ends = scenes.make_layout("object-centric", seed=2, appearance_jitter=0.5, appearance_bracket=True, **small)
    low, high = (c.appearance_gains for c in ends.captures)
    np.testing.assert_allclose(high / low, [2**1.5, 2**1.0, 2**0.5])  # exposure +1 stop, red +0.5, blue -0.5
    assert "appearance_bracket" not in jittered.params and ends.params["appearance_bracket"] is True
    with pytest.raises(ValueError, match="appearance_bracket"):
        scenes.make_layout("object-centric", seed=2, appearance_bracket=True, **small)

    # Written images carry the gains; the estimate from the same view, neutral vs recorded, inverts them.
    out = scenes.write_scene(jittered, tmp_path / "scene", supersample=1)
    cap = jittered.captures[0]
    view = scenes.render(jittered.scene, cap.c2w_world[0], cap.intrinsics, supersample=1).rgb
    recorded = scenes.apply_appearance(view, cap.appearance_gains)
    stored = np.asarray(scenes.Image.open(out / cap.name / "images" / "frame_00000.png"), dtype=np.float64) / 255
    np.testing.assert_allclose(stored, recorded.numpy(), atol=0.6 / 255)
    fit = fit_colour_map(recorded.numpy(), view.numpy(), min_pixels=16)
    np.testing.assert_allclose(np.diag(fit[:, :3]), 1 / cap.appearance_gains, rtol=0.05)
    gt = json.loads((out / "ground_truth.json").read_text())
    assert gt["params"]["appearance_jitter"] == 0.5
    assert gt["captures"][0]["appearance"]["exposure"] == pytest.approx(cap.exposure)
