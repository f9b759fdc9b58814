"""Plain helpers shared by the registration tests (fixtures are in ``conftest.py``): the small registration
settings, the ground truth of a layout, a renderer SfM cannot use, the command run in-process with its one-line error
check, and a wrong estimate to inject.

Imported as ``registration_helpers`` (pytest puts this folder on ``sys.path``; the tests are not a package, so the
name is unique across the suite)."""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import numpy as np

from nerfuser_ns import registration as reg
from nerfuser_ns import sim3
from nerfuser_ns.registration import estimate as reg_estimate
from nerfuser_ns.renderers import RenderBatch
from nerfuser_ns.scripts import register as cli

W, H = 240, 180  # smallest size at which SIFT finds enough on these scenes (160x120: nothing reconstructs)


def small_config(**kw) -> reg.RegistrationConfig:
    # the paper's hemisphere at a fixed camera (the automatic choice has tests of its own)
    sampling_kw = {"source": "hemisphere", "fov_deg": 60.0, **kw.pop("sampling", {})}
    sampling = reg.PoseSamplingConfig(num_poses=kw.pop("num_poses", 20), width=W, height=H, **sampling_kw)
    kw.setdefault("mode", "sfm")  # the SfM mode's tests; the other modes build their own configs
    kw.setdefault("colour_views", 2)  # as few as the NCC views: the colour fit has tests of its own
    return reg.RegistrationConfig(sampling=sampling, self_check_views=kw.pop("self_check_views", 2), **kw)


def gt_of(layout, names=None) -> list[np.ndarray]:
    caps = {c.name: c for c in layout.captures}
    return [caps[n].capture_to_world for n in (names or [c.name for c in layout.captures])]


# ---------------------------------------------------------------------------------------------------------------------
# Fakes for bad inputs


class FakeRenderer:
    """Noise, blank or NaN images: nothing SfM can use."""

    def __init__(self, name: str, kind: str):
        self.name, self.kind = name, kind

    def cache_key(self) -> str:
        return f"fake:{self.name}:{self.kind}"

    def render(self, c2w, intrinsics) -> RenderBatch:
        n, h, w = len(c2w), intrinsics.height, intrinsics.width
        if self.kind == "noise":
            rng = np.random.default_rng(zlib.crc32(np.asarray(c2w).tobytes()))
            return RenderBatch(rng.random((n, h, w, 3), dtype=np.float32), None)
        if self.kind == "blank":
            return RenderBatch(np.zeros((n, h, w, 3), np.float32), np.zeros((n, h, w), np.float32))
        return RenderBatch(np.full((n, h, w, 3), np.nan, np.float32), np.ones((n, h, w), np.float32))

    def training_poses(self):
        return None


def run_cli(tmp_path: Path, renderers=None, capsys=None, **kw) -> tuple[int, Path, str]:
    out = tmp_path / "registration.json"
    cmd = cli.RegisterCommand(**{**vars(small_config()), "output": out, **kw})
    rc = cli.run(cmd, renderers)
    err = capsys.readouterr().err if capsys is not None else ""
    return rc, out, err


def assert_one_line_error(rc: int, out: Path, err: str, *fragments: str) -> None:
    assert rc == 1
    assert not out.exists(), "no registration file may be written on error"
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error:")
    for f in fragments:
        assert f in lines[0], (f, lines[0])


# ---------------------------------------------------------------------------------------------------------------------
# A wrong estimate


WRONG = sim3.make_sim3(sim3.so3_exp(np.radians([0.0, 40.0, 0.0])))  # 40 deg about the frame's origin


def perturb_second_estimate(monkeypatch) -> None:
    """The paper's estimator returns NeRF B's transform rotated by ``WRONG``."""
    real = sim3.estimate_sim3_from_poses
    calls = []

    def perturbed(G_nerf, G_sfm, **kw):
        est = real(G_nerf, G_sfm, **kw)
        calls.append(est)
        return dataclasses.replace(est, T=WRONG @ est.T) if len(calls) == 2 else est

    monkeypatch.setattr(reg_estimate.sim3, "estimate_sim3_from_poses", perturbed)
