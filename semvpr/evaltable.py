"""One table for a multi-dataset evaluation: ``results.csv`` / ``results.md`` in the sweep dir.

``python -m semvpr.eval -m ckpt=PATH data=pitts30k,msls_val,...`` runs one job per dataset, each
writing ``eval.json``; when the sweep ends, :class:`EvalTableCallback` reads them back and writes a
row per dataset (Recall@N, counts, descriptor size, wall time), each followed by the published
numbers of the same model family on the same protocol (``semvpr/data/published.yaml``;
``semvpr.reporting.benchmarks_table`` writes it). ``python -m semvpr.evaltable SWEEP_DIR`` writes the
table again.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from semvpr.core.errors import exit_on_user_error
from semvpr.core.stops import stop_on_signals
from semvpr.reporting.benchmarks_table import write_table
from semvpr.reporting.markdown import terminal_text
from semvpr.reporting.sweep import sweep_dir_of


def _sweep_dir(config: DictConfig) -> Path:
    """The multirun's sweep dir as Hydra's config names it."""
    return sweep_dir_of(str(config.hydra.sweep.dir), OmegaConf.select(config, "hydra.runtime.cwd", default=None))


class EvalTableCallback(Callback):
    """Hydra callback: write the table when an evaluation multirun ends (conf/eval.yaml)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """A signal to the sweep's own process stops it whole (``core.stops``): one line and the table."""
        from semvpr.config.runs import record_plan  # torch and Lightning: only where a sweep runs

        stop_on_signals(_sweep_dir(config))
        record_plan(config, _sweep_dir(config))  # its report counts the jobs that never started too

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Never raise: each job's eval.json is the result; the table is a summary of them."""
        where = "the sweep dir"
        try:
            sweep_dir = _sweep_dir(config)
            where = str(sweep_dir)
            md = write_table(sweep_dir)
            print(f"semvpr eval table: {md}")
            print(terminal_text(ln for ln in md.read_text(encoding="utf-8").splitlines() if ln.startswith("|")))
        except Exception as err:  # noqa: BLE001
            print(
                f"semvpr: eval table failed for {where} ({type(err).__name__}: {err}); "
                f"rerun with `python -m semvpr.evaltable {where}`",
                file=sys.stderr,
            )


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.evaltable``."""
    parser = argparse.ArgumentParser(prog="python -m semvpr.evaltable", description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir", help="multirun dir of `python -m semvpr.eval -m ...`")
    return parser


@exit_on_user_error
def main(argv: list[str] | None = None) -> int:
    """CLI: python -m semvpr.evaltable <sweep dir>."""
    print(write_table(parser().parse_args(argv).sweep_dir))
    return 0


if __name__ == "__main__":
    main()
