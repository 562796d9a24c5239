"""Retrieval scoring: faiss kNN and Recall@N (the positives come from the place set, ``semvpr.data.places``).

Two denominators, because the references differ:

- ``R@N`` (the project's headline number): percentage of **all** queries whose top-N retrievals
  contain a positive. pytorch-NetVlad and the VPR benchmark divide by the number of queries, so a
  query without any positive counts as a miss.
- ``R@N_pos``: percentage of the queries **with at least one positive** (mapillary_sls's official
  evaluation drops queries without positives before scoring).

They differ only where some query has no database image within the radius (none does in
Pitts30k-test or SynthCity). ``recall_result`` returns both with the query counts;
``recall_at_n`` / ``recall_curve`` are the all-queries shortcuts.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import faiss
import numpy as np

from semvpr.core.errors import SemvprError

RECALL_NS = (1, 5, 10, 20)  # the cut-offs every table reports


@dataclass(frozen=True)
class RecallResult:
    """Recall@N in percent over all queries (``recalls``) and over those with positives."""

    recalls: dict[int, float]
    recalls_pos: dict[int, float]
    num_queries: int
    num_without_positives: int


def _unit_float32(x: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(x, dtype=np.float32).copy()
    faiss.normalize_L2(arr)
    return arr


def knn(db: np.ndarray, q: np.ndarray, k: int, chunk_bytes: int = 1 << 30) -> np.ndarray:
    """(M, min(k,N)) database indices nearest to each query, exact L2 on L2-normalised descriptors.

    The database is searched in chunks of at most ``chunk_bytes`` (it may be a memory-mapped
    array larger than RAM); per-chunk top-k lists are merged, ties keeping the lower index.
    """
    if db.ndim != 2 or q.ndim != 2 or db.shape[1] != q.shape[1]:
        raise ValueError(f"db and queries must be (N,D) and (M,D) with the same D, got {db.shape} and {q.shape}")
    k = min(k, db.shape[0])
    queries = _unit_float32(q)
    rows = max(k, chunk_bytes // (4 * db.shape[1]))
    best_d = np.empty((len(q), 0), np.float32)
    best_i = np.empty((len(q), 0), np.int64)
    for start in range(0, db.shape[0], rows):
        index = faiss.IndexFlatL2(db.shape[1])
        index.add(_unit_float32(db[start : start + rows]))
        dist, idx = index.search(queries, min(k, index.ntotal))
        best_d = np.concatenate([best_d, dist], axis=1)
        best_i = np.concatenate([best_i, idx.astype(np.int64) + start], axis=1)
        order = np.argsort(best_d, axis=1, kind="stable")[:, :k]
        best_d, best_i = np.take_along_axis(best_d, order, 1), np.take_along_axis(best_i, order, 1)
    return best_i


def first_hit_ranks(predictions: np.ndarray, positives: Sequence[np.ndarray]) -> np.ndarray:
    """0-based rank of the first positive in each query's predictions; k if none in the top-k, -1 if no positives."""
    predictions = np.asarray(predictions)
    if len(predictions) != len(positives):
        raise ValueError(f"{len(predictions)} prediction rows but {len(positives)} positive lists")
    k = predictions.shape[1]
    ranks = np.full(len(predictions), k, dtype=np.int64)
    for i, (pred, pos) in enumerate(zip(predictions, positives)):
        if len(pos) == 0:
            ranks[i] = -1
            continue
        hits = np.flatnonzero(np.isin(pred, pos))
        if hits.size:
            ranks[i] = hits[0]
    return ranks


def recall_result(
    predictions: np.ndarray, positives: Sequence[np.ndarray], ns: Iterable[int] = RECALL_NS
) -> RecallResult:
    """Recall@N (percent) for each N in ``ns`` plus the query counts behind it."""
    ns = tuple(int(n) for n in ns)
    if max(ns) > np.asarray(predictions).shape[1]:
        raise ValueError(
            f"Recall@{max(ns)} needs at least {max(ns)} predictions per query, got {np.asarray(predictions).shape[1]}"
        )
    ranks = first_hit_ranks(predictions, positives)
    valid = ranks[ranks >= 0]
    if valid.size == 0:
        raise SemvprError(
            "no query has a database image within the positive radius; check the UTM coordinates "
            "of the test set (or the radius)"
        )
    # A query without positives has rank -1 and never counts as a hit.
    hits = {n: int(np.count_nonzero(valid < n)) for n in ns}
    return RecallResult(
        recalls={n: 100.0 * h / len(ranks) for n, h in hits.items()},
        recalls_pos={n: 100.0 * h / valid.size for n, h in hits.items()},
        num_queries=int(len(ranks)),
        num_without_positives=int((ranks < 0).sum()),
    )


def recall_at_n(
    predictions: np.ndarray, positives: Sequence[np.ndarray], ns: Iterable[int] = RECALL_NS
) -> dict[int, float]:
    """{N: Recall@N in percent of all queries} (``recall_result`` also gives the MSLS denominator)."""
    return recall_result(predictions, positives, ns).recalls


def recall_curve(predictions: np.ndarray, positives: Sequence[np.ndarray], max_n: int = 20) -> dict[int, float]:
    """{N: Recall@N} for N = 1..max_n (for recall curves)."""
    return recall_at_n(predictions, positives, range(1, max_n + 1))


def check_finite(desc: np.ndarray, what: str, chunk_rows: int = 4096) -> None:
    """Refuse descriptors holding NaN or inf (weights that overflow give them; every distance to them is
    NaN, so recall would read 0 with nothing said). Checked in chunks: ``desc`` may be memory-mapped."""
    for start in range(0, len(desc), chunk_rows):
        rows = np.flatnonzero(~np.isfinite(np.asarray(desc[start : start + chunk_rows])).all(1))
        if rows.size:
            raise SemvprError(
                f"the descriptors of {what} are not finite (row {start + int(rows[0])} first): the model's "
                f"weights overflow on these images; the checkpoint is unusable as it is"
            )


def evaluate(
    db_desc: np.ndarray, q_desc: np.ndarray, positives: Sequence[np.ndarray], max_n: int = 20
) -> dict[str, Any]:
    """Top-k retrieval and Recall@1..max_n in percent: of all queries (``recalls``, ``curve``, as
    pytorch-NetVlad and the benchmark) and of queries with a positive (``recalls_pos``, as MSLS).
    Non-finite descriptors are refused (:func:`check_finite`)."""
    check_finite(db_desc, "the database")
    check_finite(q_desc, "the queries")
    k = min(max_n, len(db_desc))
    predictions = knn(db_desc, q_desc, k)
    result = recall_result(predictions, positives, ns=tuple(range(1, k + 1)))
    # A database smaller than N is retrieved whole: Recall@N = Recall@len(db).
    curve = {n: result.recalls[min(n, k)] for n in range(1, max_n + 1)}
    return {
        "predictions": predictions,
        "curve": curve,
        "recalls": {n: curve[n] for n in RECALL_NS},
        "recalls_pos": {n: result.recalls_pos[min(n, k)] for n in RECALL_NS},
        "num_without_positives": result.num_without_positives,
    }
