"""A tiny CamVid in the SegNet layout: sky over building over road with a car, colour tells the class."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

# CamVid label indices of the scene and their colours.
SKY, BUILDING, ROAD, CAR, UNLABELLED = 0, 1, 3, 8, 11
COLOURS = {SKY: (70, 130, 180), BUILDING: (90, 90, 90), ROAD: (128, 64, 128), CAR: (0, 0, 200), UNLABELLED: (0, 0, 0)}


def scene(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """An RGB image and its CamVid label map (with an unlabelled corner)."""
    ids = np.full((h, w), SKY, np.uint8)
    ids[h // 4 :] = BUILDING
    ids[h // 2 :] = ROAD
    x = int(rng.integers(0, w // 2))
    ids[h // 2 : h // 2 + h // 4, x : x + w // 3] = CAR
    ids[:2, :2] = UNLABELLED
    img = np.zeros((h, w, 3), np.float32)
    for c, colour in COLOURS.items():
        img[ids == c] = colour
    img += rng.normal(0, 8, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), ids


def write_camvid(
    root: Path, sizes: dict[str, int] | None = None, hw: tuple[int, int] = (36, 48), absolute_lists: bool = False
) -> Path:
    """``root/{split}/*.png``, ``root/{split}annot/*.png`` and ``root/{split}.txt``; lists in SegNet's
    original absolute form (/SegNet/CamVid/...) when ``absolute_lists``."""
    rng = np.random.default_rng(0)
    for split, n in (sizes or {"train": 6, "val": 2, "test": 3}).items():
        (root / split).mkdir(parents=True)
        (root / f"{split}annot").mkdir()
        lines = []
        for i in range(n):
            name = f"0001TP_{i:06d}.png"
            img, ids = scene(rng, *hw)
            Image.fromarray(img).save(root / split / name)
            Image.fromarray(ids).save(root / f"{split}annot" / name)
            prefix = "/SegNet/CamVid/" if absolute_lists else ""
            lines.append(f"{prefix}{split}/{name} {prefix}{split}annot/{name}")
        (root / f"{split}.txt").write_text("\n".join(lines) + "\n")
    return root
