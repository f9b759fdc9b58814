"""The walk order of scripts/repose_in_order.py: the order a person filming a street could have taken its views."""

from __future__ import annotations

import numpy as np
import pytest

from nerfuser_ns.bench.practitioner_cases import case_layout
from nerfuser_ns.capture_check import neighbour_turns


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("repose_in_order")


def _camera(x: float, forward: tuple[float, float, float]) -> np.ndarray:
    """A level camera at (x, 0, 1.5) looking along ``forward`` (OpenGL: -z forward, +y up)."""
    f = np.asarray(forward, dtype=float) / np.linalg.norm(forward)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, up, -f], axis=1)
    c2w[:3, 3] = [x, 0.0, 1.5]
    return c2w


def test_out_along_one_facade_then_back_along_the_other(script):
    views = [(3.0, (0, 1, 0)), (0.0, (0, -1, 0)), (1.0, (0.2, 1, 0)), (1.5, (1, 0.1, 0)), (5.0, (0, -1, 0.1)),
             (4.0, (-1, 0, 0)), (2.0, (0, 1, 0))]  # fmt: skip
    order = script.walk_order(np.stack([_camera(x, f) for x, f in views]))
    # out in +x: the +y facade and the views ahead (+x); back in -x: the -y facade and the views ahead (-x)
    assert order.tolist() == [2, 3, 6, 0, 4, 5, 1]


def test_a_generated_street_capture_in_walk_order_turns_little_between_neighbours(script):
    """What makes sequential matching apt: in the generated order a street's neighbouring views mostly face opposite
    facades; in the walk order they mostly face the same way (a view looking ahead turns a quarter from its
    neighbours)."""
    cap = case_layout("street:20").captures[0]
    order = script.walk_order(cap.c2w_world)
    assert sorted(order.tolist()) == list(range(cap.num_views))
    generated, walked = neighbour_turns(cap.c2w_world), neighbour_turns(cap.c2w_world[order])
    assert np.median(walked) < 60 < 90 < np.median(generated)
