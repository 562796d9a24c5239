"""Images as every stage reads them: decoded whole (a corrupt file fails with its name), RGB in
[0, 1], resized to [H, W] where asked, and a dataset of image files for batched passes."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch.utils.data import Dataset

from semvpr.core.errors import SemvprError

#: [H, W] as a config gives it.
Size = tuple[int, int] | list[int]


def open_image(path: Path, what: str) -> Image.Image:
    """Open and decode fully, so truncated files fail here with their name, not deep in a worker."""
    try:
        img = Image.open(path)
        img.load()
    except FileNotFoundError:
        raise SemvprError(f"{what} {path} not found") from None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as err:
        raise SemvprError(f"{what} {path} is unreadable or corrupt ({err})") from None
    return img


def hw_of(size: Size | None) -> tuple[int, int] | None:
    if size is None:
        return None
    h, w = (int(v) for v in size)
    return h, w


def load_image(path: str | Path, size: Size | None = None) -> torch.Tensor:
    """(3,H,W) float RGB in [0,1]; `size` = [H, W] resizes bilinearly (antialiased)."""
    img = open_image(Path(path), "image").convert("RGB")
    hw = hw_of(size)
    if hw is not None and img.size != (hw[1], hw[0]):
        img = img.resize((hw[1], hw[0]), Image.BILINEAR)
    return torch.from_numpy(np.asarray(img).copy()).permute(2, 0, 1).float().div_(255.0)


class ImageDataset(Dataset):
    """Images from paths as (image (3,H,W) float [0,1], index)."""

    def __init__(self, paths: Sequence[str | Path], image_size: Size | None) -> None:
        self.paths = [Path(p) for p in paths]
        self.image_size = image_size

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, int]:
        return load_image(self.paths[index], self.image_size), index
