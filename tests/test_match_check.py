"""The match check (nerfuser_ns.match_check): a synthetic COLMAP database and model of unordered street views, once
consistent and once with a block of views posed by a half-turn twin, and its verdicts in ns-nerfuser-check-capture."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from colmap_helpers import (
    FOLDED,
    HEIGHT,
    NUM_VIEWS,
    TWO_WAY_RIGHT,
    TWO_WAY_VIEWS,
    WIDTH,
    two_way_street,
    write_colmap_capture,
)
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import case_layout, colmap_tie
from nerfuser_ns.capture_check import LARGER_SIDE_NAME, REPOSE_FOLDER_NAME, write_larger_side, write_repose_images
from nerfuser_ns.match_check import (
    MAX_REPOSE_SHARE,
    MAX_UNEXPLAINED_SHARE,
    MIN_VIEW_UNEXPLAINED_SHARE,
    MatchCheck,
    check_dataset_matches,
    fold_sides,
    pair_cover,
    read_verified_pairs,
    sampson_distances,
)
from nerfuser_ns.registration.pipeline import check_captures
from nerfuser_ns.scripts import check_capture as cli


def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


@pytest.fixture
def consistent(tmp_path) -> Path:
    return write_colmap_capture(tmp_path / "consistent", folded=False)


@pytest.fixture
def folded(tmp_path) -> Path:
    return write_colmap_capture(tmp_path / "folded", folded=True)


@pytest.fixture
def one_misposed(tmp_path) -> Path:
    """Twelve unordered street views, one (frame_00006.png) posed by the twin, with their image files."""
    folder = write_colmap_capture(tmp_path / "one_misposed", folded=True, twins=(5,))
    (folder / "images").mkdir()
    for i in range(NUM_VIEWS):
        (folder / "images" / f"frame_{i + 1:05d}.png").write_bytes(bytes([i]) * 16)
    return folder


@pytest.fixture
def two_way(tmp_path) -> Path:
    return write_colmap_capture(tmp_path / "two_way", folded=True, scene=two_way_street, twins=TWO_WAY_RIGHT)


def test_sampson_distance_is_zero_on_the_epipolar_line_and_the_offset_off_it():
    R, t = sim3.so3_exp(np.array([0.0, 0.1, 0.0])), np.array([1.0, 0.0, 0.2])
    X = np.array([[0.3, -0.2, 4.0], [-1.0, 0.5, 6.0]])
    x1 = X[:, :2] / X[:, 2:]
    Y = X @ R.T + t
    x2 = Y[:, :2] / Y[:, 2:]
    assert sampson_distances(x1, x2, R, t) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert sampson_distances(x1, x2, R, 7.0 * t) == pytest.approx([0.0, 0.0], abs=1e-12)  # scale-free in t
    # off the line by d in the second image (the line's normal): distance about d / sqrt(2) (both images share it)
    E = sim3.so3_hat(t / np.linalg.norm(t)) @ R
    line = E @ np.array([*x1[0], 1.0])
    normal = line[:2] / np.linalg.norm(line[:2])
    d = sampson_distances(x1[:1], x2[:1] + 1e-3 * normal, R, t)[0]
    assert 0.5e-3 < d < 1.0e-3
    assert np.isnan(sampson_distances(x1, x2, R, np.zeros(3))).all()  # no baseline: nothing to judge


def test_a_consistent_reconstruction_explains_every_verified_pair(consistent):
    check = check_dataset_matches(consistent)
    assert check.checked and check.pairs >= 40 and check.unexplained == [] and not check.folded
    assert check.warning("capture") is None
    assert check_dataset_matches(consistent / "transforms.json").pairs == check.pairs  # the file or its folder


def test_views_posed_by_the_twin_leave_exactly_their_pairs_with_the_others_unexplained(folded):
    check = check_dataset_matches(folded)
    names = [f"frame_{i + 1:05d}.png" for i in range(NUM_VIEWS)]
    twins = {names[i] for i in FOLDED}
    _, _, pairs = read_verified_pairs(folded / "colmap" / "database.db")
    across = {(names[a - 1], names[b - 1]) for a, b, _ in pairs if (names[a - 1] in twins) != (names[b - 1] in twins)}
    assert set(check.unexplained) == across and len(across) > MAX_UNEXPLAINED_SHARE * check.pairs
    assert check.folded and "does not explain" in check.warning("capture_1")
    assert {name for name, _ in check.views()[: len(FOLDED)]} == twins  # the folded views head the list
    record = check.to_record()
    assert record["folded"] and record["unexplained_pairs"] == len(across)


def test_the_check_never_writes_its_inputs(folded):
    database = folded / "colmap" / "database.db"
    con = sqlite3.connect(database)
    con.execute("PRAGMA journal_mode=WAL")  # as COLMAP leaves its databases
    con.close()
    before = sorted(p.name for p in database.parent.iterdir()), _md5(database)
    check_dataset_matches(folded)
    assert (sorted(p.name for p in database.parent.iterdir()), _md5(database)) == before


def test_no_colmap_folder_is_not_checked_and_a_broken_database_is_one_line(consistent, tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    check = check_dataset_matches(bare)
    assert not check.checked and not check.folded and "no COLMAP database" in check.reason
    (consistent / "colmap" / "database.db").write_bytes(b"not a database")
    with pytest.raises(ValueError, match="not a readable COLMAP database"):
        check_dataset_matches(consistent)


def test_cli_reports_a_fold_of_unordered_views_and_exits_1(consistent, folded, capsys):
    assert cli.run(cli.CheckCaptureCommand([consistent])) == 0
    assert "COLMAP's poses explain its verified matches" in capsys.readouterr().out
    assert cli.run(cli.CheckCaptureCommand([consistent, folded])) == 1
    out = capsys.readouterr().out
    assert "does not explain" in out and "views in the most unexplained pairs: frame_" in out
    assert cli.POSE_AGAIN_ADVICE in " ".join(out.split())
    assert cli.ONE_FOCAL_ADVICE in " ".join(out.split())  # posed with one focal length: another camera to try
    # the recipe with this capture's paths, to copy: its images into a new dataset beside it, then checked
    recipe = [line.strip() for line in out.splitlines() if line.startswith("    ")]
    radial = folded.with_name("folded_radial")
    assert recipe == cli.radial_recipe_lines(folded) and recipe[-1] == f"ns-nerfuser-check-capture {radial}"
    assert f"--image_path {folded / 'images'} --ImageReader.camera_model SIMPLE_RADIAL" in recipe[1]
    assert recipe[0] == f"mkdir -p {radial / 'colmap' / 'sparse'}"
    assert f"--output-dir {radial} --skip-colmap" in recipe[4]
    transforms = folded / "transforms.json"
    meta = json.loads(transforms.read_text())
    transforms.write_text(json.dumps({**meta, "fl_y": meta["fl_x"] * 1.001}))  # a focal length per axis
    assert cli.run(cli.CheckCaptureCommand([folded])) == 1
    out = " ".join(capsys.readouterr().out.split())
    assert cli.POSE_AGAIN_ADVICE in out and cli.ONE_FOCAL_ADVICE not in out


def test_the_check_says_when_colmap_compared_only_some_pairs(consistent, tmp_path, capsys):
    """Exhaustive matching compares every pair; sequential matching only neighbours in file order, which leaves a
    fold between far views nothing to contradict it: the check says how many pairs it could judge from."""
    exhaustive = check_dataset_matches(consistent)
    assert (exhaustive.compared_pairs, exhaustive.possible_pairs) == (NUM_VIEWS * (NUM_VIEWS - 1) // 2,) * 2
    assert exhaustive.blind_spot() is None
    sequential = check_dataset_matches(write_colmap_capture(tmp_path / "sequential", folded=False, overlap=2))
    assert sequential.compared_pairs == 2 * NUM_VIEWS - 3 and sequential.possible_pairs == exhaustive.possible_pairs
    assert not sequential.folded and sequential.pairs <= sequential.compared_pairs
    said = sequential.blind_spot()
    assert f"COLMAP compared {2 * NUM_VIEWS - 3} of its {exhaustive.possible_pairs} image pairs" in said
    assert sequential.to_record()["compared_pairs"] == 2 * NUM_VIEWS - 3
    assert cli.run(cli.CheckCaptureCommand([tmp_path / "sequential"])) == 0  # a caveat, not a finding
    out = " ".join(capsys.readouterr().out.split())
    assert "explain its verified matches" in out and "but COLMAP compared 21 of its 66 image pairs" in out
    assert cli.run(cli.CheckCaptureCommand([consistent])) == 0 and "COLMAP compared" not in capsys.readouterr().out
    # a database without COLMAP's matches table (written by another tool) does not say
    con = sqlite3.connect(consistent / "colmap" / "database.db")
    con.execute("DROP TABLE matches")
    con.commit()
    con.close()
    unknown = check_dataset_matches(consistent)
    assert unknown.compared_pairs is None and unknown.blind_spot() is None and unknown.pairs == exhaustive.pairs


def _two_way_names() -> tuple[set[str], set[str]]:
    names = {f"frame_{i + 1:05d}.png" for i in range(TWO_WAY_VIEWS)}
    right = {f"frame_{i + 1:05d}.png" for i in TWO_WAY_RIGHT}
    return names - right, right


def test_two_groups_joined_by_unexplained_pairs_are_the_folds_sides(two_way):
    check = check_dataset_matches(two_way)
    left, right = _two_way_names()
    assert check.folded and set(check.smaller_side) == right
    assert set(check.to_record()["smaller_side"]) == right
    assert fold_sides(check.explained[::-1], check.unexplained[::-1]) == (tuple(sorted(left)), tuple(sorted(right)))
    # checked on the views of the larger side alone (what a run trained on it saw): nothing unexplained
    larger = write_larger_side(two_way, right, two_way / LARGER_SIDE_NAME, "matches")
    alone = check_dataset_matches(larger)
    assert not alone.folded and alone.unexplained == [] and alone.pairs == check.pairs - len(check.unexplained) - sum(
        (a in right) and (b in right) for a, b in check.explained)


def test_no_sides_where_the_fold_runs_through_the_capture_or_the_sides_share_many_pairs(folded):
    assert check_dataset_matches(folded).folded and check_dataset_matches(folded).smaller_side is None
    a = [(f"a{i}", f"a{j}") for i in range(8) for j in range(i + 1, 8)]  # 28 pairs within each group
    b = [(f"b{i}", f"b{j}") for i in range(6) for j in range(i + 1, 6)]
    bridge = [("a0", "b0"), ("a1", "b1")]
    assert fold_sides(a + b, bridge) == tuple(tuple(sorted({v for pair in g for v in pair})) for g in (a, b))
    assert fold_sides(a + b + bridge, [("a2", "b2")]) is None  # most pairs across are explained (our rooms)
    many = [(f"a{i}", f"b{i % 6}") for i in range(8)]
    assert fold_sides(a + b, bridge + many) is None  # too many pairs across
    assert fold_sides(a[2:] + b, bridge + a[:2]) is None  # a side that does not explain itself (our row houses)
    assert fold_sides([], bridge) is None


def test_cli_writes_the_larger_side_the_matches_show_and_advises_without_it(two_way, folded, capsys):
    assert cli.run(cli.CheckCaptureCommand([two_way])) == 1
    out = capsys.readouterr().out
    assert "two sides" in out and "6 views were posed by the fold" in out and "--write-larger-side" in out
    assert not (two_way / LARGER_SIDE_NAME).exists()
    assert cli.run(cli.CheckCaptureCommand([two_way, folded], write_larger_side=True)) == 1
    out = capsys.readouterr().out
    meta = json.loads((two_way / LARGER_SIDE_NAME).read_text())
    left, right = _two_way_names()
    assert {Path(f["file_path"]).name for f in meta["frames"]} == left
    assert meta["nerfuser_larger_side"]["found_by"] == "matches"
    assert {Path(f).name for f in meta["nerfuser_larger_side"]["dropped"]} == right
    assert f"({len(left)} views, the larger side by the matches)" in out
    assert not (folded / LARGER_SIDE_NAME).exists()  # folded all through: no side to train on
    assert "pose the capture again" in out


class DatasetRun:
    """A run as the registration sees it: training cameras in file order, and the folder of its dataset."""

    def __init__(self, name: str, folder: Path | None):
        self.name, self.folder = name, folder

    def training_image_files(self) -> list[Path]:
        return [Path(f"images/frame_{i + 1:05d}.png") for i in range(NUM_VIEWS)]

    def training_poses(self) -> np.ndarray:
        return np.tile(np.eye(4), (NUM_VIEWS, 1, 1))

    def dataset_path(self) -> Path | None:
        return self.folder


def test_registration_warns_about_a_run_whose_dataset_poses_do_not_explain_its_matches(consistent, folded, two_way):
    console = Console(record=True, width=400)
    larger = write_larger_side(two_way, _two_way_names()[1], two_way / LARGER_SIDE_NAME, "matches")
    runs = [DatasetRun("a", consistent), DatasetRun("b", folded), DatasetRun("c", None), DatasetRun("d", larger),
            DatasetRun("e", two_way)]  # fmt: skip
    records = check_captures(runs, console)
    assert not records["a"]["matches"]["folded"] and records["b"]["matches"]["folded"]
    assert not records["d"]["matches"]["folded"]  # trained on the larger side: its views alone are checked
    assert "matches" not in records["c"]  # no dataset folder: nothing to check, no warning
    text = console.export_text()
    assert "warning: NeRF b's dataset: COLMAP's reconstruction does not explain" in text
    warnings = {w.split("'s dataset")[0]: w for w in " ".join(text.split()).split("warning: ")}
    assert "pose it again" in warnings["NeRF b"]  # folded all through: no side to train on
    assert "--write-larger-side" in warnings["NeRF e"] and "pose it again" not in warnings["NeRF e"]
    assert "NeRF a" not in text and "NeRF d" not in text


def test_the_benchmarks_colmap_record_carries_the_verdict(consistent, folded, tmp_path):
    """scripts/bench_practitioner.py reports the check per capture from the record of :func:`colmap_tie`."""
    layout = case_layout("street:3", width=WIDTH, height=HEIGHT)
    case = tmp_path / "case"
    for cap, source in zip(layout.captures, (consistent, folded), strict=False):
        shutil.copytree(source, case / "datasets" / cap.name)
        transforms = case / "datasets" / cap.name / "transforms.json"
        data = json.loads(transforms.read_text())
        for i, frame in enumerate(data["frames"]):  # posed at the truth: the tie itself is not under test
            frame["transform_matrix"] = cap.c2w_world[i].tolist()
        transforms.write_text(json.dumps(data))
    records = [colmap_tie(cap, case)[0] for cap in layout.captures[:2]]
    assert [r["match_check_folded"] for r in records] == [False, True]
    assert records[0]["match_check_unexplained_share"] == 0.0
    assert records[1]["match_check_unexplained_share"] > MAX_UNEXPLAINED_SHARE
    assert records[0]["match_check_pairs"] == records[1]["match_check_pairs"] > 0
    shutil.rmtree(case / "datasets" / layout.captures[0].name / "colmap")  # posed another way: no verdict, no key
    assert "match_check_folded" not in colmap_tie(layout.captures[0], case)[0]


def test_pair_cover_takes_the_view_in_most_pairs_first_and_covers_every_pair():
    star = [("c", f"v{i}") for i in range(5)]
    assert pair_cover(star) == ["c"]
    assert pair_cover(star + [("a", "b")]) == ["c", "a"]  # ties by name
    cover = pair_cover([("a", "b"), ("c", "d"), ("b", "c")])
    assert all(set(pair) & set(cover) for pair in [("a", "b"), ("c", "d"), ("b", "c")]) and len(cover) == 2
    assert pair_cover([]) == []


def test_one_misposed_view_is_named_to_pose_again_without_and_a_fold_is_not(one_misposed, folded, two_way):
    check = check_dataset_matches(one_misposed)
    assert check.folded and check.smaller_side is None
    assert check.repose_without == ("frame_00006.png",)
    assert all("frame_00006.png" in pair for pair in check.unexplained)
    assert check.to_record()["repose_without"] == ["frame_00006.png"]
    # three of twelve views by the twin: more than MAX_REPOSE_SHARE, a fold rather than a few misposed views
    assert len(FOLDED) > MAX_REPOSE_SHARE * NUM_VIEWS and check_dataset_matches(folded).repose_without is None
    assert check_dataset_matches(two_way).repose_without is None  # two sides: train on the larger one instead


def test_a_view_that_contradicts_few_of_its_matches_is_not_named_misposed():
    """Twenty views matched in a ring, each to its four nearest: the unexplained pairs all go through v00, which a
    greedy cover names; v00 is named misposed only while most of its own pairs are unexplained."""
    ring = [(f"v{i:02d}", f"v{(i + k) % 20:02d}") for i in range(20) for k in (1, 2)]
    for lost in (3, 1):  # of v00's 4 pairs in the ring, this many unexplained
        through = [pair for pair in ring if "v00" in pair]
        unexplained = through[:lost]
        explained = [pair for pair in ring if pair not in unexplained]
        check = MatchCheck(checked=True, pairs=len(ring), unexplained=unexplained, explained=explained)
        assert check.folded and check.smaller_side is None
        share = lost / len(through)
        assert check.repose_without == (("v00",) if share >= MIN_VIEW_UNEXPLAINED_SHARE else None), lost


def test_view_shares_count_each_views_own_judged_pairs():
    unexplained = [("a", "b"), ("a", "c")]
    explained = [("a", "d"), ("b", "c"), ("b", "d"), ("c", "d")]
    shares = MatchCheck(checked=True, pairs=6, unexplained=unexplained, explained=explained).view_shares()
    assert shares == {"a": 2 / 3, "b": 1 / 3, "c": 1 / 3}  # d is in no unexplained pair
    assert MatchCheck(checked=True, pairs=1, explained=[("a", "b")]).view_shares() == {}


def test_cli_copies_every_image_but_the_misposed_view_to_pose_again_and_never_overwrites(one_misposed, capsys):
    assert cli.run(cli.CheckCaptureCommand([one_misposed])) == 1
    out = capsys.readouterr().out
    assert "every unexplained pair goes through frame_00006.png, posed inconsistently" in out
    assert "pose it again without frame_00006.png" in out and "--write-images-to-repose" in out
    assert not (one_misposed / REPOSE_FOLDER_NAME).exists()
    before = sorted(p.name for p in one_misposed.iterdir())
    assert cli.run(cli.CheckCaptureCommand([one_misposed], write_images_to_repose=True)) == 1
    out = capsys.readouterr().out
    folder = one_misposed / REPOSE_FOLDER_NAME
    names = sorted(p.name for p in folder.iterdir())
    assert names == [f"frame_{i + 1:05d}.png" for i in range(NUM_VIEWS) if i != 5]
    assert all((folder / n).read_bytes() == (one_misposed / "images" / n).read_bytes() for n in names)
    assert f"wrote {folder} (11 images, without frame_00006.png)" in out
    # what to run next, filled in: those images posed into a new dataset beside the capture, then checked
    reposed = one_misposed.with_name("one_misposed_reposed")
    commands = [line.strip() for line in out.splitlines() if line.startswith("    ")]
    assert commands == [f"ns-process-data images --data {folder} --output-dir {reposed}",
                        f"ns-nerfuser-check-capture {reposed}"]  # fmt: skip
    assert sorted(p.name for p in one_misposed.iterdir()) == sorted([*before, REPOSE_FOLDER_NAME])
    # a second run names the folder it will not overwrite, in one line, before it checks or writes anything
    other = shutil.copytree(one_misposed, one_misposed.parent / "other", ignore=shutil.ignore_patterns(folder.name))
    assert cli.run(cli.CheckCaptureCommand([other, one_misposed], write_images_to_repose=True)) == 1
    captured = capsys.readouterr()
    assert f"{folder}: already exists" in captured.err and len(captured.err.strip().splitlines()) == 1
    assert captured.out == "" and not (other / REPOSE_FOLDER_NAME).exists()


def test_cli_poses_a_drifted_capture_without_its_misposed_view_in_one_posing(one_misposed, capsys):
    """A capture with both a few misposed views and a drifted camera gets one posing: the copied images with one
    focal length; the drift's advice points to it instead of printing a second posing of every image."""
    file = one_misposed / "transforms.json"
    meta = json.loads(file.read_text())
    file.write_text(json.dumps({**meta, "fl_y": 1.2 * meta["fl_x"]}))
    assert cli.run(cli.CheckCaptureCommand([one_misposed], write_images_to_repose=True)) == 1
    out = capsys.readouterr().out
    assert "COLMAP's camera looks drifted" in out and "below, without its misposed views" in out
    reposed = one_misposed.with_name("one_misposed_reposed")
    commands = [line.strip() for line in out.splitlines() if line.startswith("    ")]
    assert commands == [f"ns-process-data images --data {one_misposed / REPOSE_FOLDER_NAME} --output-dir {reposed} "
                        "--camera-type simple_pinhole", f"ns-nerfuser-check-capture {reposed}"]  # fmt: skip


def test_repose_images_refuses_names_not_in_the_images_folder_and_leaves_nothing(one_misposed, tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="no image frame_00099.png"):
        write_repose_images(one_misposed, ["frame_00099.png"], tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))
    # a copy that fails halfway leaves no folder behind
    calls = []

    def failing_copy(src, dst):
        calls.append(src)
        if len(calls) == 3:
            raise OSError("disk full")
        return shutil.copyfile(src, dst)

    monkeypatch.setattr("nerfuser_ns.capture_check.shutil.copy2", failing_copy)
    with pytest.raises(OSError, match="disk full"):
        write_repose_images(one_misposed, ["frame_00006.png"], tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))
    shutil.rmtree(one_misposed / "images")
    with pytest.raises(ValueError, match="no images folder"):
        write_repose_images(one_misposed, ["frame_00006.png"], tmp_path / "out")
