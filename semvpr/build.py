"""Build a run's components from its config: place sets, backbone, semantic artifacts, retriever.

Shared by ``semvpr.train`` and ``semvpr.eval`` so both construct exactly the same model. Teacher,
pseudo-labels, student and feature caches come from the artifact cache (built on first use).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue
from PIL import Image
from torch import Tensor, nn

from semvpr.data.classes import static_lut
from semvpr.data.places import PlaceSet
from semvpr.errors import SemvprError, unwrap_user_error
from semvpr.features import FeatureStore, autocast_context, grid_size
from semvpr.models.masks import OracleMask, StudentMask, TeacherMask


@dataclass
class Semantic:
    """Semantic artifacts a filter needs: teacher, its pseudo-labels of the train images, student."""

    teacher: nn.Module | None = None
    teacher_key: Any = None
    labels_dir: Path | None = None
    student: nn.Module | None = None
    student_key: Any = None


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


def backbone_name(cfg: DictConfig) -> str:
    """Short backbone name for tables (vgg16, resnet50) from its class."""
    return cfg.backbone._target_.rsplit(".", 1)[-1].removesuffix("Backbone").lower()


def check_config(cfg: DictConfig) -> None:
    """Reject config values that would fail deep inside training with a cryptic error."""
    if cfg.filter.mask not in MASK_SOURCES:
        raise SemvprError(f"filter.mask={cfg.filter.mask!r} is not one of {sorted(MASK_SOURCES)}")
    if cfg.filter.init not in ("kmeans", "semantic"):
        raise SemvprError(f"filter.init={cfg.filter.init!r} must be 'kmeans' or 'semantic'")
    for key in ("num_clusters", "batch_size", "eval_batch_size", "num_negatives", "init_features"):
        if int(cfg.model[key]) < 1:
            raise SemvprError(f"model.{key}={cfg.model[key]} must be a positive integer")
    if len(cfg.data.image_size) != 2:
        raise SemvprError(f"data.image_size={list(cfg.data.image_size)} must be [H, W]")


def build_places(cfg: DictConfig, splits: tuple[str, ...] = ("train", "val", "test")) -> dict[str, PlaceSet]:
    """Instantiate the place sets of the requested splits (the data config's readers)."""
    places = {}
    for split in splits:
        if cfg.data.get(split) is None:
            raise SemvprError(f"data={cfg.data.name} has no {split} split; use it for evaluation only")
        places[split] = instantiate_node(cfg.data[split])
    return places


def build_backbone(cfg: DictConfig) -> nn.Module:
    """The backbone with the run seed's random init (or its pretrained weights)."""
    torch.manual_seed(cfg.seed)
    return instantiate_node(cfg.backbone).to(memory_format=torch.channels_last)


def backbone_key(cfg: DictConfig) -> dict:
    """What determines the backbone's frozen weights (for caching its outputs)."""
    return {"backbone": OmegaConf.to_container(cfg.backbone, resolve=True), "seed": cfg.seed}


def build_semantic(cfg: DictConfig, train: PlaceSet, backbone: nn.Module) -> Semantic:
    """Teacher, pseudo-labels and student, as far as the filter needs them."""
    needs_labels = cfg.filter.init == "semantic" or cfg.filter.mask in ("teacher", "student")
    if not needs_labels:
        return Semantic()
    from semvpr.models.student import build_student
    from semvpr.models.teacher import build_teacher
    from semvpr.pseudolabels import pseudo_labels

    seg = cfg.data.get("segmentation")
    needs_training = cfg.teacher.get("checkpoint") is None
    seg_train = instantiate_node(seg.train) if needs_training else None
    seg_val = instantiate_node(seg.val) if needs_training else None
    teacher = build_teacher(cfg.teacher, seg_train, seg_val, cfg.paths.cache_dir)
    images = list(train.db_paths) + list(train.q_paths)
    labels_dir = pseudo_labels(teacher, teacher.teacher_key, images, tuple(cfg.data.image_size),
                               cfg.paths.cache_dir)
    semantic = Semantic(teacher, teacher.teacher_key, labels_dir)
    if cfg.filter.mask == "student":
        semantic.student = build_student(cfg.student, backbone, images, labels_dir,
                                         tuple(cfg.data.image_size), cfg.paths.cache_dir)
        semantic.student_key = {"student": OmegaConf.to_container(cfg.student, resolve=True),
                                "backbone": backbone_key(cfg), "labels": labels_dir.name}
    return semantic


MASK_SOURCES: dict[str, Callable[[Semantic], tuple[nn.Module | None, Any]]] = {
    "none": lambda s: (None, None),
    "teacher": lambda s: (TeacherMask(s.teacher), {"teacher": s.teacher_key}),
    "student": lambda s: (StudentMask(s.student), s.student_key),
    "oracle": lambda s: (OracleMask(), "oracle"),
}


def build_mask_source(cfg: DictConfig, semantic: Semantic) -> tuple[nn.Module | None, Any]:
    """The filter's mask source and the key that identifies its output (for the mask cache)."""
    return MASK_SOURCES[cfg.filter.mask](semantic)


@torch.no_grad()
def sample_local_features(backbone: nn.Module, store: FeatureStore, max_features: int,
                          seed: int) -> tuple[Tensor, Tensor]:
    """Random local features (N,D) of a store's images, and their (image, location) indices."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(store))
    feats, where = [], []
    total = 0
    for start in range(0, len(order), 32):
        idx = torch.from_numpy(order[start : start + 32])
        with autocast_context():
            local = backbone.forward_trainable(store.trunk[idx].contiguous(memory_format=torch.channels_last))
        local = local.float().flatten(2).transpose(1, 2)  # (B, h*w, D)
        feats.append(local.reshape(-1, local.shape[-1]))
        loc = torch.arange(local.shape[1]).repeat(len(idx))
        where.append(torch.stack([idx.repeat_interleave(local.shape[1]), loc], dim=1))
        total += feats[-1].shape[0]
        if total >= max_features:
            break
    feats_t, where_t = torch.cat(feats), torch.cat(where)
    keep = torch.from_numpy(rng.permutation(len(feats_t))[:max_features])
    return feats_t[keep], where_t[keep]


def static_grid(labels_dir: Path, image_paths: list[Path], grid: tuple[int, int],
                static_names: list[str]) -> Tensor:
    """Static fraction of each feature-grid cell (N,h*w) from pseudo-label PNGs."""
    lut = torch.from_numpy(static_lut(tuple(static_names)))
    maps = []
    for path in image_paths:
        label = torch.from_numpy(np.asarray(Image.open(labels_dir / f"{path.stem}.png"))).long()
        maps.append(lut[label])
    pooled = torch.nn.functional.adaptive_avg_pool2d(torch.stack(maps)[:, None], grid)
    return pooled.flatten(1)


def init_aggregator(cfg: DictConfig, aggregator: nn.Module, backbone: nn.Module, train_db: FeatureStore,
                    train: PlaceSet, semantic: Semantic) -> dict:
    """k-means (NetVLAD) or semantic-constrained (SRAL) initialisation; returns what was used."""
    feats, where = sample_local_features(backbone, train_db, int(cfg.model.init_features), cfg.seed)
    if cfg.filter.init == "kmeans":
        alpha = aggregator.init_from_features(feats, seed=cfg.seed)
        return {"init": "kmeans", "features": len(feats), "alpha": float(alpha)}
    assert semantic.labels_dir is not None
    grid = grid_size(backbone, tuple(cfg.data.image_size))
    static = static_grid(semantic.labels_dir, list(train.db_paths), grid,
                         list(cfg.teacher.static_classes))
    is_static = static[where[:, 0], where[:, 1]] >= 0.5
    counts = aggregator.init_semantic(feats[is_static], feats[~is_static], seed=cfg.seed)
    return {"init": "semantic", **{k: (float(v) if isinstance(v, float) else v) for k, v in counts.items()}}
