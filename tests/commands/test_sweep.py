"""The four-way comparison as one Hydra multirun, with the report at the end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers import REPO


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
    lines = [line for line in results_md.read_text().splitlines() if line.startswith("| efficientnet_lite0 ")]
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
    rows = {row[0]: row for row in _table_rows(sweep / "results.md")}
    # A row per value of the swept setting: the failed job's (its recalls 'failed'), the finished one's.
    failed, ok = (
        rows.pop("efficientnet_lite0 (model.num_clusters=0)"),
        rows.pop("efficientnet_lite0 (model.num_clusters=4)"),
    )
    assert not rows and (failed[2], failed[-2]) == ("failed", "1") and ok[-2] == "0" and ok[2] != "failed"
    finished = json.loads((sweep / "experiment=tiny,filter=none,model.num_clusters=4" / "metrics.json").read_text())
    assert finished["threads"]["processes"] == 2  # the launcher's two jobs side by side share the cores
    assert "model.num_clusters=0 must be a whole number from 2 to 2147483647" in md
    # Every stage line names the job that printed it: jobs side by side interleave their lines.
    staged = [ln for ln in proc.stderr.splitlines() if ln.startswith("semvpr: ") and "job failed" not in ln]
    assert any(" retriever: epoch " in ln for ln in staged), proc.stderr[-2000:]
    assert all(ln.startswith("semvpr: [#1 experiment=tiny,filter=none,model.num_clusters=4] ") for ln in staged), staged


@pytest.mark.slow
@pytest.mark.parametrize(
    ("how", "line"),
    [
        ("SIGTERM to the sweep", "stopped by SIGTERM"),
        ("Ctrl-C (SIGINT to its group)", "stopped by SIGINT"),
        ("SIGKILL to a worker", "a job's worker process was killed (SIGKILL(-9)), so the sweep stopped"),
    ],
)
def test_a_stop_of_a_two_at_a_time_sweep_is_one_line_no_worker_left_and_a_final_report(
    tmp_path: Path, how: str, line: str
) -> None:
    """Stopped while two jobs run (a signal to it, or one of its workers killed under it): the sweep's own
    process ends its workers (none left running), exits 2 with one line naming its report, and the report
    is final (not marked as still running), counting the jobs that did not finish and the one never started."""
    sweep = tmp_path / "sweep"
    args = [
        "experiment=tiny",
        "filter=none",
        "threads=1",
        "trainer.max_epochs=400",
        "seed=0,1,2",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.sweep.dir={sweep}",
    ]
    proc = subprocess.Popen(
        [sys.executable, "-m", "semvpr.train", "-m", *args],
        cwd=tmp_path,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"},
    )
    try:
        deadline = time.monotonic() + 600
        while not list(sweep.glob("*/checkpoints/last.ckpt")) and proc.poll() is None:
            assert time.monotonic() < deadline, "no job saved a checkpoint"
            time.sleep(0.5)
        workers = [
            int(p)
            for p in subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        ]
        assert workers, "the sweep runs its jobs in worker processes"
        if how.startswith("Ctrl-C"):
            os.killpg(proc.pid, signal.SIGINT)
        elif how.startswith("SIGTERM"):
            proc.send_signal(signal.SIGTERM)
        else:
            loky = [pid for pid in workers if "LokyProcess" in Path(f"/proc/{pid}/cmdline").read_text()]
            os.kill(loky[0], signal.SIGKILL)
        _, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    errors = [ln for ln in stderr.splitlines() if ln.startswith("semvpr: error: ")]
    assert proc.returncode == 2 and len(errors) == 1 and stderr.strip().splitlines()[-1] == errors[0], stderr[-3000:]
    assert errors[0].startswith(f"semvpr: error: {line}; its report")
    assert str(sweep / "results.md") in errors[0]
    time.sleep(1)
    alive = [pid for pid in workers if Path(f"/proc/{pid}").exists() and "Z" not in _state(pid)]
    assert alive == [], f"workers left running: {alive}"
    md = (sweep / "results.md").read_text()
    assert "still running" not in md and "did not finish: no metrics.json" in md
    # Three jobs given, two at a time: the third never started, and the report counts it.
    assert md.splitlines()[2].startswith("**Incomplete:** 3 jobs, 0 ok, 0 failed, 2 did not finish, 1 never started")
    assert "## Jobs not started" in md and "seed=2" in md.split("## Jobs not started")[1]
    stopped = next(p.parents[1] for p in sweep.glob("*/checkpoints/last.ckpt"))
    assert not (stopped / "metrics.json").exists()


def _state(pid: int) -> str:
    """A process's state letter (Z: a zombie, already ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except OSError:
        return "Z"


@pytest.mark.slow
def test_a_stop_hammered_at_10_hz_on_an_evaluation_sweep_is_one_line_exit_2_and_no_result_after_it(
    tmp_path: Path,
) -> None:
    """SIGINT to the sweep's process group ten times a second (Ctrl-C held down): joblib's abort was broken
    off (four tracebacks, exit 130) and an orphaned worker wrote its job's eval.json after the stop line. Now:
    one line, exit 2, no process of the sweep left, nothing written after it, a table that says so."""
    sweep = tmp_path / "sweep"
    args = ["experiment=tiny", "ckpt=none", "aggregator=gem,netvlad,mixvpr", "threads=1"]
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "-m",
            *args,
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"},
    )
    try:
        deadline = time.monotonic() + 600
        while not list(sweep.glob("*/.hydra")) and proc.poll() is None:  # a job has started
            assert time.monotonic() < deadline, "no job started"
            time.sleep(0.2)
        group = [
            int(p)
            for p in subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()
        ]
        for _ in range(30):
            if proc.poll() is not None:
                break
            os.killpg(proc.pid, signal.SIGINT)
            time.sleep(0.1)
        _, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    ended = time.time()
    errors = [ln for ln in stderr.splitlines() if ln.startswith("semvpr: error: ")]
    assert proc.returncode == 2 and len(errors) == 1 and "Traceback" not in stderr, stderr[-3000:]
    assert errors[0].startswith("semvpr: error: stopped by SIGINT; its report") and stderr.strip().endswith(errors[0])
    time.sleep(2)
    alive = [pid for pid in group if pid != proc.pid and Path(f"/proc/{pid}").exists() and "Z" not in _state(pid)]
    assert alive == [], f"processes of the sweep left running: {alive}"
    written = [p for p in sweep.rglob("*") if p.is_file() and p.stat().st_mtime > ended]
    assert written == [], f"written after the stop: {written}"
    assert (sweep / "results.md").read_text().count("**Incomplete:**") == 1
