"""Rendering the registration's views (:mod:`nerfuser_ns.registration.render_cache`): the renderer protocol and
training poses, subsets of them, and damaged caches rebuilt (renders) or named (the SfM's observations)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image
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


class CountingRenderer:
    """A renderer that counts the views it is asked for (and can be told to stop rendering)."""

    def __init__(self, inner):
        self.inner, self.name, self.rendered, self.broken = inner, inner.name, 0, False

    def cache_key(self):
        return self.inner.cache_key()

    def training_poses(self):
        return self.inner.training_poses()

    def render(self, c2w, intrinsics, **kw):
        assert not self.broken, "asked to render a view it had rendered before"
        self.rendered += len(c2w)
        return self.inner.render(c2w, intrinsics, **kw)


@pytest.mark.parametrize("depth", [False, True])
def test_a_later_pose_source_renders_only_the_poses_it_adds(oc_renderers, tmp_path, depth):
    sampling = reg.PoseSamplingConfig(source="training", num_poses=5, width=24, height=18, max_training_poses=6)
    both = reg.PoseSamplingConfig(**{**sampling.__dict__, "source": "both"})
    counting = CountingRenderer(oc_renderers[0])
    console = Console(record=True, width=200)
    train = reg.render_views_cached(counting, sampling, tmp_path / "renders", console, depth=depth)
    assert counting.rendered == 6
    mixed = reg.render_views_cached(counting, both, tmp_path / "renders", console, depth=depth)
    assert counting.rendered == 6 + 5 and not mixed.reused  # only the hemisphere was rendered
    assert "6 of 11 views taken from earlier renders" in console.export_text()
    fresh = reg.render_views_cached(CountingRenderer(oc_renderers[0]), both, tmp_path / "fresh", Console(quiet=True),
                                    depth=depth)  # fmt: skip
    assert mixed.sources == fresh.sources and np.array_equal(mixed.c2w, fresh.c2w)
    np.testing.assert_array_equal(mixed.load_accumulation(), fresh.load_accumulation())
    if depth:
        np.testing.assert_array_equal(mixed.load_depth(), fresh.load_depth())
    # Read back from its folder alone (what scripts do): the same views, depth found where it was stored.
    read = reg.ViewSet.from_folder(mixed.folder)
    assert read.name == counting.name and read.sources == mixed.sources and read.has_depth == depth
    np.testing.assert_array_equal(read.c2w, mixed.c2w)
    np.testing.assert_array_equal(read.kept, mixed.kept)
    assert reg.render_cache.load_render_intrinsics(mixed.folder) == both.intrinsics()
    for k in range(len(mixed.c2w)):
        a, b = (np.asarray(Image.open(v.folder / "images" / f"{k:05d}.png")) for v in (mixed, fresh))
        np.testing.assert_array_equal(a, b)
    # Another run (another cache key) or other intrinsics take nothing; a hemisphere alone is all taken.
    counting.broken = True
    hemi = reg.PoseSamplingConfig(**{**sampling.__dict__, "source": "hemisphere"})
    assert len(reg.render_views_cached(counting, hemi, tmp_path / "renders", Console(quiet=True), depth=depth).c2w) == 5
    other = CountingRenderer(oc_renderers[1])
    reg.render_views_cached(other, sampling, tmp_path / "renders", Console(quiet=True), depth=depth)
    assert other.rendered == 6
    wider = reg.PoseSamplingConfig(**{**sampling.__dict__, "width": 32})
    counting.broken = False
    reg.render_views_cached(counting, wider, tmp_path / "renders", Console(quiet=True), depth=depth)
    assert counting.rendered == 6 + 5 + 6
    assert train.folder.is_dir()
