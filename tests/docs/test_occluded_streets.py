"""experiments/occluded-streets end to end on fixtures: run.sh's evaluations (a tiny CamVid, three tiny
traversals, the tiny SynthCity for NetVLAD's k-means) and summarize.py's data file, checked against the
ranks the evaluations wrote."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.camvid_fixture import write_camvid
from tests.helpers import REPO, write_frames

EXPERIMENT = REPO / "experiments" / "occluded-streets"


@pytest.mark.slow
def test_run_sh_and_summarize_on_fixtures(tmp_path: Path) -> None:
    # Frame i of every traversal is the same image: clean, every query finds its place.
    gardens = write_frames(
        tmp_path / "gardens", {t: [0, 1, 2, 3, 4] for t in ("day_left", "day_right", "night_right")}, "Image{:03d}.jpg"
    )
    camvid = write_camvid(tmp_path / "camvid", sizes={"train": 1, "val": 1, "test": 6})
    out = tmp_path / "out"
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "PAIRS": "day_left:night_right",
        "COVERAGES": "0.1,0.2",
        "SEEDS": "0,1",
        "EXTRA": "data.num_workers=0 data.image_size=[64,96] hydra.launcher.n_jobs=1 experiment=tiny "
        "init.overrides=['preset=tiny','image_size=[64,80]']",
    }
    run = subprocess.run(
        ["bash", str(EXPERIMENT / "run.sh"), str(out), str(gardens), str(camvid)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1500,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    sweeps = sorted(p.name for p in (out / "eval" / "day_left-night_right").iterdir())
    assert sweeps == ["m0-clean-none", "m0-holes-oracle", "m0-occluded-none", "m0-occluded-oracle"]
    summary = subprocess.run(
        [sys.executable, str(EXPERIMENT / "summarize.py"), str(out), "--out-dir", str(tmp_path / "summary")],
        env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert summary.returncode == 0, summary.stderr[-3000:]
    rows = {
        (r["condition"], r["mask"], int(r["coverage"])): r
        for r in csv.DictReader((tmp_path / "summary" / "results.csv").open())
    }
    assert set(rows) == {("clean", "none", 0)} | {
        (c, m, cov) for c, m in (("occluded", "none"), ("occluded", "oracle"), ("holes", "oracle")) for cov in (10, 20)
    }
    assert float(rows["clean", "none", 0]["r1"]) == 100.0
    # Every R@1 re-read from the jobs' ranks, by the set name each job's eval.json carries.
    for job in (out / "eval" / "day_left-night_right").glob("m0-*/*/ranks.npy"):
        condition, mask = job.parent.parent.name.split("-")[1:]
        name = (job.parent / "eval.json").read_text()
        coverage = 0 if condition == "clean" else (10 if "CamVid 10%" in name else 20)
        row = rows[condition, mask, coverage]
        ranks = [np.load(p) for p in job.parent.parent.glob("*/ranks.npy") if _coverage(p) == coverage]
        assert float(row["r1"]) == pytest.approx(100 * np.mean([np.mean(r == 0) for r in ranks]), abs=0.01)
        assert int(row["seeds"]) == (1 if condition == "clean" else 2)
    for coverage in (10, 20):
        none, oracle = rows["occluded", "none", coverage], rows["occluded", "oracle", coverage]
        # Paired by query over the seeds' mean hit rate: the gain is the difference of the mean R@1s.
        assert float(oracle["gain"]) == pytest.approx(float(oracle["r1"]) - float(none["r1"]), abs=0.02)
        holes = rows["holes", "oracle", coverage]
        assert float(holes["gain"]) == pytest.approx(float(holes["r1"]) - 100.0, abs=0.02)
        assert float(oracle["leak"]) == pytest.approx(float(oracle["r1"]) - float(holes["r1"]), abs=0.02)
        if oracle["recovered"]:
            expected = (float(oracle["r1"]) - float(none["r1"])) / (100.0 - float(none["r1"]))
            assert float(oracle["recovered"]) == pytest.approx(expected, abs=0.002)
    assert (tmp_path / "summary" / "figure_coverage.png").stat().st_size > 0
    assert (
        "| NetVLAD (k-means, no VPR training) | occluded | 20 % | oracle"
        in (tmp_path / "summary" / "results.md").read_text()
    )


def _coverage(ranks: Path) -> int:
    text = (ranks.parent / "eval.json").read_text()
    return 10 if "CamVid 10%" in text else 20 if "CamVid 20%" in text else 0
