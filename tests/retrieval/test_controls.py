"""Mask controls do what they promise on cached grid masks: area-matched random cells, a derangement of the
side's masks, the sky or the objects alone removed; the side a control leaves unmasked weighs 1 in training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from semvpr.data.classes import TRAIN_ID_NAMES
from semvpr.models.masks import OracleMask
from semvpr.retrieval.control_masks import control_features, control_masks, derangement
from semvpr.retrieval.controls import MaskControl
from semvpr.retrieval.features import FeatureStore, PlaceFeatures

SKY, CAR, ROAD = (TRAIN_ID_NAMES.index(name) for name in ("sky", "car", "road"))


def binary_masks(n: int = 12, grid: tuple[int, int] = (6, 8), seed: int = 0) -> torch.Tensor:
    """(n,1,h,w) binary masks, image i removing a different number of cells (0 for the first)."""
    rng = np.random.default_rng(seed)
    cells = grid[0] * grid[1]
    masks = np.ones((n, cells), np.float16)
    for i in range(n):
        masks[i, rng.choice(cells, size=(i * 3) % cells, replace=False)] = 0
    return torch.from_numpy(masks.reshape(n, 1, *grid))


@pytest.mark.parametrize("side", ["db", "q"])
def test_random_removes_as_many_cells_as_the_source_from_each_image(side: str) -> None:
    own = binary_masks()
    random = control_masks(MaskControl("random", seed=3), own, side)
    removed = (own < 0.5).sum((1, 2, 3))
    assert torch.equal((random < 0.5).sum((1, 2, 3)), removed)  # exactly: within the promised ±1 cell
    assert set(random.unique().tolist()) <= {0.0, 1.0} and random.shape == own.shape
    assert not torch.equal(random, own)  # other cells than the source's
    assert torch.equal(control_masks(MaskControl("random", seed=3), own, side), random)  # seeded
    assert not torch.equal(control_masks(MaskControl("random", seed=4), own, side), random)


def test_random_draws_the_database_apart_from_the_queries() -> None:
    own = binary_masks()
    control = MaskControl("random", seed=0)
    assert not torch.equal(control_masks(control, own, "db"), control_masks(control, own, "q"))


@pytest.mark.parametrize("n", [2, 3, 7, 50])
def test_shuffled_gives_every_image_another_images_mask(n: int) -> None:
    own = torch.arange(n, dtype=torch.float16).reshape(n, 1, 1, 1).expand(n, 1, 2, 3).contiguous()
    for seed in range(5):
        shuffled = control_masks(MaskControl("shuffled", seed=seed), own, "q")
        source = shuffled[:, 0, 0, 0].long()  # which image's mask each image got
        assert sorted(source.tolist()) == list(range(n))  # each mask used once
        assert not torch.any(source == torch.arange(n))  # never an image's own


def test_shuffled_is_seeded_and_refuses_a_single_image() -> None:
    first = derangement(20, torch.Generator().manual_seed(1))
    assert np.array_equal(first, derangement(20, torch.Generator().manual_seed(1)))
    from semvpr.core.errors import SemvprError

    with pytest.raises(SemvprError, match="mask.control=shuffled needs at least 2 images"):
        derangement(1, torch.Generator().manual_seed(0))


def oracle_classes(labels: np.ndarray, grid: tuple[int, int], tmp: Path) -> torch.Tensor:
    """The oracle's cached masks of label maps written as PNGs: pooled class shares (N,C,h,w), float16."""
    from PIL import Image

    paths = []
    for i, label in enumerate(labels):
        paths.append(tmp / f"{i}.png")
        Image.fromarray(label.astype(np.uint8)).save(paths[-1])
    return OracleMask().grid_mask(None, [], paths, grid, "learned").to(torch.float16)


def cell_share(labels: np.ndarray, classes: tuple[int, ...], cell: int) -> np.ndarray:
    """Each cell's share of pixels of ``classes``, (N,1,h,w)."""
    n, height, width = labels.shape
    hit = np.isin(labels, classes).reshape(n, height // cell, cell, width // cell, cell)
    return hit.mean((2, 4))[:, None]


def test_sky_removes_exactly_the_cells_mostly_sky_and_objects_exactly_the_cells_mostly_objects(
    tmp_path: Path,
) -> None:
    rng = np.random.default_rng(0)
    labels = rng.choice([SKY, CAR, ROAD, 11, 18, 255], size=(5, 32, 48))  # 255: ignored pixels
    labels[:, :8] = SKY  # whole cells of sky ...
    labels[:, 8:16, :16] = CAR  # ... and of a car
    pooled = oracle_classes(labels, (4, 6), tmp_path)
    sky = control_masks(MaskControl("sky"), pooled, "db")
    objects = control_masks(MaskControl("objects"), pooled, "db")
    assert torch.equal(sky, torch.from_numpy(cell_share(labels, (SKY,), 8) <= 0.5).to(torch.float16))
    assert torch.equal(objects, torch.from_numpy(cell_share(labels, tuple(range(11, 19)), 8) <= 0.5).half())
    assert (sky[:, 0, 0] == 0).all() and (sky[:, 0, 1, :2] == 1).all()  # the sky goes, the car stays
    assert (objects[:, 0, 0] == 1).all() and (objects[:, 0, 1, :2] == 0).all()  # the car goes, the sky stays


def test_training_weighs_the_unmasked_side_one_everywhere() -> None:
    own = binary_masks(6)

    def store() -> FeatureStore:
        return FeatureStore(tuple(Path(f"{i}.jpg") for i in range(6)), (32, 48), None, own.clone())

    features = control_features(PlaceFeatures(None, store(), store()), MaskControl("random", "database", 1))
    assert torch.equal(features.db.mask, control_masks(MaskControl("random", seed=1), own, "db"))
    assert torch.equal(features.q.mask, torch.ones_like(own))
    queries = control_features(PlaceFeatures(None, store(), store()), MaskControl(apply="queries"))
    assert torch.equal(queries.db.mask, torch.ones_like(own)) and torch.equal(queries.q.mask, own)
