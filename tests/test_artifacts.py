"""The artifact cache: built once, atomically, even by concurrent jobs."""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import pytest

from semvpr.core.cache import LOCK_DIR, artifact_dir, build_once


def _slow_build(log: str, tmp: Path) -> None:
    with open(log, "a") as handle:
        handle.write("built\n")
    time.sleep(0.5)
    (tmp / "content.txt").write_text("done")


def _job(cache: str, log: str, out: mp.Queue[str]) -> None:
    out.put(str(build_once(cache, "thing", {"a": 1}, lambda tmp: _slow_build(log, tmp))))


def test_concurrent_jobs_build_an_artifact_once(tmp_path: Path) -> None:
    cache, log = tmp_path / "cache", tmp_path / "builds.log"
    ctx = mp.get_context("fork")
    out: mp.Queue[str] = ctx.Queue()
    jobs = [ctx.Process(target=_job, args=(str(cache), str(log), out)) for _ in range(3)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(timeout=30)
        assert job.exitcode == 0
    paths = {out.get(timeout=5) for _ in jobs}
    assert paths == {str(artifact_dir(cache, "thing", {"a": 1}))}
    assert log.read_text().count("built") == 1
    assert (Path(paths.pop()) / "content.txt").read_text() == "done"


def test_failed_build_leaves_nothing_and_the_next_call_builds(tmp_path: Path) -> None:
    def failing(tmp: Path) -> None:
        (tmp / "half.txt").write_text("partial")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        build_once(tmp_path, "thing", {"a": 2}, failing)
    assert [p.name for p in tmp_path.iterdir() if p.name != LOCK_DIR] == []
    final = build_once(tmp_path, "thing", {"a": 2}, lambda tmp: (tmp / "ok.txt").write_text("ok"))
    assert (final / "ok.txt").read_text() == "ok" and (final / "key.json").is_file()
