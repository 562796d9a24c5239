"""A trained retriever rebuilt from its checkpoint, and its descriptors of a place set: what the
entry points that read checkpoints (``semvpr.eval``, ``semvpr.localize``) and the hub share.

The model comes from the checkpoint's record (``semvpr.core.checkpoint``: validated against the project's
own configs, nothing stored in the file is run); a command-line choice that would change the model is
refused. Descriptors are computed once per model and image set and cached memory-mapped (kind
``descriptors``), so memory does not grow with the dataset.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from semvpr.core.cache import build_once, state_hash
from semvpr.config.build import build_aggregator, build_backbone, build_class_weights, build_mask_source
from semvpr.core.checkpoint import model_config, read_checkpoint
from semvpr.data.places import PlaceSet
from semvpr.core.errors import SemvprError
from semvpr.core.io import open_array
from semvpr.models.aggregators.netvlad import PCAWhitening
from semvpr.retrieval.retriever import Retriever


#: Command-line group choices that would change the model, and the groups each one sets.
MODEL_OVERRIDES = {"backbone": ("backbone",), "aggregator": ("aggregator",), "mask": ("mask",),
                   "filter": ("aggregator", "mask")}


def load_retriever(cfg: DictConfig, explicit: set[str] = frozenset()) -> tuple[Retriever, DictConfig]:
    """The checkpoint ``cfg.ckpt`` as a retriever in eval mode, and the config it was rebuilt with."""
    state, record = read_checkpoint(cfg.ckpt)
    merged = model_config(record, cfg, where=f"checkpoint {cfg.ckpt}")
    trained = f"backbone={merged.backbone.name} aggregator={merged.aggregator.name} mask={merged.mask.name}"
    for override in sorted(explicit & set(MODEL_OVERRIDES)):
        if any(cfg[group].name != merged[group].name for group in MODEL_OVERRIDES[override]):
            raise SemvprError(f"checkpoint {cfg.ckpt} was trained with {trained}; drop the {override}= override "
                              "(the model comes from the checkpoint)")
    backbone = build_backbone(merged, pretrained=False)
    aggregator = build_aggregator(merged, backbone)
    whitening = PCAWhitening(aggregator.output_dim, merged.model.pca_dim) if merged.model.pca_dim else None
    retriever = Retriever(backbone, aggregator, build_mask_source(merged, backbone), whitening,
                          eval_batch_size=merged.model.eval_batch_size, num_workers=merged.data.num_workers,
                          record=record, class_weights=build_class_weights(merged))
    try:
        retriever.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise SemvprError(f"checkpoint {cfg.ckpt} does not fit {trained}: {str(err).splitlines()[0]}") from None
    return retriever.eval(), merged


def descriptor_dim(retriever: Retriever) -> int:
    """Size of the retriever's global descriptor (after PCA-whitening, if any)."""
    return retriever.whitening.out_dim if retriever.whitening is not None else retriever.aggregator.output_dim


def place_descriptors(retriever: Retriever, places: PlaceSet, side: str, cfg: DictConfig) -> np.ndarray:
    """Descriptors of a place set's database or queries (memory-mapped), computed once per model and data."""
    paths, labels = (places.db_paths, places.db_labels) if side == "db" else (places.q_paths, places.q_labels)
    key = {"model": state_hash(retriever.state_dict()), "images": places.identity(side),
           "image_size": list(cfg.data.image_size)}
    dim = descriptor_dim(retriever)

    def build(tmp: Path) -> None:
        out = open_array(tmp / "descriptors.npy", np.float32, (len(paths), dim), f"the descriptors of {places.name}")
        retriever.describe_images(paths, labels, cfg.data.image_size, out, desc=f"{places.name} {side}")
        out.flush()

    folder = build_once(cfg.paths.cache_dir, "descriptors", key, build)
    try:
        desc = np.load(folder / "descriptors.npy", mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SemvprError(f"descriptor cache {folder} is unreadable ({type(err).__name__}); delete it to rebuild") from None
    if desc.shape != (len(paths), dim) or desc.dtype != np.float32:
        raise SemvprError(f"descriptor cache {folder} holds {desc.dtype}{list(desc.shape)}, expected "
                          f"float32[{len(paths)}, {dim}]; delete it to rebuild")
    return desc


def explicit_keys() -> set[str]:
    """Config keys this invocation overrode on the command line."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}
