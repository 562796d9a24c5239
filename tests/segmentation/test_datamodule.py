"""Image / segmentation datasets, augmentation alignment and the segmentation datamodule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.data.images import ImageDataset
from semvpr.data.segmentation import SegmentationSet, read_cityscapes
from semvpr.models.teacher import TeacherTraining
from semvpr.segmentation.datamodule import (
    SegmentationDataModule,
    SegmentationDataset,
    segmentation_augmentation,
    split_set,
)

# Vertical stripes of unequal width, so a flip applied to only one of image/mask shows.
STRIPES = [
    (7, 0, (0.8, 0.1, 0.1)),
    (11, 9, (0.1, 0.8, 0.1)),
    (26, 23, (0.1, 0.1, 0.8)),
    (23, 41, (0.5, 0.5, 0.5)),
]  # (labelId, first column, colour)
TRAIN_ID = {7: 0, 11: 2, 26: 13, 23: 10}
H, W = 32, 64


def make_cityscapes(root: Path, n: int = 5) -> Path:
    """n identical pairs whose image colour encodes the stripe's label."""
    label = np.zeros((H, W), np.uint8)
    rgb = np.zeros((H, W, 3), np.uint8)
    for label_id, x0, colour in STRIPES:
        label[:, x0:] = label_id
        rgb[:, x0:] = np.array(colour) * 255
    for i in range(n):
        img = root / "leftImg8bit" / "train" / "city" / f"city_{i:06d}_leftImg8bit.png"
        lab = root / "gtFine" / "train" / "city" / f"city_{i:06d}_gtFine_labelIds.png"
        img.parent.mkdir(parents=True, exist_ok=True)
        lab.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rgb).save(img)
        Image.fromarray(label).save(lab)
    return root


def assert_aligned(image: torch.Tensor, ids: torch.Tensor) -> None:
    """Away from stripe borders, each label's pixels share one colour, and labels differ in colour."""
    edge = torch.zeros_like(ids, dtype=torch.bool)
    edge[:, 1:] |= ids[:, 1:] != ids[:, :-1]
    edge[:, :-1] |= ids[:, :-1] != ids[:, 1:]
    # Bilinear image upsampling (crop zoom up to ~2x) blends colours up to 2 px from a border.
    interior = F.max_pool2d(edge[None, None].float(), 5, stride=1, padding=2)[0, 0] == 0
    medians = {}
    for t in ids[interior].unique().tolist():
        pix = image[:, interior & (ids == t)]
        med = pix.median(dim=1).values
        assert (pix - med[:, None]).abs().max() < 0.06, f"label {t} covers pixels of another colour"
        medians[t] = med
    values = list(medians.values())
    for i in range(len(values)):
        for j in range(i + 1, len(values)):
            assert (values[i] - values[j]).abs().max() > 0.1


def test_image_dataset(tmp_path: Path) -> None:
    paths = []
    for i in range(3):
        paths.append(tmp_path / f"{i}.jpg")
        Image.new("RGB", (20, 10), (i * 50, 0, 0)).save(paths[-1])
    ds = ImageDataset(paths, [8, 12])
    assert len(ds) == 3
    image, index = ds[2]
    assert image.shape == (3, 8, 12) and index == 2 and 0.0 <= image.min() <= image.max() <= 1.0


def test_segmentation_dataset_plain(tmp_path: Path) -> None:
    seg = read_cityscapes(make_cityscapes(tmp_path, 2), "train")
    image, ids = SegmentationDataset((seg.images, seg.labels), None, augment=False)[0]
    assert image.shape == (3, H, W) and ids.shape == (H, W) and ids.dtype == torch.long
    assert ids[0, 0] == 0 and ids[0, 10] == 2 and ids[0, 30] == 13 and ids[0, 50] == 10
    assert_aligned(image, ids)


def test_augmentation_keeps_mask_aligned_and_integer(tmp_path: Path) -> None:
    seg = read_cityscapes(make_cityscapes(tmp_path, 1), "train")
    ds = SegmentationDataset(seg, (H, W), augment=True)
    torch.manual_seed(0)
    flipped = changed = 0
    for _ in range(12):
        image, ids = ds[0]
        assert image.shape == (3, H, W) and ids.shape == (H, W) and ids.dtype == torch.long
        assert set(ids.unique().tolist()) <= set(TRAIN_ID.values())  # nearest: no blended ids
        assert_aligned(image, ids)
        flipped += int(ids[0, 0] == 10)  # sky stripe moved to the left edge
        changed += int(not torch.equal(ids[0], SegmentationDataset(seg, (H, W))[0][1][0]))
    assert flipped > 0 and changed > 0  # the augmentation actually did something


def test_geometric_augmentation_exact_alignment() -> None:
    """Without colour jitter, image = labels/255 must survive the same crop/flip as the mask."""
    torch.manual_seed(1)
    labels = torch.zeros(1, 1, H, W)
    for k, (_, x0, _) in enumerate(STRIPES):
        labels[..., x0:] = float(k * 40)
    image = (labels / 255).expand(1, 3, H, W).contiguous()
    aug = segmentation_augmentation((H, W), color=False)
    for _ in range(5):
        out_img, out_mask = aug(image, labels)
        ids = out_mask[0, 0].round().long()
        assert set(ids.unique().tolist()) <= {0, 40, 80, 120}
        assert_aligned(out_img[0], ids)


def test_datamodule_batches_and_split(tmp_path: Path) -> None:
    seg = read_cityscapes(make_cityscapes(tmp_path, 5), "train")
    settings = TeacherTraining(batch_size=2, num_workers=0, augment=True)
    dm = SegmentationDataModule(seg, None, (16, 32), settings, val_fraction=0.2)
    assert len(dm.train_ds) == 4 and len(dm.val_ds) == 1
    assert not set(dm.train_set.images) & set(dm.val_set.images)
    image, ids = next(iter(dm.train_dataloader()))
    assert image.shape == (2, 3, 16, 32) and ids.shape == (2, 16, 32) and ids.dtype == torch.long
    image, ids = next(iter(dm.val_dataloader()))
    assert image.shape == (1, 3, 16, 32)
    # The split is deterministic for a seed.
    again = SegmentationDataModule(seg, None, (16, 32), TeacherTraining(num_workers=0), val_fraction=0.2)
    assert again.val_set == dm.val_set
    explicit = SegmentationDataModule(seg, seg, (16, 32), TeacherTraining(num_workers=0))
    assert len(explicit.train_ds) == len(explicit.val_ds) == 5


def test_empty_inputs_raise(tmp_path: Path) -> None:
    empty = SegmentationSet((), ())
    with pytest.raises(SemvprError, match="empty"):
        SegmentationDataModule(empty, None, (8, 8), TeacherTraining(num_workers=0))
    with pytest.raises(SemvprError, match="empty"):
        SegmentationDataset(empty, (8, 8))
    one = read_cityscapes(make_cityscapes(tmp_path, 1), "train")
    with pytest.raises(SemvprError, match="cannot split 1"):
        split_set(one, 0.1)
    with pytest.raises(SemvprError, match="validation set is empty"):
        SegmentationDataModule(one, empty, (8, 8), TeacherTraining(num_workers=0))
