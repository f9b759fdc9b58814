"""The practitioner reports' summary (:func:`nerfuser_ns.bench.practitioner_cases.summarise`) and the tally of case
records from several reports (scripts/tally_practitioner.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nerfuser_ns.bench.practitioner_cases import blend_gains, summarise


@pytest.fixture(scope="module")
def tally(load_script):
    return load_script("tally_practitioner")


def _record(case: str, r: float | None, failure: bool = False, nearest: float = 20.0, idw_sample: float = 21.0,
            optimized: float | None = None, pose: float | None = None,
            content: float | None = None) -> dict:  # fmt: skip
    errors = None if r is None else [{"nerf": "b", "r_err_deg": r, "t_err": r / 10, "s_err": r / 100,
                                      "failure": failure}]  # fmt: skip
    registration = {"errors": errors}
    for key, value in (("errors_optimized", optimized), ("errors_pose", pose), ("errors_content", content)):
        if value is not None:
            registration[key] = [{"nerf": "b", "r_err_deg": value, "t_err": 0.0, "s_err": 0.0, "failure": False}]
    return {"case": case, "spec": ":".join(case.rsplit("-", 1)),
            "captures": [{"colmap_rot_err_deg_median": 0.05, "colmap_bend_deg": 0.1}],
            "registration": registration, "blend_psnr": {"nearest": nearest, "idw_sample": idw_sample},
            "registered_at_commit": "abc1234"}  # fmt: skip


def test_summary_counts_a_refused_registration_as_a_failure_and_takes_medians_over_the_scored():
    records = [_record("street-1", 0.05), _record("street-2", 0.2), _record("drive-1", 7.0, failure=True),
               _record("room-1", None, nearest=15.0, idw_sample=14.0)]  # fmt: skip
    s = summarise(records)
    assert (s.cases, s.nerfs) == (4, 4)
    assert s.success == pytest.approx(0.5)
    assert s.median["r_err_deg"] == pytest.approx(0.2) and s.median["t_err"] == pytest.approx(0.02)
    assert s.idw_sample_over_nearest == [True, True, True, False]
    verdicts = dict(s.targets())
    assert not verdicts["success rate >= 0.95"] and not verdicts["median r_err <= 0.1 deg"]
    assert verdicts["median s_err <= 0.005"] and not verdicts["IDW-Sample >= Nearest on every scene"]
    assert s.line() == ("4 case(s), 4 registered NeRF(s): median r_err 0.2000 deg, t_err 0.02000, s_err 0.00200; "
                        "success rate 0.50.")  # fmt: skip


def test_summary_against_another_truth_leaves_out_the_cases_without_it():
    records = [_record("street-1", 0.3, optimized=0.05), _record("street-2", 0.2), _record("room-1", None)]
    s = summarise(records, "errors_optimized")
    assert (s.cases, s.nerfs, s.success) == (1, 1, 1.0) and s.median["r_err_deg"] == pytest.approx(0.05)
    empty = summarise([_record("room-1", None)], "errors_optimized")
    assert empty.nerfs == 0 and np.isnan(empty.median["r_err_deg"]) and empty.success == 0.0


def test_tally_takes_each_case_from_the_last_file_and_summarises_all(tally, tmp_path):
    first, second = tmp_path / "bench_practitioner_a.json", tmp_path / "bench_practitioner_b.json"
    obj, street, room = (_record("object-centric-1", 0.08), _record("street-1", 0.06, optimized=0.04, pose=0.03,
                                                                    content=0.02), _record("room-3", 117.0, True))
    obj["blend_psnr"]["coverage"], street["blend_psnr"]["coverage"] = 20.5, 19.5  # Nearest 20 in both
    first.write_text(json.dumps([_record("street-1", 0.3), obj]))
    second.write_text(json.dumps([street, room]))
    rows = tally.collect([first, second])
    assert [(r["case"], src) for r, src in rows] == [("street-1", second), ("object-centric-1", first),
                                                     ("room-3", second)]  # fmt: skip
    out = tmp_path / "tally.md"
    tally.write_tally(rows, out)
    text = out.read_text()
    assert "| street-1 | 0.0600 | 0.00600 | 0.00060 | ok | 0.0400 | 0.0300 | 0.0200 |" in text and "0.3000" not in text
    assert "| room-3 | 117.0000 | 11.70000 | 1.17000 | FAIL | - | - | - |" in text
    assert ("Against the camera-optimised truth, 1 case(s), 1 registered NeRF(s): median r_err 0.0400 deg" in text)
    assert ("Against the pose truth (the cases scored with it), 1 case(s), 1 registered NeRF(s): median r_err "
            "0.0300" in text)  # fmt: skip
    assert ("Against the content truth (the cases scored with it), 1 case(s), 1 registered NeRF(s): median r_err "
            "0.0200" in text)  # fmt: skip
    assert "[bench_practitioner_b](bench_practitioner_b.md)" in text
    assert "| layout | Nearest | IDW-Sample |" in text
    assert "| street | -1.00 (-1.00 to -1.00); best 0/1 | best 1/1 |" in text
    assert "| room |" not in text  # its one case failed: no blend method is judged on it
    assert ("IDW-Sample >= Nearest on 3 of 3 cases with a blend; Coverage (ours) >= Nearest on 1 of the 2 that "
            "scored it." in text)  # fmt: skip
    assert text.rstrip().endswith("3 case(s), 3 registered NeRF(s): median r_err 0.0800 deg, t_err 0.00800, "
                                  "s_err 0.00080; success rate 0.67.")  # fmt: skip


def test_tally_refuses_a_file_that_holds_no_case_records(tally, tmp_path):
    bad = tmp_path / "eval.json"
    bad.write_text(json.dumps({"results": {"psnr": 20.0}}))
    with pytest.raises(SystemExit, match="eval.json: expected a list of case records"):
        tally.collect([bad])
    with pytest.raises(SystemExit, match="missing.json: not a readable"):
        tally.collect([tmp_path / "missing.json"])


def test_blend_gains_against_idw_sample_leave_out_misregistered_and_unscored_cases():
    records = [_record("street-1", 0.1), _record("street-2", 0.1), _record("street-3", 9.0, failure=True),
               _record("street-4", None)]  # fmt: skip
    records[0]["blend_psnr"].update(idw_2d=21.5, coverage=22.0)
    records[1]["blend_psnr"].update(idw_2d=20.0, coverage=20.5, coverage_3d=22.0)
    records[2]["blend_psnr"].update(idw_2d=30.0, coverage=30.0)  # a failed registration: left out
    gains = blend_gains(records)
    assert set(gains) == {"nearest", "idw_2d", "idw_sample", "coverage", "coverage_3d"}
    cov = gains["coverage"]
    assert (cov.cases, cov.median, cov.low, cov.high, cov.best) == (2, pytest.approx(0.25), pytest.approx(-0.5),
                                                                   pytest.approx(1.0), 1)  # fmt: skip
    assert (gains["coverage_3d"].cases, gains["coverage_3d"].best) == (1, 1)
    assert gains["idw_sample"].median == 0.0 and gains["idw_sample"].best == 0
    assert gains["nearest"].cell() == "-1.00 (-1.00 to -1.00); best 0/2"
    assert blend_gains([_record("room-1", 170.0, failure=True)]) == {}
