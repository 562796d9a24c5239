"""A resume continues the run as it was started: its own config, its .hydra record untouched."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from semvpr.core.errors import SemvprError
from semvpr.core.resume import keep_run_record, resumed_config
from tests.helpers import config, tiny_config

REPO = Path(__file__).resolve().parents[1]


def train_cli(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``python -m semvpr.train`` from ``cwd`` (where a default outputs/ would land)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "semvpr.train", *overrides],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_a_resume_takes_the_runs_own_config_and_refuses_what_contradicts_it(tmp_path: Path) -> None:
    own = tiny_config(tmp_path / "cache", "trainer.max_epochs=3", "filter=unet")
    record = tmp_path / "run" / ".hydra" / "config.yaml"
    record.parent.mkdir(parents=True)
    OmegaConf.save(own, record)
    default = config()
    resumed = resumed_config(config("ckpt_path=last"), default, record, ["ckpt_path=last"])
    assert (resumed.trainer.max_epochs, resumed.filter.name, resumed.ckpt_path) == (3, "unet", "last")
    assert resumed.data.preset == own.data.preset == "tiny" and resumed.paths.cache_dir == own.paths.cache_dir
    # Repeating the original overrides agrees with the record; another value does not.
    again = ["ckpt_path=last", "experiment=tiny", "filter=unet", "trainer.max_epochs=3"]
    assert resumed_config(config(*again), default, record, again).trainer.max_epochs == 3
    for override, message in (
        ("trainer.max_epochs=5", "trainer.max_epochs=5 contradicts the run's own trainer.max_epochs=3"),
        ("filter=none", r"filter\..* contradicts the run's own filter\."),
    ):
        with pytest.raises(SemvprError, match=message):
            resumed_config(config("ckpt_path=last", override), default, record, ["ckpt_path=last", override])
    # Hydra is told not to rewrite the run's .hydra record; a fresh run is left alone.
    argv = ["ckpt_path=last", f"hydra.run.dir={tmp_path / 'run'}"]
    assert keep_run_record(argv) == [*argv, "hydra.output_subdir=null"]
    assert keep_run_record([f"hydra.run.dir={tmp_path / 'new'}", "ckpt_path=last"])[-1] != "hydra.output_subdir=null"


@pytest.mark.slow
def test_resume_reloads_the_runs_own_config_and_refuses_contradictions(tmp_path: Path) -> None:
    run, cache, cwd = tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    cwd.mkdir()
    start = train_cli(
        cwd, "experiment=tiny", f"paths.cache_dir={cache}", "trainer.max_epochs=1", f"hydra.run.dir={run}"
    )
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
