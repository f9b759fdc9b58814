"""Tests for nerfuser_ns.scripts.register's summary (what a user reads after ns-nerfuser-register)."""

from types import SimpleNamespace

from rich.console import Console

from nerfuser_ns.scripts.register import camera_optimizer_tip, print_summary, short_names

A = "/home/me/outputs/part_a/nerfacto/2026-11-27_101500/config.yml"
B = "/home/me/outputs/part_b/nerfacto/2026-11-27_101500/config.yml"


def test_short_names_drop_the_shared_folders_and_file_name():
    assert short_names([A, B]) == {A: "part_a/nerfacto/2026-11-27_101500", B: "part_b/nerfacto/2026-11-27_101500"}
    other = "/home/me/outputs/part_a/instant-ngp/run/config.yml"
    assert short_names([A, other]) == {A: "nerfacto/2026-11-27_101500", other: "instant-ngp/run"}
    assert short_names(["a", "b"]) == {"a": "a", "b": "b"}  # nothing shared: unchanged
    assert short_names([A, A]) == {A: A}  # the same run twice: nothing to shorten
    assert short_names(["x/config.yml", "config.yml"]) == {"x/config.yml": "x/config.yml", "config.yml": "config.yml"}


def _record(names: list[str]) -> dict:
    views = {"rendered": 32, "kept": 32, "registered": 31}
    residuals = {"rotation_deg_median": 0.1, "centre_median": 0.001}
    nerfs = [{"name": n, "views": views, "residuals": residuals, "scale_to_reference": 1.0, "scale_spread": 0.001,
              "estimator": "weiszfeld"} for n in names]  # fmt: skip
    pair = {"names": names, "covisible_points": 100,
            "self_check": {"ncc": 0.7, "passed": True, "depth_i_in_j": 0.012, "depth_j_in_i": -0.031}}
    return {"reference": {"name": names[0], "index": 0}, "nerfs": nerfs, "pairs": [pair], "timings_s": {"render": 1.0}}


def test_the_summary_tells_the_runs_apart_in_a_narrow_terminal():
    console = Console(record=True, width=100)
    print_summary(_record([A, B]), console)
    text = console.export_text()
    assert "part_a/nerfacto/2026-11-27_1" in text and "part_b/nerfacto/2026-11-27_1" in text
    assert f"frame of {A}" in text.replace("\n", "")  # the title keeps the reference's full path
    assert "-0.031" in text and "0.012" not in text  # the depth direction farther from 0, as the check judges it
    assert "not cross-render checked" not in text


def test_the_summary_says_why_a_pair_has_no_check():
    C = B.replace("part_b", "part_c")
    record = _record([A, B, C])
    linked = record["pairs"][0]
    record["pairs"] = [{**linked, "names": [A, B]}, {**linked, "names": [B, C]},
                       {"names": [A, C], "covisible_points": 7, "self_check": None}]  # outside the spanning tree
    console = Console(record=True, width=120)
    print_summary(record, console)
    assert "-: not cross-render checked; its NeRFs are linked, and checked, through" in console.export_text()
    for p in record["pairs"]:
        p["self_check"] = None
    console = Console(record=True, width=120)
    print_summary(record, console)
    assert "no pair cross-render checked (--self-check-views 0)" in console.export_text()


def test_the_camera_optimiser_tip_names_the_runs_trained_with_one():
    def run(name, mode):
        return SimpleNamespace(name=name, camera_optimizer_mode=mode)

    tip = camera_optimizer_tip([run(A, "SO3xR3"), run(B, "off"), run("/x/ngp/config.yml", None)])
    assert tip is not None and "--pipeline.model.camera-optimizer.mode off" in tip
    assert A in tip and B not in tip and "ngp" not in tip  # only the run that had one
    assert camera_optimizer_tip([run(A, "off"), run(B, None)]) is None
    assert camera_optimizer_tip([SimpleNamespace(name=A)]) is None  # a renderer that does not say (tests' fakes)


def test_the_summary_repeats_what_the_capture_checks_found():
    """A folded capture is warned about at the start of the registration; the summary says it again, by the NeRF's
    short name, since the start scrolled away during the renders."""
    record = _record([A, B])
    record["capture_checks"] = {
        A: {"checked": True, "folded": False, "matches": {"folded": False}, "camera": {"drifted": False}},
        B: {"checked": False, "folded": False, "matches": {"folded": True, "pairs": 630, "unexplained_pairs": 32,
                                                           "unexplained_share": 0.0508}},
    }  # fmt: skip
    console = Console(record=True, width=100)
    print_summary(record, console)
    said = " ".join(console.export_text().split())
    assert ("warning: NeRF part_b/nerfacto/2026-11-27_101500's capture: folded by COLMAP: its reconstruction does not "
            "explain 32 of 630 verified image pairs (5.1%)") in said  # fmt: skip
    assert "ns-nerfuser-check-capture" in said and "part_a/nerfacto/2026-11-27_101500's capture" not in said
    record["capture_checks"][B]["matches"]["folded"] = False
    console = Console(record=True, width=100)
    print_summary(record, console)
    assert "warning" not in console.export_text()
