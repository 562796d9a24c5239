"""Frozen-trunk feature cache: what the frozen backbone prefix and the mask source give per image.

Below ``backbone.train_from`` nothing learns, so its output (and the static mask, which depends
only on the image and frozen networks) is computed once per image and reused by every epoch, by
mining, and by every sweep job with the same backbone and data (artifact kinds ``trunk``/``masks``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from semvpr.artifacts import artifact_dir, build_once
from semvpr.data.datamodule import ImageDataset
from semvpr.data.places import PlaceSet
from semvpr.models.masks import pool_to_grid


@dataclass
class FeatureStore:
    """Cached frozen-trunk outputs (N,C,h',w') and grid masks (N,1,h,w) of one image list."""

    trunk: Tensor
    mask: Tensor | None

    def __len__(self) -> int:
        return len(self.trunk)


@dataclass
class PlaceFeatures:
    """A place set with the feature stores of its database and queries."""

    places: PlaceSet
    db: FeatureStore
    q: FeatureStore


def autocast_context(device: torch.device | str = "cpu") -> torch.autocast:
    """bf16 autocast where the device supports it (AMX CPUs, recent GPUs), else a no-op autocast."""
    device_type = torch.device(device).type
    enabled = device_type == "cuda" or torch.backends.mkldnn.is_available()
    return torch.autocast(device_type=device_type, dtype=torch.bfloat16, enabled=enabled)


@torch.no_grad()
def grid_size(backbone: nn.Module, image_size: Sequence[int]) -> tuple[int, int]:
    """Local-feature grid (h, w) of the backbone at this image size."""
    probe = torch.zeros(1, 3, *image_size)
    return tuple(backbone(probe)[-1].shape[-2:])  # type: ignore[return-value]


@torch.no_grad()
def extract(
    backbone: nn.Module,
    mask_source: nn.Module | None,
    paths: Sequence[Path],
    label_paths: Sequence[Path] | None,
    image_size: Sequence[int],
    batch_size: int = 32,
    num_workers: int = 2,
    desc: str = "features",
    trunk: bool = True,
) -> FeatureStore:
    """One pass over the images: trunk outputs (bf16) and, with a mask source, grid masks.

    With ``trunk=False`` only the masks are computed, and the backbone runs only if the mask
    source reads its features; the returned store then holds an empty trunk.
    """
    grid = grid_size(backbone, image_size)
    run_backbone = trunk or (mask_source is not None and mask_source.needs_features)
    loader = DataLoader(ImageDataset(list(paths), tuple(image_size)), batch_size=batch_size,
                        num_workers=num_workers)
    trunks, masks = [], []
    backbone.eval()
    for images, index in tqdm(loader, desc=desc, unit="batch", leave=False):
        images = images.contiguous(memory_format=torch.channels_last)
        with autocast_context():
            outs = backbone.forward_frozen(images) if run_backbone else []
            if mask_source is not None:
                labels = [label_paths[i] for i in index] if label_paths is not None else None
                masks.append(pool_to_grid(mask_source(images, outs, labels), grid))
        if trunk:
            trunks.append(outs[-1].to(torch.bfloat16))
    return FeatureStore(torch.cat(trunks) if trunks else torch.empty(0), torch.cat(masks) if masks else None)


def cached_place_features(
    places: PlaceSet,
    backbone: nn.Module,
    backbone_key: Any,
    mask_source: nn.Module | None,
    mask_key: Any,
    image_size: Sequence[int],
    cache_dir: str | Path,
    batch_size: int = 32,
    num_workers: int = 2,
) -> PlaceFeatures:
    """Trunk features and masks of a place set, from the artifact cache or computed once."""
    data_key = {"db": [str(p) for p in places.db_paths], "q": [str(p) for p in places.q_paths],
                "image_size": list(image_size)}
    trunk_key = {"backbone": backbone_key, "data": data_key}
    kinds = {"trunk": trunk_key}
    if mask_source is not None:
        kinds["masks"] = {"mask": mask_key, "trunk": trunk_key}
    missing = [k for k, key in kinds.items() if not artifact_dir(cache_dir, k, key).is_dir()]
    stores: dict[str, FeatureStore] = {}
    if missing:
        for side, paths, labels in (("db", places.db_paths, places.db_labels),
                                    ("q", places.q_paths, places.q_labels)):
            stores[side] = extract(backbone, mask_source if "masks" in missing else None, paths,
                                   labels, image_size, batch_size, num_workers,
                                   desc=f"{places.name} {side}", trunk="trunk" in missing)
    for kind in missing:
        field = "trunk" if kind == "trunk" else "mask"

        def save(tmp: Path, field: str = field) -> None:
            for side, store in stores.items():
                torch.save(getattr(store, field), tmp / f"{side}.pt")

        build_once(cache_dir, kind, kinds[kind], save)
    loaded = {side: FeatureStore(_load(cache_dir, "trunk", trunk_key, side),
                                 _load(cache_dir, "masks", kinds["masks"], side)
                                 if "masks" in kinds else None)
              for side in ("db", "q")}
    return PlaceFeatures(places, loaded["db"], loaded["q"])


def _load(cache_dir: str | Path, kind: str, key: Any, side: str) -> Tensor:
    return torch.load(artifact_dir(cache_dir, kind, key) / f"{side}.pt", weights_only=True)
