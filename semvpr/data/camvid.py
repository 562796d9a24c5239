"""CamVid in the SegNet layout (``{split}/``, ``{split}annot/``, ``{split}.txt``), labels mapped to Cityscapes
trainIds."""

from __future__ import annotations

from pathlib import Path

from semvpr.core.errors import SemvprError
from semvpr.core.io import read_list_text, regular_file
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES
from semvpr.data.places import dataset_root, listed_image
from semvpr.data.segmentation import SegmentationSet, check_pair

#: SegNet's 11 CamVid classes by label index; index 11 is Unlabelled (ignored).
CAMVID_NAMES: tuple[str, ...] = (
    "Sky",
    "Building",
    "Pole",
    "Road",
    "Pavement",
    "Tree",
    "SignSymbol",
    "Fence",
    "Car",
    "Pedestrian",
    "Bicyclist",
)

#: CamVid class → Cityscapes class. Bus and truck are folded into Car in this version; a Bicyclist
#: label covers rider and bicycle, and rider is the closer Cityscapes class (both are moving classes).
CAMVID_TO_CITYSCAPES: dict[str, str] = {
    "Sky": "sky",
    "Building": "building",
    "Pole": "pole",
    "Road": "road",
    "Pavement": "sidewalk",
    "Tree": "vegetation",
    "SignSymbol": "traffic sign",
    "Fence": "fence",
    "Car": "car",
    "Pedestrian": "person",
    "Bicyclist": "rider",
}


def camvid_lut() -> tuple[int, ...]:
    """256-entry CamVid label index → Cityscapes trainId table (Unlabelled and unknown ids → 255)."""
    lut = [IGNORE] * 256
    for index, name in enumerate(CAMVID_NAMES):
        lut[index] = TRAIN_ID_NAMES.index(CAMVID_TO_CITYSCAPES[name])
    return tuple(lut)


def _listed(root: Path, entry: str, listing: Path) -> Path:
    """A split-list path under ``root``: SegNet's lists hold absolute paths (/SegNet/CamVid/train/x.png),
    so only the last two components (folder and file) are kept, under the rule every list reader shares
    (``places.listed_image``)."""
    path = Path(entry)
    return listed_image(root, f"{path.parent.name}/{path.name}".lstrip("/"), listing)


def read_camvid(root: str | Path, split: str, key: str = "seg.root") -> SegmentationSet:
    """The image / label pairs listed in ``<root>/<split>.txt``, checked to exist and to agree in size; a bad
    root is one line naming the setting it came from (``key``)."""
    root = dataset_root(root, "CamVid root", key, f"{split}/, {split}annot/ and {split}.txt (SegNet layout)")
    listing = root / f"{split}.txt"
    if not regular_file(listing, "CamVid split list"):
        raise SemvprError(
            f"CamVid split list {listing} not found; {key} must hold {split}.txt with lines "
            f"'{split}/<name>.png {split}annot/<name>.png' (SegNet layout)"
        )
    images, labels = [], []
    for number, line in enumerate(read_list_text(listing, "CamVid split list").splitlines(), start=1):
        if not line.strip():
            continue
        entries = line.split()
        if len(entries) != 2:
            raise SemvprError(f"{listing}:{number}: expected '<image> <label map>', got {line.strip()!r}")
        image, label = (_listed(root, e, listing) for e in entries)
        for path, what in ((image, "image"), (label, "label map")):
            if not regular_file(path, f"{listing}:{number}: {what}"):
                raise SemvprError(f"{listing}:{number}: {what} {path} is missing")
        check_pair(image, label)  # headers only: a wrong or truncated file fails here, named, not in a worker
        images.append(image)
        labels.append(label)
    if not images:
        raise SemvprError(f"CamVid split list {listing} lists no images")
    seg = SegmentationSet(images=tuple(images), labels=tuple(labels), label_lut=camvid_lut())
    seg.check_labelled(f"CamVid split {listing}")
    return seg
