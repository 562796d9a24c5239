"""A semvpr checkpoint as other tools' scripts expect a VPR model (VPR-methods-evaluation style).

:func:`load_model` rebuilds the checkpoint through the same trusted path as ``semvpr.eval``
(``semvpr.core.checkpoint`` validates the record against the project's configs; ``config.restore``
loads the weights and takes eval's overrides: another mask source, or ``ckpt="none"``) and wraps it
in :class:`HubModel`: a module mapping a batch of images normalised with the ImageNet mean/std to
L2-normalised global descriptors, with the matching preprocessing as ``model.transform`` (PIL image →
normalised tensor) and ``model.feature_dim``. It computes them in ``semvpr.eval``'s arithmetic for the same
model and overrides (``config.command.model_arithmetic``: an author's release file in fp32 unless
``trainer.precision=`` is given), so the same images give eval's descriptors.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor, nn
from torchvision import transforms

from semvpr.config.checks import check_config, check_overrides
from semvpr.config.command import Arithmetic, model_arithmetic
from semvpr.config.plan import data_settings
from semvpr.config.restore import is_untrained, load_retriever
from semvpr.core.device import resolve
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast
from semvpr.data.images import EightBitRGB
from semvpr.models.backbones import IMAGENET_MEAN, IMAGENET_STD
from semvpr.retrieval.recall import check_finite
from semvpr.retrieval.retriever import Retriever


class HubModel(nn.Module):
    """ImageNet-normalised images (B, 3, H, W) → L2-normalised descriptors (B, feature_dim), computed in
    ``arithmetic`` (``model.arithmetic``: eval's for the same model) on the device the model is on: eval's
    descriptors, a half precision's rounding included."""

    def __init__(
        self,
        retriever: Retriever,
        arithmetic: Arithmetic,
        image_size: Sequence[int] | None = None,
        resize: str = "bilinear",
    ) -> None:
        super().__init__()
        self.retriever = retriever
        self.arithmetic = arithmetic
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.feature_dim = retriever.descriptor_dim
        #: PIL image → the normalised tensor this module takes: RGB as semvpr's image reader makes it (grey,
        #: palette, alpha and CMYK converted; 16-bit refused), resized to ``image_size`` if given as semvpr's
        #: loader resizes for this model (``resize``, ``data.images.RESIZES``: PIL's bilinear, or bicubic with
        #: antialiasing on the tensor as Bag-of-Queries' transform does).
        self.transform = transforms.Compose(
            [EightBitRGB(), *_resized(image_size, resize), transforms.Normalize(IMAGENET_MEAN, IMAGENET_STD)]
        )

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> HubModel:
        """Moved as a module (``model.to``, ``.cuda``): the retriever's own (Lightning's) device follows."""
        super()._apply(fn, recurse)
        self.retriever.to(self.mean.device)
        return self

    @torch.no_grad()
    def forward(self, images: Tensor) -> Tensor:
        """Descriptors of a normalised batch (the retriever itself takes [0, 1] images)."""
        if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 3:
            shape = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
            raise SemvprError(f"images must be a batch (B, 3, H, W), got {shape}; model.transform makes one image")
        if not images.is_floating_point():  # 0..255 bytes read as normalised values give wrong descriptors
            raise SemvprError(
                f"images must be floats normalised with the ImageNet mean/std (model.transform), got {images.dtype}"
            )
        cast = {p.dtype for p in self.retriever.parameters() if p.is_floating_point()} - {torch.float32}
        if cast:  # .half() / .bfloat16() / .double(): weights the float activations of its layers cannot meet
            raise SemvprError(
                f"the model's weights are {min(map(str, cast))}; it keeps them float32 and computes in semvpr.eval's "
                f"precision for it ({self.arithmetic.precision}; overrides=['trainer.precision=...'] sets another): "
                "model.float() (or load it again: 16 bits rounded them)"
            )
        device = self.mean.device
        if images.device != device:
            raise SemvprError(
                f"images are on {images.device}, the model on {device}: move the images there "
                f"(images.to('{device}')), or the model (model.to('{images.device}'))"
            )
        if not len(images):
            return images.new_zeros((0, self.feature_dim), dtype=torch.float32)
        images = images.to(self.mean.dtype)
        with self.arithmetic.run(device.type), autocast(device):
            descriptors = self.retriever(images * self.std + self.mean).float()
        if not bool(torch.isfinite(descriptors).all()):  # refused as semvpr.eval refuses them
            check_finite(descriptors.cpu().numpy(), "these images")
        return descriptors


def load_model(
    ckpt: str | Path,
    image_size: Sequence[int] | None = None,
    overrides: Sequence[str] | None = (),
    device: torch.device | str = "cpu",
) -> HubModel:
    """The checkpoint as a :class:`HubModel` in eval mode on ``device`` (eval's ``device=``: cpu, cuda, cuda:N or
    auto; move it with ``.to`` or ``.cuda``).
    ``overrides`` are ``semvpr.eval``'s: ``["mask=student", "student.checkpoint=DIR"]`` replaces the checkpoint's mask
    source; ``ckpt="none"`` with e.g. ``["aggregator=gem"]`` is the model with no VPR training."""
    from hydra import compose, initialize_config_dir

    # The path is passed as a value, never through Hydra's override syntax: there ',' '=' and quotes
    # are syntax and '${...}' an interpolation, so the file loaded would not be the one named.
    if isinstance(overrides, str):
        raise SemvprError(f"overrides={overrides!r} is one string; pass a list of them: overrides=[{overrides!r}]")
    given = [str(o) for o in overrides or ()]
    if not isinstance(ckpt, (str, os.PathLike)):
        raise SemvprError(f"ckpt={ckpt!r} names no file; name a checkpoint or release file, or ckpt='none'")
    if image_size is not None and not _image_size(image_size):
        raise SemvprError(f"image_size={image_size!r} is not a size: give [height, width] (or one side) in pixels")
    if isinstance(ckpt, str) and not ckpt:
        raise SemvprError("ckpt='' names no file; name a checkpoint or release file, or ckpt='none'")
    untrained = is_untrained(ckpt)
    check_overrides(given, "eval")  # as the CLI checks them: an unknown key or a _target_ is one line
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="eval", overrides=[*(["ckpt=none"] if untrained else []), *given])
    check_config(cfg)
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in given}
    target = None if untrained else Path(ckpt).expanduser()
    where = resolve(str(device))
    retriever, merged = load_retriever(cfg, explicit, new_images=True, warn=False, ckpt=target, device=where)
    arithmetic = model_arithmetic(cfg, merged, explicit)
    resize = data_settings(merged).resize
    return HubModel(retriever, arithmetic, image_size, resize).to(where).eval()


def _resized(image_size: Sequence[int] | None, resize: str) -> list[Callable[[object], object]]:
    """PIL image → [0, 1] tensor, resized to ``image_size`` (if given) as ``data.images.load_image`` resizes."""
    if not image_size:
        return [transforms.ToTensor()]
    if resize == "bilinear":
        return [transforms.Resize(tuple(image_size), antialias=True), transforms.ToTensor()]
    bicubic = transforms.InterpolationMode.BICUBIC
    return [transforms.ToTensor(), transforms.Resize(tuple(image_size), interpolation=bicubic, antialias=True)]


def _image_size(value: object) -> bool:
    """Whether ``value`` is a size torchvision's Resize takes as meant: one or two positive whole numbers."""
    sides = [value] if isinstance(value, int) else list(value) if isinstance(value, (list, tuple)) else []
    return len(sides) in (1, 2) and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in sides)
