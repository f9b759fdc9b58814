"""The practitioner benchmark's case folders (:mod:`nerfuser_ns.bench.practitioner_cases`): which ``ns-eval`` JSON
holds which appearance-matching setting."""

from __future__ import annotations

from nerfuser_ns.bench.practitioner_cases import appearance_evals, fused_appearance_matching, fused_config


def _fused(case, label, text):
    config = fused_config(case, label)
    config.parent.mkdir(parents=True)
    config.write_text(text)


def test_the_eval_of_each_appearance_setting(tmp_path):
    case = tmp_path / "street-9"
    assert fused_appearance_matching(case) is None and appearance_evals(case) == {}  # before the fuse stage
    _fused(case, None, "pipeline:\n  model:\n    appearance_matching: true\n    gamma: 5\n")
    assert fused_appearance_matching(case) is True
    assert appearance_evals(case) == {}  # fused, not yet scored
    (case / "eval.json").write_text("{}")
    (case / "eval_unmatched.json").write_text("{}")
    assert appearance_evals(case) == {True: case / "eval.json", False: case / "eval_unmatched.json"}
    (case / "eval_matched.json").write_text("{}")  # a forced setting's eval wins over the default's
    assert appearance_evals(case)[True] == case / "eval_matched.json"


def test_runs_fused_before_the_option_had_it_off(tmp_path):
    _fused(tmp_path / "old", None, "pipeline:\n  model:\n    gamma: 5\n")
    assert fused_appearance_matching(tmp_path / "old") is False
    _fused(tmp_path / "off", None, "pipeline:\n  model:\n    appearance_matching: false\n")
    (tmp_path / "off" / "eval.json").write_text("{}")
    assert appearance_evals(tmp_path / "off") == {False: tmp_path / "off" / "eval.json"}
