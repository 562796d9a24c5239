"""``check_config``: the one place a run's settings are checked, first thing in every command, before
anything is read or written, so a bad value is one line naming its key instead of a late traceback."""

from __future__ import annotations

import math
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from semvpr.config.components import COMPONENTS, component_class, options
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import CONF_DIR, check_dir_path
from semvpr.core.threads import parse_setting
from semvpr.data.places import check_radius
from semvpr.models.masks import WEIGHTINGS
from semvpr.retrieval.features import STORAGES

#: Lightning 2's precision settings (``Trainer(precision=...)``).
PRECISIONS = (
    "transformer-engine",
    "transformer-engine-float16",
    "16-true",
    "16-mixed",
    "bf16-true",
    "bf16-mixed",
    "32-true",
    "64-true",
    "64",
    "32",
    "16",
    "bf16",
)
SEED_MAX = 2**32 - 1  # numpy's (and Lightning's seed_everything) range


def whole_number(value: object, key: str, low: int, high: int | None = None) -> int:
    """``value`` as an int in [low, high], or one line naming ``key``."""
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)
    if not ok:
        bounds = f"from {low} to {high}" if high is not None else f">= {low}"
        raise SemvprError(f"{key}={value!r} must be a whole number {bounds}")
    return int(value)  # type: ignore[arg-type]


def _leaves(node: object, prefix: str = "") -> set[str]:
    """Dotted keys of a plain mapping's leaves."""
    if not isinstance(node, dict):
        return {prefix.rstrip(".")}
    return set().union(*(_leaves(v, f"{prefix}{k}.") for k, v in node.items())) if node else set()


def check_overrides(argv: list[str]) -> None:
    """An override that names the training protocol as a ``model`` group or ``model.`` setting (it is the
    ``recipe`` group) gets one line saying where it is, instead of Hydra's error."""
    recipe = _leaves(OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "recipe" / "triplet.yaml")))
    model = _leaves(OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "train.yaml").model))
    for arg in argv:
        key, sep, value = arg.lstrip("+~").partition("=")
        if key == "model" and sep:
            raise SemvprError(
                f"{arg}: the training protocol is the recipe group now: model=netvlad is recipe=triplet "
                f"({', '.join(options('recipe'))})"
            )
        rest = key.removeprefix("model.")
        if (
            key.startswith("model.")
            and rest not in model
            and any(r == rest or r.startswith(f"{rest}.") for r in recipe)
        ):
            raise SemvprError(f"{arg}: {key} is a setting of the training protocol now: recipe.{rest}={value}")


@exit_on_user_error
def check_overrides_or_exit(argv: list[str]) -> None:
    """:func:`check_overrides` as a command's first step: one line and exit code 2."""
    check_overrides(argv)


def check_config(cfg: DictConfig) -> None:
    """Reject config values that would fail deep inside a run with a cryptic error (or none at all).

    One function for every command's config: the retrieval settings where the config has them (train,
    eval, localize), the segmentation set's where it has one (segment).
    """
    whole_number(cfg.seed, "seed", 0, SEED_MAX)
    parse_setting(cfg.get("threads", "auto"))
    check_dir_path(Path(str(cfg.paths.cache_dir)), "paths.cache_dir")
    if "model" in cfg:
        _check_retrieval(cfg)
    if "seg" in cfg:
        _check_segmentation(cfg)


def _check_retrieval(cfg: DictConfig) -> None:
    if cfg.get("num_figure_queries") is not None:
        whole_number(cfg.num_figure_queries, "num_figure_queries", 1)
    if cfg.get("top_k") is not None:
        whole_number(cfg.top_k, "top_k", 1)
    lr = cfg.recipe.optimizer.get("lr")
    try:
        lr_ok = lr is not None and math.isfinite(float(lr)) and float(lr) > 0
    except (TypeError, ValueError):
        lr_ok = False
    if not lr_ok:
        raise SemvprError(f"recipe.optimizer.lr={lr!r} must be a number > 0")
    if str(cfg.trainer.precision) not in PRECISIONS:
        raise SemvprError(f"trainer.precision={cfg.trainer.precision!r} is not one of {list(PRECISIONS)}")
    if cfg.get("ckpt_path") not in (None, "last"):
        from semvpr.core.checkpoint import read_checkpoint

        read_checkpoint(cfg.ckpt_path)
    for group in COMPONENTS:
        component_class(cfg, group)
    for key in ("num_clusters", "eval_batch_size", "init_features", "init_per_image"):
        whole_number(cfg.model[key], f"model.{key}", 1)
    for key in ("batch_size", "num_negatives", "cache_refresh"):
        whole_number(cfg.recipe[key], f"recipe.{key}", 1)
    if cfg.recipe.get("queries_per_epoch") is not None:
        whole_number(cfg.recipe.queries_per_epoch, "recipe.queries_per_epoch (or null = all)", 1)
    positive = check_radius(cfg.recipe.positive_radius, "recipe.positive_radius")
    if check_radius(cfg.recipe.negative_radius, "recipe.negative_radius") < positive:
        raise SemvprError(
            f"recipe.negative_radius={cfg.recipe.negative_radius} is below recipe.positive_radius="
            f"{cfg.recipe.positive_radius}: a negative could then be a positive"
        )
    if len(cfg.data.image_size) != 2:
        raise SemvprError(f"data.image_size={list(cfg.data.image_size)} must be [H, W]")
    if cfg.features.storage not in STORAGES:
        raise SemvprError(f"features.storage={cfg.features.storage!r} is not one of {list(STORAGES)}")
    weighting = cfg.mask.weights
    if weighting not in WEIGHTINGS:
        raise SemvprError(f"mask.weights={weighting!r} is not one of {list(WEIGHTINGS)}")
    if "ckpt" not in cfg and cfg.student.get("checkpoint"):
        raise SemvprError(
            f"student.checkpoint={cfg.student.checkpoint}: a saved student is read by semvpr.eval, localize and "
            "the hub (mask=student student.checkpoint=DIR); a training run trains its own: drop it"
        )
    if weighting == "learned" and cfg.mask.get("module") is None:
        raise SemvprError(
            "mask=none has no mask to weight; mask.weights=learned (filter.weights=learned) needs "
            "mask=student, teacher or oracle (filter=unet, mask2former or oracle)"
        )


def _check_segmentation(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg.seg, "root"):
        raise SemvprError(
            f"seg.root is not set; pass the {cfg.seg.name} folder, e.g. seg.root=../shared/realdata/camvid"
        )
    if len(cfg.seg.image_size) != 2:
        raise SemvprError(f"seg.image_size={list(cfg.seg.image_size)} must be [H, W]")
    if not cfg.backbones:
        raise SemvprError(
            "backbones is empty: the command trains one student per backbone (e.g. backbone@backbones.vgg16=vgg16)"
        )
