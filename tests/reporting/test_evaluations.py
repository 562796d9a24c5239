"""An evaluation sweep's jobs read back with their per-query hits, checked against their eval.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from semvpr.core.errors import SemvprError
from semvpr.reporting.evaluations import read_evaluations


def _job(sweep: Path, num: int, hits: np.ndarray, **result: object) -> Path:
    job = sweep / str(num)
    job.mkdir(parents=True)
    recalls = {f"test/R@{n}": 100.0 * hits[:, i].mean() for i, n in enumerate((1, 5, 10, 20))}
    (job / "eval.json").write_text(json.dumps({"status": "ok", "queries": len(hits), **recalls, **result}))
    np.savez(job / "hits.npz", ns=np.array([1, 5, 10, 20], np.int32), hits=hits)
    return job


def test_each_job_comes_with_its_hits_and_a_mismatch_is_one_line(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    first = np.sort(rng.random((50, 4)) < 0.5, axis=1)  # a hit at N stays a hit at every larger N
    _job(tmp_path, 0, first, aggregator="gem")
    _job(tmp_path, 1, ~first[:, ::-1], aggregator="netvlad")
    read = read_evaluations(tmp_path)
    assert [e.result["aggregator"] for e in read] == ["gem", "netvlad"]
    assert np.array_equal(read[0].r1, first[:, 0]) and read[1].dir == tmp_path / "1"
    result = json.loads((tmp_path / "1" / "eval.json").read_text())
    (tmp_path / "1" / "eval.json").write_text(json.dumps({**result, "test/R@1": result["test/R@1"] + 2.0}))
    with pytest.raises(SemvprError, match=r"1: hits\.npz does not give eval\.json's R@1$"):
        read_evaluations(tmp_path)
    (tmp_path / "1" / "eval.json").write_text(json.dumps({"status": "failed", "error": "x"}))
    with pytest.raises(SemvprError, match=r"status 'failed', not a finished evaluation"):
        read_evaluations(tmp_path)
    (tmp_path / "1" / "eval.json").write_text(json.dumps(result))
    np.savez(tmp_path / "1" / "hits.npz", ns=np.array([1, 5, 10, 20], np.int32), hits=first[:10])
    with pytest.raises(SemvprError, match=r"is not the hits of eval\.json's 50 queries"):
        read_evaluations(tmp_path)
