"""Atomic writes: a reader never sees half a file, and a planted temp name or link is never followed."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from semvpr.core.io import atomic_dir, atomic_file, write_json


def test_a_failed_write_leaves_neither_target_nor_temp(tmp_path: Path) -> None:
    target = tmp_path / "metrics.json"
    with pytest.raises(RuntimeError), atomic_file(target) as fh:
        fh.write(b"{half")
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_planted_links_at_old_fixed_temp_names_are_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("keep")
    run = tmp_path / "run"
    run.mkdir()
    for name in (".metrics.json.tmp", f".metrics.json.{os.getpid()}.tmp"):  # the names used before
        (run / name).symlink_to(victim)
    write_json(run / "metrics.json", {"status": "ok"})
    assert victim.read_text() == "keep"
    assert (run / "metrics.json").read_text().startswith("{")


def test_two_writers_never_share_a_temp_name(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    with atomic_file(target) as first, atomic_file(target) as second:
        assert first.name != second.name
        first.write(b"1")
        second.write(b"2")
    # Each writer's content arrives whole: the inner (second) block is renamed first, the outer last.
    assert target.read_bytes() == b"1"


def test_atomic_dir_replaces_the_target_only_when_complete(tmp_path: Path) -> None:
    out = tmp_path / "teacher"
    out.mkdir()
    (out / "old").write_text("old")
    with pytest.raises(ValueError), atomic_dir(out) as tmp:
        (tmp / "new").write_text("new")
        raise ValueError
    assert [p.name for p in tmp_path.iterdir()] == ["teacher"] and (out / "old").exists()
    with atomic_dir(out) as tmp:
        (tmp / "new").write_text("new")
    assert [p.name for p in out.iterdir()] == ["new"]
