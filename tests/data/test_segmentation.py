"""Cityscapes reader, image / trainId loaders and their error messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.data.classes import IGNORE
from semvpr.data.images import load_image
from semvpr.data.segmentation import SegmentationSet, load_pair, load_train_ids, read_cityscapes


def write_pair(
    root: Path, split: str, city: str, stem: str, label_ids: np.ndarray, label_hw: tuple[int, int] | None = None
) -> tuple[Path, Path]:
    """A Cityscapes image (red channel = labelId) and its labelIds PNG."""
    h, w = label_ids.shape
    image = root / "leftImg8bit" / split / city / f"{stem}_leftImg8bit.png"
    label = root / "gtFine" / split / city / f"{stem}_gtFine_labelIds.png"
    image.parent.mkdir(parents=True, exist_ok=True)
    label.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = label_ids
    Image.fromarray(rgb).save(image)
    lab = label_ids if label_hw is None else np.zeros(label_hw, np.uint8)
    Image.fromarray(lab.astype(np.uint8)).save(label)
    return image, label


def test_read_cityscapes_pairs_by_name(tmp_path: Path) -> None:
    ids = np.full((4, 6), 7, np.uint8)
    write_pair(tmp_path, "train", "aachen", "aachen_000001_000019", ids)
    write_pair(tmp_path, "train", "aachen", "aachen_000000_000019", ids)
    write_pair(tmp_path, "train", "bremen", "bremen_000000_000019", ids)
    write_pair(tmp_path, "val", "lindau", "lindau_000000_000019", ids)
    seg = read_cityscapes(tmp_path, "train")
    assert isinstance(seg, SegmentationSet) and len(seg) == 3
    assert [p.name for p in seg.images][:2] == [
        "aachen_000000_000019_leftImg8bit.png",
        "aachen_000001_000019_leftImg8bit.png",
    ]
    for image, label in zip(seg.images, seg.labels):
        assert label.name == image.name.replace("_leftImg8bit", "_gtFine_labelIds")
        assert label.parent.name == image.parent.name and label.is_file()
    assert len(read_cityscapes(tmp_path, "val")) == 1


def test_read_cityscapes_bad_inputs(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"leftImg8bit/train not found"):
        read_cityscapes(tmp_path, "train")
    image, label = write_pair(tmp_path, "train", "aachen", "aachen_000000_000019", np.zeros((2, 2), np.uint8))
    label.unlink()
    missing = r"aachen_000000_000019_leftImg8bit\.png.*gtFine_labelIds\.png is missing"
    with pytest.raises(SemvprError, match=missing):
        read_cityscapes(tmp_path, "train")
    (tmp_path / "leftImg8bit" / "val").mkdir()
    with pytest.raises(SemvprError, match=r"leftImg8bit/val: no <city>"):
        read_cityscapes(tmp_path, "val")


def test_load_image_rgb_float_and_resize(tmp_path: Path) -> None:
    path = tmp_path / "a.png"
    Image.new("RGB", (10, 6), (255, 0, 51)).save(path)
    img = load_image(path)
    assert img.shape == (3, 6, 10) and img.dtype == torch.float32
    torch.testing.assert_close(img[:, 0, 0], torch.tensor([1.0, 0.0, 0.2]))
    assert load_image(path, [3, 5]).shape == (3, 3, 5)
    Image.new("L", (4, 4), 128).save(tmp_path / "gray.png")  # grey → 3 channels
    assert load_image(tmp_path / "gray.png").shape == (3, 4, 4)


def test_load_image_resizes_bilinear_on_pil_or_bicubic_on_the_tensor_as_torchvision_does(tmp_path: Path) -> None:
    """``bilinear``: torchvision's Resize on the PIL image (MixVPR's, SALAD's transform); ``bicubic``: ToTensor
    then Resize(BICUBIC, antialias=True) on the tensor (Bag-of-Queries' transform), shrinking and enlarging."""
    from torchvision import transforms

    rng = np.random.default_rng(0)
    path = tmp_path / "a.png"
    Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(path)
    pil = Image.open(path).convert("RGB")
    for size in ([24, 36], [90, 100]):
        bilinear = transforms.Compose([transforms.Resize(size, antialias=True), transforms.ToTensor()])(pil)
        bicubic = transforms.Resize(size, transforms.InterpolationMode.BICUBIC, antialias=True)(
            transforms.ToTensor()(pil)
        )
        torch.testing.assert_close(load_image(path, size), bilinear, rtol=0, atol=0)
        torch.testing.assert_close(load_image(path, size, "bicubic"), bicubic, rtol=0, atol=1e-6)
        assert float((bicubic - bilinear).abs().max()) > 0.05  # the two are other images


def test_load_image_corrupt_names_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"\xff\xd8\xff not really a jpeg")
    with pytest.raises(SemvprError, match=r"broken\.jpg is unreadable"):
        load_image(bad)
    good = tmp_path / "trunc.png"
    Image.new("RGB", (64, 64), (1, 2, 3)).save(good)
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:60])
    with pytest.raises(SemvprError, match=r"cut\.png"):
        load_image(tmp_path / "cut.png")
    with pytest.raises(SemvprError, match=r"absent\.png not found"):
        load_image(tmp_path / "absent.png")


