"""Images as every stage reads them: decoded whole (a corrupt file fails with its name), RGB in
[0, 1], resized to [H, W] where asked (:data:`RESIZES`), and a dataset of image files for batched passes.

Only regular files are opened (a FIFO named ``.jpg`` would block the reader forever), and only 8-bit
images are decoded: a 16-bit or float image (PIL modes ``I``, ``I;16*``, ``F``: a 16-bit PNG, a float
TIFF) has no single right mapping to [0, 1] (PIL's RGB conversion saturates or blacks it out), so it is
refused in one line naming the file; convert it to 8 bits first.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch.utils.data import Dataset

from semvpr.core.errors import SemvprError

#: [H, W] as a config gives it.
Size = tuple[int, int] | list[int]

#: How an image is resized to the size a model sees: ``bilinear``, PIL's bilinear (antialiased when it shrinks:
#: torchvision's ``Resize`` on a PIL image, most authors' test transform); ``bicubic``, torch's bicubic with
#: antialiasing on the [0, 1] tensor (Bag-of-Queries' ``ToTensor`` then ``Resize(BICUBIC, antialias=True)``).
RESIZES = ("bilinear", "bicubic")


#: PIL modes of 8-bit images, which convert to RGB without loss of meaning.
EIGHT_BIT_MODES = frozenset(
    {"1", "L", "LA", "La", "P", "PA", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr", "LAB", "HSV"}
)


def open_image(path: Path, what: str) -> Image.Image:
    """Open and decode fully, so truncated files fail here with their name, not deep in a worker; only
    a regular file is opened."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise SemvprError(f"{what} {path} is not a regular file (a folder, FIFO or device)")
        img = Image.open(path)
        img.load()
    except FileNotFoundError:
        raise SemvprError(f"{what} {path} not found") from None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as err:
        raise SemvprError(f"{what} {path} is unreadable or corrupt ({' '.join(str(err).split())})") from None
    return img


def eight_bit_rgb(img: Image.Image, name: str | Path) -> Image.Image:
    """``img`` as 8-bit RGB (grey, palette, alpha and CMYK images converted as PIL converts them); a 16-bit or
    float image is refused in one line naming it (``name``: its file)."""
    if img.mode not in EIGHT_BIT_MODES:
        raise SemvprError(
            f"image {name} has PIL mode {img.mode} (16-bit or float pixels); semvpr reads 8-bit images: "
            f"convert it to 8 bits per channel"
        )
    return img.convert("RGB")


class EightBitRGB:
    """A transform step: a PIL image as :func:`eight_bit_rgb` makes it (named by its file where it has one);
    anything else passed on unchanged, for the next steps to take or refuse."""

    def __call__(self, img: object) -> object:
        if not isinstance(img, Image.Image):
            return img
        return eight_bit_rgb(img, getattr(img, "filename", "") or "(a PIL image)")

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def hw_of(size: Size | None) -> tuple[int, int] | None:
    if size is None:
        return None
    h, w = (int(v) for v in size)
    return h, w


def read_image(path: str | Path, size: Size | None = None, resize: str = "bilinear") -> torch.Tensor:
    """(3,H,W) RGB at ``size`` = [H, W] resized as ``resize`` says (:data:`RESIZES`): its 8-bit values (uint8)
    where it keeps them (no resize, or PIL's bilinear), floats in [0, 1] where bicubic resizing makes new ones.
    :func:`to_unit` makes either the floats :func:`load_image` gives, on any device (a quarter of the bytes
    copied)."""
    img = eight_bit_rgb(open_image(Path(path), "image"), path)
    hw = hw_of(size)
    if hw is None or img.size == (hw[1], hw[0]):
        return _eight_bits(img)
    if resize == "bilinear":
        return _eight_bits(img.resize((hw[1], hw[0]), Image.BILINEAR))
    unit = to_unit(_eight_bits(img))[None]
    return F.interpolate(unit, size=hw, mode="bicubic", antialias=True, align_corners=False)[0]


def load_image(path: str | Path, size: Size | None = None, resize: str = "bilinear") -> torch.Tensor:
    """(3,H,W) float RGB in [0,1]; `size` = [H, W] resizes it as ``resize`` says (:data:`RESIZES`)."""
    return to_unit(read_image(path, size, resize))


def to_unit(images: torch.Tensor) -> torch.Tensor:
    """Images as floats in [0, 1]: 8-bit values divided by 255 (the same bits on every device: IEEE division),
    floats as they are."""
    return images.float().div_(255.0) if images.dtype == torch.uint8 else images


def _eight_bits(img: Image.Image) -> torch.Tensor:
    """An RGB image as (3,H,W) uint8."""
    return torch.from_numpy(np.asarray(img).copy()).permute(2, 0, 1)


@dataclass(frozen=True)
class Reading:
    """How a pass reads a set's images: the size a model sees them at, images per batch, loader workers."""

    image_size: Sequence[int]
    batch_size: int = 8
    num_workers: int = 2


class ImageDataset(Dataset):
    """Images from paths as (image (3,H,W) float [0,1], index), at ``image_size`` resized as ``resize`` says;
    ``eight_bit``: as :func:`read_image` gives them (uint8 where resizing keeps 8 bits), for :func:`to_unit` to
    make floats on the device they are copied to."""

    def __init__(
        self, paths: Sequence[str | Path], image_size: Size | None, resize: str = "bilinear", eight_bit: bool = False
    ) -> None:
        self.paths = [Path(p) for p in paths]
        self.image_size = image_size
        self.resize = resize
        self.read = read_image if eight_bit else load_image

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, int]:
        return self.read(self.paths[index], self.image_size, self.resize), index
