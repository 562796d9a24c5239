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
Under DDP the refresh is sharded, rank 0 mines and broadcasts, and each rank trains on its slice
of every batch (:class:`TrainingEpoch`), with the same gradient as one process.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch.utils.data import Dataset

from semvpr.core.errors import SemvprError
from semvpr.core.precision import fp32
from semvpr.data.places import check_radius
from semvpr.retrieval.distributed import Describe, from_rank_zero, rank_slice, world
from semvpr.retrieval.features import FeatureStore, PlaceFeatures
from semvpr.retrieval.loading import FitLoader

#: A mined tuple: query, positive, negatives (rows of the query and database stores).
Tuple = tuple[int, int, np.ndarray]


class TupleImages(Dataset):
    """The images of the tuple an item's key names, as one item: {"trunk" or "image": (2+n, ...), "mask":
    (2+n, 1, h, w) or empty}. The key is the tuple itself, so a loader over it reads whatever its batch sampler
    names (:class:`semvpr.retrieval.loading.FitLoader`: one loader serves every sub-epoch)."""

    def __init__(self, db: FeatureStore, q: FeatureStore) -> None:
        self.db, self.q = db, q

    def __getitem__(self, key: Tuple) -> dict[str, Tensor]:
        qi, pos, negs = key
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


def query_batches(queries: np.ndarray, tuples: list[Tuple], batch_size: int) -> list[list[Tuple]]:
    """The tuples of each ``batch_size`` consecutive sub-epoch queries (empty where none was minable)."""
    of = {t[0]: t for t in tuples}
    return [[of[q] for q in queries[s : s + batch_size] if q in of] for s in range(0, len(queries), batch_size)]


@dataclass(frozen=True)
class Mining:
    """How training tuples are mined and batched (module docstring); ``batch_size`` is the global
    batch: under DDP each rank trains on its consecutive share of every batch's tuples."""

    batch_size: int = 4
    cache_refresh: int = 1000
    queries_per_epoch: int | None = None
    seed: int = 0
    positive_radius: float = 10.0
    negative_radius: float = 25.0
    num_negatives: int = 10
    negative_candidates: int = 1000
    margin: float = 0.1

    def mine(
        self,
        db_desc: np.ndarray,
        q_desc: np.ndarray,
        places: Any,
        query_ids: np.ndarray,
        rng: np.random.Generator,
        neg_cache: np.ndarray | None = None,
        device: torch.device | str = "cpu",
    ) -> list[tuple[int, int, np.ndarray]]:
        """(query, positive, violating hard negatives) per minable query of ``query_ids`` (module docstring),
        with these radii, counts and margin; ``q_desc`` rows follow ``query_ids``, positions are ``places``'
        ``db_utm`` / ``q_utm``; the distances on ``device``.

        ``neg_cache`` (num_queries, num_negatives), -1 padded, is read and updated in place.
        """
        positive_radius = check_radius(self.positive_radius, "recipe.positive_radius")
        negative_radius = check_radius(self.negative_radius, "recipe.negative_radius")
        num_negatives, margin = self.num_negatives, self.margin
        db_utm, q_utm = places.db_utm, places.q_utm
        tree = cKDTree(db_utm)
        near = tree.query_ball_point(q_utm[query_ids], r=positive_radius)
        not_far = tree.query_ball_point(q_utm[query_ids], r=negative_radius)
        # One BLAS call for all query-database distances; the loop below only indexes into it.
        # On the job's device (a GPU's matmul in full fp32: the ranking must not move with TF32).
        with fp32(torch.device(device).type):
            q, db = (torch.from_numpy(d).float().to(device) for d in (q_desc, db_desc))
            dist = torch.cdist(q, db).cpu().numpy()
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
            sample = rng.choice(candidates, min(self.negative_candidates, len(candidates)), replace=False)
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


