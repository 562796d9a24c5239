"""A trained retriever rebuilt from its checkpoint: what the commands that read checkpoints
(``semvpr.eval``, ``semvpr.localize``) and the hub share.

The model comes from the checkpoint's record (``semvpr.core.checkpoint``: validated against the
project's own configs, nothing stored in the file is run) and is assembled by the same builder as a
training run; a command-line choice that would change the model is refused.
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from semvpr.config.build import build_backbone, build_mask_source, build_retriever
from semvpr.config.checks import check_model
from semvpr.core.checkpoint import model_config, read_checkpoint
from semvpr.core.errors import SemvprError
from semvpr.retrieval.retriever import Retriever

#: Command-line group choices that would change the model, and the groups each one sets.
MODEL_OVERRIDES = {
    "backbone": ("backbone",),
    "aggregator": ("aggregator",),
    "mask": ("mask",),
    "filter": ("aggregator", "mask"),
}


def load_retriever(
    cfg: DictConfig, explicit: set[str] = frozenset(), *, new_images: bool = False, ckpt: str | Path | None = None
) -> tuple[Retriever, DictConfig]:
    """The checkpoint ``ckpt`` (default ``cfg.ckpt``) as a retriever in eval mode, and the config it was
    rebuilt with, whose model values are checked as a run's are (``check_model``: a record may hold
    values of the right type that no run could use). ``new_images``: the caller describes images that
    come without label maps (localize, the hub), which a mask source that reads ground truth cannot."""
    path = Path(str(cfg.ckpt)) if ckpt is None else Path(ckpt)
    state, record = read_checkpoint(path)
    merged = model_config(record, cfg, where=f"checkpoint {path}")
    check_model(merged, where=f"checkpoint {path}")
    trained = f"backbone={merged.backbone.name} aggregator={merged.aggregator.name} mask={merged.mask.name}"
    for override in sorted(explicit & set(MODEL_OVERRIDES)):
        if any(cfg[group].name != merged[group].name for group in MODEL_OVERRIDES[override]):
            raise SemvprError(
                f"checkpoint {path} was trained with {trained}; drop the {override}= override "
                "(the model comes from the checkpoint)"
            )
    backbone = build_backbone(merged.backbone, int(merged.seed), pretrained=False)
    mask_source = build_mask_source(merged, backbone)
    if new_images and mask_source is not None and not mask_source.describes_new_images:
        raise SemvprError(
            f"checkpoint {path} uses mask={merged.mask.name}, which needs ground-truth label maps "
            f"for every image; it cannot describe new images"
        )
    retriever = build_retriever(merged, backbone, mask_source, training=False)
    try:
        retriever.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise SemvprError(f"checkpoint {path} does not fit {trained}: {str(err).splitlines()[0]}") from None
    return retriever.eval(), merged


def explicit_keys() -> set[str]:
    """Config keys this invocation overrode on the command line."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}
