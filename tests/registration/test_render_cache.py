"""Rendering the registration's views (:mod:`nerfuser_ns.registration.render_cache`): the renderer protocol and
training poses, subsets of them, and damaged caches rebuilt (renders) or named (the SfM's observations)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from registration_helpers import FakeRenderer
from rich.console import Console

from nerfuser_ns import registration as reg
from nerfuser_ns.renderers import Renderer


def test_renderer_protocol(oc_renderers):
    assert all(isinstance(r, Renderer) for r in oc_renderers)
    assert isinstance(FakeRenderer("x", "noise"), Renderer)
    train = oc_renderers[0].training_poses()
    assert train.shape == (16, 4, 4)
    # capture frames are normalised: unit mean camera distance to the origin
    assert np.isclose(np.linalg.norm(train[:, :3, 3], axis=-1).mean(), 1.0)


def test_training_pose_subsets(oc_renderers):
    train = oc_renderers[0].training_poses()
    pick = lambda seed: reg.sample_poses(oc_renderers[0], reg.PoseSamplingConfig(  # noqa: E731
        source="training", max_training_poses=5, seed=seed))[0]  # fmt: skip
    even = pick(0)
    np.testing.assert_array_equal(even, train[[0, 4, 8, 11, 15]])  # evenly spaced, first and last included
    a, b, c = pick(3), pick(3), pick(4)
    np.testing.assert_array_equal(a, b)  # deterministic by seed
    assert not np.array_equal(a, c) and not np.array_equal(a, even)
    idx = [int(np.flatnonzero((train == p).all(axis=(1, 2)))[0]) for p in a]
    assert idx == sorted(set(idx)) and len(idx) == 5  # distinct training poses, in capture order


def test_damaged_caches_are_rebuilt_or_named(tmp_path):
    sampling = reg.PoseSamplingConfig(source="hemisphere", num_poses=4, width=16, height=12)
    renderer = FakeRenderer("noise", "noise")
    first = reg.render_views_cached(renderer, sampling, tmp_path / "renders", Console(quiet=True))
    assert not first.reused
    assert reg.render_views_cached(renderer, sampling, tmp_path / "renders", Console(quiet=True)).reused
    image = first.folder / "images" / "00002.png"
    good = image.read_bytes()
    image.write_bytes(good[: len(good) // 2])  # truncated
    console = Console(record=True, width=200)
    again = reg.render_views_cached(renderer, sampling, tmp_path / "renders", console)
    assert not again.reused and image.read_bytes() == good  # rendered again, identically
    text = console.export_text()
    assert "images/00002.png" in text and "rendering again" in text
    (tmp_path / "sfm").mkdir()
    (tmp_path / "sfm" / "observations.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(reg.RegistrationError, match=r"observations.npz: damaged SfM cache .*delete"):
        reg.load_observations(SimpleNamespace(folder=str(tmp_path / "sfm")))
