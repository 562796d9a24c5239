"""Mining picks the feature-nearest positive and the hardest violating negatives."""
from __future__ import annotations

import numpy as np
import torch

from semvpr.features import FeatureStore
from semvpr.mining import TupleDataset, mine


def _unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def test_mine_picks_nearest_positive_and_hardest_negatives() -> None:
    # db 0..2 lie within 10 m of the query, 3 at 20 m (neither positive nor negative), 4..9 far.
    db_utm = np.array([[0, 0], [5, 0], [0, 8], [20, 0]] + [[100 + 50 * i, 0] for i in range(6)], float)
    q_utm = np.array([[1.0, 0.0]])
    rng = np.random.default_rng(0)
    db = _unit(rng.normal(size=(10, 8)))
    q = _unit(db[2] + 0.05 * rng.normal(size=8))[None]
    # Make far images 4 and 7 the closest in feature space: the two hardest negatives.
    db[7] = _unit(q[0] + 0.10 * rng.normal(size=8))
    db[4] = _unit(q[0] + 0.20 * rng.normal(size=8))
    tuples = mine(db, q, db_utm, q_utm, np.array([0]), rng, num_negatives=2, negative_candidates=1000)
    assert tuples.tolist() == [[0, 2, 7, 4]]


def test_mine_skips_queries_without_positive_or_violation() -> None:
    db_utm = np.array([[0.0, 0.0], [500.0, 0.0], [900.0, 0.0]])
    q_utm = np.array([[300.0, 0.0], [0.0, 1.0]])
    db = _unit(np.eye(3, 8))
    q = _unit(np.stack([np.eye(1, 8, 1)[0], np.eye(1, 8, 0)[0]]))
    # Query 0 has no db image within 10 m; query 1's negatives are orthogonal (distance sqrt 2)
    # while its positive is identical: the margin is already satisfied.
    tuples = mine(db, q, db_utm, q_utm, np.array([0, 1]), np.random.default_rng(0), num_negatives=2)
    assert tuples.shape == (0, 4)


def test_tuple_dataset_stacks_query_positive_negatives() -> None:
    db = FeatureStore(torch.arange(5.0).view(5, 1, 1, 1), torch.ones(5, 1, 1, 1))
    q = FeatureStore(torch.tensor([10.0, 20.0]).view(2, 1, 1, 1), torch.zeros(2, 1, 1, 1))
    trunk, mask = TupleDataset(np.array([[1, 3, 0, 4]]), db, q)[0]
    assert trunk.flatten().tolist() == [20.0, 3.0, 0.0, 4.0]
    assert mask.flatten().tolist() == [0.0, 1.0, 1.0, 1.0]
