"""Test helpers: compose the project's Hydra config with the tiny SynthCity preset."""
from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def tiny_config(cache_dir: Path, *overrides: str, config_name: str = "train") -> DictConfig:
    """The train config on the tiny preset, caching into ``cache_dir``."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name,
                       overrides=["experiment=tiny", f"paths.cache_dir={cache_dir}", *overrides])
