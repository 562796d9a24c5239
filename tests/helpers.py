"""Test helpers: compose the project's Hydra config with the tiny SynthCity preset."""
from __future__ import annotations

from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def tiny_config(cache_dir: Path, *overrides: str, config_name: str = "train") -> DictConfig:
    """The train config on the tiny preset, caching into ``cache_dir``."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name,
                       overrides=["experiment=tiny", f"paths.cache_dir={cache_dir}", *overrides])


def config(*overrides: str, config_name: str = "train") -> DictConfig:
    """The project's config with these overrides."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))


def write_checkpoint(cfg: DictConfig, path: Path) -> dict[str, torch.Tensor]:
    """Write an untrained model's checkpoint as a run does (Lightning's state_dict + hyper_parameters)."""
    from semvpr.config.build import build_backbone, build_mask_source, build_retriever

    backbone = build_backbone(cfg.backbone, cfg.seed)
    retriever = build_retriever(cfg, backbone, build_mask_source(cfg, backbone), training=False)
    torch.save({"state_dict": retriever.state_dict(), "hyper_parameters": dict(retriever.hparams), "epoch": 0}, path)
    return retriever.state_dict()


def record_first_unit_batches(backbone) -> list[int]:
    """The batch size of every pass through a backbone's first unit, appended as they happen."""
    seen: list[int] = []
    backbone.units[0].register_forward_hook(lambda _m, args, _out: seen.append(args[0].shape[0]))
    return seen