def test_load_train_ids_maps_label_ids_and_resizes_nearest(tmp_path: Path) -> None:
    # labelIds: 7 road→0, 26 car→13, 33 bicycle→18, 0 unlabeled→255, 23 sky→10
    label_ids = np.array([[7, 7, 26, 26], [0, 0, 33, 33], [23, 23, 7, 7], [23, 23, 7, 7]], np.uint8)
    path = tmp_path / "x_gtFine_labelIds.png"
    Image.fromarray(label_ids).save(path)
    ids = load_train_ids(path, from_label_ids=True)
    assert ids.dtype == torch.long
    assert ids.tolist() == [[0, 0, 13, 13], [IGNORE, IGNORE, 18, 18], [10, 10, 0, 0], [10, 10, 0, 0]]
    small = load_train_ids(path, (2, 2), from_label_ids=True)
    assert small.shape == (2, 2) and set(small.unique().tolist()) <= {0, 13, 18, 10, IGNORE}
    big = load_train_ids(path, (8, 8), from_label_ids=True)
    assert big[::2, ::2].tolist() == ids.tolist()  # nearest: every id stays an id
    # trainId PNGs pass through; non-trainIds become ignore.
    train_path = tmp_path / "t.png"
    Image.fromarray(np.array([[0, 18], [19, 255]], np.uint8)).save(train_path)
    assert load_train_ids(train_path, from_label_ids=False).tolist() == [[0, 18], [IGNORE, IGNORE]]


def test_label_size_mismatch_names_both(tmp_path: Path) -> None:
    image, label = write_pair(tmp_path, "train", "c", "c_0", np.zeros((4, 6), np.uint8), label_hw=(5, 6))
    both = r"c_0_gtFine_labelIds\.png is 5x6 but its image .*c_0_leftImg8bit\.png is 4x6"
    with pytest.raises(SemvprError, match=both):
        load_pair(image, label, (4, 6), from_label_ids=True)
    with pytest.raises(SemvprError, match="5x6"):
        load_train_ids(label, from_label_ids=True, image=image)
    rgb_label = tmp_path / "rgb.png"
    Image.new("RGB", (6, 4)).save(rgb_label)
    with pytest.raises(SemvprError, match=r"rgb\.png has mode RGB"):
        load_train_ids(rgb_label, from_label_ids=True)


def test_load_pair_aligned(tmp_path: Path) -> None:
    ids = np.array([[7, 26], [33, 23]], np.uint8)
    image, label = write_pair(tmp_path, "train", "c", "c_1", ids)
    img, train_ids = load_pair(image, label, from_label_ids=True)
    assert img.shape == (3, 2, 2) and train_ids.tolist() == [[0, 13], [18, 10]]
    torch.testing.assert_close(img[0] * 255, torch.from_numpy(ids).float())
