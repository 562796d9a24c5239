"""Segmentation pairs as a dataset, their augmentation, and the teacher's LightningDataModule."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import kornia.augmentation as K
import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from semvpr.core.errors import SemvprError
from semvpr.data.images import Size
from semvpr.data.segmentation import SegmentationSet, load_pair
from semvpr.models.teacher import TeacherTraining


def segmentation_augmentation(image_size: Size, color: bool = True) -> K.AugmentationSequential:
    """Flip + resized crop on image and mask alike (mask resampled nearest), colour jitter on the image."""
    ops: list[torch.nn.Module] = [
        K.RandomHorizontalFlip(),
        K.RandomResizedCrop(tuple(int(v) for v in image_size), scale=(0.5, 1.0), ratio=(0.75, 1.333)),
    ]
    if color:
        # Intensity ops touch only "input": kornia skips them for the "mask" key.
        ops.append(K.ColorJitter(0.3, 0.3, 0.3, 0.05, p=0.8))
    # kornia's default extra_args resample masks with NEAREST, so ids are never blended.
    return K.AugmentationSequential(*ops, data_keys=["input", "mask"])


class SegmentationDataset(Dataset):
    """(image (3,H,W) float [0,1], trainIds (H,W) long) pairs, optionally augmented per sample."""

    def __init__(
        self,
        data: SegmentationSet | tuple[Sequence[str | Path], Sequence[str | Path]],
        image_size: Size | None,
        augment: bool = False,
    ) -> None:
        if not isinstance(data, SegmentationSet):
            data = SegmentationSet(images=tuple(data[0]), labels=tuple(data[1]))
        if len(data) == 0:
            raise SemvprError("segmentation dataset is empty: no image/label pairs given")
        self.data = data
        self.image_size = image_size
        if augment and image_size is None:
            raise SemvprError("segmentation augmentation needs an image_size [H, W]")
        self.augment = augment
        # Built once per dataset; DataLoader workers get their own copy and their own torch seed.
        self._aug = segmentation_augmentation(image_size) if self.augment else None

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        image, ids = load_pair(
            self.data.images[index],
            self.data.labels[index],
            self.image_size,
            from_label_ids=True,
            lut=self.data.label_lut,
        )
        if self._aug is not None:
            image, mask = self._aug(image[None], ids[None, None].float())
            image = image[0].clamp_(0.0, 1.0)
            ids = mask[0, 0].round().long()
        return image, ids


def split_set(data: SegmentationSet, val_fraction: float, seed: int = 0) -> tuple[SegmentationSet, SegmentationSet]:
    """Deterministic random train/val split of one SegmentationSet (at least one item on each side)."""
    n = len(data)
    n_val = max(1, round(n * val_fraction))
    if n < 2 or n_val >= n:
        raise SemvprError(
            f"cannot split {n} segmentation pairs into train/val with "
            f"val_fraction={val_fraction}; give a separate validation set"
        )
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).tolist()

    def pick(idx: list[int]) -> SegmentationSet:
        idx = sorted(idx)
        return SegmentationSet(
            tuple(data.images[i] for i in idx), tuple(data.labels[i] for i in idx), label_lut=data.label_lut
        )

    return pick(order[n_val:]), pick(order[:n_val])


class SegmentationDataModule(L.LightningDataModule):
    """Train/val loaders of (image, trainIds) for teacher training, at ``image_size`` in the batches, workers,
    augmentation and seed of its ``settings``; val split off train (``val_fraction``) when not given."""

    def __init__(
        self,
        train: SegmentationSet,
        val: SegmentationSet | None,
        image_size: Size,
        settings: TeacherTraining,
        val_fraction: float = 0.1,
    ) -> None:
        super().__init__()
        if len(train) == 0:
            raise SemvprError("segmentation training set is empty: no image/label pairs found")
        if val is None:
            train, val = split_set(train, val_fraction, settings.seed)
        elif len(val) == 0:
            raise SemvprError("segmentation validation set is empty: no image/label pairs found")
        self.train_set, self.val_set = train, val
        self.image_size = tuple(int(v) for v in image_size)
        self.batch_size, self.num_workers = settings.batch_size, settings.num_workers
        # Built here, not in setup(): cheap (paths only), and loaders work without a Trainer.
        self.train_ds = SegmentationDataset(train, self.image_size, settings.augment)
        self.val_ds = SegmentationDataset(val, self.image_size, False)

    def _loader(self, ds: Dataset, shuffle: bool) -> DataLoader:
        return DataLoader(
            ds,
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            # A ragged last batch of one breaks BatchNorm in training.
            drop_last=shuffle and len(ds) > self.batch_size,
        )

    def train_dataloader(self) -> DataLoader:
        """Shuffled, augmented training batches."""
        return self._loader(self.train_ds, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        """Validation batches in a fixed order, no augmentation."""
        return self._loader(self.val_ds, shuffle=False)
