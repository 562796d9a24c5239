"""Segmentation scores on a hand-built label map whose IoUs are worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchmetrics.classification import MulticlassJaccardIndex

from semvpr.data.classes import TRAIN_ID_NAMES
from semvpr.segmentation.confusion import Confusion, binary_pred, class_iou, class_scores, mask_scores

ROAD, BUILDING, SKY, PERSON, CAR, X = 0, 2, 10, 11, 13, 255
GT = torch.tensor(
    [[ROAD, ROAD, ROAD, ROAD], [ROAD, ROAD, SKY, SKY], [CAR, CAR, BUILDING, BUILDING], [PERSON, X, BUILDING, BUILDING]]
)
PRED = torch.tensor(
    [[ROAD, ROAD, ROAD, ROAD], [ROAD, CAR, SKY, SKY], [CAR, ROAD, BUILDING, BUILDING], [CAR, CAR, BUILDING, SKY]]
)
R, K = 0, 1  # removed, kept
KEEP = torch.tensor([[K, K, K, R], [K, K, R, R], [R, K, K, K], [R, R, K, R]])


def test_class_iou_by_hand() -> None:
    conf = Confusion()
    conf.update(PRED, GT)
    assert conf.counts.sum() == 15  # the ignore pixel is not scored, whatever was predicted there
    scores = class_scores(conf.counts, [ROAD, BUILDING, SKY, PERSON, CAR])
    iou = scores["class_iou"]
    assert iou["road"] == pytest.approx(5 / 7)  # 5 agree; 6 labelled + 6 predicted - 5
    assert iou["building"] == pytest.approx(3 / 4)
    assert iou["sky"] == pytest.approx(2 / 3)
    assert iou["car"] == pytest.approx(1 / 4)  # 1 agrees; 2 labelled, 3 predicted on scored pixels
    assert iou["person"] == 0.0
    assert scores["miou"] == pytest.approx((5 / 7 + 3 / 4 + 2 / 3 + 0 + 1 / 4) / 5)
    # person mistaken for car still counts for the moving class: 2 of 3 labelled, 3 predicted
    assert scores["moving_iou"] == pytest.approx(2 / 4)
    assert scores["pixel_accuracy"] == pytest.approx(11 / 15)
    assert np.isnan(class_iou(conf.counts)[TRAIN_ID_NAMES.index("bus")])  # absent from labels and predictions


def test_mask_scores_by_hand() -> None:
    conf = Confusion(2)
    conf.update(KEEP, GT)
    s = mask_scores(conf.counts)
    assert s["static_removed"] == pytest.approx(2 / 10)  # road and building each lose a pixel
    assert s["dynamic_removed"] == pytest.approx(2 / 3)  # one car pixel kept
    assert s["sky_removed"] == 1.0
    # sky pixels neither help nor hurt the moving-object IoU: 2 / (3 moving + 2 static removed)
    assert s["dynamic_iou"] == pytest.approx(2 / 5)
    assert s["nonstatic_iou"] == pytest.approx(4 / 7)  # 4 of 5 non-static removed, 2 static removed
    assert s["static_iou"] == pytest.approx(8 / 11)  # 8 static kept; 10 static + 1 kept car pixel
    assert s["removed_by_class"] == pytest.approx(
        {"road": 1 / 6, "building": 1 / 4, "sky": 1.0, "person": 1.0, "car": 0.5}
    )


def test_all_static_mask_scores_zero_on_moving_objects() -> None:
    conf = Confusion(2)
    conf.update(torch.ones_like(GT), GT)
    s = mask_scores(conf.counts)
    assert s["static_iou"] == pytest.approx(10 / 15) and s["dynamic_iou"] == 0.0 and s["static_removed"] == 0.0


def test_binary_pred_threshold() -> None:
    assert binary_pred(torch.tensor([0.2, 0.5, 0.9])).tolist() == [R, K, K]


def test_class_iou_matches_torchmetrics_on_random_maps() -> None:
    gen = torch.Generator().manual_seed(0)
    target = torch.randint(0, 19, (3, 17, 23), generator=gen)
    target[:, :3] = X
    pred = torch.where(
        torch.rand(target.shape, generator=gen) < 0.6,
        target.clamp(max=18),
        torch.randint(0, 19, target.shape, generator=gen),
    )
    conf = Confusion()
    conf.update(pred[:2], target[:2])
    conf.update(pred[2:], target[2:])  # accumulates over batches
    reference = MulticlassJaccardIndex(19, ignore_index=X, average="none")(pred, target)
    np.testing.assert_allclose(class_iou(conf.counts), reference.numpy(), rtol=1e-6)
