"""Mining as pytorch-NetVlad: feature-nearest positive, violating hard negatives, negative cache, epochs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from semvpr.core.errors import SemvprError
from semvpr.retrieval.features import FeatureStore
from semvpr.retrieval.mining import Mining, TupleImages, collate_tuples, query_batches


def mine(
    db: np.ndarray,
    q: np.ndarray,
    db_utm: np.ndarray,
    q_utm: np.ndarray,
    query_ids: np.ndarray,
    rng: np.random.Generator,
    neg_cache: np.ndarray | None = None,
    **rules: float,
) -> list:
    """``Mining(**rules).mine`` on descriptors and positions given apart."""
    return Mining(**rules).mine(db, q, SimpleNamespace(db_utm=db_utm, q_utm=q_utm), query_ids, rng, neg_cache)


def _unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def _scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """db 0..2 within 10 m of the query, 3 at 20 m (neither positive nor negative), 4..9 far.
    In feature space: db 2 is the query's twin, then 3 (at 20 m), 7 and 4 (far, hard)."""
    db_utm = np.array([[0, 0], [5, 0], [0, 8], [20, 0]] + [[100 + 50 * i, 0] for i in range(6)], float)
    q_utm = np.array([[1.0, 0.0]])
    rng = np.random.default_rng(seed)
    db = _unit(rng.normal(size=(10, 8)))
    q = _unit(db[2] + 0.05 * rng.normal(size=8))[None]
    db[3] = _unit(q[0] + 0.08 * rng.normal(size=8))
    db[7] = _unit(q[0] + 0.10 * rng.normal(size=8))
    db[4] = _unit(q[0] + 0.13 * rng.normal(size=8))
    return db, q, db_utm, q_utm


def test_mine_picks_nearest_positive_and_hardest_violating_negatives() -> None:
    db, q, db_utm, q_utm = _scene()
    d = np.linalg.norm(db - q[0], axis=1)
    tuples = mine(db, q, db_utm, q_utm, np.array([0]), np.random.default_rng(0), num_negatives=2)
    assert len(tuples) == 1
    qi, pos, negs = tuples[0]
    assert (qi, pos) == (0, 2) and pos == int(np.argmin(d[:3]))
    # The image at 20 m is not a negative (beyond 25 m only), although it is the hardest one.
    assert negs.tolist() == [7, 4]
    radius_10 = mine(
        db, q, db_utm, q_utm, np.array([0]), np.random.default_rng(0), negative_radius=10.0, num_negatives=2
    )
    assert radius_10[0][2].tolist() == [3, 7]  # what a 10 m negative radius would (wrongly) give


def test_only_margin_violating_negatives_are_kept() -> None:
    db, q, db_utm, q_utm = _scene()
    d = np.linalg.norm(db - q[0], axis=1)
    tuples = mine(db, q, db_utm, q_utm, np.array([0]), np.random.default_rng(0), num_negatives=10)
    negs = tuples[0][2]
    far = np.arange(4, 10)
    expected = far[d[far] < d[2] + 0.1**0.5]
    assert 0 < len(negs) < len(far)  # some far images already satisfy the margin
    assert sorted(negs.tolist()) == sorted(expected.tolist())
    assert (np.diff(d[negs]) >= 0).all()  # hardest first


def test_query_without_positive_or_violation_is_skipped() -> None:
    db_utm = np.array([[0.0, 0.0], [500.0, 0.0], [900.0, 0.0]])
    q_utm = np.array([[300.0, 0.0], [0.0, 1.0]])
    db = _unit(np.eye(3, 8))
    q = _unit(np.stack([np.eye(1, 8, 1)[0], np.eye(1, 8, 0)[0]]))
    # Query 0 has no db image within 10 m; query 1's negatives are orthogonal (distance sqrt 2)
    # while its positive is identical: the margin is already satisfied.
    assert mine(db, q, db_utm, q_utm, np.array([0, 1]), np.random.default_rng(0), num_negatives=2) == []


