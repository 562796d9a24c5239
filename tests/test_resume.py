"""A resume continues the run as it was started: its own config, its .hydra record untouched."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def train_cli(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``python -m semvpr.train`` from ``cwd`` (where a default outputs/ would land)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "semvpr.train", *overrides], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def test_resume_reloads_the_runs_own_config_and_refuses_contradictions(tmp_path: Path) -> None:
    run, cache, cwd = tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    cwd.mkdir()
    start = train_cli(cwd, "experiment=tiny", f"paths.cache_dir={cache}", "trainer.max_epochs=1",
                      f"hydra.run.dir={run}")
    assert start.returncode == 0, start.stderr[-2000:]
    record = {p.name: p.read_text() for p in (run / ".hydra").iterdir()}
    first = json.loads((run / "metrics.json").read_text())

    # The README's resume command with an override that contradicts the run: one line, nothing written.
    refused = train_cli(cwd, "ckpt_path=last", "trainer.max_epochs=3", f"hydra.run.dir={run}")
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr[-2000:]
    assert "trainer.max_epochs=3 contradicts the run's own trainer.max_epochs=1" in refused.stderr

    # Without the original overrides it is still the same run (before: the default config, 1 epoch, status ok).
    resumed = train_cli(cwd, "ckpt_path=last", f"hydra.run.dir={run}")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    again = json.loads((run / "metrics.json").read_text())
    assert again["status"] == "ok" and again["recalls"] == first["recalls"]
    assert {p.name: p.read_text() for p in (run / ".hydra").iterdir()} == record
    assert list(cwd.iterdir()) == []  # nothing composed from today's defaults (outputs/cache) appeared
