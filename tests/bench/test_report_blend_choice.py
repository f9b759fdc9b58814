"""scripts/report_blend_choice.py: auto's choice and its measures per case, from true cameras or registration files."""

from __future__ import annotations

import numpy as np
import pytest

from nerfuser_ns.registration import NerfEntry, write_minimal_registration
from nerfuser_ns.registration.record import TrainingCameras
from nerfuser_ns.sampling import look_at


def test_the_table_has_one_row_per_case_with_each_nerfs_measures(load_script, tmp_path):
    script = load_script("report_blend_choice")
    az = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = look_at(np.stack([2 * np.cos(az), 2 * np.sin(az), np.ones(12)], axis=-1), np.zeros(3))
    case = tmp_path / "object-centric-7"
    case.mkdir()
    cameras = TrainingCameras(ring, np.tile([100.0, 100.0, 80.0, 60.0, 160.0, 120.0], (12, 1)))
    write_minimal_registration([NerfEntry("capture_a/nerfacto/run", tmp_path / "a.yml", np.eye(4), cameras),
                                NerfEntry("capture_b/nerfacto/run", tmp_path / "b.yml", np.eye(4))],
                               case / "registration.json")  # fmt: skip
    out = tmp_path / "choice.md"
    script.main(script.ReportBlendChoice(report=out, layouts=["drive"], seeds=[903],
                                         registrations=[case / "registration.json"]))  # fmt: skip
    rows = [line for line in out.read_text().splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert len(rows) == 2
    assert rows[0].startswith("| drive-903 | true cameras | capture_0: ") and rows[0].endswith("| idw-2d |")
    assert "(centre)" not in rows[0] and rows[0].count("rig offset 0.000 (rig)") == 3  # the drive's rig
    # one NeRF around a centre, the other without recorded cameras: auto falls back to the paper's method
    assert rows[1].startswith("| object-centric-7 | registration file | capture_a: 0.0 deg, R 0.")
    assert "(centre)" in rows[1] and "(rig)" not in rows[1]
    assert "capture_b: not recorded | idw-sample |" in rows[1]
    with pytest.raises(SystemExit, match="missing.json: not a readable registration file"):
        script.main(script.ReportBlendChoice(report=out, registrations=[tmp_path / "missing.json"]))
