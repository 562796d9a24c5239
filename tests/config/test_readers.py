"""Data readers attach one way: a ``conf/reader`` file holds a reader's ``_target_`` and what its splits share, a
``data`` or ``seg`` file places it under each split (its defaults list) and names no class itself, and every
split composes to a call its reader accepts (the split's keys bind to the reader's parameters)."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf

from semvpr.config.components import options
from semvpr.core.io import CONF_DIR
from tests.helpers import config

CONF = Path(CONF_DIR)
#: Where a place set or a segmentation set keeps its split nodes.
PLACE_SPLITS = ("train", "val", "test", "segmentation.train", "segmentation.val")
SEG_SPLITS = ("train", "val", "test")


def reader_targets() -> set[str]:
    """The classes and functions the ``conf/reader`` files name."""
    return {str(OmegaConf.load(path)["_target_"]) for path in CONF.glob("reader/*.yaml")}


def check_split(node: object, where: str) -> None:
    """A split is null or a call of one of conf/reader's readers with keys it takes (every one it requires)."""
    if node is None:
        return
    assert isinstance(node, DictConfig), where
    keys = OmegaConf.to_container(node, resolve=False)
    assert isinstance(keys, dict)
    target = keys.pop("_target_", None)
    assert target in reader_targets(), (where, target)
    inspect.signature(get_method(target)).bind(**keys)  # TypeError: a key the reader does not take, or one missing


@pytest.mark.parametrize("group", ["data", "seg"])
def test_no_data_or_seg_file_names_a_class(group: str) -> None:
    for path in CONF.glob(f"{group}/*.yaml"):
        assert "_target_" not in path.read_text(), (
            f"{path}: a reader belongs in conf/reader, placed by the defaults list"
        )


@pytest.mark.parametrize("name", options("data"))
def test_every_place_split_is_a_reader_call(name: str) -> None:
    cfg = config(f"data={name}")
    splits = [*PLACE_SPLITS, *(f"eval_sets.{s}.{p}" for s in cfg.data.get("eval_sets", {}) for p in ("val", "test"))]
    for split in splits:
        check_split(OmegaConf.select(cfg.data, split), f"data={name} {split}")
    assert any(OmegaConf.select(cfg.data, split) is not None for split in ("train", "test")), name


@pytest.mark.parametrize("name", options("seg"))
def test_every_segmentation_split_is_a_reader_call(name: str) -> None:
    cfg = config(f"seg={name}", config_name="segment")
    for split in SEG_SPLITS:
        assert cfg.seg[split] is not None, (name, split)
        check_split(cfg.seg[split], f"seg={name} {split}")


def test_a_split_key_its_reader_does_not_take_is_found() -> None:
    cfg = config("data=pitts30k", "++data.test.split=test")
    with pytest.raises(TypeError):
        check_split(cfg.data.test, "data=pitts30k test")
