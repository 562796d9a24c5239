"""Segmentation scores that stay meaningful when moving objects are a few % of the pixels.

Everything is read off one confusion matrix of ground-truth trainIds (rows, ignore pixels left
out) against predictions (columns): per-class IoU and mIoU for a class map, and for a binary
static mask what it removes: moving objects (the point of the mask), static pixels (the damage
the retriever feels) and sky (uninformative, removed by the project's mask on purpose).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from semvpr.data.classes import NUM_CLASSES, STATIC_NAMES, TRAIN_ID_NAMES

#: Objects that move between two visits of a place: person … bicycle (sky is non-static but does not move).
MOVING_NAMES: tuple[str, ...] = TRAIN_ID_NAMES[TRAIN_ID_NAMES.index("person") :]
REMOVED, KEPT = 0, 1


class Confusion:
    """Running pixel counts (19 ground-truth trainIds × ``num_pred`` labels + one column for any other label)."""

    def __init__(self, num_pred: int = NUM_CLASSES) -> None:
        self.num_pred = num_pred
        self.counts = np.zeros((NUM_CLASSES, num_pred + 1), dtype=np.int64)

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add a batch of predicted labels and trainId targets of the same shape."""
        if pred.shape != target.shape:
            raise ValueError(f"prediction {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
        target, pred = target.reshape(-1).long().cpu(), pred.reshape(-1).long().cpu()
        valid = (target >= 0) & (target < NUM_CLASSES)  # IGNORE and unknown ids are not scored
        pred = torch.where((pred >= 0) & (pred < self.num_pred), pred, self.num_pred)[valid]
        flat = target[valid] * (self.num_pred + 1) + pred
        self.counts += torch.bincount(flat, minlength=self.counts.size).reshape(self.counts.shape).numpy()


def _ratio(num: float, den: float) -> float:
    return float(num / den) if den > 0 else float("nan")


def class_iou(counts: np.ndarray) -> np.ndarray:
    """IoU per trainId of a class-map confusion (nan where a class is neither in the labels nor predicted)."""
    inter = np.diag(counts[:, :NUM_CLASSES]).astype(np.float64)
    union = counts.sum(1) + counts[:, :NUM_CLASSES].sum(0) - inter
    return np.array([_ratio(i, u) for i, u in zip(inter, union)])


def group_iou(counts: np.ndarray, group: Sequence[int]) -> float:
    """IoU of a union of classes (e.g. all moving classes) in a class-map confusion."""
    rows = counts[list(group)]
    inter = rows[:, list(group)].sum()
    return _ratio(inter, rows.sum() + counts[:, list(group)].sum() - inter)


def class_scores(counts: np.ndarray, classes: Sequence[int]) -> dict[str, object]:
    """Per-class IoU by name, mIoU over ``classes`` (the ones the dataset labels), and the moving-class IoU."""
    iou = class_iou(counts)
    moving = [TRAIN_ID_NAMES.index(n) for n in MOVING_NAMES]
    return {
        "miou": float(np.nanmean(iou[list(classes)])),
        "class_iou": {TRAIN_ID_NAMES[c]: float(iou[c]) for c in classes},
        "moving_iou": group_iou(counts, moving),
        "pixel_accuracy": _ratio(np.trace(counts[:, :NUM_CLASSES]), counts.sum()),
    }


def mask_scores(
    counts: np.ndarray, static_names: Sequence[str] = STATIC_NAMES, moving_names: Sequence[str] = MOVING_NAMES
) -> dict[str, object]:
    """Scores of a binary mask from a (trainId × [removed, kept]) confusion.

    dynamic_iou: removed vs moving objects, over pixels that are static or moving (sky and other
    non-static, non-moving classes are meant to be removed too, so they neither help nor hurt it);
    nonstatic_iou: removed vs everything not static, sky included; static_iou: kept vs static.
    """
    static = [TRAIN_ID_NAMES.index(n) for n in static_names]
    moving = [TRAIN_ID_NAMES.index(n) for n in moving_names]
    nonstatic = [c for c in range(NUM_CLASSES) if c not in static]
    removed, kept, total = counts[:, REMOVED], counts[:, KEPT], counts.sum(1)
    sky = TRAIN_ID_NAMES.index("sky")
    return {
        "dynamic_iou": _ratio(removed[moving].sum(), total[moving].sum() + removed[static].sum()),
        "nonstatic_iou": _ratio(removed[nonstatic].sum(), total[nonstatic].sum() + removed[static].sum()),
        "static_iou": _ratio(kept[static].sum(), total[static].sum() + kept[nonstatic].sum()),
        "dynamic_removed": _ratio(removed[moving].sum(), total[moving].sum()),
        "static_removed": _ratio(removed[static].sum(), total[static].sum()),
        "sky_removed": _ratio(removed[sky], total[sky]),
        "removed_by_class": {TRAIN_ID_NAMES[c]: _ratio(removed[c], total[c]) for c in range(NUM_CLASSES) if total[c]},
    }


def binary_pred(static_prob: Tensor, threshold: float = 0.5) -> Tensor:
    """A static probability map as [removed, kept] labels (the project's mask keeps prob ≥ 0.5)."""
    return torch.where(static_prob >= threshold, KEPT, REMOVED)
