"""Run the teacher and a student over a segmentation set and score them against its labels.

Models see the images at their input size; predictions are resized to each label map's native
size (CamVid 360x480) before scoring, so a lower input resolution is paid for in the scores.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from semvpr.core.logs import progress
from semvpr.core.precision import autocast
from semvpr.data.images import Reading, load_image
from semvpr.data.segmentation import SegmentationSet, load_train_ids
from semvpr.models.masks import static_vector
from semvpr.segmentation.confusion import Confusion, binary_pred, class_scores, mask_scores


class ScoringDataset(Dataset):
    """(image at the model's input size, trainIds at the label's native size, index)."""

    def __init__(self, seg: SegmentationSet, image_size: Sequence[int]) -> None:
        self.seg, self.image_size = seg, [int(v) for v in image_size]

    def __len__(self) -> int:
        return len(self.seg)

    def __getitem__(self, index: int) -> tuple[Tensor, Tensor, int]:
        image, label = self.seg.images[index], self.seg.labels[index]
        ids = load_train_ids(label, from_label_ids=True, image=image, lut=self.seg.label_lut)
        return load_image(image, self.image_size), ids, index


def _collate(batch: list[tuple[Tensor, Tensor, int]]) -> tuple[Tensor, list[Tensor], list[int]]:
    """Stack images; keep label maps as a list (native sizes may differ between images)."""
    images, labels, index = zip(*batch)
    return torch.stack(images), list(labels), list(index)


def loader(seg: SegmentationSet, reading: Reading) -> DataLoader:
    """Batches of :class:`ScoringDataset` in the set's order."""
    return DataLoader(
        ScoringDataset(seg, reading.image_size),
        batch_size=reading.batch_size,
        num_workers=reading.num_workers,
        collate_fn=_collate,
    )


@torch.no_grad()
def teacher_outputs(
    teacher: nn.Module, images: Tensor, size: Sequence[int], static_names: Sequence[str]
) -> tuple[Tensor, Tensor]:
    """trainIds (B,H,W) and static probability (B,1,H,W) at ``size`` from one forward pass.

    The same post-processing as ``Teacher.predict_train_ids`` / ``class_prob`` summed over the
    static classes (what the binary filter reads), but the scores are resized once to the label
    size (one pass instead of two, no resize of a resized map).
    """
    scores = teacher.semantic_scores(images)
    static = static_vector(static_names).to(scores.device)
    share = torch.einsum("bmhw,mc,c->bhw", scores, teacher.to_train, static) / scores.sum(1).clamp_min(1e-6)
    scores = F.interpolate(scores, size=tuple(size), mode="bilinear", align_corners=False)
    prob = F.interpolate(share[:, None], size=tuple(size), mode="bilinear", align_corners=False).clamp(0.0, 1.0)
    return teacher.model_to_train[scores.argmax(1)], prob


@torch.no_grad()
def student_prob(student: nn.Module, backbone: nn.Module, images: Tensor, size: Sequence[int], bf16: bool) -> Tensor:
    """Student static probability (B,1,H,W) at ``size`` from the backbone's frozen features."""
    x = images.to(next(backbone.parameters()).device).contiguous(memory_format=torch.channels_last)
    with autocast(x.device, enabled=bf16):
        skips = backbone.forward_frozen(x)
    return student.static_prob(skips, out_hw=size)


def by_size(labels: list[Tensor]) -> dict[tuple[int, ...], list[int]]:
    """Batch positions grouped by label size (usually one group)."""
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, label in enumerate(labels):
        groups.setdefault(tuple(label.shape), []).append(i)
    return groups


def score_teacher(
    teacher: nn.Module,
    seg: SegmentationSet,
    reading: Reading,
    classes: Sequence[int],
    static_names: Sequence[str],
) -> dict[str, Any]:
    """Class-map scores (mIoU over ``classes``, per-class IoU) and binary-mask scores of the teacher."""
    class_conf, mask_conf = Confusion(), Confusion(2)
    for images, labels, _ in progress(loader(seg, reading), "teacher scores", len(seg), size=lambda b: len(b[0])):
        for size, pos in by_size(labels).items():
            ids, prob = teacher_outputs(teacher, images[pos], size, static_names)
            target = torch.stack([labels[i] for i in pos])
            class_conf.update(ids, target)
            mask_conf.update(binary_pred(prob[:, 0]), target)
    return {**class_scores(class_conf.counts, classes), **mask_scores(mask_conf.counts, static_names)}


def score_student(
    student: nn.Module,
    backbone: nn.Module,
    seg: SegmentationSet,
    reading: Reading,
    static_names: Sequence[str],
    bf16: bool,
) -> dict[str, Any]:
    """Binary-mask scores of a student (static vs not) against the labels."""
    conf = Confusion(2)
    for images, labels, _ in progress(loader(seg, reading), "student scores", len(seg), size=lambda b: len(b[0])):
        for size, pos in by_size(labels).items():
            prob = student_prob(student, backbone, images[pos], size, bf16)
            conf.update(binary_pred(prob[:, 0]), torch.stack([labels[i] for i in pos]))
    return mask_scores(conf.counts, static_names)


def frame_counts(
    predict: Callable[[Tensor, list[int]], Tensor], frames: SegmentationSet, size: Sequence[int]
) -> np.ndarray:
    """(frames, 19, 3) confusion counts of a binary mask, frame by frame: ``predict(images, label size)`` gives
    the static probability (B,1,H,W) of images read at ``size``, scored at each label's own size."""
    counts: dict[int, np.ndarray] = {}
    for images, labels, index in loader(frames, Reading(size, batch_size=8, num_workers=0)):
        for label_size, pos in by_size(labels).items():  # one group where the labels share a size (CamVid)
            prob = predict(images[pos], list(label_size))
            for row, i in enumerate(pos):
                confusion = Confusion(2)
                confusion.update(binary_pred(prob[row : row + 1, 0]), labels[i][None])
                counts[index[i]] = confusion.counts
    return np.stack([counts[i] for i in range(len(frames))])
