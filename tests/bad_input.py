"""Bad input through the real CLIs, the machinery every surface's table shares: a row (:class:`Case`) runs
``python -m <cli> ...`` from an empty working directory with its run directory and cache under the test's tmp
dir; it must exit 2 with exactly one stderr line, and new files may appear only in the run directory and the
cache. Rows that start a Python with torch take seconds each: one per class runs by default, the whole table
with ``-m slow`` (:func:`rows`). The tables: tests/config/test_bad_settings.py (command-line values),
tests/data/test_bad_data.py (datasets, lists, images), tests/core/test_bad_files.py (checkpoints, run
directories, caches, the file system); inputs that must not fail but must not be silently wrong either sit
beside them and in tests/reporting/test_bad_records.py (sweep records).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.helpers import REPO, make_folder, write_image

EVAL_SIZE = ["data.image_size=[32,48]"]


#: Folders made immutable by a row (root ignores permissions); made mutable again after the row.
IMMUTABLE: list[Path] = []


def a_file(tmp: Path) -> str:
    (tmp / "file").write_text("x")
    return str(tmp / "file")


def folder(t: Path, c: Path, edit: Callable[[Path], None]) -> list[str]:
    root = make_folder(t / "folder", n=3)
    edit(root / "images" / "test")
    return [f"ckpt={c}", "data=folder", f"data.root={root}"]


def dangling(test: Path) -> None:
    (test / "database" / "@585900.00@4477000.00@17@T@@@@@@@@@@@.jpg").symlink_to("/nonexistent/x.jpg")


def nordland(t: Path, c: Path, *extra: str, frame: str | None = None) -> list[str]:
    for i in range(3):
        write_image(t / "nord" / "ref" / f"{i:05d}.jpg", i)
        write_image(t / "nord" / "query" / f"{i:05d}.jpg", i)
    if frame is not None:
        write_image(t / "nord" / "query" / f"{frame}.jpg", 5)
    return [f"ckpt={c}", "data=nordland", f"data.root={t / 'nord'}", *extra]


TRAIN = ["semvpr.train", "experiment=tiny"]


EVAL = ["semvpr.eval", "experiment=tiny", *EVAL_SIZE]


LOCALIZE = ["semvpr.localize", *EVAL_SIZE, "data.num_workers=0"]


@dataclass
class Case:
    """A bad input: the CLI and its fixed args, the bad args (given the tmp inputs dir and a checkpoint),
    a fragment of the one line; a row may name its own run dir / cache, environment and time limit, and
    check what the cache holds afterwards."""

    cli: list[str]
    args: Callable[[Path, Path], list[str]]
    fragment: str
    env: dict[str, str] = field(default_factory=dict)
    timeout: int = 600
    cache_check: Callable[[Path], None] | None = None


def stage_line(line: str) -> bool:
    """A progress line of semvpr's own (``semvpr: <set> db: 3/6 images``), not an error."""
    return line.startswith("semvpr: ") and not line.startswith("semvpr: error: ")


def files(folder: Path) -> set[Path]:
    return {Path(d) / n for d, dirs, names in os.walk(folder) for n in names + dirs}


def cli(module: str, *args: str, cwd: Path, timeout: int = 600, env: dict | None = None, limit_gb: float = 0):
    """Run ``python -m module args`` (optionally with its address space limited, so a blow-up fails fast)."""

    def limit() -> None:
        if limit_gb:
            size = int(limit_gb * 2**30)
            resource.setrlimit(resource.RLIMIT_AS, (size, size))

    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})},
        preexec_fn=limit,
    )


def rows(cases: dict[str, Case], fast: set[str]) -> list:
    """A table's rows as pytest parameters: those in ``fast`` by default, the others under ``-m slow``."""
    return [c if c in fast else pytest.param(c, marks=pytest.mark.slow) for c in sorted(cases)]


def run_case(row: Case, tmp_path: Path, checkpoint: Path) -> None:
    """Run one row: exit 2, one error line holding the row's fragment, nothing written outside the run and cache."""
    (module, *fixed), bad, fragment = row.cli, row.args, row.fragment
    inputs, run, cache, cwd = tmp_path / "in", tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    inputs.mkdir()
    cwd.mkdir()
    try:
        args = bad(inputs, checkpoint)
        if module != "semvpr.data.synthcity":
            if not any(a.startswith("paths.cache_dir=") for a in args):
                args.append(f"paths.cache_dir={cache}")
            if not any(a.startswith("hydra.run.dir=") for a in args):
                args.append(f"hydra.run.dir={run}")
            # A row may name its own run dir or cache: files may appear there.
            run = Path(next(a for a in args if a.startswith("hydra.run.dir=")).partition("=")[2])
            cache = Path(next(a for a in args if a.startswith("paths.cache_dir=")).partition("=")[2])
        before = files(tmp_path)
        proc = subprocess.run(
            [sys.executable, "-m", module, *fixed, *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=row.timeout,
            env={**os.environ, "PYTHONPATH": str(REPO), **row.env},
        )
        # Besides semvpr's own stage lines (a pass may have started), exactly one line: the error, last.
        lines = [ln for ln in proc.stderr.strip().splitlines() if not stage_line(ln)]
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
        assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
        assert proc.stderr.strip().splitlines()[-1] == lines[0]
        new = files(tmp_path) - before
        assert {p for p in new if not (p.is_relative_to(run) or p.is_relative_to(cache))} == set()
        if row.cache_check is not None:
            row.cache_check(cache)
    finally:
        while IMMUTABLE:
            subprocess.run(["chattr", "-i", str(IMMUTABLE.pop())], check=False, capture_output=True)
