"""The drawn predictions: each tile's mask shading and captions, on images whose pixels are known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from semvpr.data.places import PlaceSet
from semvpr.reporting.prediction_images import CAPTION, DIM, FRAME, THUMB_H, drawn_queries, write_prediction_images


def _grey(path: Path, value: int) -> Path:
    Image.fromarray(np.full((60, 80, 3), value, np.uint8)).save(path)
    return path


def test_a_mask_darkens_what_it_weights_down_and_leaves_the_rest(tmp_path: Path) -> None:
    db = tuple(_grey(tmp_path / f"db{j}.png", 200) for j in range(2))
    q = (_grey(tmp_path / "q0.png", 200),)
    places = PlaceSet("s", db, q, np.array([[0.0, 0.0], [30.0, 40.0]]), np.array([[0.0, 0.0]]))
    left_out = np.ones((3, 4), np.float32)
    left_out[:, :2] = 0  # the left half weighted by 0
    names = write_prediction_images(
        tmp_path,
        places,
        [0],
        np.array([[1, 0]]),
        np.array([[0.5, 0.7]]),
        [np.array([0])],
        (60, 80),
        lambda side, i: left_out if side == "q" else None,
    )
    assert names == ["predictions/0.jpg"]
    image = np.asarray(Image.open(tmp_path / names[0]).convert("L"), dtype=float)
    width = round(THUMB_H * 80 / 60)
    top = CAPTION + FRAME + THUMB_H // 2
    left, right = image[top, FRAME + width // 4], image[top, FRAME + 3 * width // 4]
    assert abs(left - 200 * (1 - DIM)) < 8 and abs(right - 200) < 8, (left, right)
    second = FRAME + width + 2 * FRAME + 8  # the first retrieval's tile: no mask, unshaded
    assert abs(image[top, second + FRAME + width // 4] - 200) < 8


def test_drawn_queries_spread_over_the_set_or_over_its_misses() -> None:
    right = np.array([True, False, True, False, False, True, True, False])
    assert drawn_queries(right, 3, only_wrong=False).tolist() == [0, 4, 7]
    assert drawn_queries(right, 2, only_wrong=True).tolist() == [1, 7]
    assert drawn_queries(right, 10, only_wrong=True).tolist() == [1, 3, 4, 7]
    assert drawn_queries(np.ones(4, bool), 3, only_wrong=True).tolist() == []
