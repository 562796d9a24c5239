"""Evaluate a checkpoint on any place set: ``python -m semvpr.eval ckpt=PATH [data=... data.root=...]``.

The model is rebuilt from the configuration stored in the checkpoint (its semantic artifacts come
from the artifact cache, rebuilt deterministically if absent), then the weights are loaded.
Prints the recalls; the last line is one JSON object.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from semvpr.build import (backbone_key, backbone_name, build_backbone, build_mask_source, build_places,
                          build_semantic, Semantic)
from semvpr.errors import SemvprError
from semvpr.features import cached_place_features
from semvpr.models.netvlad import PCAWhitening
from semvpr.models.retriever import Retriever
from semvpr.train import CONF_DIR, evaluate_features, write_json

MODEL_KEYS = ("backbone", "filter", "model", "teacher", "student", "seed")


def load_checkpoint(path: str | Path) -> tuple[dict[str, Any], DictConfig]:
    """The checkpoint's state dict and the run config saved in it."""
    path = Path(path)
    if not path.is_file():
        raise SemvprError(f"checkpoint {path} not found (a run writes <run dir>/checkpoints/tested.ckpt)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        config = ckpt["hyper_parameters"]["config"]
    except Exception as err:  # noqa: BLE001 - any unreadable file gets the same one line
        raise SemvprError(f"{path} is not a semvpr checkpoint ({type(err).__name__}: {err})") from None
    return ckpt["state_dict"], OmegaConf.create(config)


def model_config(cfg: DictConfig, trained: DictConfig, explicit: set[str]) -> DictConfig:
    """The checkpoint's model config with this invocation's data and paths."""
    for key in explicit & {"backbone", "filter"}:
        if OmegaConf.to_container(cfg[key]) != OmegaConf.to_container(trained[key]):
            raise SemvprError(
                f"checkpoint {cfg.ckpt} was trained with backbone={backbone_name(trained)} "
                f"filter={trained.filter.name}; drop the {key}= override (the model comes from the checkpoint)")
    merged = OmegaConf.merge(trained, {"data": cfg.data, "paths": cfg.paths, "ckpt": cfg.ckpt})
    return merged


def load_retriever(cfg: DictConfig, explicit: set[str] = frozenset()) -> tuple[Retriever, DictConfig, Any]:
    """The checkpoint's retriever (eval mode), its merged config and its mask-cache key."""
    state, trained = load_checkpoint(cfg.ckpt)
    merged = model_config(cfg, trained, set(explicit))
    backbone = build_backbone(merged)
    # The semantic artifacts belong to the training run: rebuild them from its own data config.
    semantic = Semantic()
    if trained.filter.mask in ("teacher", "student"):
        semantic = build_semantic(trained, build_places(trained, ("train",))["train"], backbone)
    mask_source, mask_key = build_mask_source(merged, semantic)
    aggregator = instantiate(merged.filter.aggregator, dim=backbone.out_channels)
    whitening = PCAWhitening(aggregator.output_dim, merged.model.pca_dim) if merged.model.pca_dim else None
    retriever = Retriever(backbone, aggregator, mask_source, whitening,
                          eval_batch_size=merged.model.eval_batch_size)
    try:
        retriever.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise SemvprError(f"checkpoint {cfg.ckpt} does not fit backbone={backbone_name(merged)} "
                          f"filter={merged.filter.name}: {str(err).splitlines()[0]}") from None
    return retriever.eval(), merged, mask_key


def evaluate_checkpoint(cfg: DictConfig, explicit: set[str] = frozenset()) -> dict[str, Any]:
    """Recall@1/5/10/20 of the checkpoint on cfg.data's test split."""
    retriever, merged, mask_key = load_retriever(cfg, explicit)
    backbone, mask_source = retriever.backbone, retriever.mask_source
    test = build_places(merged, ("test",))["test"]
    features = cached_place_features(test, backbone, backbone_key(merged), mask_source, mask_key,
                                     merged.data.image_size, merged.paths.cache_dir,
                                     merged.model.eval_batch_size, merged.data.num_workers)
    result = evaluate_features(retriever, features)
    return {"checkpoint": str(cfg.ckpt), "data": merged.data.name, "filter": merged.filter.name,
            "backbone": backbone_name(merged), "database": len(test.db_paths), "queries": len(test.q_paths),
            "queries_without_positives": result["num_without_positives"],
            **{f"test/R@{n}": round(v, 2) for n, v in result["recalls"].items()}}


@hydra.main(config_path=CONF_DIR, config_name="eval", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}
    try:
        result = evaluate_checkpoint(cfg, explicit)
    except SemvprError as err:
        print(f"semvpr: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    write_json(Path(HydraConfig.get().runtime.output_dir) / "eval.json", result)
    for n in (1, 5, 10, 20):
        print(f"R@{n:<2d} {result[f'test/R@{n}']:6.2f}")
    print(json.dumps(result))


def main() -> None:
    """Console entry point."""
    _hydra_main()


if __name__ == "__main__":
    main()
