"""The four-way comparison as one Hydra multirun, with the report at the end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _sweep(tmp_path: Path, name: str, *overrides: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    sweep_dir = tmp_path / name
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.train",
            "-m",
            "experiment=tiny",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep_dir}",
            *overrides,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    return proc, sweep_dir


def _table_rows(results_md: Path) -> list[list[str]]:
    lines = [line for line in results_md.read_text().splitlines() if line.startswith("| efficientnet_lite0 |")]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


@pytest.mark.slow
def test_four_filter_sweep_writes_report_and_reuses_artifacts(tmp_path: Path) -> None:
    proc, sweep = _sweep(tmp_path, "sweep1", "filter=none,attention,unet,mask2former")
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = _table_rows(sweep / "results.md")
    # rows named by the preset asked for, with what it selected, in the report's order (baseline first)
    assert [row[1] for row in rows] == [
        "none (netvlad · none)",
        "attention (sral · none)",
        "unet (sral · student)",
        "mask2former (sral · teacher)",
    ]
    assert all(row[-2] == "0" for row in rows)  # no failed job
    for figure in ("recall_at_n.png", "figure3.png", "retrievals.png"):
        assert (sweep / figure).stat().st_size > 10_000
    cache = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert {name.split("-")[0] for name in cache} >= {"synthcity", "teacher", "labels", "student", "trunk", "masks"}
    proc, sweep = _sweep(tmp_path, "sweep2", "filter=none,attention,unet,mask2former")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == cache  # nothing rebuilt


def test_failed_job_does_not_stop_the_sweep(tmp_path: Path) -> None:
    proc, sweep = _sweep(tmp_path, "sweep", "filter=none", "model.num_clusters=0,4")
    assert proc.returncode == 0, proc.stderr[-2000:]
    md = (sweep / "results.md").read_text()
    rows = _table_rows(sweep / "results.md")
    assert len(rows) == 1 and rows[0][-2] == "1"  # one ok run, one failed
    assert "model.num_clusters=0 must be a whole number >= 1" in md
