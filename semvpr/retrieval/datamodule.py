"""The VPR DataModules: train/val/test feature stores, one training protocol each. ``RetrievalDataModule``
(recipe=triplet) re-mines training tuples per sub-epoch (semvpr.retrieval.mining); ``PlaceDataModule``
(recipe=gsv) draws P places × K images per batch (semvpr.retrieval.places). Both validate and test alike.

Data flows one way: the descriptor function that mining needs is given at construction (the model's
``describe_store``, sharded across ranks by semvpr.retrieval.distributed), and the datamodule never reads the
trainer's model. Val/test batches are whole eval batches over database then queries; under DDP each
rank loads a contiguous block of them (semvpr.retrieval.validation gathers the descriptors back in order).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import lightning as L
import torch
from torch.utils.data import ConcatDataset, DataLoader, Sampler

from semvpr.core.errors import SemvprError
from semvpr.retrieval.distributed import Describe, batch_block, world
from semvpr.retrieval.features import PlaceFeatures, StoreDataset
from semvpr.retrieval.loading import FitLoader, loader_settings
from semvpr.retrieval.mining import Mining, MiningPool, TrainingEpoch, tuple_loader
from semvpr.retrieval.places import (
    PlaceBatching,
    PlaceImages,
    collate_places,
    epoch_batches,
    report_left_out,
    training_places,
)


class RankBatches(Sampler[list[int]]):
    """Batches of ``batch_size`` consecutive rows of ``n``: this rank's contiguous block of them
    (all of them in a single process). The rank is read when iterated, inside the trainer."""

    def __init__(self, n: int, batch_size: int) -> None:
        self.n, self.batch_size = n, batch_size

    def _rows(self) -> range:
        block = batch_block(self.n, self.batch_size, *world())
        return range(block.start, block.stop)

    def __len__(self) -> int:
        return -(-len(self._rows()) // self.batch_size)

    def __iter__(self) -> Iterator[list[int]]:
        rows = self._rows()
        return (list(rows[s : s + self.batch_size]) for s in range(0, len(rows), self.batch_size))


class EvalDataModule(L.LightningDataModule):
    """Feature stores of train/val/test, and the val/test loaders every training protocol shares."""

    def __init__(self, features: dict[str, PlaceFeatures], eval_batch_size: int = 64, num_workers: int = 0) -> None:
        super().__init__()
        self.features = features
        self.eval_batch_size, self.num_workers = eval_batch_size, num_workers

    def epoch_facts(self) -> dict[str, Any]:
        """What the training epochs held, for metrics.json."""
        return {}

    def nothing_trained(self) -> str | None:
        """Why the fit that ended trained nothing, or None (a job then fails instead of reporting ok)."""
        return None

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader(self.features["val"])

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader(self.features["test"])

    def _eval_loader(self, features: PlaceFeatures) -> DataLoader:
        # Database first, then queries: semvpr.retrieval.validation splits the descriptors at len(db).
        dataset = ConcatDataset([StoreDataset(features.db), StoreDataset(features.q)])
        settings = loader_settings(self.num_workers, features.db.streams, self._device())
        return DataLoader(dataset, batch_sampler=RankBatches(len(dataset), self.eval_batch_size), **settings)

    def _device(self) -> torch.device:
        """The device of the module this datamodule feeds (the CPU before a trainer holds one)."""
        module = self.trainer.lightning_module if self.trainer is not None else None
        return module.device if module is not None else torch.device("cpu")


class RetrievalDataModule(EvalDataModule):
    """Feature stores of train/val/test; training batches re-mined per sub-epoch (semvpr.retrieval.mining)."""

    def __init__(
        self,
        features: dict[str, PlaceFeatures],
        mining: Mining,
        describe: Describe,
        eval_batch_size: int = 64,
        num_workers: int = 0,
    ) -> None:
        super().__init__(features, eval_batch_size, num_workers)
        self.mining, self.describe = mining, describe
        # Tuples mined per epoch (the last epoch's count goes into metrics.json).
        self.num_tuples: list[int] = []
        self._epoch: TrainingEpoch | None = None
        self._loader: FitLoader | None = None  # the fit's, made at its first epoch
        train = features.get("train")
        if train is not None:
            if not len(train.q):
                raise SemvprError(
                    f"recipe=triplet mines training queries, and {train.places.name} has none (it is a set of "
                    "places): train it with recipe=gsv"
                )
            self.pool = MiningPool.of(train, mining)

    def train_dataloader(self) -> TrainingEpoch:
        self._count_tuples()
        train, device = self.features["train"], self._device()
        if self._loader is None:
            self._loader = tuple_loader(train, self.num_workers, device)
        self._epoch = TrainingEpoch(
            train, self.mining, self.pool, self.trainer.current_epoch, self.describe, self._loader, device
        )
        return self._epoch

    def _count_tuples(self) -> None:
        if self._epoch is not None and self._epoch.iterated:
            self.num_tuples.append(self._epoch.num_tuples)

    def teardown(self, stage: str) -> None:
        if stage == "fit":
            self._count_tuples()
            self._epoch = self._loader = None

    def epoch_facts(self) -> dict[str, Any]:
        return {"tuples_per_epoch": self.num_tuples}

    def nothing_trained(self) -> str | None:
        """Why the fit trained nothing (no epoch mined a tuple), or None."""
        if self.num_tuples and not any(self.num_tuples):
            return (
                f"training mined no tuple in {len(self.num_tuples)} epoch(s): no training query had a positive "
                f"within recipe.positive_radius={self.mining.positive_radius} m and a negative violating "
                f"recipe.margin={self.mining.margin}"
            )
        return None

    def state_dict(self) -> dict[str, Any]:
        """The negative cache: a resumed run mines with the hard negatives of the epochs before."""
        return {"neg_cache": torch.from_numpy(self.pool.neg_cache.copy())} if "train" in self.features else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "neg_cache" in state and "train" in self.features:
            self.pool.neg_cache = state["neg_cache"].numpy().copy()


class PlaceDataModule(EvalDataModule):
    """Feature stores of train/val/test; training batches of P places × K images (semvpr.retrieval.places),
    drawn anew every epoch from ``rng(seed, epoch)``: nothing to carry in a checkpoint."""

    def __init__(
        self,
        features: dict[str, PlaceFeatures],
        batching: PlaceBatching,
        eval_batch_size: int = 64,
        num_workers: int = 0,
    ) -> None:
        super().__init__(features, eval_batch_size, num_workers)
        self.batching = batching
        # Batches and places per epoch (the last epoch's go into metrics.json).
        self.batches: list[list[list[int]]] = []
        self._loader: FitLoader | None = None  # the fit's, made at its first epoch
        train = features.get("train")
        if train is not None:
            self.places = training_places(train.places, batching.images_per_place)
            report_left_out(self.places, train.places.name, batching.images_per_place)
            if len(self.places.rows) < 2:
                raise SemvprError(
                    f"{train.places.name}: {len(self.places.rows)} place(s) with {batching.images_per_place} or more "
                    "images (recipe.images_per_place); a batch needs two (with SynthCity: data.traversals >= "
                    f"{batching.images_per_place - 1})"
                )

    def train_dataloader(self) -> DataLoader:
        train = self.features["train"]
        batches = epoch_batches(self.places, self.batching, self.trainer.current_epoch)
        self.batches.append(batches)
        if self._loader is None:
            images = PlaceImages(train, self.places.labels)
            self._loader = FitLoader(images, collate_places, self.num_workers, train.db.streams, self._device())
        return self._loader.over(batches)

    def teardown(self, stage: str) -> None:
        if stage == "fit":
            self._loader = None

    def epoch_facts(self) -> dict[str, Any]:
        last = self.batches[-1] if self.batches else []
        return {
            "places": len(self.places.rows) if "train" in self.features else 0,
            "batches_per_epoch": len(last),
            "places_per_epoch": sum(len(b) for b in last) // self.batching.images_per_place,
        }
