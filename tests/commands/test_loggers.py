"""logger=wandb and logger=mlflow: Lightning's loggers beside CSV and TensorBoard, each writing into the run
directory with no server (W&B offline, MLflow's SQLite store), holding the run's validation and test recalls.
Each skips where its extra (``semvpr[wandb]``, ``semvpr[mlflow]``) is not installed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.bad_input import cli


def _train(tmp_path: Path, *overrides: str, env: dict | None = None) -> tuple[Path, dict]:
    run = tmp_path / "run"
    proc = cli(
        "semvpr.train",
        "experiment=tiny",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={run}",
        *overrides,
        cwd=tmp_path,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run, json.loads((run / "metrics.json").read_text())


def test_logger_mlflow_records_the_runs_recalls_in_an_sqlite_store_in_the_run(tmp_path: Path) -> None:
    pytest.importorskip("mlflow")
    pytest.importorskip("sqlalchemy")
    from mlflow.tracking import MlflowClient

    run, metrics = _train(tmp_path, "logger=mlflow")
    client = MlflowClient(tracking_uri=f"sqlite:///{run / 'mlflow.db'}")
    (recorded,) = client.search_runs([client.get_experiment_by_name("semvpr").experiment_id])
    logged = recorded.data.metrics  # MLflow names them without '@' (Lightning's MLFlowLogger renames them)
    assert logged["test/R1"] == pytest.approx(metrics["test/R@1"], abs=1e-3)
    assert "val/R5" in logged and any(name.startswith("lr-") for name in logged), sorted(logged)
    assert (run / "tensorboard").is_dir() and (run / "csv").is_dir()  # beside the default loggers
    assert not (tmp_path / "mlruns").exists()  # nothing in the working directory


def test_logger_wandb_offline_keeps_its_run_in_the_run_directory(tmp_path: Path) -> None:
    pytest.importorskip("wandb")
    home = tmp_path / "home"
    run, metrics = _train(tmp_path, "logger=wandb", "logger.wandb.offline=true", env={"HOME": str(home)})
    (offline,) = (run / "wandb").glob("offline-run-*")
    (records,) = offline.glob("run-*.wandb")
    data = records.read_bytes()
    assert b"val/R@1" in data and b"test/R@1" in data  # the history records, keyed by the metrics' names
    assert metrics["status"] == "ok"
    # wandb's own service logs go to the job's cache, not the user's home.
    assert list((tmp_path / "cache" / "wandb").rglob("*.log")) and not (home / ".cache" / "wandb").exists()
