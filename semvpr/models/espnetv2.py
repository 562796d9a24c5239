"""ESPNetv2 semantic segmentation (Mehta et al., "ESPNetv2: A Light-weight, Power Efficient, and General
Purpose Convolutional Neural Network", CVPR 2019), as its authors' Cityscapes releases define it
(sacmehta/EdgeNets, ``model/segmentation/espnetv2.py``): the EESPNet encoder's levels 1-4 and a bottom-up
decoder of efficient pyramid pooling stages with gated skips, returning 20 logits per pixel (the 19
Cityscapes train ids, then background) at the input resolution.

A released file is read as data (weights only): its width, class count and depth come from the shapes, and
every key and shape is checked against the network those imply before any weight is used (docs/trust.md).
Module and parameter names are the authors' so a file's state dict loads as it is."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.checkpoint import read_weights
from semvpr.core.errors import SemvprError
from semvpr.data.classes import TRAIN_ID_NAMES
from semvpr.models.weights import check_tensor

#: The channel order of the authors' Cityscapes files: train ids 0-18, then background.
CITYSCAPES_CHANNELS: tuple[str, ...] = (*TRAIN_ID_NAMES, "background")
#: Parallel branches of every EESP unit, and the receptive-field limit (a 3x3 kernel dilated up to it) of
#: level 2's, level 3's and level 4's down-sampler and of the units at levels 3 and 4.
BRANCHES = 4
DOWN_LIMITS = (13, 11, 9)
UNIT_LIMITS = (9, 7)
#: EESP units after level 3's and level 4's down-samplers (the authors' ``rep_layers``).
UNITS = (3, 7)
#: The decoder's widths for Cityscapes (the authors' ``dec_feat_dict['city']``).
DECODER_BASE = 16
#: The scales of the efficient pyramid pooling, largest first.
PYRAMID_SCALES = (2.0, 1.5, 1.0, 0.5, 0.1)
#: Channels of the image itself, fed again to each down-sampler (input reinforcement).
IMAGE_CHANNELS = 3


def dilations(limit: int, branches: int = BRANCHES) -> list[int]:
    """The dilation of each branch of an EESP unit: branch i a 3x3 kernel of receptive field 3 + 2i, or 3 past
    ``limit``, in ascending order of receptive field."""
    fields = sorted(3 + 2 * i if 3 + 2 * i <= limit else 3 for i in range(branches))
    return [(field - 1) // 2 for field in fields]


class ConvBN(nn.Module):
    """Convolution (same padding, no bias), BatchNorm and, where ``act``, a per-channel PReLU."""

    def __init__(
        self, cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1, dilation: int = 1, act: bool = True
    ) -> None:
        super().__init__()
        pad = (kernel - 1) // 2 * dilation
        self.conv = nn.Conv2d(cin, cout, kernel, stride, pad, dilation=dilation, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.act = nn.PReLU(cout) if act else None

    def forward(self, x: Tensor) -> Tensor:
        x = self.bn(self.conv(x))
        return x if self.act is None else self.act(x)


class DepthwiseDilated(nn.Module):
    """A 3x3 depthwise convolution with a dilation, no bias (the authors' ``CDilated``)."""

    def __init__(self, channels: int, stride: int, dilation: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, stride, dilation, dilation=dilation, groups=channels, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x)


class BNAct(nn.Module):
    """BatchNorm then a per-channel PReLU."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.bn = nn.BatchNorm2d(channels)
        self.act = nn.PReLU(channels)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.bn(x))


class EESP(nn.Module):
    """Extremely efficient spatial pyramid unit: reduce with a grouped 1x1, split into depthwise dilated
    branches summed hierarchically (each adds the previous one), merge with BatchNorm + PReLU and a grouped
    1x1 expansion; the input is added where shapes agree, then a PReLU. A strided unit (inside a
    :class:`DownSampler`) returns the expansion as it is."""

    def __init__(self, cin: int, cout: int, stride: int, limit: int, branches: int = BRANCHES) -> None:
        super().__init__()
        width = cout // branches
        self.strided = stride == 2
        self.proj_1x1 = ConvBN(cin, width, 1, groups=branches)
        self.spp_dw = nn.ModuleList(DepthwiseDilated(width, stride, d) for d in dilations(limit, branches))
        self.conv_1x1_exp = ConvBN(cout, cout, 1, groups=branches, act=False)
        self.br_after_cat = BNAct(cout)
        self.module_act = nn.PReLU(cout)

    def forward(self, x: Tensor) -> Tensor:
        reduced = self.proj_1x1(x)
        branches = [self.spp_dw[0](reduced)]
        for branch in self.spp_dw[1:]:
            branches.append(branch(reduced) + branches[-1])
        out = self.conv_1x1_exp(self.br_after_cat(torch.cat(branches, 1)))
        if self.strided:
            return out
        if out.shape == x.shape:
            out = out + x
        return self.module_act(out)


class DownSampler(nn.Module):
    """Halves the resolution: [3x3 average pool of the input, strided EESP] concatenated, plus a projection of
    the image average-pooled to the same size (input reinforcement), then a PReLU."""

    def __init__(self, cin: int, cout: int, limit: int) -> None:
        super().__init__()
        self.eesp = EESP(cin, cout - cin, stride=2, limit=limit)
        self.inp_reinf = nn.Sequential(
            ConvBN(IMAGE_CHANNELS, IMAGE_CHANNELS, 3), ConvBN(IMAGE_CHANNELS, cout, 1, act=False)
        )
        self.act = nn.PReLU(cout)

    def forward(self, x: Tensor, image: Tensor) -> Tensor:
        pooled = F.avg_pool2d(x, 3, stride=2, padding=1)
        out = torch.cat([pooled, self.eesp(x)], 1)
        while image.shape[-2] > pooled.shape[-2]:
            image = F.avg_pool2d(image, 3, stride=2, padding=1)
        return self.act(out + self.inp_reinf(image))


class EESPNet(nn.Module):
    """The encoder (EESPNet's levels 1-4): a strided 3x3 at 1/2, a down-sampler each to 1/4, 1/8 (then
    :data:`UNITS` [0] EESP units) and 1/16 (then :data:`UNITS` [1])."""

    def __init__(self, widths: Sequence[int]) -> None:
        super().__init__()
        w1, w2, w3, w4 = widths
        self.level1 = ConvBN(IMAGE_CHANNELS, w1, 3, stride=2)
        self.level2_0 = DownSampler(w1, w2, DOWN_LIMITS[0])
        self.level3_0 = DownSampler(w2, w3, DOWN_LIMITS[1])
        self.level3 = nn.ModuleList(EESP(w3, w3, 1, UNIT_LIMITS[0]) for _ in range(UNITS[0]))
        self.level4_0 = DownSampler(w3, w4, DOWN_LIMITS[2])
        self.level4 = nn.ModuleList(EESP(w4, w4, 1, UNIT_LIMITS[1]) for _ in range(UNITS[1]))

    def forward(self, image: Tensor) -> list[Tensor]:
        """The four levels' outputs (strides 2, 4, 8, 16)."""
        l1 = self.level1(image)
        l2 = self.level2_0(l1, image)
        l3 = self.level3_0(l2, image)
        for unit in self.level3:
            l3 = unit(l3)
        l4 = self.level4_0(l3, image)
        for unit in self.level4:
            l4 = unit(l4)
        return [l1, l2, l3, l4]


class SeqConvBN(nn.Module):
    """:class:`ConvBN` as the decoder's layers name it (one ``cbr`` sequence)."""

    def __init__(self, cin: int, cout: int, kernel: int, groups: int = 1) -> None:
        super().__init__()
        conv = nn.Conv2d(cin, cout, kernel, 1, (kernel - 1) // 2, groups=groups, bias=False)
        self.cbr = nn.Sequential(conv, nn.BatchNorm2d(cout), nn.PReLU(cout))

    def forward(self, x: Tensor) -> Tensor:
        return self.cbr(x)


class SeqBNAct(nn.Module):
    """:class:`BNAct` as the decoder's layers name it (one ``br`` sequence)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.br = nn.Sequential(nn.BatchNorm2d(channels), nn.PReLU(channels))

    def forward(self, x: Tensor) -> Tensor:
        return self.br(x)


class ChannelShuffle(nn.Module):
    """Interleaves ``groups`` equal groups of channels (channel g*n + i goes to i*groups + g)."""

    def __init__(self, groups: int) -> None:
        super().__init__()
        self.groups = groups

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        return x.view(b, self.groups, c // self.groups, h, w).transpose(1, 2).reshape(b, c, h, w)


class PyramidPool(nn.Module):
    """Efficient pyramid pooling: a 1x1 projection, one depthwise 3x3 per scale of :data:`PYRAMID_SCALES`
    (applied at that scale of the map, at least 5x5, and brought back), the scales' maps concatenated,
    normalised, shuffled, fused by a grouped 3x3 and projected by a 1x1 (with a bias where it is the last
    layer, else BatchNorm + PReLU after it)."""

    def __init__(self, cin: int, proj: int, cout: int, last: bool = False) -> None:
        super().__init__()
        n = len(PYRAMID_SCALES)
        self.projection_layer = SeqConvBN(cin, proj, 1)
        self.stages = nn.ModuleList(nn.Conv2d(proj, proj, 3, 1, 1, groups=proj, bias=False) for _ in range(n))
        self.merge_layer = nn.Sequential(
            SeqBNAct(proj * n),
            ChannelShuffle(n),
            SeqConvBN(proj * n, proj, 3, groups=proj),
            nn.Conv2d(proj, cout, 1, bias=last),
        )
        self.br = None if last else SeqBNAct(cout)

    def forward(self, x: Tensor) -> Tensor:
        x = self.projection_layer(x)
        size = x.shape[-2:]
        maps = []
        for scale, stage in zip(PYRAMID_SCALES, self.stages, strict=True):
            scaled = tuple(max(5, math.ceil(v * scale)) for v in size)
            if scale > 1:
                up = F.interpolate(x, scaled, mode="bilinear", align_corners=True)
                maps.append(F.adaptive_avg_pool2d(stage(up), size))
            elif scale < 1:
                down = stage(F.adaptive_avg_pool2d(x, scaled))
                maps.append(F.interpolate(down, size, mode="bilinear", align_corners=True))
            else:
                maps.append(stage(x))
        out = self.merge_layer(torch.cat(maps, 1))
        return out if self.br is None else self.br(out)


class GatedSkip(nn.Module):
    """An encoder map brought to the decoder's width by a grouped 3x3 (groups: the widths' gcd) and scaled per
    channel by a sigmoid gate of its global average (the authors' ``EfficientPWConv``)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.wt_layer = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(cin, cout, 1, bias=False), nn.Sigmoid())
        self.expansion_layer = SeqConvBN(cin, cout, 3, groups=math.gcd(cin, cout))

    def forward(self, x: Tensor) -> Tensor:
        return self.expansion_layer(x) * self.wt_layer(x)


class ESPNetv2Segmentation(nn.Module):
    """ESPNetv2's segmentation network: logits (B, classes, H, W) of a normalised image (B, 3, H, W).

    ``widths``: the encoder's four level widths (32, 128, 256, 512 at s=2; 32, 64, 128, 256 at s=1)."""

    def __init__(self, widths: Sequence[int], classes: int) -> None:
        super().__init__()
        self.base_net = EESPNet(widths)
        dec = (4 * DECODER_BASE, 3 * DECODER_BASE, 2 * DECODER_BASE)
        proj = min(classes // 2, DECODER_BASE)
        self.bu_dec_l1 = PyramidPool(widths[3], proj, dec[0])
        self.bu_dec_l2 = PyramidPool(dec[0], proj, dec[1])
        self.bu_dec_l3 = PyramidPool(dec[1], proj, dec[2])
        self.bu_dec_l4 = PyramidPool(dec[2], proj, classes, last=True)
        self.merge_enc_dec_l2 = GatedSkip(widths[2], dec[0])
        self.merge_enc_dec_l3 = GatedSkip(widths[1], dec[1])
        self.merge_enc_dec_l4 = GatedSkip(widths[0], dec[2])
        self.bu_br_l2 = nn.Sequential(nn.BatchNorm2d(dec[0]), nn.PReLU(dec[0]))
        self.bu_br_l3 = nn.Sequential(nn.BatchNorm2d(dec[1]), nn.PReLU(dec[1]))
        self.bu_br_l4 = nn.Sequential(nn.BatchNorm2d(dec[2]), nn.PReLU(dec[2]))

    def forward(self, image: Tensor) -> Tensor:
        l1, l2, l3, l4 = self.base_net(image)
        out = self.bu_dec_l1(l4)
        steps = (
            (l3, self.merge_enc_dec_l2, self.bu_br_l2, self.bu_dec_l2),
            (l2, self.merge_enc_dec_l3, self.bu_br_l3, self.bu_dec_l3),
            (l1, self.merge_enc_dec_l4, self.bu_br_l4, self.bu_dec_l4),
        )
        for skip, gate, norm, decode in steps:
            # x2 (align_corners) where the sizes are even; an odd level's size otherwise, never off by one.
            up = F.interpolate(out, skip.shape[-2:], mode="bilinear", align_corners=True)
            out = decode(norm(gate(skip) + up))
        return F.interpolate(out, image.shape[-2:], mode="bilinear", align_corners=True)


# ---------------------------------------------------------------------------------------------- released files
def _shape(state: Mapping[str, Tensor], key: str, path: Path) -> torch.Size:
    value = state.get(key)
    if not isinstance(value, Tensor):
        raise SemvprError(f"{path}: no {key!r}; {_what_it_is(state)}")
    return value.shape


def _what_it_is(state: Mapping[str, object]) -> str:
    """What a state dict that is not an ESPNetv2 segmenter looks like, for the refusal."""
    keys = list(state)
    if any(k.startswith(("eff_pool_", "proj_enc_")) for k in keys):
        return "it is a DiCENet segmentation file (EdgeNets), not ESPNetv2: teacher=espnetv2 reads ESPNetv2 only"
    if any(k.startswith(("classifier.", "level5")) for k in keys):
        return "it is an ESPNetv2 ImageNet classifier, not a segmenter: give a Cityscapes segmentation file"
    if not any(k.startswith("base_net.") for k in keys):
        return f"it is not an ESPNetv2 segmentation state dict (its keys start {sorted(keys)[:3]})"
    return "the file is incomplete or of another architecture than ESPNetv2's segmentation network"


def architecture_of(state: Mapping[str, Tensor], path: Path) -> ESPNetv2Segmentation:
    """The (untrained) network a released state dict's shapes describe; refused in one line where they
    describe none."""
    if not isinstance(state, Mapping) or not all(isinstance(k, str) for k in state):
        raise SemvprError(f"{path}: not a state dict (a mapping of parameter names to tensors)")
    levels = ("level2_0", "level3_0", "level4_0")
    widths = [_shape(state, "base_net.level1.conv.weight", path)[0]]
    widths += [_shape(state, f"base_net.{level}.act.weight", path)[0] for level in levels]
    classes = _shape(state, "bu_dec_l4.merge_layer.3.weight", path)[0]
    if classes != len(CITYSCAPES_CHANNELS):
        named = " (Pascal VOC's 21 classes)" if classes == 21 else ""
        raise SemvprError(
            f"{path}: an ESPNetv2 segmenter of {classes} classes{named}; teacher=espnetv2 reads the Cityscapes "
            f"files ({len(CITYSCAPES_CHANNELS)} channels: the 19 train ids and background)"
        )
    # Each down-sampler widens its input by a strided EESP unit of 4 equal branches.
    if any((wider - w) % BRANCHES or wider <= w for w, wider in itertools.pairwise(widths)):
        raise SemvprError(f"{path}: level widths {widths} are not ESPNetv2's; {_what_it_is(state)}")
    return ESPNetv2Segmentation([int(w) for w in widths], int(classes))


def check_state(model: nn.Module, state: Mapping[str, Tensor], path: Path) -> None:
    """Every key of the network in the file and nothing else, each of the network's shape and kind (a float
    where it has a float), every float finite, every variance >= 0."""
    wanted = model.state_dict()
    missing = [k for k in wanted if k not in state]
    extra = [k for k in state if k not in wanted]
    if missing or extra:
        detail = f"lacks {len(missing)} of its keys ({missing[0]!r}, ...)" if missing else ""
        detail += "; " if missing and extra else ""
        detail += f"has {len(extra)} keys it does not ({extra[0]!r}, ...)" if extra else ""
        raise SemvprError(f"{path}: {detail}: {_what_it_is(state)}")
    for key, value in wanted.items():
        given = state[key]
        if not isinstance(given, Tensor) or given.shape != value.shape:
            shape = tuple(given.shape) if isinstance(given, Tensor) else type(given).__name__
            raise SemvprError(f"{path}: {key!r} is {shape}, ESPNetv2 of these widths has {tuple(value.shape)}")
        if given.is_floating_point() != value.is_floating_point():
            raise SemvprError(f"{path}: {key!r} is {given.dtype} where the network has {value.dtype}")
        check_tensor(given, key, path)


def load_espnetv2(path: str | Path) -> ESPNetv2Segmentation:
    """A released ESPNetv2 Cityscapes segmenter (the authors' ``espnetv2_s_*_city_*.pth``, or any file of that
    layout), its weights checked and loaded, in eval mode."""
    path = Path(path).expanduser()
    state = read_weights(path, "ESPNetv2 weights")
    model = architecture_of(state, path)
    check_state(model, state, path)
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    return model.eval()
