"""Weakly-supervised triplet mining and the training epoch, as pytorch-NetVlad runs them.

An epoch is one pass over the training queries (those with a database image within
``positive_radius``; ``queries_per_epoch`` caps it, e.g. 5000 as the VPR benchmark does), in
sub-epochs of ``cache_refresh`` queries. Before each sub-epoch the current model describes the
training database and the sub-epoch's queries (the descriptor cache), and every query is mined:

- positive: the database image within ``positive_radius`` nearest in descriptor space;
- negatives: ``negative_candidates`` random database images beyond ``negative_radius``, plus the
  query's hard negatives of its previous visit (the negative cache); of the ``10 × num_negatives``
  nearest, those violating the margin (d_neg < d_pos + sqrt(margin)) are kept, at most
  ``num_negatives``; a query with none is skipped.

Batches are ``batch_size`` consecutive queries of the sub-epoch, so a batch holds between 0 and
``batch_size`` tuples with 1 to ``num_negatives`` negatives each; the loss averages over the
(query, negative) pairs present. The epoch's randomness comes from ``rng(seed, epoch)`` and the
negative cache travels in the checkpoint, so a resumed run mines what the uninterrupted one did.
"""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Callable

import lightning as L
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch.utils.data import ConcatDataset, DataLoader, Dataset, Sampler

from semvpr.errors import SemvprError
from semvpr.metrics import check_radius
from semvpr.features import FeatureStore, PlaceFeatures, StoreDataset


def mine(
    db_desc: np.ndarray,
    q_desc: np.ndarray,
    db_utm: np.ndarray,
    q_utm: np.ndarray,
    query_ids: np.ndarray,
    rng: np.random.Generator,
    neg_cache: np.ndarray | None = None,
    positive_radius: float = 10.0,
    negative_radius: float = 25.0,
    num_negatives: int = 10,
    negative_candidates: int = 1000,
    margin: float = 0.1,
) -> list[tuple[int, int, np.ndarray]]:
    """(query, positive, violating hard negatives) per minable query; ``q_desc`` rows follow ``query_ids``.

    ``neg_cache`` (num_queries, num_negatives), -1 padded, is read and updated in place.
    """
    positive_radius = check_radius(positive_radius, "model.positive_radius")
    negative_radius = check_radius(negative_radius, "model.negative_radius")
    tree = cKDTree(db_utm)
    near = tree.query_ball_point(q_utm[query_ids], r=positive_radius)
    not_far = tree.query_ball_point(q_utm[query_ids], r=negative_radius)
    # One BLAS call for all query-database distances; the loop below only indexes into it.
    dist = torch.cdist(torch.from_numpy(q_desc).float(), torch.from_numpy(db_desc).float()).numpy()
    tuples = []
    for row, qi, pos, excluded in zip(dist, query_ids, near, not_far):
        if not pos:
            continue
        best_pos = pos[int(np.argmin(row[pos]))]
        potential = np.ones(len(row), dtype=bool)
        potential[excluded] = False
        candidates = np.flatnonzero(potential)
        if len(candidates) == 0:
            continue
        sample = rng.choice(candidates, min(negative_candidates, len(candidates)), replace=False)
        if neg_cache is not None:
            sample = np.union1d(sample, neg_cache[qi][neg_cache[qi] >= 0])
        nearest = sample[np.argsort(row[sample], kind="stable")[: 10 * num_negatives]]
        # Same distance and margin as the loss (TripletMarginLoss on L2 distances, margin sqrt(m)).
        violating = nearest[row[nearest] < row[best_pos] + margin**0.5][:num_negatives]
        if len(violating) == 0:
            continue
        if neg_cache is not None:
            neg_cache[qi] = -1
            neg_cache[qi, : len(violating)] = violating
        tuples.append((int(qi), int(best_pos), violating))
    return tuples


class TupleDataset(Dataset):
    """A mined tuple's images as one item: {"x" or "image": (2+n, ...), "mask": (2+n, 1, h, w) or empty}."""

    def __init__(self, tuples: list[tuple[int, int, np.ndarray]], db: FeatureStore, q: FeatureStore) -> None:
        self.tuples, self.db, self.q = tuples, db, q

    def __len__(self) -> int:
        return len(self.tuples)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        qi, pos, negs = self.tuples[i]
        items = [self.q.item(qi), self.db.item(pos), *(self.db.item(int(j)) for j in negs)]
        # Per-row stacking: advanced indexing of bf16 tensors is ~10x slower on CPU.
        return {key: torch.stack([it[key] for it in items]) for key in items[0]}


