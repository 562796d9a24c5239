"""A semvpr checkpoint as other tools' scripts expect a VPR model (VPR-methods-evaluation style).

:func:`load_model` rebuilds the checkpoint through the same trusted path as ``semvpr.eval``
(``semvpr.core.checkpoint`` validates the record against the project's configs; ``config.restore``
loads the weights and takes eval's overrides: another mask source, or ``ckpt="none"``) and wraps it
in :class:`HubModel`: a module mapping a batch of images normalised with the ImageNet mean/std to
L2-normalised global descriptors, with the matching preprocessing as ``model.transform`` (PIL image →
normalised tensor) and ``model.feature_dim``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchvision import transforms

from semvpr.config.checks import check_config, check_overrides
from semvpr.config.restore import is_untrained, load_retriever
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR
from semvpr.models.backbones import IMAGENET_MEAN, IMAGENET_STD
from semvpr.retrieval.retriever import Retriever


class HubModel(nn.Module):
    """ImageNet-normalised images (B, 3, H, W) → L2-normalised descriptors (B, feature_dim)."""

    def __init__(self, retriever: Retriever, image_size: Sequence[int] | None = None) -> None:
        super().__init__()
        self.retriever = retriever
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.feature_dim = retriever.descriptor_dim
        resize = [transforms.Resize(tuple(image_size), antialias=True)] if image_size else []
        #: PIL image → the normalised tensor this module takes (resized to ``image_size`` if given).
        self.transform = transforms.Compose(
            [*resize, transforms.ToTensor(), transforms.Normalize(IMAGENET_MEAN, IMAGENET_STD)]
        )

    @torch.no_grad()
    def forward(self, images: Tensor) -> Tensor:
        """Descriptors of a normalised batch (the retriever itself takes [0, 1] images)."""
        if self.retriever.device != images.device:  # moved as a submodule (.cuda()): Lightning's own device follows
            self.retriever.to(images.device)
        return F.normalize(self.retriever(images * self.std + self.mean).float(), dim=1)


def load_model(
    ckpt: str | Path,
    image_size: Sequence[int] | None = None,
    overrides: Sequence[str] = (),
    device: torch.device | str = "cpu",
) -> HubModel:
    """The checkpoint as a :class:`HubModel` in eval mode on ``device`` (move it with ``.to`` or ``.cuda``).
    ``overrides`` are ``semvpr.eval``'s: ``["mask=student", "student.checkpoint=DIR"]`` replaces the checkpoint's mask
    source; ``ckpt="none"`` with e.g. ``["aggregator=gem"]`` is the model with no VPR training."""
    from hydra import compose, initialize_config_dir

    # The path is passed as a value, never through Hydra's override syntax: there ',' '=' and quotes
    # are syntax and '${...}' an interpolation, so the file loaded would not be the one named.
    if isinstance(overrides, str):
        raise SemvprError(f"overrides={overrides!r} is one string; pass a list of them: overrides=[{overrides!r}]")
    given = [str(o) for o in overrides]
    if isinstance(ckpt, str) and not ckpt:
        raise SemvprError("ckpt='' names no file; name a checkpoint or release file, or ckpt='none'")
    untrained = is_untrained(ckpt)
    check_overrides(given, "eval")  # as the CLI checks them: an unknown key or a _target_ is one line
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="eval", overrides=[*(["ckpt=none"] if untrained else []), *given])
    check_config(cfg)
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in given}
    target = None if untrained else Path(ckpt).expanduser()
    retriever, _ = load_retriever(cfg, explicit, new_images=True, warn=False, ckpt=target)
    return HubModel(retriever, image_size).to(device).eval()