def test_negative_cache_brings_back_last_visits_hard_negatives() -> None:
    db, q, db_utm, q_utm = _scene()
    cache = np.full((1, 2), -1, dtype=np.int64)
    first = mine(db, q, db_utm, q_utm, np.array([0]), np.random.default_rng(0), cache, num_negatives=2)
    assert cache[0].tolist() == first[0][2].tolist() == [7, 4]
    # One random candidate per visit: without the cache the hard negatives are usually missed.
    hits = {"cache": 0, "none": 0}
    for seed in range(20):
        with_cache = mine(
            db,
            q,
            db_utm,
            q_utm,
            np.array([0]),
            np.random.default_rng(seed),
            cache.copy(),
            num_negatives=2,
            negative_candidates=1,
        )
        without = mine(
            db,
            q,
            db_utm,
            q_utm,
            np.array([0]),
            np.random.default_rng(seed),
            None,
            num_negatives=2,
            negative_candidates=1,
        )
        hits["cache"] += with_cache[0][2][0] == 7
        hits["none"] += bool(without) and without[0][2][0] == 7
    assert hits["cache"] == 20 and hits["none"] < 10


def test_batches_hold_consecutive_queries_and_pair_every_negative_with_its_query() -> None:
    db = FeatureStore(tuple(f"db{i}" for i in range(6)), (1, 1), torch.arange(6.0).view(6, 1, 1, 1), None)
    q = FeatureStore(("q0", "q1", "q2"), (1, 1), torch.tensor([10.0, 20.0, 30.0]).view(3, 1, 1, 1), None)
    tuples = [(0, 1, np.array([2, 3])), (2, 0, np.array([5]))]  # query 1 had nothing to mine
    batches = query_batches(np.array([2, 1, 0]), tuples, batch_size=2)
    assert batches == [[tuples[1]], [tuples[0]]]  # queries (2, 1) then (0,)
    batch = collate_tuples([TupleImages(db, q)[t] for t in tuples])
    assert batch["trunk"].flatten().tolist() == [10.0, 1.0, 2.0, 3.0, 30.0, 0.0, 5.0]
    assert batch["tuples"].tolist() == [[0, 1, 2, 3], [4, 5, 6, -1]]
    assert collate_tuples([]) is None


def test_loss_averages_over_query_negative_pairs() -> None:
    # pytorch-NetVlad: sum of per-(query, negative) triplet losses divided by the number of negatives.
    from semvpr.retrieval.losses import triplet_loss

    torch.manual_seed(0)
    desc = torch.nn.functional.normalize(torch.randn(7, 4), dim=1)
    triples = [[0, 1, 2], [0, 1, 3], [4, 5, 6]]
    margin = 0.1**0.5
    by_hand = (
        sum(
            max(0.0, (desc[a] - desc[p]).norm().item() - (desc[a] - desc[n]).norm().item() + margin)
            for a, p, n in triples
        )
        / 3
    )
    reference = torch.nn.TripletMarginLoss(margin=margin)(*(desc[[t[i] for t in triples]] for i in range(3)))
    loss = triplet_loss(desc, torch.tensor([[0, 1, 2, 3], [4, 5, 6, -1]]), margin=0.1)
    assert loss.item() == pytest.approx(by_hand, rel=1e-4) and loss.item() == pytest.approx(reference.item(), rel=1e-6)


def _line(num_queries: int):
    """Training features on a line: query i at 10 i m, database every 5 m; the last query is far away."""
    from semvpr.data.places import PlaceSet
    from semvpr.retrieval.features import PlaceFeatures

    db_utm = np.stack([np.arange(0, 10 * num_queries, 5.0), np.zeros(2 * num_queries)], 1)
    q_utm = np.stack([np.arange(num_queries) * 10.0 + 1.0, np.zeros(num_queries)], 1)
    q_utm[-1] = (1e6, 0)  # no database image within 10 m: never a training query
    places = PlaceSet(
        "line",
        tuple(f"/d/db{i}.jpg" for i in range(len(db_utm))),
        tuple(f"/d/q{i}.jpg" for i in range(num_queries)),
        db_utm,
        q_utm,
    )
    store = lambda n: FeatureStore(tuple(f"x{i}" for i in range(n)), (1, 1), torch.zeros(n, 1, 1, 1), None)  # noqa: E731
    return PlaceFeatures(places, store(len(db_utm)), store(num_queries))


