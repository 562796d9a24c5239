"""An evaluation sweep's jobs read back with their per-query hits (``hits.npz``), each checked against its
``eval.json``: what the experiments' summaries pair and pool (``reporting.paired``)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import read_json, write_csv, write_npz
from semvpr.reporting.benchmarks_table import HITS_FILE
from semvpr.retrieval.recall import RECALL_NS


@dataclass(frozen=True)
class Evaluation:
    """One finished evaluation: its folder, its ``eval.json`` and its hits (queries × N at ``RECALL_NS``)."""

    dir: Path
    result: dict[str, Any]
    hits: np.ndarray

    @property
    def r1(self) -> np.ndarray:
        """Each query's hit at N = 1 (bool)."""
        return self.hits[:, 0]


def read_evaluations(sweep_dir: Path) -> list[Evaluation]:
    """Every job of the evaluation sweep in ``sweep_dir`` (the folders holding an eval.json); a job that did
    not end ok, or whose hits do not give its eval.json's recalls, is one line naming it."""
    out = []
    for record in sorted(sweep_dir.glob("*/eval.json")):
        result = read_json(record, "job result")
        if not isinstance(result, dict) or result.get("status") != "ok":
            status = result.get("status") if isinstance(result, dict) else None
            raise SemvprError(f"{record}: status {status!r}, not a finished evaluation; run its sweep again")
        queries = result.get("queries")
        try:
            with np.load(record.parent / HITS_FILE, allow_pickle=False) as saved:
                ns, hits = saved["ns"], saved["hits"]
        except (OSError, KeyError, ValueError) as err:
            raise SemvprError(f"{record.parent / HITS_FILE} is not readable hits ({type(err).__name__})") from None
        if list(ns) != list(RECALL_NS) or hits.dtype != bool or hits.shape != (queries, len(RECALL_NS)):
            raise SemvprError(f"{record.parent / HITS_FILE} is not the hits of eval.json's {queries} queries")
        for column, n in enumerate(RECALL_NS):
            if abs(100.0 * hits[:, column].mean() - result.get(f"test/R@{n}", float("nan"))) > 0.006:
                raise SemvprError(f"{record.parent}: {HITS_FILE} does not give eval.json's R@{n}")
        out.append(Evaluation(record.parent, result, hits))
    return out


def write_summary(folder: Path, fields: Sequence[str], rows: list[dict[str, Any]], hits: dict[str, np.ndarray]) -> None:
    """An experiment's summary: ``results.csv`` (``rows`` of ``fields``) and ``hits.npz`` (every evaluation's
    per-query hits, by the names ``hits`` gives them) in ``folder``, each written whole or not at all."""
    write_csv(folder / "results.csv", fields, rows)
    write_npz(folder / "hits.npz", hits)
    print(f"wrote {folder / 'results.csv'} and {folder / 'hits.npz'} ({len(hits)} evaluations)")


def summary_input(description: str, run_sh: str) -> Path:
    """The folder an experiment's summary reads, from its command line (``summarize.py OUT``: what ``run_sh``
    wrote); a missing one is one line saying how to make it."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("out", type=Path, help="the folder run.sh wrote")
    out = parser.parse_args().out
    if not out.is_dir():
        raise SemvprError(f"{out} is not a folder run.sh wrote (bash {run_sh} OUT)")
    return out
