"""Metrics: Recall@N on a hand-made case, kNN equals brute force, positives by radius."""

from __future__ import annotations

import numpy as np
import pytest

from semvpr.core.errors import SemvprError
from semvpr.data.places import positives_within
from semvpr.retrieval.recall import knn, recall_at_n, recall_curve, recall_result


def test_recall_hand_made_case() -> None:
    predictions = np.array(
        [
            [3, 1, 2, 0, 4],  # positive {1}: first hit at rank 1 → counts from N=2
            [0, 2, 4, 1, 3],  # positive {0, 9}: hit at rank 0
            [4, 3, 2, 1, 0],  # positive {7}: never retrieved
            [1, 2, 3, 4, 0],  # no positives: excluded
            [2, 4, 1, 3, 0],  # positive {3, 0}: hit at rank 3
        ]
    )
    positives = [np.array([1]), np.array([0, 9]), np.array([7]), np.array([], np.int64), np.array([3, 0])]
    res = recall_result(predictions, positives, ns=(1, 2, 4, 5))
    assert res.num_queries == 5 and res.num_without_positives == 1
    # pytorch-NetVlad / the benchmark: hits over all 5 queries (the one without positives is a miss).
    assert res.recalls == {1: 20.0, 2: 40.0, 4: 60.0, 5: 60.0}
    # mapillary_sls: hits over the 4 queries that have a positive.
    assert res.recalls_pos == {1: 25.0, 2: 50.0, 4: 75.0, 5: 75.0}
    assert recall_at_n(predictions, positives, ns=(1, 5)) == {1: 20.0, 5: 60.0}
    assert recall_curve(predictions, positives, max_n=5) == {1: 20.0, 2: 40.0, 3: 40.0, 4: 60.0, 5: 60.0}
    with pytest.raises(ValueError, match="Recall@20"):
        recall_at_n(predictions, positives)
    with pytest.raises(SemvprError, match="no query"):
        recall_at_n(predictions[:1], [np.array([], np.int64)], ns=(1,))


def test_knn_equals_brute_force() -> None:
    rng = np.random.default_rng(0)
    db, q = rng.standard_normal((300, 24)), rng.standard_normal((40, 24))
    got = knn(db, q, 7)
    dbn = db / np.linalg.norm(db, axis=1, keepdims=True)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    expected = np.argsort(-(qn @ dbn.T), axis=1, kind="stable")[:, :7]
    assert got.shape == (40, 7) and got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)
    assert knn(db[:5], q, 10).shape == (40, 5)  # k is capped at the database size


def test_positives_within_radius_sorted() -> None:
    # Real-scale UTM values: float32 would lose the metre-level precision here.
    base = np.array([585000.0, 4477000.0])
    db = base + np.array([[0.0, 0.0], [10.0, 0.0], [24.9, 0.0], [25.1, 0.0], [3.0, 4.0]])
    q = base + np.array([[0.0, 0.0], [100.0, 100.0]])
    pos = positives_within(db, q, radius=25.0)
    np.testing.assert_array_equal(pos[0], [0, 4, 1, 2])
    assert pos[1].size == 0


def test_knn_in_database_chunks_equals_one_pass() -> None:
    rng = np.random.default_rng(1)
    db, q = rng.standard_normal((250, 16)).astype(np.float32), rng.standard_normal((30, 16))
    whole = knn(db, q, 9)
    # 40 rows per chunk: seven chunks, merged.
    np.testing.assert_array_equal(knn(db, q, 9, chunk_bytes=40 * 4 * 16), whole)
