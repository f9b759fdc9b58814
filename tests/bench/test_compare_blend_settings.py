"""scripts/compare_blend_settings.py: one fused run's blends under its own gamma / tau and under another setting."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml
from nerfuser_ns.method_configs.nerfuser import nerfuser_config

from nerfuser_ns.bench.practitioner_cases import BLEND_COLUMNS, fused_config


@pytest.fixture(scope="module")
def compare(load_script):
    return load_script("compare_blend_settings")


def _eval(path, psnr: dict[str, float]) -> None:
    results = {}
    for key, _ in BLEND_COLUMNS:
        results[f"psnr_{key}"], results[f"ssim_{key}"] = psnr[key], psnr[key] / 40
    path.write_text(json.dumps({"results": results}))


def _case(tmp_path, name: str, own: dict[str, float], other: dict[str, float] | None):
    case = tmp_path / name
    config = nerfuser_config()
    config.pipeline.model.gamma, config.pipeline.model.tau = 5.0, 1.8
    fused_config(case, None).parent.mkdir(parents=True)
    fused_config(case, None).write_text(yaml.dump(config))  # as ns-train saves it
    _eval(case / "eval.json", own)
    if other is not None:  # scored before: the script reuses it instead of running ns-eval
        _eval(case / "eval_gamma10_tau1.2.json", other)
    return case


def test_the_two_settings_side_by_side(compare, tmp_path):
    base = {"nerf": 20.0, "nearest": 21.0, "idw_2d": 21.5, "idw_3d": 21.2, "idw_sample": 20.9, "coverage": 21.8,
            "coverage_3d": 21.4}  # fmt: skip
    other = {**base, "idw_2d": 21.3, "idw_3d": 21.0, "idw_sample": 21.1, "coverage": 21.4}
    case = _case(tmp_path, "street-3", base, other)
    report = tmp_path / "report.md"
    compare.main(compare.CompareBlendSettings(cases=[case], report=report, note="A note."))
    text = report.read_text()
    assert "A note." in text
    rows = [line for line in text.splitlines() if line.startswith("| street-3 |")]
    assert rows[0].startswith("| street-3 | gamma 5 / tau 1.8 (the run's) | 20.00 / 0.500 | 21.00 / 0.525 |")
    assert rows[0].endswith("| -0.10 | +0.30 |")  # IDW-Sample - Nearest; coverage - IDW-2D, the best IDW
    assert rows[1].startswith("| street-3 | gamma 10 / tau 1.2 |") and rows[1].endswith("| +0.10 | +0.10 |")
    assert "- street-3: IDW-Sample 20.90 -> 21.10 dB (+0.20; Nearest 21.00), IDW-2D -0.20" in text


def test_a_case_without_its_eval_or_fused_run_is_one_line(compare, tmp_path):
    case = _case(tmp_path, "street-4", {k: 20.0 for k, _ in BLEND_COLUMNS}, None)
    (case / "eval.json").unlink()
    with pytest.raises(SystemExit, match="street-4/eval.json is missing; run the case's fuse stage first"):
        compare.main(compare.CompareBlendSettings(cases=[case], report=tmp_path / "r.md"))
    (case / "eval.json").write_text("{}")
    shutil.rmtree(case / "fused")
    with pytest.raises(SystemExit, match="street-4/fused/.*/config.yml is missing"):  # checked before any ns-eval
        compare.main(compare.CompareBlendSettings(cases=[case], report=tmp_path / "r.md"))
    assert not (tmp_path / "r.md").exists()
