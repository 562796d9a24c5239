"""CamVid reader: pairing from the split lists, the label table, and one-line errors."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.data.camvid import CAMVID_NAMES, camvid_lut, read_camvid
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES
from semvpr.segmentation.datamodule import SegmentationDataset, split_set
from semvpr.segmentation.training import dataset_identity
from tests.camvid_fixture import write_camvid


def test_label_table_maps_onto_cityscapes_train_ids() -> None:
    lut = camvid_lut()
    names = {camvid: TRAIN_ID_NAMES[lut[i]] for i, camvid in enumerate(CAMVID_NAMES)}
    assert names == {
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
    assert [lut[i] for i in (0, 3, 8, 9, 10)] == [10, 0, 13, 11, 12]
    assert lut[11] == IGNORE and set(lut[12:]) == {IGNORE}  # Unlabelled and unknown ids are ignored


@pytest.mark.parametrize("absolute_lists", [False, True])
def test_read_pairs_listed_files_and_maps_labels(tmp_path: Path, absolute_lists: bool) -> None:
    root = write_camvid(tmp_path / "camvid", absolute_lists=absolute_lists)
    seg = read_camvid(root, "train")
    assert len(seg) == 6 and len(read_camvid(root, "test")) == 3
    assert [p.parent.name for p in seg.images] == ["train"] * 6
    assert [p.parent.name for p in seg.labels] == ["trainannot"] * 6
    assert [p.name for p in seg.images] == [p.name for p in seg.labels]
    image, ids = SegmentationDataset(seg, None)[0]
    raw = np.asarray(Image.open(seg.labels[0]))
    assert image.shape == (3, 36, 48)
    # CamVid ids 0 sky, 1 building, 3 road, 8 car, 11 unlabelled → trainIds 10, 2, 0, 13, 255
    expected = {0: 10, 1: 2, 3: 0, 8: 13, 11: IGNORE}
    assert ids.numpy().tolist() == np.vectorize(expected.get)(raw).tolist()
    train, val = split_set(seg, 0.5)
    assert train.label_lut == val.label_lut == seg.label_lut  # a split keeps the table


def test_label_table_is_part_of_the_teacher_cache_key(tmp_path: Path) -> None:
    seg = read_camvid(write_camvid(tmp_path / "camvid"), "train")
    plain = type(seg)(seg.images, seg.labels)
    assert dataset_identity(seg) != dataset_identity(plain)


def test_bad_root_and_missing_split_list(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"CamVid root .*nowhere is not a directory; set seg.root"):
        read_camvid(tmp_path / "nowhere", "train")
    root = write_camvid(tmp_path / "camvid")
    (root / "val.txt").unlink()
    with pytest.raises(SemvprError, match=r"split list .*val\.txt not found"):
        read_camvid(root, "val")
    (root / "test.txt").write_text("test/a.png\n")
    with pytest.raises(SemvprError, match=r"test\.txt:1: expected '<image> <label map>'"):
        read_camvid(root, "test")
    (root / "test.txt").write_text("\n")
    with pytest.raises(SemvprError, match="lists no images"):
        read_camvid(root, "test")


def test_missing_corrupt_and_mismatched_files_are_named(tmp_path: Path) -> None:
    root = write_camvid(tmp_path / "camvid")
    (root / "trainannot" / "0001TP_000002.png").unlink()
    (root / "val" / "0001TP_000001.png").write_bytes(b"not an image")
    Image.fromarray(np.zeros((36, 40), np.uint8)).save(root / "testannot" / "0001TP_000000.png")
    cases = {
        "train": r"train\.txt:3: label map .*trainannot/0001TP_000002\.png is missing",
        "val": r"val/0001TP_000001\.png is unreadable or corrupt",
        "test": r"0001TP_000000\.png is 36x40 but its image .* is 36x48",
    }
    for split, message in cases.items():
        with pytest.raises(SemvprError, match=message) as err:
            read_camvid(root, split)
        assert "\n" not in str(err.value)


def test_truncated_image_fails_with_its_name_when_loaded(tmp_path: Path) -> None:
    root = write_camvid(tmp_path / "camvid")
    path = root / "train" / "0001TP_000004.png"
    path.write_bytes(path.read_bytes()[:80])  # the header survives, the pixels do not
    seg = read_camvid(root, "train")
    with pytest.raises(SemvprError, match=r"0001TP_000004\.png is unreadable or corrupt"):
        SegmentationDataset(seg, (18, 24))[4]


def _replace(path: Path, make: Callable[[Path], None]) -> None:
    path.unlink()
    make(path)


DAMAGES: dict[str, tuple[Callable[[Path], None], str]] = {
    "split list a FIFO": (
        lambda r: _replace(r / "train.txt", os.mkfifo),
        r"split list .*train\.txt is not a regular file",
    ),
    "split list a folder": (lambda r: _replace(r / "train.txt", Path.mkdir), r"train\.txt is not a regular file"),
    "split list not UTF-8": (
        lambda r: (r / "train.txt").write_bytes(b"train/\xe9.png trainannot/\xe9.png\n"),
        r"split list .*train\.txt is not UTF-8 text \(a byte 0xe9 at offset 6\)",
    ),
    "label map a FIFO": (
        lambda r: _replace(r / "trainannot" / "0001TP_000002.png", os.mkfifo),
        r"train\.txt:3: label map .*0001TP_000002\.png is not a regular file",
    ),
    "image a link to a device": (
        lambda r: _replace(r / "train" / "0001TP_000001.png", lambda p: p.symlink_to("/dev/zero")),
        r"train\.txt:2: image .*0001TP_000001\.png is not a regular file",
    ),
    "label map in colour": (
        lambda r: Image.fromarray(np.zeros((36, 48, 3), np.uint8)).save(r / "trainannot" / "0001TP_000005.png"),
        r"0001TP_000005\.png has mode RGB; expected a single-channel PNG of ids",
    ),
    "no known class in the split": (
        lambda r: [Image.fromarray(np.full((36, 48), 200, np.uint8)).save(p) for p in r.glob("trainannot/*.png")],
        r"none of its 6 label maps holds a pixel of a known class",
    ),
}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_a_malformed_root_is_one_line_naming_what_is_wrong_before_anything_is_read(tmp_path: Path, damage: str) -> None:
    """Every file the reader takes from the root is a regular file (a FIFO, a folder or a device is refused,
    never taken as absent nor opened), lists are UTF-8, label maps one channel, and a split holds labels."""
    make, message = DAMAGES[damage]
    root = write_camvid(tmp_path / "camvid")
    make(root)
    with pytest.raises(SemvprError, match=message) as err:
        read_camvid(root, "train")
    assert "\n" not in str(err.value)


def test_unknown_ids_in_some_pixels_and_images_linked_from_outside_are_read(tmp_path: Path) -> None:
    """Ids CamVid does not have are ignored pixels (not a refusal) where the split holds known ones, and an
    image linked from outside the root is data that is read, never a place anything is written."""
    root = write_camvid(tmp_path / "camvid")
    label = root / "trainannot" / "0001TP_000000.png"
    ids = np.asarray(Image.open(label)).copy()
    ids[:6] = 77
    Image.fromarray(ids).save(label)
    outside = tmp_path / "elsewhere.png"
    (root / "train" / "0001TP_000001.png").rename(outside)
    (root / "train" / "0001TP_000001.png").symlink_to(outside)
    seg = read_camvid(root, "train")
    _, target = SegmentationDataset(seg, (36, 48))[0]
    assert (target[:6] == IGNORE).all() and (target[6:] != IGNORE).any()
    assert SegmentationDataset(seg, (36, 48))[1][0].shape == (3, 36, 48)
