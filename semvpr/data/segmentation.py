"""Cityscapes-format segmentation sets and their label maps (trainIds)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.core.io import regular_file
from semvpr.data.classes import IGNORE, LABEL_TO_TRAIN_LUT, TRAIN_ID_NAMES
from semvpr.data.images import Size, hw_of, load_image, open_image

IMAGE_SUFFIX = "_leftImg8bit.png"
#: PIL modes of a label map: one channel of ids.
LABEL_MODES = ("L", "P", "I", "I;16", "I;16B", "I;16L")
LABEL_SUFFIX = "_gtFine_labelIds.png"


@dataclass(frozen=True)
class SegmentationSet:
    """Paired images and label PNGs (same order): Cityscapes labelIds, or the set's own ids via ``label_lut``."""

    images: tuple[Path, ...]
    labels: tuple[Path, ...]
    #: 256 entries, label-map id → trainId (255 ignore), for sets not in Cityscapes ids (e.g. CamVid).
    label_lut: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "images", tuple(Path(p) for p in self.images))
        object.__setattr__(self, "labels", tuple(Path(p) for p in self.labels))
        if len(self.images) != len(self.labels):
            raise SemvprError(f"segmentation set has {len(self.images)} images but {len(self.labels)} labels")
        if self.label_lut is not None:
            object.__setattr__(self, "label_lut", tuple(int(v) for v in self.label_lut))
            if len(self.label_lut) != 256:
                raise SemvprError(f"label_lut has {len(self.label_lut)} entries; it maps all 256 8-bit ids")

    def __len__(self) -> int:
        return len(self.images)

    def check_labelled(self, what: str) -> None:
        """Raise unless some label map holds a pixel of a known class: a split of only unknown or ignored
        ids would train or score nothing. Reads label maps until the first such pixel (usually one)."""
        for label in self.labels:
            if (load_train_ids(label, from_label_ids=True, lut=self.label_lut) != IGNORE).any():
                return
        raise SemvprError(
            f"{what}: none of its {len(self.labels)} label maps holds a pixel of a known class (every id is "
            "unknown or ignored); check the label maps are the set's own ids"
        )


def read_cityscapes(root: str | Path, split: str) -> SegmentationSet:
    """Pair leftImg8bit/<split>/<city>/*_leftImg8bit.png with gtFine/.../*_gtFine_labelIds.png."""
    root = Path(root).expanduser()
    image_dir = root / "leftImg8bit" / split
    if not image_dir.is_dir():
        raise SemvprError(
            f"Cityscapes images {image_dir} not found; set the segmentation root to the "
            f"folder holding leftImg8bit/ and gtFine/"
        )
    images = sorted(image_dir.glob(f"*/*{IMAGE_SUFFIX}"))
    if not images:
        raise SemvprError(f"{image_dir}: no <city>/*{IMAGE_SUFFIX} images")
    labels = []
    for image in images:
        stem = image.name[: -len(IMAGE_SUFFIX)]
        label = root / "gtFine" / split / image.parent.name / f"{stem}{LABEL_SUFFIX}"
        if not regular_file(label, f"{image}: label map"):
            raise SemvprError(f"{image}: label map {label} is missing")
        labels.append(label)
    seg = SegmentationSet(images=tuple(images), labels=tuple(labels))
    seg.check_labelled(f"Cityscapes {split} split under {root}")
    return seg


def load_train_ids(
    path: str | Path,
    size: Size | None = None,
    *,
    from_label_ids: bool,
    image: str | Path | None = None,
    lut: Sequence[int] | None = None,
) -> torch.Tensor:
    """(H,W) long trainIds from a labelIds PNG (from_label_ids=True), a trainId PNG, or any ids via ``lut``
    (256 entries; overrides from_label_ids); nearest resize."""
    path = Path(path)
    if image is not None:
        check_pair(image, path)
    img = open_image(path, "label map")
    if img.mode not in LABEL_MODES:
        raise SemvprError(f"label map {path} has mode {img.mode}; expected a single-channel PNG of ids")
    hw = hw_of(size)
    if hw is not None and img.size != (hw[1], hw[0]):
        img = img.resize((hw[1], hw[0]), Image.NEAREST)  # nearest: ids must never be blended
    ids = np.asarray(img).astype(np.int64)
    if lut is not None:
        ids = np.where((ids >= 0) & (ids < 256), np.asarray(lut, dtype=np.int64)[np.clip(ids, 0, 255)], IGNORE)
    elif from_label_ids:
        ids = np.where((ids >= 0) & (ids < 256), LABEL_TO_TRAIN_LUT[np.clip(ids, 0, 255)], IGNORE)
    else:
        # Anything that is not a trainId would crash a cross-entropy with ignore_index=255.
        ids = np.where((ids >= 0) & (ids < len(TRAIN_ID_NAMES)), ids, IGNORE)
    return torch.from_numpy(ids.astype(np.int64))


def check_pair(image: str | Path, label: str | Path) -> None:
    """Raise if a label map's size differs from its image's, or it is not one channel of ids (reads headers
    only)."""
    sizes, modes = [], []
    for path in (Path(image), Path(label)):
        try:
            with Image.open(path) as img:
                sizes.append(img.size)
                modes.append(img.mode)
        except FileNotFoundError:
            raise SemvprError(f"{path} not found") from None
        except (OSError, ValueError, SyntaxError) as err:
            raise SemvprError(f"{path} is unreadable or corrupt ({err})") from None
    if modes[1] not in LABEL_MODES:
        raise SemvprError(f"label map {label} has mode {modes[1]}; expected a single-channel PNG of ids")
    if sizes[0] != sizes[1]:
        (iw, ih), (lw, lh) = sizes
        raise SemvprError(f"label map {label} is {lh}x{lw} but its image {image} is {ih}x{iw} (HxW)")


def load_pair(
    image: str | Path,
    label: str | Path,
    size: Size | None = None,
    *,
    from_label_ids: bool,
    lut: Sequence[int] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Image (3,H,W) and trainIds (H,W), after checking their native sizes agree."""
    return load_image(image, size), load_train_ids(label, size, from_label_ids=from_label_ids, image=image, lut=lut)
