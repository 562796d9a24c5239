"""Weakly-supervised triplet mining (NetVLAD): feature-nearest positive, hardest negatives.

Each training query gets the database image within ``positive_radius`` that is nearest in
descriptor space (GPS is too weak to pick it), and the ``num_negatives`` nearest of
``negative_candidates`` random database images farther than ``negative_radius``. Queries whose
hardest negative already satisfies the margin are skipped: they would contribute zero loss.
"""
from __future__ import annotations

from typing import Callable

import lightning as L
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch.utils.data import ConcatDataset, DataLoader, Dataset

from semvpr.errors import SemvprError
from semvpr.features import FeatureStore, PlaceFeatures


def mine(
    db_desc: np.ndarray,
    q_desc: np.ndarray,
    db_utm: np.ndarray,
    q_utm: np.ndarray,
    query_ids: np.ndarray,
    rng: np.random.Generator,
    positive_radius: float = 10.0,
    negative_radius: float = 25.0,
    num_negatives: int = 10,
    negative_candidates: int = 1000,
    margin: float = 0.1,
) -> np.ndarray:
    """Training tuples (T, 2+num_negatives): query index, positive db index, negative db indices."""
    tree = cKDTree(db_utm)
    near = tree.query_ball_point(q_utm[query_ids], r=positive_radius)
    not_far = tree.query_ball_point(q_utm[query_ids], r=negative_radius)
    # One BLAS call for all query-database distances; the loop below only indexes into it.
    dist = torch.cdist(torch.from_numpy(q_desc[query_ids]).float(), torch.from_numpy(db_desc).float()).numpy()
    tuples = []
    for row, qi, pos, excluded in zip(dist, query_ids, near, not_far):
        if not pos:
            continue
        best_pos = pos[int(np.argmin(row[pos]))]
        keep = np.ones(len(row), dtype=bool)
        keep[excluded] = False
        candidates = np.flatnonzero(keep)
        if len(candidates) < num_negatives:
            continue
        if len(candidates) > negative_candidates:
            candidates = rng.choice(candidates, negative_candidates, replace=False)
        hardest = candidates[np.argsort(row[candidates], kind="stable")[:num_negatives]]
        # Same distance and margin as the loss (TripletMarginLoss on L2 distances, margin sqrt(m)).
        if row[hardest[0]] >= row[best_pos] + margin**0.5:
            continue
        tuples.append([qi, best_pos, *hardest])
    return np.asarray(tuples, dtype=np.int64).reshape(-1, 2 + num_negatives)


class StoreDataset(Dataset):
    """Items of a feature store: (trunk features, grid mask or empty tensor)."""

    def __init__(self, store: FeatureStore) -> None:
        self.store = store

    def __len__(self) -> int:
        return len(self.store)

    def __getitem__(self, i: int) -> tuple[Tensor, Tensor]:
        mask = self.store.mask[i] if self.store.mask is not None else torch.empty(0)
        return self.store.trunk[i], mask


class TupleDataset(Dataset):
    """Training tuples as stacked features: item = ((2+N, C, h', w'), (2+N, 1, h, w) or empty)."""

    def __init__(self, tuples: np.ndarray, db: FeatureStore, q: FeatureStore) -> None:
        self.tuples, self.db, self.q = tuples, db, q

    def __len__(self) -> int:
        return len(self.tuples)

    def __getitem__(self, i: int) -> tuple[Tensor, Tensor]:
        qi, *db_ids = self.tuples[i]
        # Per-row stacking: advanced indexing of bf16 tensors is ~10x slower on CPU.
        trunk = torch.stack([self.q.trunk[qi], *(self.db.trunk[j] for j in db_ids)])
        if self.db.mask is None:
            return trunk, torch.empty(0)
        return trunk, torch.stack([self.q.mask[qi], *(self.db.mask[j] for j in db_ids)])


Describe = Callable[[FeatureStore], np.ndarray]


class RetrievalDataModule(L.LightningDataModule):
    """Cached features of train/val/test place sets; re-mines training tuples every epoch."""

    def __init__(
        self,
        train: PlaceFeatures | None,
        val: PlaceFeatures | None,
        test: PlaceFeatures,
        batch_size: int = 4,
        eval_batch_size: int = 64,
        cache_refresh: int = 1000,
        seed: int = 0,
        **mining: float,
    ) -> None:
        super().__init__()
        self.train, self.val, self.test = train, val, test
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.cache_refresh, self.mining = cache_refresh, mining
        self.rng = np.random.default_rng(seed)
        self.num_tuples: list[int] = []

    def train_dataloader(self) -> DataLoader:
        # One epoch = one descriptor-cache refresh over at most `cache_refresh` queries (NetVLAD).
        assert self.train is not None
        describe: Describe = self.trainer.lightning_module.describe_store
        query_ids = self.rng.permutation(len(self.train.q))[: self.cache_refresh]
        tuples = mine(describe(self.train.db), describe(self.train.q), self.train.places.db_utm,
                      self.train.places.q_utm, np.sort(query_ids), self.rng, **self.mining)
        self.num_tuples.append(len(tuples))
        if len(tuples) == 0:
            raise SemvprError(
                f"no training query of {self.train.places.name} has a database image within "
                f"{self.mining.get('positive_radius', 10.0)} m and a violating negative; "
                "check the training split's UTM coordinates")
        return DataLoader(TupleDataset(tuples, self.train.db, self.train.q),
                          batch_size=self.batch_size, shuffle=True, drop_last=len(tuples) > self.batch_size)

    def val_dataloader(self) -> DataLoader:
        assert self.val is not None
        return self._eval_loader(self.val)

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader(self.test)

    def _eval_loader(self, features: PlaceFeatures) -> DataLoader:
        # Database first, then queries: the module splits the descriptors at len(db).
        dataset = ConcatDataset([StoreDataset(features.db), StoreDataset(features.q)])
        return DataLoader(dataset, batch_size=self.eval_batch_size)
