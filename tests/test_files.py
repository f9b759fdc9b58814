"""Atomic output: whole results or nothing."""

from pathlib import Path

import pytest

from nerfuser_ns.files import atomic_path, write_text_atomic


def test_write_text_atomic_creates_parents_and_replaces(tmp_path: Path):
    out = tmp_path / "a" / "b" / "report.json"
    write_text_atomic(out, "one")
    write_text_atomic(out, "two")
    assert out.read_text() == "two"
    assert sorted(p.name for p in out.parent.iterdir()) == ["report.json"]  # no temporary left behind
    assert out.stat().st_mode & 0o044 == 0o044  # readable by others, like a normal file


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path):
    out = tmp_path / "cloud.ply"
    out.write_text("old")
    with pytest.raises(RuntimeError, match="writer died"):
        with atomic_path(out) as tmp:
            assert tmp.suffix == ".ply" and tmp.parent == tmp_path  # same folder: the rename is atomic
            tmp.write_text("half")
            raise RuntimeError("writer died")
    assert out.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply"]