def collate_tuples(items: list[dict[str, Tensor]]) -> dict[str, Tensor] | None:
    """All images of a batch's tuples in one tensor, and per tuple its rows in it:
    ``tuples`` (T, 2+max negatives) = query, positive, negatives, padded with -1."""
    if not items:
        return None
    batch = {key: torch.cat([it[key] for it in items]) for key in items[0]}
    sizes = [len(it["trunk" if "trunk" in it else "image"]) for it in items]
    tuples = torch.full((len(items), max(sizes)), -1, dtype=torch.long)
    start = 0
    for row, n in zip(tuples, sizes):
        row[:n] = torch.arange(start, start + n)
        start += n
    batch["tuples"] = tuples
    return batch


class QueryBatches(Sampler[list[int]]):
    """Tuple indices of ``batch_size`` consecutive sub-epoch queries (empty where none was minable)."""

    def __init__(self, queries: np.ndarray, tuples: list[tuple[int, int, np.ndarray]], batch_size: int) -> None:
        where = {qi: i for i, (qi, _, _) in enumerate(tuples)}
        self.batches = [[where[q] for q in queries[s : s + batch_size] if q in where]
                        for s in range(0, len(queries), batch_size)]

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self) -> Iterator[list[int]]:
        return iter(self.batches)


Describe = Callable[[FeatureStore, np.ndarray | None], np.ndarray]


class TrainingEpoch:
    """One epoch's batches: for each sub-epoch, refresh the descriptor cache, mine, then train."""

    def __init__(self, dm: RetrievalDataModule, epoch: int, describe: Describe) -> None:
        self.dm, self.describe = dm, describe
        self.rng = np.random.default_rng([dm.seed, epoch])
        queries = self.rng.permutation(dm.trainable_queries)[: dm.queries_per_epoch]
        self.chunks = np.array_split(queries, max(1, -(-len(queries) // dm.cache_refresh)))

    def __len__(self) -> int:
        return sum(-(-len(c) // self.dm.batch_size) for c in self.chunks)

    def __iter__(self) -> Iterator[dict[str, Tensor] | None]:
        dm, train = self.dm, self.dm.train
        assert train is not None
        for chunk in self.chunks:
            tuples = mine(self.describe(train.db, None), self.describe(train.q, chunk), train.places.db_utm,
                          train.places.q_utm, chunk, self.rng, dm.neg_cache, **dm.mining)
            dm.num_tuples[-1] += len(tuples)
            yield from DataLoader(TupleDataset(tuples, train.db, train.q),
                                  batch_sampler=QueryBatches(chunk, tuples, dm.batch_size),
                                  collate_fn=collate_tuples, num_workers=dm.num_workers if train.db.streams else 0)


class RetrievalDataModule(L.LightningDataModule):
    """Feature stores of train/val/test; training batches re-mined per sub-epoch (see module docstring)."""

    def __init__(
        self,
        train: PlaceFeatures | None,
        val: PlaceFeatures | None,
        test: PlaceFeatures,
        batch_size: int = 4,
        eval_batch_size: int = 64,
        cache_refresh: int = 1000,
        seed: int = 0,
        queries_per_epoch: int | None = None,
        num_workers: int = 0,
        **mining: Any,
    ) -> None:
        super().__init__()
        self.train, self.val, self.test = train, val, test
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.cache_refresh, self.mining, self.seed = cache_refresh, mining, seed
        self.queries_per_epoch, self.num_workers = queries_per_epoch, num_workers
        self.num_tuples: list[int] = []
        if train is not None:
            near = cKDTree(train.places.db_utm).query_ball_point(train.places.q_utm, r=mining.get("positive_radius", 10.0))
            self.trainable_queries = np.flatnonzero([len(n) > 0 for n in near])
            if len(self.trainable_queries) == 0:
                raise SemvprError(
                    f"no training query of {train.places.name} has a database image within "
                    f"{mining.get('positive_radius', 10.0)} m; check the training split's UTM coordinates")
            self.neg_cache = np.full((len(train.q), int(mining.get("num_negatives", 10))), -1, dtype=np.int64)

    def train_dataloader(self) -> TrainingEpoch:
        self.num_tuples.append(0)
        module = self.trainer.lightning_module
        return TrainingEpoch(self, self.trainer.current_epoch, module.describe_store)

    def val_dataloader(self) -> DataLoader:
        assert self.val is not None
        return self._eval_loader(self.val)

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader(self.test)

    def _eval_loader(self, features: PlaceFeatures) -> DataLoader:
        # Database first, then queries: the module splits the descriptors at len(db).
        dataset = ConcatDataset([StoreDataset(features.db), StoreDataset(features.q)])
        workers = self.num_workers if features.db.streams else 0
        return DataLoader(dataset, batch_size=self.eval_batch_size, num_workers=workers)

    def state_dict(self) -> dict[str, Any]:
        """The negative cache: a resumed run mines with the hard negatives of the epochs before."""
        return {"neg_cache": torch.from_numpy(self.neg_cache.copy())} if self.train is not None else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "neg_cache" in state and self.train is not None:
            self.neg_cache = state["neg_cache"].numpy().copy()

