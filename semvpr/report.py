"""Sweep-end report: ``python -m semvpr.report <sweep dir>`` and the Hydra callback that runs it after a
multirun (``semvpr.reporting.sweep_report`` writes results.csv / results.md and the figures)."""

from __future__ import annotations

import argparse
import fcntl
import os
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import open_lock
from semvpr.core.stops import stop_on_signals
from semvpr.reporting.sweep import sweep_dir_of
from semvpr.reporting.sweep_report import print_summary, write_report


def _sweep_dir(config: DictConfig) -> Path:
    """The multirun's sweep dir as Hydra's config names it."""
    return sweep_dir_of(str(config.hydra.sweep.dir), OmegaConf.select(config, "hydra.runtime.cwd", default=None))


class ReportCallback(Callback):
    """Hydra callback (hydra.callbacks.report._target_): the table of the jobs finished so far after each
    job of a multirun (marked partial), the whole report when the multirun ends."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """A signal to the sweep's own process stops it whole (``core.stops``): one line and the report."""
        from semvpr.config.runs import record_plan  # torch and Lightning: only where a sweep runs

        stop_on_signals(_sweep_dir(config))
        record_plan(config, _sweep_dir(config))  # its report counts the jobs that never started too

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        """Rewrite the partial table after a sweep's job (one writer at a time); never raise."""
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        from semvpr.retrieval.launch import launched_rank

        if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN or launched_rank() != 0:
            return
        try:
            sweep_dir = Path(str(HydraConfig.get().sweep.dir))
            with os.fdopen(open_lock(sweep_dir / ".report.lock"), "rb") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                write_report(sweep_dir, partial=True)
        except Exception as err:  # noqa: BLE001 - the job's own files are the results
            print(f"semvpr: the partial report was not written ({type(err).__name__}: {err})", file=sys.stderr)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Report on config.hydra.sweep.dir; never raise, the runs' own files are the results."""
        where = "the sweep dir"
        try:
            sweep_dir = _sweep_dir(config)
            where = str(sweep_dir)
            print_summary(write_report(sweep_dir))
        except Exception as err:
            print(
                f"semvpr: report failed for {where} ({type(err).__name__}: {err}); "
                f"rerun with `python -m semvpr.report {where}`",
                file=sys.stderr,
            )


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.report``."""
    parser = argparse.ArgumentParser(
        prog="python -m semvpr.report", description="Write results.csv/.md and figures for a finished sweep."
    )
    parser.add_argument("sweep_dir", help="multirun dir, e.g. outputs/multiruns/<date>/<time>")
    return parser


@exit_on_user_error
def main(argv: list[str] | None = None) -> int:
    """CLI: python -m semvpr.report <sweep dir>."""
    print_summary(write_report(parser().parse_args(argv).sweep_dir))
    return 0


if __name__ == "__main__":
    main()
