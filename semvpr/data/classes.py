"""Cityscapes class table: labelIds → 19 trainIds, and the static / dynamic split of the masks (ARCHITECTURE §3.2)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from semvpr.core.errors import SemvprError

IGNORE = 255

#: The 19 Cityscapes evaluation classes, indexed by trainId.
TRAIN_ID_NAMES: tuple[str, ...] = (
    "road",
    "sidewalk",
    "building",
    "wall",
    "fence",
    "pole",
    "traffic light",
    "traffic sign",
    "vegetation",
    "terrain",
    "sky",
    "person",
    "rider",
    "car",
    "truck",
    "bus",
    "train",
    "motorcycle",
    "bicycle",
)

#: Classes whose features describe the place (ARCHITECTURE §3.2); everything else is dynamic/uninformative.
NUM_CLASSES = len(TRAIN_ID_NAMES)
STATIC_NAMES: tuple[str, ...] = TRAIN_ID_NAMES[:10]
DYNAMIC_NAMES: tuple[str, ...] = TRAIN_ID_NAMES[10:]

# Cityscapes labelId → trainId (labels.py of the cityscapesScripts); unlisted ids are ignored.
_LABEL_TO_TRAIN = {
    label: train
    for train, label in enumerate((7, 8, 11, 12, 13, 17, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 31, 32, 33))
}
TRAIN_TO_LABEL: tuple[int, ...] = tuple(sorted(_LABEL_TO_TRAIN, key=_LABEL_TO_TRAIN.get))

LABEL_TO_TRAIN_LUT = np.full(256, IGNORE, dtype=np.uint8)
for _label, _train in _LABEL_TO_TRAIN.items():
    LABEL_TO_TRAIN_LUT[_label] = _train


def label_ids_to_train_ids(label_ids: np.ndarray) -> np.ndarray:
    """Map a Cityscapes labelIds image to trainIds (255 = ignore)."""
    return LABEL_TO_TRAIN_LUT[label_ids.astype(np.uint8)]


def train_ids_to_label_ids(train_ids: np.ndarray) -> np.ndarray:
    """Map trainIds back to Cityscapes labelIds (ignore → 0, 'unlabeled')."""
    lut = np.zeros(256, dtype=np.uint8)
    lut[: len(TRAIN_TO_LABEL)] = TRAIN_TO_LABEL
    return lut[train_ids.astype(np.uint8)]


def static_lut(static_names: tuple[str, ...] | list[str] = STATIC_NAMES) -> np.ndarray:
    """Lookup table trainId → 1.0 (static) / 0.0 (dynamic or ignore), length 256."""
    unknown = set(static_names) - set(TRAIN_ID_NAMES)
    if unknown:
        raise SemvprError(f"unknown static class names {sorted(unknown)}; known: {TRAIN_ID_NAMES}")
    lut = np.zeros(256, dtype=np.float32)
    for name in static_names:
        lut[TRAIN_ID_NAMES.index(name)] = 1.0
    return lut


def check_class_names(names: Sequence[str], where: str, *, empty: bool = False) -> None:
    """A list of Cityscapes class names (``empty``: may be empty), each once: a static list that keeps
    nothing would make every mask empty without a word."""
    if not isinstance(names, list | tuple) or (not names and not empty):
        raise SemvprError(f"{where}={names!r}: expected a non-empty list of Cityscapes class names")
    unknown = [n for n in names if not isinstance(n, str) or n not in TRAIN_ID_NAMES]
    if unknown:
        raise SemvprError(f"{where}: {unknown[0]!r} is not a Cityscapes class name ({', '.join(TRAIN_ID_NAMES)})")
    if len(set(names)) != len(names):
        raise SemvprError(f"{where}={list(names)!r} names a class twice")


#: The colour of each trainId in Cityscapes' own label images (cityscapesScripts ``labels.py``), for label PNGs.
TRAIN_ID_COLOURS: tuple[tuple[int, int, int], ...] = (
    (128, 64, 128),
    (244, 35, 232),
    (70, 70, 70),
    (102, 102, 156),
    (190, 153, 153),
    (153, 153, 153),
    (250, 170, 30),
    (220, 220, 0),
    (107, 142, 35),
    (152, 251, 152),
    (70, 130, 180),
    (220, 20, 60),
    (255, 0, 0),
    (0, 0, 142),
    (0, 0, 70),
    (0, 60, 100),
    (0, 80, 100),
    (0, 0, 230),
    (119, 11, 32),
)
