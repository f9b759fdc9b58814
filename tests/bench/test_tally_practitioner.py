"""The practitioner reports' summary (:func:`nerfuser_ns.bench.practitioner_cases.summarise`) and the tally of case
records from several reports (scripts/tally_practitioner.py), with each check's refusals judged by the truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nerfuser_ns.bench.practitioner_cases import auto_blend_choice, blend_gains, refusing_check, summarise, with_auto
from nerfuser_ns.registration import NerfEntry, RegistrationConfig, write_minimal_registration
from nerfuser_ns.registration.record import TrainingCameras
from nerfuser_ns.registration.self_check import CrossRenderCheck, camera_failure, failure_message
from nerfuser_ns.sampling import look_at


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
    # each truth per layout, over the layout's cases scored with it: only the street has the other three truths
    assert "- street: 1 case(s), 1 registered NeRF(s): median r_err 0.0300 deg" in text
    assert text.count("- street: 1 case(s)") == 4 and text.count("- object-centric: 1 case(s)") == 1
    assert "[bench_practitioner_b](bench_practitioner_b.md)" in text
    assert "| layout | Nearest | IDW-Sample |" in text
    assert "| street | -1.00 (-1.00 to -1.00); best 0/1 | best 1/1 |" in text
    assert "| room |" not in text  # its one case failed: no blend method is judged on it
    assert ("IDW-Sample >= Nearest on 3 of 3 cases with a blend; Coverage (ours) >= Nearest on 1 of the 2 that "
            "scored it; Auto (ours, the default) >= Nearest on 1 of 2." in text)  # fmt: skip
    assert "| layout | Nearest | IDW-Sample | Coverage (ours) | Auto (ours, the default) |" in text
    # around objects auto is IDW-Sample (+0.00 over it); along the street coverage (19.5 against IDW-Sample's 21)
    assert "| object-centric | -1.00 (-1.00 to -1.00); best 0/1 | best 1/1 | -0.50 (-0.50 to -0.50); best 0/1 | " \
           "+0.00 (+0.00 to +0.00); best 1/1 |" in text
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
    assert set(gains) == {"nearest", "idw_2d", "idw_sample", "coverage", "coverage_3d", "auto"}
    # auto on a street is coverage, under another name: the same gains, and it is no rival that takes a best
    assert (gains["auto"].median, gains["auto"].best) == (gains["coverage"].median, gains["coverage"].best)
    cov = gains["coverage"]
    assert (cov.cases, cov.median, cov.low, cov.high, cov.best) == (2, pytest.approx(0.25), pytest.approx(-0.5),
                                                                   pytest.approx(1.0), 1)  # fmt: skip
    assert (gains["coverage_3d"].cases, gains["coverage_3d"].best) == (1, 1)
    assert gains["idw_sample"].median == 0.0 and gains["idw_sample"].best == 0
    assert gains["nearest"].cell() == "-1.00 (-1.00 to -1.00); best 0/2"
    assert blend_gains([_record("room-1", 170.0, failure=True)]) == {}


def test_auto_takes_the_recorded_choice_or_the_layouts_and_reads_a_registration_file(tmp_path):
    street, obj = _record("street-1", 0.1), _record("object-centric-1", 0.1)
    for r in (street, obj):
        r["blend_psnr"].update(coverage=22.5)
    assert with_auto(street)["blend_psnr"]["auto"] == 22.5 and with_auto(obj)["blend_psnr"]["auto"] == 21.0
    assert "auto" not in street["blend_psnr"]  # a copy
    street["auto_blend"] = {"method": "idw-sample", "reason": "...", "rule": 2}  # what the report recorded wins
    assert with_auto(street)["blend_psnr"]["auto"] == 21.0
    # ... when recorded under the rule in force; a drive recorded under the first rule (coverage) gets IDW-2D's now
    drive = _record("drive-1", 0.1)
    drive["blend_psnr"].update(coverage=22.5, idw_2d=22.7)
    drive["auto_blend"] = {"method": "coverage", "reason": "..."}
    assert with_auto(drive)["blend_psnr"]["auto"] == 22.7
    assert with_auto(_record("street-2", None) | {"blend_psnr": None})["blend_psnr"] is None

    az = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = look_at(np.stack([2 * np.cos(az), 2 * np.sin(az), np.ones(16)], axis=-1), np.zeros(3))
    walk = np.stack([np.linspace(0, 20, 16), np.zeros(16), np.ones(16)], axis=-1)
    facade = look_at(walk, walk + np.stack([0.3 * np.sin(np.arange(16)), np.full(16, 5.0), np.zeros(16)], axis=-1))
    beside = ring.copy()
    beside[:, 0, 3] += 3.0  # the same ring around an object 3 m away
    intrinsics = np.tile([100.0, 100.0, 80.0, 60.0, 160.0, 120.0], (16, 1))

    def registration(*poses):
        nerfs = [NerfEntry(f"capture_{i}", tmp_path / f"run{i}/config.yml", np.eye(4), TrainingCameras(c, intrinsics))
                 for i, c in enumerate(poses)]  # fmt: skip
        return write_minimal_registration(nerfs, tmp_path / f"registration_{len(list(tmp_path.iterdir()))}.json")

    around = auto_blend_choice(registration(ring, beside))
    assert around["method"] == "idw-sample" and "capture_1 0" in around["reason"]
    along = auto_blend_choice(registration(ring, facade))
    assert along["method"] == "coverage" and "not every NeRF's cameras look at a centre" in along["reason"]
    assert along["rule"] == around["rule"] == 2


def _refusal_lines() -> dict[str, str]:
    """One refusal line of each check: the camera, NCC and depth lines written by the registration's own functions, the
    model and twin lines (whose functions need an SfM or renders) copied from theirs."""
    config = RegistrationConfig()
    return {
        "camera": camera_failure(["a", "b"], [1.0, 1.0], [0.1, 9.0], [0.0, 0.0], config),
        "NCC": failure_message([CrossRenderCheck(0, 1, 0.1, 0.2, 4)], ["a", "b"], config),
        "depth": failure_message([CrossRenderCheck(0, 1, 0.9, 0.8, 4, depth_i_in_j=0.3)], ["a", "b"], config),
        "model": ("b: another SfM model (31 views) links it to a 13.4 deg, 0.647 reference units and 2.132 in log "
                  "scale away from the registration's link"),  # fmt: skip
        "twin": "twin check: a / b: another transform (180 deg, 2 units from the SfM's link, 40 3D matches against 9)",
    }


def test_each_refusal_line_names_its_check_and_a_summary_line_none():
    lines = _refusal_lines()
    assert {check: refusing_check(line) for check, line in lines.items()} == {c: c for c in lines}
    assert refusing_check(f"no pose source registered the runs, 4 tried: training (sfm): {lines['camera']}") is None
    assert refusing_check("a: 3 of 16 views registered by the SfM (needs 4)") is None


def test_each_checks_refusals_are_judged_by_the_truth_of_the_link_they_refused(tally):
    lines = _refusal_lines()

    def attempt(check, r, failure=False):
        errors = None if r is None else [{"nerf": "b", "r_err_deg": r, "t_err": 0.0, "s_err": 0.0, "failure": failure}]
        return {"source": "training", "mode": "sfm", "error": lines[check], "errors": errors}

    right, wrong = _record("drive-1", 0.4), _record("drive-2", None)
    right["registration"]["attempts"] = [attempt("camera", 9.0, failure=True), attempt("depth", 1.9)]
    wrong["registration"]["attempts"] = [attempt("camera", 0.3), attempt("camera", None),
                                         {"source": "both", "mode": "sfm", "error": "a: no views", "errors": None}]
    failed = _record("drive-3", 6.0, failure=True)  # a right refusal, then a failure kept from the next source
    failed["registration"]["attempts"] = [attempt("camera", 30.0, failure=True)]
    table = {line.split(" | ")[0].strip("| "): line for line in tally.refusal_lines([right, wrong, failed]) if
             line.startswith("| ") and not line.startswith(("| check", "| ---"))}  # fmt: skip
    assert set(table) == {"camera", "depth"}  # the line no check wrote is no refusal
    # after the right refusals: drive-1 kept a success, drive-3 a failure; drive-2's wrong refusal ended refused
    assert table["camera"] == "| camera | 4 | 2 | 1 / 1 / 0 | 1 | drive-2: 0.30 -> - | 1 |"
    assert table["depth"] == "| depth | 1 | 0 | 0 / 0 / 0 | 1 | drive-1: 1.90 -> 0.40 | 0 |"
