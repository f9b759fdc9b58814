"""Tests for nerfuser_ns.blend_choice (what the ``auto`` blend method renders with)."""

import numpy as np
import pytest
import torch

from nerfuser_ns import sim3
from nerfuser_ns.bench import scenes
from nerfuser_ns.blend_choice import (
    BLEND_CHOICES,
    CENTRE_MISS_DEG,
    CENTRE_SPREAD,
    RIG_OFFSET,
    choose_blend_method,
    forms_rig,
    looks_at_centre,
    miss_angles,
    rig_offsets,
)
from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.blending import BLEND_METHODS
from nerfuser_ns.coverage import CameraIndex
from nerfuser_ns.sampling import look_at

INTRINSICS = [100.0, 100.0, 80.0, 60.0, 160.0, 120.0]


def _index(c2w: np.ndarray) -> CameraIndex:
    return CameraIndex.from_cameras(c2w, INTRINSICS)


def ring(centre=(0.0, 0.0, 0.5), radius=2.0, n=24, jitter=0.0, seed=0) -> np.ndarray:
    """Cameras circling ``centre`` at two heights, looking at it (their targets off by ``jitter`` metres)."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = np.stack([radius * np.cos(az), radius * np.sin(az), 0.6 + 0.8 * (np.arange(n) % 2)], axis=-1)
    eyes = eyes + np.asarray(centre)
    return look_at(eyes, np.asarray(centre) + rng.normal(0, jitter, (n, 3)) if jitter else np.asarray(centre))


def street(n=24, sideways=True, turned_deg=0.0) -> np.ndarray:
    """Cameras walking 20 m along x, looking at the facades on their left (or ahead along the street), each view
    turned by up to ``turned_deg`` (a hand-held camera)."""
    eyes = np.stack([np.linspace(0, 20, n), np.zeros(n), np.full(n, 1.6)], axis=-1)
    yaw = np.radians(turned_deg) * np.sin(np.arange(n)) + (np.pi / 2 if sideways else 0.0)
    return look_at(eyes, eyes + 8.0 * np.stack([np.cos(yaw), np.sin(yaw), np.zeros(n)], axis=-1))


def rig(stops=8, cameras=8, step=0.5, lever=0.0, seed=0) -> np.ndarray:
    """A car's roof rig driving along x: ``cameras`` level cameras turned evenly around, ``lever`` metres from the
    rig's centre, fired every ``step`` metres (the car's heading jittered by 1.5 deg)."""
    rng = np.random.default_rng(seed)
    eyes, targets = [], []
    for s in range(stops):
        heading = rng.normal(0, np.radians(1.5))
        yaws = heading + 2 * np.pi * np.arange(cameras) / cameras
        dirs = np.stack([np.cos(yaws), np.sin(yaws), np.zeros(cameras)], axis=-1)
        e = np.array([s * step, -1.2, 1.9]) + lever * dirs
        eyes.append(e)
        targets.append(e + 5.0 * dirs)
    return look_at(np.concatenate(eyes), np.concatenate(targets))


def test_auto_is_a_choice_besides_every_blend_method():
    assert BLEND_CHOICES == ("auto", *BLEND_METHODS)
    assert BlendSettings().method == "auto"
    assert BlendSettings().replace(method="auto").method == "auto"


def test_cameras_circling_an_object_look_at_a_centre_and_miss_it_by_their_jitter():
    angles, spread = miss_angles(torch.tensor(ring()))
    assert float(angles.max()) < 1e-4 and spread < 0.5
    inward, median, _ = looks_at_centre(_index(ring(jitter=0.1)))  # 0.1 m off at 2 m: ~3 deg
    assert inward and 0.5 < median < 8.0
    # Half a ring (one side of an object) still looks at its centre.
    assert looks_at_centre(_index(ring()[:12]))[0]


@pytest.mark.parametrize("sideways", [True, False])
def test_cameras_along_a_street_do_not_look_at_a_centre(sideways):
    inward, median, _ = looks_at_centre(_index(street(sideways=sideways)))
    assert not inward and median is None  # parallel axes have no focus at all
    # Views turned a little: facing the facades they converge far away, each missing that point by little, but all
    # from one side of it; facing ahead, their focus lies behind most of them.
    inward, median, spread = looks_at_centre(_index(street(sideways=sideways, turned_deg=4.0)))
    assert not inward
    assert (median < CENTRE_MISS_DEG and spread > CENTRE_SPREAD) if sideways else median > 90


def test_the_verdict_is_the_same_in_any_frame():
    T = sim3.make_sim3(scenes.yaw_rotation(0.9), np.array([3.0, -2.0, 1.0]), 0.37)
    mixed = np.concatenate([ring(), street()])
    for c2w in (ring(jitter=0.2), ring()[:8], street()[::2], street(turned_deg=10.0), mixed):
        assert looks_at_centre(_index(c2w))[0] == looks_at_centre(_index(c2w).transformed(T))[0]
    # the measures too, where the focus is well determined (a walk's is far and ill-conditioned, in float32 cameras)
    for c2w in (ring(jitter=0.2), ring()[:8]):
        here, moved = looks_at_centre(_index(c2w)), looks_at_centre(_index(c2w).transformed(T))
        np.testing.assert_allclose(here[1:], moved[1:], atol=1e-3)


@pytest.mark.parametrize(
    ("cameras", "lever", "stops", "step"),
    [(8, 0.0, 8, 0.5), (12, 0.0, 8, 0.5), (8, 0.15, 20, 1.0), (6, 0.3, 20, 1.0), (12, 0.5, 40, 1.0)],
)
def test_a_rigs_cameras_form_a_rig(cameras, lever, stops, step):
    """Rig mates look elsewhere from (nearly) the same place: the drive layout's rig (no lever arms) and rigs whose
    cameras stand 0.15-0.5 m from its centre on 20-40 m blocks."""
    is_rig, median = forms_rig(_index(rig(cameras=cameras, lever=lever, stops=stops, step=step)))
    assert is_rig and median <= (1e-6 if lever == 0 else RIG_OFFSET)


def test_walks_and_rings_do_not_form_a_rig():
    # A walk past facades, each view turned a little (hand-held): no turned camera close by.
    for c2w in (street(), street(turned_deg=15.0), street(n=300, turned_deg=8.0), ring(), ring()[:12]):
        is_rig, median = forms_rig(_index(c2w))
        assert not is_rig and (median is None or median > RIG_OFFSET)
    # One camera, or every camera in one place: undefined, never a rig.
    assert rig_offsets(torch.tensor(rig(stops=1)[:1])) is None
    assert forms_rig(_index(rig(stops=1))) == (False, None)


def test_the_rig_measure_is_the_same_in_any_frame():
    T = sim3.make_sim3(scenes.yaw_rotation(0.9), np.array([3.0, -2.0, 1.0]), 0.37)
    for c2w in (rig(lever=0.2, stops=20, step=1.0), street(turned_deg=15.0), ring()):
        np.testing.assert_allclose(forms_rig(_index(c2w))[1], forms_rig(_index(c2w).transformed(T))[1], rtol=1e-4)


def test_auto_picks_the_papers_method_only_when_every_nerf_circles_an_object():
    objects = [_index(ring()), _index(ring(centre=(3.0, 0.0, 0.5), jitter=0.1, seed=1))]
    method, why = choose_blend_method(objects, ["a", "b"])
    assert method == "idw-sample" and "every NeRF's cameras look at a centre" in why and "a 0" in why
    method, why = choose_blend_method([objects[0], _index(street())], ["a", "b"])
    assert method == "coverage" and "not every NeRF" in why and "nor form a rig" in why
    # Every NeRF filmed by a rig: the paper's per-image blend; one rig beside a walk: coverage.
    rigs = [_index(rig()), _index(rig(lever=0.2, stops=20, step=1.0, seed=1))]
    method, why = choose_blend_method(rigs, ["a", "b"])
    assert method == "idw-2d" and "every NeRF's were filmed by a rig" in why and "a 0.000" in why
    assert choose_blend_method([rigs[0], _index(street())], ["a", "b"])[0] == "coverage"
    # A NeRF without cameras: coverage could not score it, so the paper's method, and the line names it.
    method, why = choose_blend_method([_index(street()), None], ["a", "b"])
    assert method == "idw-sample" and "the training cameras of b are not in the registration file" in why


@pytest.mark.parametrize("layout", scenes.LAYOUT_NAMES)
def test_auto_on_the_generated_layouts(layout):
    """Validation seed 903 (the thresholds were fixed on 900-902): rings around objects take IDW-Sample, the drive's
    rig IDW-2D, every other layout coverage."""
    built = scenes.make_layout(layout, **scenes.benchmark_params(layout, 903))
    method, _ = choose_blend_method([_index(c.c2w_world) for c in built.captures])
    assert method == {"object-centric": "idw-sample", "drive": "idw-2d"}.get(layout, "coverage")
