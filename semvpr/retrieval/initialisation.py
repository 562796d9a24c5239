"""An aggregator's initialisation from a sample of training local features (NetVLAD's recipe: k-means
on 50,000 random locations), labelled static / dynamic by the teacher's pseudo-labels where the
aggregator asks for labels (SRAL's semantic-constrained init)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from semvpr.core.logs import say
from semvpr.core.precision import autocast
from semvpr.data.classes import static_lut
from semvpr.models.aggregators.base import Aggregator
from semvpr.retrieval.features import FeatureStore
from semvpr.segmentation.pseudolabels import read_label


@dataclass(frozen=True)
class InitSample:
    """How many local features the initialisation samples: ``per_image`` random locations of each of
    ``max_features / per_image`` random training database images (pytorch-NetVlad: 50,000 / 100)."""

    max_features: int = 50_000
    per_image: int = 100
    seed: int = 0


@dataclass(frozen=True)
class StaticLabels:
    """The teacher's pseudo-labels of the training database images, and which classes are static."""

    labels_dir: Path
    root: Path
    #: The training database images, in the feature store's order.
    image_paths: Sequence[Path]
    static_names: Sequence[str]
    #: The local-feature grid (h, w) the labels are pooled to.
    grid: tuple[int, int]


@torch.no_grad()
def sample_local_features(
    backbone: nn.Module, store: FeatureStore, max_features: int, per_image: int, seed: int, batch_size: int = 16
) -> tuple[Tensor, Tensor]:
    """NetVLAD's k-means sample: ``per_image`` random locations of each of ``max_features / per_image``
    random images (all of them when fewer). Returns (N,D) features and their (image, location) indices."""
    rng = np.random.default_rng(seed)
    num_images = min(len(store), math.ceil(max_features / per_image))
    images = np.sort(rng.choice(len(store), num_images, replace=False))
    device = next(backbone.parameters()).device
    feats, where = [], []
    for start in range(0, len(images), batch_size):
        idx = images[start : start + batch_size]
        trunk = store.trunk_of(idx, backbone).to(device).float()
        with autocast(device):
            local = backbone.forward_trainable(trunk.contiguous(memory_format=torch.channels_last))
        local = local.float().flatten(2).transpose(1, 2).cpu()  # (B, h*w, D)
        for image, grid in zip(idx, local):
            loc = np.sort(rng.choice(len(grid), min(per_image, len(grid)), replace=False))
            feats.append(grid[torch.from_numpy(loc)])
            where.append(torch.from_numpy(np.stack([np.full(len(loc), image), loc], axis=1)))
    return torch.cat(feats), torch.cat(where)


def static_grid(
    labels_dir: Path, root: Path, image_paths: Sequence[Path], grid: tuple[int, int], static_names: Sequence[str]
) -> Tensor:
    """Static fraction of each feature-grid cell (N,h*w) from pseudo-label PNGs."""
    lut = torch.from_numpy(static_lut(tuple(static_names)))
    maps = []
    for path in image_paths:
        label = torch.from_numpy(read_label(labels_dir, path, root)).long()
        maps.append(lut[label])
    pooled = torch.nn.functional.adaptive_avg_pool2d(torch.stack(maps)[:, None], grid)
    return pooled.flatten(1)


def static_locations(fraction: Tensor, at_least: int) -> Tensor:
    """Which sampled locations the semantic init treats as static: those whose static fraction is >= 0.5,
    or, where the labels call fewer than ``at_least`` static (a weak teacher), the ``at_least`` most static
    ones (said on stderr), so the init degrades towards k-means instead of failing."""
    is_static = fraction >= 0.5
    at_least = min(at_least, len(fraction))
    if int(is_static.sum()) >= at_least:
        return is_static
    say(
        f"the teacher's labels call only {int(is_static.sum())} of {len(fraction)} k-means sample "
        f"locations static; the semantic init uses the {at_least} most static ones"
    )
    is_static = torch.zeros_like(is_static)
    is_static[torch.argsort(fraction, descending=True, stable=True)[:at_least]] = True
    return is_static


def initialise_aggregator(
    aggregator: Aggregator, backbone: nn.Module, train_db: FeatureStore, sample: InitSample, labels: StaticLabels | None
) -> dict[str, Any]:
    """Initialise ``aggregator`` as its ``init_sample`` asks (nothing, features, or labelled features);
    returns what was used, for metrics.json."""
    if aggregator.init_sample == "none":
        return {"init": "none"}
    feats, where = sample_local_features(backbone, train_db, sample.max_features, sample.per_image, sample.seed)
    if aggregator.init_sample == "features":
        return aggregator.init_from_sample(feats, None, sample.seed)
    if labels is None:
        raise ValueError(f"{type(aggregator).__name__} initialises from labelled features; no labels were given")
    used = np.unique(where[:, 0].numpy())
    static = static_grid(
        labels.labels_dir, labels.root, [labels.image_paths[i] for i in used], labels.grid, labels.static_names
    )
    row = torch.from_numpy(np.searchsorted(used, where[:, 0].numpy()))
    is_static = static_locations(static[row, where[:, 1]], aggregator.init_min_static)
    return aggregator.init_from_sample(feats, is_static, sample.seed)
