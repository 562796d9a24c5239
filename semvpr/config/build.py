"""Build a run's components from its config: place sets, backbone, semantic artifacts, mask source,
aggregator (from ``conf/aggregator``, against :class:`semvpr.models.aggregators.base.Aggregator`).

Shared by ``semvpr.train`` and ``semvpr.eval`` so both construct exactly the same model. Teacher,
pseudo-labels, student and feature caches come from the artifact cache (built on first use).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue
from torch import Tensor, nn

from semvpr.core.cache import config_hash, state_hash
from semvpr.data.classes import static_lut
from semvpr.data.places import PlaceSet
from semvpr.core.errors import SemvprError, unwrap_user_error
from semvpr.core.io import check_dir_path
from semvpr.retrieval.features import STORAGES, FeatureStore, grid_size
from semvpr.retrieval.recall import check_radius
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.masks import WEIGHTINGS, ClassWeights, MaskSource, OracleMask, StudentMask, TeacherMask
from semvpr.core.precision import autocast
from semvpr.segmentation.pseudolabels import read_label

MASK_SOURCES = ("none", "teacher", "student", "oracle")
MIN_STATIC_PER_CLUSTER = 10  # static k-means sample the semantic init needs at the least, per cluster


@dataclass
class Semantic:
    """Semantic artifacts a run needs: teacher, its pseudo-labels of the train images, student."""

    teacher: nn.Module | None = None
    labels_dir: Path | None = None
    labels_root: Path | None = None
    student: nn.Module | None = None


def instantiate_node(node: Any, **kwargs: Any) -> Any:
    """hydra.utils.instantiate, with a SemvprError from inside the target re-raised unwrapped."""
    try:
        return instantiate(node, **kwargs)
    except Exception as err:
        user = unwrap_user_error(err)
        if user is not None:
            raise user from None
        if isinstance(err, MissingMandatoryValue):
            raise SemvprError(f"{err.full_key} is not set; pass it as an override, e.g. "
                              f"{err.full_key}=DIR") from None
        raise


#: Lightning 2's precision settings (``Trainer(precision=...)``).
PRECISIONS = ("transformer-engine", "transformer-engine-float16", "16-true", "16-mixed", "bf16-true", "bf16-mixed",
              "32-true", "64-true", "64", "32", "16", "bf16")
SEED_MAX = 2**32 - 1  # numpy's (and Lightning's seed_everything) range


def check_config(cfg: DictConfig) -> None:
    """Reject config values that would fail deep inside a run with a cryptic error (or none at all).

    Called first by every CLI (train, eval, localize), before anything is read or written.
    """
    whole_number(cfg.seed, "seed", 0, SEED_MAX)
    if cfg.get("num_figure_queries") is not None:
        whole_number(cfg.num_figure_queries, "num_figure_queries", 1)
    if cfg.get("top_k") is not None:
        whole_number(cfg.top_k, "top_k", 1)
    lr = cfg.model.optimizer.get("lr")
    try:
        lr_ok = lr is not None and math.isfinite(float(lr)) and float(lr) > 0
    except (TypeError, ValueError):
        lr_ok = False
    if not lr_ok:
        raise SemvprError(f"model.optimizer.lr={lr!r} must be a number > 0")
    if str(cfg.trainer.precision) not in PRECISIONS:
        raise SemvprError(f"trainer.precision={cfg.trainer.precision!r} is not one of {list(PRECISIONS)}")
    check_dir_path(Path(str(cfg.paths.cache_dir)), "paths.cache_dir")
    if cfg.get("ckpt_path") not in (None, "last"):
        from semvpr.core.checkpoint import read_checkpoint

        read_checkpoint(cfg.ckpt_path)
    if cfg.mask.name not in MASK_SOURCES:
        raise SemvprError(f"mask.name={cfg.mask.name!r} is not one of {list(MASK_SOURCES)}")
    for key in ("num_clusters", "batch_size", "eval_batch_size", "num_negatives", "init_features",
                "init_per_image", "cache_refresh"):
        whole_number(cfg.model[key], f"model.{key}", 1)
    if cfg.model.get("queries_per_epoch") is not None:
        whole_number(cfg.model.queries_per_epoch, "model.queries_per_epoch (or null = all)", 1)
    positive = check_radius(cfg.model.positive_radius, "model.positive_radius")
    if check_radius(cfg.model.negative_radius, "model.negative_radius") < positive:
        raise SemvprError(f"model.negative_radius={cfg.model.negative_radius} is below model.positive_radius="
                          f"{cfg.model.positive_radius}: a negative could then be a positive")
    if len(cfg.data.image_size) != 2:
        raise SemvprError(f"data.image_size={list(cfg.data.image_size)} must be [H, W]")
    if cfg.features.storage not in STORAGES:
        raise SemvprError(f"features.storage={cfg.features.storage!r} is not one of {list(STORAGES)}")
    weighting = cfg.mask.weights
    if weighting not in WEIGHTINGS:
        raise SemvprError(f"mask.weights={weighting!r} is not one of {list(WEIGHTINGS)}")
    if weighting == "learned" and cfg.mask.name == "none":
        raise SemvprError("mask=none has no mask to weight; mask.weights=learned (filter.weights=learned) needs "
                          "mask=student, teacher or oracle (filter=unet, mask2former or oracle)")


def whole_number(value: object, key: str, low: int, high: int | None = None) -> int:
    """``value`` as an int in [low, high], or one line naming ``key``."""
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)
    if not ok:
        bounds = f"from {low} to {high}" if high is not None else f">= {low}"
        raise SemvprError(f"{key}={value!r} must be a whole number {bounds}")
    return int(value)  # type: ignore[arg-type]


def build_places(cfg: DictConfig, splits: tuple[str, ...] = ("train", "val", "test")) -> dict[str, PlaceSet]:
    """Instantiate the place sets of the requested splits (the data config's readers)."""
    places = {}
    for split in splits:
        if cfg.data.get(split) is None:
            raise SemvprError(f"data={cfg.data.name} has no {split} split; use it for evaluation only")
        places[split] = instantiate_node(cfg.data[split]).with_eval_radius(cfg.data.get("eval_radius"))
    return places


def build_backbone(cfg: DictConfig, pretrained: bool = True) -> nn.Module:
    """The run's backbone (see ``instantiate_backbone``)."""
    return instantiate_backbone(cfg.backbone, int(cfg.seed), pretrained)


#: Backbone config keys that are not constructor arguments.
CONFIG_ONLY_KEYS = ("name", "paper_train_from")


def instantiate_backbone(node: DictConfig, seed: int, pretrained: bool = True) -> nn.Module:
    """A backbone config node with the seed's random init, or its pretrained weights (``pretrained``;
    eval skips them: the checkpoint carries every weight); channels_last."""
    torch.manual_seed(seed)
    args = {k: v for k, v in OmegaConf.to_container(node, resolve=True).items() if k not in CONFIG_ONLY_KEYS}
    if not pretrained:
        args["weights"] = "none"
    return instantiate_node(args).to(memory_format=torch.channels_last)


def build_semantic(cfg: DictConfig, train: PlaceSet, backbone: nn.Module,
                   timings: dict[str, float] | None = None) -> Semantic:
    """Teacher, pseudo-labels and student, as far as the aggregator's init and the mask need them; the
    seconds each took (built or read from the cache) into ``timings`` as teacher_s, labels_s, student_s."""
    timings = {} if timings is None else timings
    needs_labels = aggregator_class(cfg).init_sample == "labelled" or cfg.mask.name in ("teacher", "student")
    if not needs_labels:
        return Semantic()
    from semvpr.models.student import build_student
    from semvpr.models.teacher import build_teacher
    from semvpr.segmentation.pseudolabels import pseudo_labels

    seg = cfg.data.get("segmentation")
    needs_training = cfg.teacher.get("checkpoint") is None
    seg_train = instantiate_node(seg.train) if needs_training else None
    seg_val = instantiate_node(seg.val) if needs_training else None
    tic = time.time()
    teacher = build_teacher(cfg.teacher, seg_train, seg_val, cfg.paths.cache_dir)
    timings["teacher_s"], tic = time.time() - tic, time.time()
    images = list(train.db_paths) + list(train.q_paths)
    labels_dir = pseudo_labels(teacher, teacher.teacher_key, images, tuple(cfg.data.image_size),
                               cfg.paths.cache_dir, train.root)
    timings["labels_s"], tic = time.time() - tic, time.time()
    semantic = Semantic(teacher, labels_dir, train.root)
    if cfg.mask.name == "student":
        semantic.student = build_student(cfg.student, backbone, images, labels_dir, train.root,
                                         tuple(cfg.data.image_size), cfg.paths.cache_dir)
        timings["student_s"] = time.time() - tic
    return semantic


def build_mask_source(cfg: DictConfig, backbone: nn.Module, semantic: Semantic | None = None) -> MaskSource | None:
    """The run's mask source: trained (from ``semantic``), or untrained for weights to be loaded into."""
    mask = cfg.mask.name
    if mask == "none":
        return None
    static = list(cfg.teacher.static_classes)
    if mask == "oracle":
        return OracleMask(static)
    if mask == "teacher":
        from semvpr.models.teacher import teacher_architecture

        return TeacherMask(semantic.teacher if semantic is not None else teacher_architecture(cfg.teacher), static)
    from semvpr.models.student import student_architecture

    return StudentMask(semantic.student if semantic is not None else student_architecture(cfg.student, backbone),
                       static)


def build_class_weights(cfg: DictConfig) -> ClassWeights | None:
    """Learned per-class weights (mask.weights=learned), else None."""
    if cfg.mask.weights != "learned":
        return None
    return ClassWeights(list(cfg.teacher.static_classes), float(cfg.model.class_weights.init_logit))


def mask_key(mask_source: nn.Module | None, cfg: DictConfig) -> str | None:
    """What a mask source's output depends on: its weights (and, for the oracle, the class list)."""
    if mask_source is None:
        return None
    return config_hash([type(mask_source).__name__, state_hash(mask_source.state_dict()),
                        list(cfg.teacher.static_classes)])


@torch.no_grad()
def sample_local_features(backbone: nn.Module, store: FeatureStore, max_features: int, per_image: int,
                          seed: int, batch_size: int = 16) -> tuple[Tensor, Tensor]:
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


def static_grid(labels_dir: Path, root: Path, image_paths: list[Path], grid: tuple[int, int],
                static_names: list[str]) -> Tensor:
    """Static fraction of each feature-grid cell (N,h*w) from pseudo-label PNGs."""
    lut = torch.from_numpy(static_lut(tuple(static_names)))
    maps = []
    for path in image_paths:
        label = torch.from_numpy(read_label(labels_dir, path, root)).long()
        maps.append(lut[label])
    pooled = torch.nn.functional.adaptive_avg_pool2d(torch.stack(maps)[:, None], grid)
    return pooled.flatten(1)


def aggregator_class(cfg: DictConfig) -> type[Aggregator]:
    """The class ``aggregator.module`` names (not instantiated: its init needs are read before building)."""
    cls = get_class(cfg.aggregator.module._target_)
    if not (isinstance(cls, type) and issubclass(cls, Aggregator)):
        raise SemvprError(f"aggregator={cfg.aggregator.name}: {cfg.aggregator.module._target_} is not a "
                          "semvpr.models.aggregators.base.Aggregator")
    return cls


def build_aggregator(cfg: DictConfig, backbone: nn.Module) -> Aggregator:
    """The run's aggregator for the backbone's channels. An aggregator on a fixed grid (a ``grid`` key)
    left null gets the backbone's grid at data.image_size, written into ``cfg`` so that the checkpoint
    records the grid it was built for."""
    node = cfg.aggregator.module
    if "grid" in node and node.grid is None:
        node.grid = list(grid_size(backbone, tuple(cfg.data.image_size)))
    aggregator_class(cfg)
    return instantiate_node(node, dim=backbone.out_channels)


def init_aggregator(cfg: DictConfig, aggregator: Aggregator, backbone: nn.Module, train_db: FeatureStore,
                    train: PlaceSet, semantic: Semantic) -> dict:
    """The aggregator's initialisation from a sample of training local features (NetVLAD's recipe),
    labelled static / dynamic by the teacher where it asks for labels; returns what was used."""
    if aggregator.init_sample == "none":
        return {"init": "none"}
    feats, where = sample_local_features(backbone, train_db, int(cfg.model.init_features),
                                         int(cfg.model.init_per_image), cfg.seed)
    if aggregator.init_sample == "features":
        return aggregator.init_from_sample(feats, None, cfg.seed)
    assert semantic.labels_dir is not None and semantic.labels_root is not None
    grid = grid_size(backbone, tuple(cfg.data.image_size))
    used = np.unique(where[:, 0].numpy())
    static = static_grid(semantic.labels_dir, semantic.labels_root, [train.db_paths[i] for i in used], grid,
                         list(cfg.teacher.static_classes))
    row = torch.from_numpy(np.searchsorted(used, where[:, 0].numpy()))
    is_static = static_locations(static[row, where[:, 1]], MIN_STATIC_PER_CLUSTER * int(cfg.aggregator.module.num_clusters))
    return aggregator.init_from_sample(feats, is_static, cfg.seed)


def static_locations(fraction: Tensor, at_least: int) -> Tensor:
    """Which sampled locations the semantic init treats as static: those whose static fraction is >= 0.5,
    or, where the labels call fewer than ``at_least`` static (a weak teacher), the ``at_least`` most static
    ones (said on stderr), so the init degrades towards k-means instead of failing."""
    is_static = fraction >= 0.5
    at_least = min(at_least, len(fraction))
    if int(is_static.sum()) >= at_least:
        return is_static
    print(f"semvpr: the teacher's labels call only {int(is_static.sum())} of {len(fraction)} k-means sample "
          f"locations static; the semantic init uses the {at_least} most static ones", file=sys.stderr)
    is_static = torch.zeros_like(is_static)
    is_static[torch.argsort(fraction, descending=True, stable=True)[:at_least]] = True
    return is_static
