"""The coverage-constant validation script's choice rule (scripts/validate_coverage.py)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from nerfuser_ns.coverage import CoverageParams

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("validate_coverage")


def _case(deltas: dict[tuple[float, int], float]) -> dict:
    return {"grid": [{"sigma_deg": s, "k": k, "candidates": max(16, k), "minus_best_idw_db": d}
                     for (s, k), d in deltas.items()]}  # fmt: skip


DEFAULTS = {"sigma_deg": 20.0, "k": 4, "candidates": 16}


def test_the_best_mean_over_the_cases_wins(script):
    cases = [_case({(10.0, 1): 0.5, (20.0, 4): 0.1, (40.0, 4): 0.0}),
             _case({(10.0, 1): -0.2, (20.0, 4): 0.1, (40.0, 4): 0.4})]  # fmt: skip
    choice = script.choose(cases, DEFAULTS)
    assert (choice["sigma_deg"], choice["k"]) == (40.0, 4)  # mean 0.2 beats 0.15 and 0.1
    assert choice["mean_minus_best_idw_db"] == pytest.approx(0.2)
    assert choice["mean_minus_best_idw_db_at_defaults"] == pytest.approx(0.1)


def test_the_defaults_stay_on_a_tie(script):
    cases = [_case({(10.0, 1): 0.105, (20.0, 4): 0.1})]
    assert (script.choose(cases, DEFAULTS)["sigma_deg"], script.choose(cases, DEFAULTS)["k"]) == (20.0, 4)
    cases = [_case({(10.0, 1): 0.12, (20.0, 4): 0.1})]
    assert script.choose(cases, DEFAULTS)["sigma_deg"] == 10.0


def test_the_grid_has_enough_candidates_for_k(script):
    cfg = script.ValidateCoverage(cases=[], output=Path("x.json"), sigma_deg=[10.0], k=[1, 32])
    assert script._grid(cfg) == [{"sigma_deg": 10.0, "k": 1, "candidates": 16},
                                 {"sigma_deg": 10.0, "k": 32, "candidates": 32}]  # fmt: skip


def test_earlier_runs_join_the_choice_only_on_the_same_grid(script, tmp_path):
    cfg = script.ValidateCoverage(cases=[], output=Path("x.json"), sigma_deg=[20.0, 40.0], k=[4])
    grid = script._grid(cfg)
    earlier = {**_case({(20.0, 4): 0.17, (40.0, 4): 0.19}), "case": "street-0", "defaults": {**DEFAULTS, "gamma": 5.0}}
    path = tmp_path / "street0.json"
    path.write_text(json.dumps({"command": "...", "cases": [earlier], "choice": {}}))
    (case,) = script.earlier_cases([path], grid, DEFAULTS)
    assert case["case"] == "street-0" and case["from"] == str(path) and case["grid"] == earlier["grid"]
    drive = _case({(20.0, 4): 0.10, (40.0, 4): -0.2})  # a new case where the wider sigma loses more than it won
    choice = script.choose([drive, case], DEFAULTS)
    assert (choice["sigma_deg"], choice["mean_minus_best_idw_db"]) == (20.0, pytest.approx(0.135))
    for grid_, defaults, message in ((script._grid(script.ValidateCoverage(cases=[], output=path, sigma_deg=[10.0],
                                                                           k=[4])), DEFAULTS, "another grid"),
                                     (grid, {**DEFAULTS, "sigma_deg": 40.0}, "other defaults")):  # fmt: skip
        with pytest.raises(SystemExit, match=message):
            script.earlier_cases([path], grid_, defaults)
    path.write_text("{")
    with pytest.raises(SystemExit, match="not an output of this script"):
        script.earlier_cases([path], grid, DEFAULTS)


def test_a_fused_run_with_other_coverage_settings_is_refused_before_the_sweep(script, monkeypatch, tmp_path):
    model = SimpleNamespace(config=SimpleNamespace(), blend_settings=SimpleNamespace(coverage=CoverageParams(40.0, 4)))
    monkeypatch.setattr(script.runs, "load_run", lambda *a, **k: SimpleNamespace(pipeline=SimpleNamespace(model=model)))
    monkeypatch.setattr(script.evaluation, "blend_sweep", lambda *a, **k: pytest.fail("swept a refused case"))
    with pytest.raises(SystemExit, match="overrides the coverage settings"):
        script.score_case(tmp_path, [], None, None, DEFAULTS)
