"""U-Net student: a small decoder over the frozen backbone prefix that predicts the teacher's classes.

It learns the Cityscapes classes of the teacher's pseudo-labels (cross-entropy, 19 outputs); its
static map is the sum of the static classes' probabilities, which is what the binary filter reads.
How it is trained (once, cached) is ``semvpr.segmentation.training``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.core.spec import from_mapping
from semvpr.data.classes import NUM_CLASSES, STATIC_NAMES
from semvpr.models.masks import static_vector


@dataclass(frozen=True)
class StudentSpec:
    """The student's architecture and training settings (``conf/student/*.yaml``)."""

    name: str = "unet"
    #: Strides of the frozen features it decodes (the output is at the smallest).
    strides: Sequence[int] = (4, 8, 16)
    width: int = 32
    #: Pseudo-label classes that count as static (the binary target).
    static_classes: Sequence[str] = STATIC_NAMES
    epochs: int = 10
    batch_size: int = 16
    lr: float = 3.0e-3
    weight_decay: float = 1.0e-4
    bf16: bool = True
    num_workers: int = 2
    #: Train on at most this many of the given images (a fixed random subset; None = all).
    max_images: int | None = None
    seed: int = 0

    @classmethod
    def from_mapping(cls, node: Mapping[str, Any]) -> StudentSpec:
        """From a ``student`` config node (unknown keys refused in one line)."""
        return from_mapping(cls, node, "student")


def _block(cin: int, cout: int) -> nn.Sequential:
    """conv3x3-BN-ReLU twice: the U-Net unit."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )  # fmt: skip


class Student(nn.Module):
    """Decoder from the deepest chosen frozen feature up through shallower skips to class logits."""

    def __init__(
        self, frozen_channels: Sequence[int], frozen_strides: Sequence[int],
        strides: Sequence[int] = (4, 8, 16), width: int = 64, static_names: Sequence[str] = STATIC_NAMES,
    ) -> None:  # fmt: skip
        super().__init__()
        self.register_buffer("static_weight", static_vector(static_names), persistent=False)
        # The deepest frozen output of each wanted stride (ResNet's stem and layer1 share none; VGG's do not).
        chosen = {s: i for i, s in enumerate(frozen_strides) if s in set(strides)}
        if not chosen:
            raise SemvprError(
                f"student.strides={list(strides)} match none of the backbone's frozen feature strides "
                f"{list(frozen_strides)}; pick some of those"
            )
        self.skip_indices = [chosen[s] for s in sorted(chosen)]  # shallow → deep
        self.out_stride = min(chosen)
        chans = [frozen_channels[i] for i in self.skip_indices]
        # 1x1 projections first: 3x3 convs on 256-512 raw channels cost ~7x more for no measured gain.
        self.lateral = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, width, 1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True))
            for c in chans
        )
        self.bottom = _block(width, width)
        self.ups = nn.ModuleList(_block(2 * width, width) for _ in chans[:-1])
        self.head = nn.Conv2d(width, NUM_CLASSES, 1)

    def forward(self, skips: Sequence[Tensor]) -> Tensor:
        """Class logits (B,C,H/s,W/s) at the shallowest chosen stride, from ``forward_frozen`` outputs."""
        return self.decode([skips[i] for i in self.skip_indices])

    def decode(self, chosen: Sequence[Tensor]) -> Tensor:
        """Logits from just the chosen features (shallow → deep), e.g. a cache of them."""
        feats = [lateral(f.float()) for lateral, f in zip(self.lateral, chosen)]
        h = self.bottom(feats[-1])
        for f, block in zip(reversed(feats[:-1]), self.ups):
            h = F.interpolate(h, size=f.shape[-2:], mode="bilinear", align_corners=False)
            h = block(torch.cat([h, f], 1))
        return self.head(h)

    def class_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Softmax over the classes (B,C,·,·), optionally resized (bilinear) to ``out_hw``."""
        prob = torch.softmax(self.forward(skips).float(), dim=1)
        if out_hw is not None:
            prob = F.interpolate(prob, size=tuple(out_hw), mode="bilinear", align_corners=False)
        return prob

    def static_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Σ of the static classes' probabilities (B,1,·,·), optionally resized to ``out_hw``."""
        prob = torch.einsum("bchw,c->bhw", self.class_prob(skips, out_hw), self.static_weight)[:, None]
        return prob


def student_architecture(spec: StudentSpec, backbone: nn.Module) -> Student:
    """An untrained student of this spec over this backbone's frozen features."""
    return Student(
        backbone.frozen_channels,
        backbone.frozen_strides,
        strides=list(spec.strides),
        width=int(spec.width),
        static_names=list(spec.static_classes),
    )
