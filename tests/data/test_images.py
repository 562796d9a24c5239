"""Reading images: 8-bit values copied as they are and made floats on the device, the same floats everywhere."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.data.images import ImageDataset, load_image, read_image, to_unit
from tests.helpers import write_image


@pytest.mark.parametrize(
    ("size", "resize", "dtype"),
    [(None, "bilinear", torch.uint8), ((24, 32), "bilinear", torch.uint8), ((24, 32), "bicubic", torch.float32)],
    ids=["as stored", "bilinear", "bicubic"],
)
def test_an_image_read_as_eight_bits_gives_the_floats_it_loads_as(
    tmp_path: Path, size: tuple[int, int] | None, resize: str, dtype: torch.dtype
) -> None:
    write_image(tmp_path / "a.png", 3)
    raw = read_image(tmp_path / "a.png", size, resize)
    assert raw.dtype == dtype and raw.shape == (3, *(size or (48, 64)))
    loaded = load_image(tmp_path / "a.png", size, resize)
    assert loaded.dtype == torch.float32 and torch.equal(to_unit(raw), loaded)
    if size is None:  # the file's own values, channel first, divided by 255
        pixels = torch.from_numpy(np.asarray(Image.open(tmp_path / "a.png"))).permute(2, 0, 1)
        assert torch.equal(raw, pixels) and torch.equal(loaded, pixels.float() / 255)
    dataset = ImageDataset([tmp_path / "a.png"], size, resize, eight_bit=True)
    assert torch.equal(dataset[0][0], raw) and torch.equal(
        ImageDataset([tmp_path / "a.png"], size, resize)[0][0], loaded
    )


def test_floats_pass_through_to_unit_unchanged() -> None:
    images = torch.rand(2, 3, 4, 5)
    assert to_unit(images) is images
    assert torch.equal(to_unit(torch.tensor([0, 51, 255], dtype=torch.uint8)), torch.tensor([0.0, 0.2, 1.0]))
