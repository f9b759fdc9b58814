"""Tests for nerfuser_ns.blend_settings (the fused model's one blend settings value)."""

import pytest

from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.model import NerfuserModelConfig


def test_blend_settings_are_checked_once_and_tau_zero_is_off():
    s = BlendSettings(method="idw-2d", gamma=2.0, tau=0.0).checked()
    assert s.tau is None and s.method == "idw-2d"
    assert s.replace(gamma=3.0).gamma == 3.0 and s.gamma == 2.0  # frozen: a new value
    for bad, match in (({"gamma": -1.0}, "gamma"), ({"gamma": float("nan")}, "gamma"), ({"tau": 0.5}, "tau"),
                       ({"method": "idw-4d"}, "unknown blend method")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            s.replace(**bad)
    with pytest.raises(ValueError, match="reference_nerf 3 out of range"):
        s.replace(num_nerfs=2, reference_nerf=3)


def test_tau_zero_turns_the_distance_test_off_everywhere():
    assert BlendSettings.from_config(NerfuserModelConfig(tau=0.0), environ={}).tau is None
    assert BlendSettings.from_config(NerfuserModelConfig(), environ={"NERFUSER_TAU": "0"}).tau is None
    assert BlendSettings.from_config(NerfuserModelConfig(), environ={"NERFUSER_TAU": "none"}).tau is None
    assert BlendSettings.from_config(NerfuserModelConfig(tau=1.2), environ={}).tau == 1.2


def test_appearance_matching_comes_from_the_config_and_the_environment():
    assert BlendSettings.from_config(NerfuserModelConfig(), environ={}).appearance_matching is True
    off = NerfuserModelConfig(appearance_matching=False)
    assert BlendSettings.from_config(off, environ={}).appearance_matching is False
    for raw, want in (("0", False), ("off", False), (" False ", False), ("1", True), ("yes", True)):
        got = BlendSettings.from_config(NerfuserModelConfig(appearance_matching=not want),
                                        environ={"NERFUSER_APPEARANCE_MATCHING": raw})  # fmt: skip
        assert got.appearance_matching is want, raw
    with pytest.raises(ValueError, match="NERFUSER_APPEARANCE_MATCHING must be one of"):
        BlendSettings.from_config(NerfuserModelConfig(), environ={"NERFUSER_APPEARANCE_MATCHING": "maybe"})
    with pytest.raises(ValueError, match="appearance_matching must be True or False"):
        BlendSettings().replace(appearance_matching="no")