def trainable_queries(places: Any, positive_radius: float) -> np.ndarray:
    """Training queries with a database image within ``positive_radius`` (the others cannot be mined)."""
    near = cKDTree(places.db_utm).query_ball_point(places.q_utm, r=positive_radius)
    queries = np.flatnonzero([len(n) > 0 for n in near])
    if len(queries) == 0:
        raise SemvprError(
            f"no training query of {places.name} has a database image within {positive_radius} m; "
            "check the training split's UTM coordinates"
        )
    return queries


@dataclass
class MiningPool:
    """What mining keeps from epoch to epoch: the training queries it can mine (those with a database image
    within the positive radius) and each training query's negative cache (pytorch-NetVlad's ``negCache``:
    the hard negatives of its last mining, offered again as candidates)."""

    queries: np.ndarray
    neg_cache: np.ndarray

    @classmethod
    def of(cls, train: PlaceFeatures, mining: Mining) -> MiningPool:
        """A fresh pool over ``train``: every trainable query, an empty (-1) negative cache."""
        queries = trainable_queries(train.places, mining.positive_radius)
        return cls(queries, np.full((len(train.q), mining.num_negatives), -1, dtype=np.int64))


def tuple_loader(train: PlaceFeatures, num_workers: int, device: torch.device | str) -> FitLoader:
    """A fit's loader of mined tuples' images from ``train``'s stores (its workers kept across sub-epochs)."""
    return FitLoader(TupleImages(train.db, train.q), collate_tuples, num_workers, train.db.streams, device)


class TrainingEpoch:
    """One epoch's batches: for each sub-epoch, refresh the descriptor cache, mine, then train.

    Under DDP every rank iterates the same global batches: ``describe`` is sharded and gathered
    (semvpr.retrieval.distributed), rank 0 mines with the single-process random stream and broadcasts the
    tuples and the negative cache, and each rank yields its slice of every global batch (see
    :meth:`__iter__`).
    """

    def __init__(
        self,
        train: PlaceFeatures,
        mining: Mining,
        pool: MiningPool,
        epoch: int,
        describe: Describe,
        loader: FitLoader | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        """``loader``: the fit's loader of tuples (:func:`tuple_loader`; without it, one without workers)."""
        self.train, self.mining, self.describe, self.pool, self.device = train, mining, describe, pool, device
        self.loader = loader if loader is not None else tuple_loader(train, 0, device)
        # Tuples mined, and whether the epoch ran at all (a resumed, finished fit builds it and never iterates).
        self.num_tuples, self.iterated = 0, False
        self.rng = np.random.default_rng([mining.seed, epoch])
        order = self.rng.permutation(pool.queries)[: mining.queries_per_epoch]
        self.chunks = np.array_split(order, max(1, -(-len(order) // mining.cache_refresh)))

    def __len__(self) -> int:
        return sum(-(-len(c) // self.mining.batch_size) for c in self.chunks)

    def __iter__(self) -> Iterator[dict[str, Any] | None]:
        """Per global batch: None if it holds no tuple (every rank skips the step, as pytorch-NetVlad
        does), else this rank's slice with ``pairs`` = global (query, negative) pairs / world size.
        Dividing each rank's summed loss by it makes DDP's gradient average the single-process
        gradient; a rank whose slice is empty gets ``{"pairs": ...}`` alone and still joins the all-reduce."""
        rank, size = world()
        train = self.train
        self.iterated = True
        for chunk in self.chunks:
            db_desc, q_desc = self.describe(train.db, None), self.describe(train.q, chunk)
            cache = self.pool.neg_cache
            if rank == 0:
                tuples = self.mining.mine(db_desc, q_desc, train.places, chunk, self.rng, cache, self.device)
                shared = (tuples, cache)
            tuples, cache[:] = from_rank_zero(shared if rank == 0 else None)
            self.num_tuples += len(tuples)
            batches = query_batches(chunk, tuples, self.mining.batch_size)
            pairs = [sum(len(t[2]) for t in batch) for batch in batches]
            loader = self.loader.over([batch[rank_slice(len(batch), rank, size)] for batch in batches])
            for batch, n in zip(loader, pairs):
                yield None if n == 0 else {**(batch or {}), "pairs": n / size}
