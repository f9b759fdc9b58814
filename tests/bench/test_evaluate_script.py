"""``scripts/evaluate.py`` end to end on the demo scene and its shipped runs (its own file: the suite's longest test,
scheduled apart from the module fixtures of test_evaluation.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def test_evaluate_quick_mode_writes_every_section_and_caches(tmp_path):
    """``scripts/evaluate.py --quick``: every section computed, a re-run reuses every cached result, and a changed
    input (the gammas) recomputes only what depends on it."""
    out = tmp_path / "eval"
    # --quick made smaller still (every section runs; the figures are not what this checks)
    smaller = ["--pose-seeds", "0", "--registration-poses", "8", "--render-size", "64", "48", "--ablation-counts", "4",
               "--ablation-hemisphere-poses", "4", "--paper-hemisphere-poses", "4", "--cloud-views", "4",
               "--timing-rays", "256", "--test-views", "1", "--gamma-views", "1"]  # fmt: skip
    cmd = [sys.executable, str(ROOT / "scripts/evaluate.py"), "--quick", "--output-dir", str(out), *smaller]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env)
    assert first.returncode == 0, first.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["quick"] and report["sections_done"] == ["registration", "blending", "gamma", "pose_ablation", "cost"]
    reg = report["registration"]
    assert reg["cases"] == 1 and set(reg["rows"]) == {
        "nerfuser_ns",
        "paper-faithful",
        *(f"{m}/{c}" for m in ("icp", "fgr", "ransac") for c in ("NeRF clouds", "RGB-D (GT depth)")),
    }
    for row in reg["rows"].values():  # one pose draw: one case per row (the paper-faithful one runs once per scene)
        assert row["n"] == 1 and 0.0 <= row["success_rate"] <= 1.0
    (faithful,) = reg["paper_faithful_cases"]
    assert faithful["case"] == "demo/paper-faithful" and len(faithful["nerfs"]) == 1
    (blend,) = report["blending"]
    for q in blend["quality"]["ground-truth"].values():
        assert 5.0 < q["psnr"] < 60.0 and 0.0 < q["ssim"] <= 1.0
    (gamma,) = report["gamma"]
    assert [float(g) for g in gamma["psnr"]] == [0.1, 5.0, 100.0]
    png = (out / gamma["plot"]).read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    arms = [(r["count"], r["source"]) for r in report["pose_ablation"]["rows"]]
    assert arms == [(4, "training"), (4, "both"), (4, "hemisphere")]
    (cost,) = report["cost"]["render"]
    assert cost["ratio"] > 0 and cost["num_rays"] == 256
    md = (out / "report.md").read_text()
    for heading in ("## 1. Registration", "## 2. Blending", "## 3. Gamma", "## 4. Re-render pose", "## 5. Cost"):
        assert heading in md
    assert report["machine"]["cpus"] and report["command"].endswith(" ".join(cmd[2:]))

    # a re-run with other gammas: every cached result reused but the gamma sweep's
    again = subprocess.run([*cmd, "--gammas", "1", "10"], capture_output=True, text=True, cwd=ROOT, env=env)
    assert again.returncode == 0, again.stderr[-3000:]
    rerun = json.loads((out / "report.json").read_text())
    assert rerun["cache"] == {"hits": sum(report["cache"].values()) - 1, "misses": 1}
    assert [float(g) for g in rerun["gamma"][0]["psnr"]] == [1.0, 10.0]
    assert rerun["registration"]["rows"] == report["registration"]["rows"]
