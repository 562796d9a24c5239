"""GSV-Cities' batches: P places × K images of each, the training data of ``recipe=gsv``.

A training set grouped into places (``PlaceSet.place_ids``) is trained on as gsv-cities trains: an
epoch is one pass over its places (those with at least K images; the others are left out, as
gsv-cities' ``min_img_per_place`` leaves them out), group by group in the groups' order (cities,
SynthCity routes), shuffled within each group, P consecutive places per batch, and K of each place's
images drawn without replacement. Rows are place-major (row p·K + k is image k of place p) and every
row carries its place as its label, for the multi-similarity miner and loss (semvpr.retrieval.losses).

One addition, for places that are not far apart by construction: two places whose centres (the mean
position of their images) are closer than ``separation`` metres never share a batch, since each
would be the other's negative although both show the same street (SynthCity's places are 5 m apart,
GSV-Cities' at least 100 m). A place that would break this waits for the next batch; the order is
otherwise kept. A batch left with fewer than two places (no negative) is dropped.

Every draw comes from ``rng(seed, epoch)``, so an epoch is the same whether or not the run was resumed
before it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from semvpr.core.errors import SemvprError
from semvpr.core.logs import say
from semvpr.data.places import PlaceSet
from semvpr.retrieval.features import PlaceFeatures


@dataclass(frozen=True)
class PlaceBatching:
    """How place batches are drawn (module docstring): P, K, the separation in metres, the seed."""

    places_per_batch: int = 32
    images_per_place: int = 4
    separation: float = 25.0
    seed: int = 0


@dataclass(frozen=True)
class TrainingPlaces:
    """The places an epoch draws from: per place its image rows (database rows, then ``len(db)`` + query
    rows), its group and its centre (east, north)."""

    rows: tuple[np.ndarray, ...]
    groups: np.ndarray
    centres: np.ndarray
    labels: np.ndarray  # per image row: its place's index in ``rows`` (-1: a place left out)
    left_out: int  # places with fewer than K images


def training_places(places: PlaceSet, images_per_place: int) -> TrainingPlaces:
    """The places of ``places`` with at least ``images_per_place`` images."""
    ids = places.place_ids
    if ids is None:
        raise SemvprError(
            f"recipe=gsv trains on places, and {places.name} is not grouped into places: use data=synthcity "
            "or data=gsv_cities (or recipe=triplet)"
        )
    place_of = np.concatenate([ids.db, ids.q])
    utm = np.concatenate([places.db_utm, places.q_utm])
    order = np.argsort(place_of, kind="stable")
    bounds = np.searchsorted(place_of[order], np.arange(ids.num_places + 1))
    kept = [p for p in range(ids.num_places) if bounds[p + 1] - bounds[p] >= images_per_place]
    rows = tuple(order[bounds[p] : bounds[p + 1]] for p in kept)
    labels = np.full(len(place_of), -1, dtype=np.int64)
    for index, r in enumerate(rows):
        labels[r] = index
    centres = np.array([utm[r].mean(0) for r in rows]).reshape(-1, 2)
    return TrainingPlaces(rows, ids.groups[kept], centres, labels, ids.num_places - len(kept))


def epoch_batches(places: TrainingPlaces, batching: PlaceBatching, epoch: int) -> list[list[int]]:
    """One epoch's batches as lists of image rows, place-major (module docstring)."""
    rng = np.random.default_rng([batching.seed, epoch])
    order = [int(p) for g in np.unique(places.groups) for p in rng.permutation(np.flatnonzero(places.groups == g))]
    batches: list[list[int]] = []
    pending = order
    while pending:
        batch: list[int] = []
        waiting: list[int] = []
        for k, place in enumerate(pending):
            if len(batch) == batching.places_per_batch:
                waiting.extend(pending[k:])
                break
            near = (
                batching.separation > 0
                and batch
                and np.hypot(*(places.centres[batch] - places.centres[place]).T).min() < batching.separation
            )
            (waiting if near else batch).append(place)
        pending = waiting
        if len(batch) >= 2:
            batches.append(batch)
    k = batching.images_per_place
    return [[int(i) for p in batch for i in rng.choice(places.rows[p], k, replace=False)] for batch in batches]


class PlaceImages(Dataset):
    """The training images of a place set, database then queries: {"trunk" or "image", "mask", "label"}."""

    def __init__(self, features: PlaceFeatures, labels: np.ndarray) -> None:
        self.features, self.labels = features, labels

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        n_db = len(self.features.db)
        item = self.features.db.item(i) if i < n_db else self.features.q.item(i - n_db)
        return {**item, "label": torch.tensor(self.labels[i])}


def collate_places(items: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    """A batch's rows stacked (per-row stacking: advanced indexing of bf16 is slow on CPU), ``labels``."""
    batch = {key: torch.stack([it[key] for it in items]) for key in items[0] if key != "label"}
    batch["labels"] = torch.stack([it["label"] for it in items])
    return batch


def report_left_out(places: TrainingPlaces, name: str, images_per_place: int) -> None:
    """One stderr line when places were left out for having fewer than K images."""
    if places.left_out:
        say(
            f"{places.left_out} of the {places.left_out + len(places.rows)} places of {name} have fewer "
            f"than {images_per_place} images (recipe.images_per_place) and are left out"
        )
