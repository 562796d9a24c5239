"""Mask sources' grid masks: binary is the seed's filter; learned class weights get gradients and move."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.data.classes import STATIC_NAMES, TRAIN_ID_NAMES
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.masks import ClassWeights, OracleMask, weighted_classes
from semvpr.retrieval.losses import triplet_loss


def _labels(tmp_path: Path, n: int = 2) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        ids = rng.choice([0, 2, 8, 10, 13, 255], size=(24, 32)).astype(np.uint8)
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray(ids).save(paths[-1])
    return paths


def test_binary_oracle_is_the_thresholded_static_fraction(tmp_path: Path) -> None:
    paths = _labels(tmp_path)
    ids = np.stack([np.asarray(Image.open(p)) for p in paths])
    # The seed's filter, by hand: static pixels (trainIds 0..9) area-pooled to the grid, >= 0.5.
    static = torch.from_numpy((ids < 10).astype(np.float32))[:, None]
    expected = (torch.nn.functional.adaptive_avg_pool2d(static, (3, 4)) >= 0.5).float()
    oracle = OracleMask(STATIC_NAMES)
    images = torch.zeros(2, 3, 24, 32)
    assert torch.equal(oracle.grid_mask(images, [], paths, (3, 4), "binary"), expected)
    classes = oracle.grid_mask(images, [], paths, (3, 4), "learned")
    assert classes.shape == (2, len(TRAIN_ID_NAMES), 3, 4)
    # Class fractions per cell; ignore pixels (255) belong to no class.
    known = torch.from_numpy((ids != 255).astype(np.float32))[:, None]
    torch.testing.assert_close(classes.sum(1, keepdim=True), torch.nn.functional.adaptive_avg_pool2d(known, (3, 4)))


def _pooled_one_hot(ids: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
    """Each class's pixel share in each adaptive-pooling window (floor(i·H/h) to ceil((i+1)·H/h)), from one-hot
    class maps, by loops in float64: (B,C,h,w)."""
    one_hot = (ids[:, None] == np.arange(len(TRAIN_ID_NAMES))[None, :, None, None]).astype(np.float64)
    (height, width), (h, w) = ids.shape[1:], grid_hw
    out = np.zeros((*one_hot.shape[:2], h, w))
    for i in range(h):
        for j in range(w):
            rows = slice(i * height // h, -(-(i + 1) * height // h))
            cols = slice(j * width // w, -(-(j + 1) * width // w))
            out[:, :, i, j] = one_hot[:, :, rows, cols].mean((2, 3))
    return out


@pytest.mark.parametrize("size, grid", [((24, 32), (3, 4)), ((27, 48), (5, 7)), ((11, 13), (11, 13)), ((9, 7), (1, 1))])
def test_learned_oracle_counts_class_shares_without_one_hot_maps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, size: tuple[int, int], grid: tuple[int, int]
) -> None:
    """The learned oracle's grid mask is each cell's class shares, as pooling one-hot class maps gives (windows
    overlapping where the grid does not divide the image), and the weighted map of any class weights with it;
    no (B,C,H,W) one-hot tensor is made."""
    rng = np.random.default_rng(1)
    paths = []
    for i in range(3):
        ids = rng.choice([0, 2, 8, 10, 11, 13, 18, 255], size=size).astype(np.uint8)
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray(ids).save(paths[-1])
    ids = np.stack([np.asarray(Image.open(p)) for p in paths])
    monkeypatch.setattr(torch.nn.functional, "one_hot", lambda *a, **k: pytest.fail("a one-hot map was built"))
    shares = OracleMask(STATIC_NAMES).grid_mask(None, [], paths, grid, "learned")
    expected = _pooled_one_hot(ids, grid)
    assert shares.dtype == torch.float32 and shares.shape == expected.shape
    torch.testing.assert_close(shares.double(), torch.from_numpy(expected), rtol=0, atol=1e-7)
    weights = torch.from_numpy(rng.uniform(0, 1, len(TRAIN_ID_NAMES)))
    weighted = np.einsum("bchw,c->bhw", expected, weights.numpy())[:, None]
    torch.testing.assert_close(
        weighted_classes(shares, weights.float()).double(), torch.from_numpy(weighted), rtol=0, atol=1e-6
    )


def test_class_weights_start_binary_and_weight_each_location() -> None:
    weights = ClassWeights(STATIC_NAMES, init_logit=4.0)
    w = weights.weights
    assert (w[:10] > 0.98).all() and (w[10:] < 0.02).all()
    probs = torch.zeros(1, len(TRAIN_ID_NAMES), 1, 2)
    probs[0, 2, 0, 0] = 1.0  # a building cell
    probs[0, 8, 0, 1], probs[0, 13, 0, 1] = 0.5, 0.5  # half vegetation, half car
    out = weights(probs)
    torch.testing.assert_close(out[0, 0, 0], torch.stack([w[2], 0.5 * w[8] + 0.5 * w[13]]))
    assert weights.named_weights()["building"] == float(w[2])


def test_learned_class_weights_receive_gradients_and_move() -> None:
    torch.manual_seed(0)
    layer = NetVLAD(num_clusters=4, dim=16)
    layer.init_from_features(torch.randn(500, 16), seed=0)
    weights = ClassWeights(STATIC_NAMES, init_logit=2.0)
    local = torch.randn(6, 16, 3, 4)
    probs = torch.softmax(torch.randn(6, len(TRAIN_ID_NAMES), 3, 4), dim=1)
    tuples = torch.tensor([[0, 1, 2, 3], [4, 5, -1, -1]])
    start = weights.theta.detach().clone()
    optimizer = torch.optim.Adam(weights.parameters(), lr=0.05)
    for _ in range(5):
        optimizer.zero_grad()
        triplet_loss(layer(local, weights(probs)), tuples, margin=0.1).backward()
        assert weights.theta.grad is not None and weights.theta.grad.abs().sum() > 0
        optimizer.step()
    assert (weights.theta - start).abs().max() > 0.1