def _datamodule(num_queries: int, cache_refresh: int, batch_size: int, queries_per_epoch: int | None = None):
    """A RetrievalDataModule over :func:`_line` (its describe function is never called here)."""
    from semvpr.retrieval.datamodule import RetrievalDataModule
    from semvpr.retrieval.mining import Mining

    train = _line(num_queries)
    mining = Mining(batch_size=batch_size, cache_refresh=cache_refresh, queries_per_epoch=queries_per_epoch)
    return RetrievalDataModule({"train": train, "test": train}, mining, describe=None)  # type: ignore[arg-type]


def test_an_epoch_is_one_pass_over_the_training_queries_in_cache_refresh_sub_epochs() -> None:
    from semvpr.retrieval.mining import TrainingEpoch

    dm = _datamodule(num_queries=26, cache_refresh=10, batch_size=4)
    assert dm.pool.queries.tolist() == list(range(25))
    calls: list[tuple[str, int]] = []
    rng = np.random.default_rng(0)

    def describe(store: FeatureStore, index: np.ndarray | None) -> np.ndarray:
        calls.append(("db" if index is None else "q", len(store) if index is None else len(index)))
        return rng.normal(size=(len(store) if index is None else len(index), 8)).astype(np.float32)

    def epoch_of(module, epoch: int) -> TrainingEpoch:
        return TrainingEpoch(module.features["train"], module.mining, module.pool, epoch, describe)

    epoch = epoch_of(dm, 0)
    assert [len(c) for c in epoch.chunks] == [9, 8, 8]  # ceil(25 / 10) sub-epochs
    assert sorted(np.concatenate(epoch.chunks).tolist()) == list(range(25))  # each query exactly once
    assert len(epoch) == 3 + 2 + 2  # batches of 4 consecutive queries per sub-epoch
    batches = list(epoch)
    assert len(batches) == len(epoch)
    # A descriptor-cache refresh (whole database + the sub-epoch's queries) before each sub-epoch.
    assert calls == [("db", 52), ("q", 9), ("db", 52), ("q", 8), ("db", 52), ("q", 8)]
    assert epoch_of(dm, 1).chunks[0].tolist() != epoch.chunks[0].tolist()  # reshuffled per epoch
    assert [c.tolist() for c in epoch_of(dm, 0).chunks] == [c.tolist() for c in epoch.chunks]
    capped = _datamodule(num_queries=26, cache_refresh=10, batch_size=4, queries_per_epoch=12)
    assert [len(c) for c in epoch_of(capped, 0).chunks] == [6, 6]


def test_negative_cache_travels_with_the_datamodule_state() -> None:
    dm = _datamodule(num_queries=6, cache_refresh=10, batch_size=2)
    dm.pool.neg_cache[2, :3] = [7, 8, 9]
    fresh = _datamodule(num_queries=6, cache_refresh=10, batch_size=2)
    fresh.load_state_dict(dm.state_dict())
    assert fresh.pool.neg_cache[2, :4].tolist() == [7, 8, 9, -1] and (fresh.pool.neg_cache[0] == -1).all()


@pytest.mark.parametrize(
    "override,message",
    [
        ("recipe.positive_radius=-10", "recipe.positive_radius=-10.* > 0"),
        ("recipe.negative_radius=5", "negative_radius=5 is below recipe.positive_radius"),
    ],
)
def test_impossible_mining_radii_are_refused_before_any_work(override: str, message: str) -> None:
    from semvpr.config.checks import check_config
    from tests.helpers import config

    with pytest.raises(SemvprError, match=message):
        check_config(config(override))
