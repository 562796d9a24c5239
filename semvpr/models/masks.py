"""Mask sources: a static-probability map per image, pooled to the feature grid as a binary filter.

A mask is a per-location weight (B,1,h,w) on the local-feature grid (DESIGN §3): the segmenter's
static map at image resolution, area-pooled to the grid and thresholded at 0.5. The aggregator
uses it to weight each location's contribution, never to zero features.
"""
from __future__ import annotations

from pathlib import Path
from typing import Protocol, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor, nn

from semvpr.data.classes import STATIC_NAMES, static_lut
from semvpr.errors import SemvprError


class MaskSource(Protocol):
    """Gives the static probability (B,1,H,W) of a batch; any resolution, pooled later."""

    #: Whether it reads the backbone's features (else the frozen pass can be skipped for it).
    needs_features: bool

    def __call__(
        self, images: Tensor, skips: list[Tensor], label_paths: Sequence[Path] | None
    ) -> Tensor: ...


def pool_to_grid(static_prob: Tensor, grid_hw: tuple[int, int], threshold: float = 0.5) -> Tensor:
    """Area-pool a static probability map to the feature grid and binarise it."""
    pooled = F.adaptive_avg_pool2d(static_prob.float(), grid_hw)
    return (pooled >= threshold).float()


class TeacherMask(nn.Module):
    """Static probability from the Mask2Former teacher, run on the images themselves."""

    needs_features = False

    def __init__(self, teacher: nn.Module) -> None:
        super().__init__()
        self.teacher = teacher.eval().requires_grad_(False)

    @torch.no_grad()
    def forward(self, images: Tensor, skips: list[Tensor], label_paths: Sequence[Path] | None) -> Tensor:
        return self.teacher.static_prob(images)


class StudentMask(nn.Module):
    """Static probability from the U-Net student over the backbone's own multi-scale features."""

    needs_features = True

    def __init__(self, student: nn.Module) -> None:
        super().__init__()
        self.student = student.eval().requires_grad_(False)

    @torch.no_grad()
    def forward(self, images: Tensor, skips: list[Tensor], label_paths: Sequence[Path] | None) -> Tensor:
        return self.student.static_prob(skips)


class OracleMask(nn.Module):
    """Ground-truth static map read from SynthCity's label PNGs (upper bound; never in training data)."""

    needs_features = False

    def __init__(self, static_names: Sequence[str] = STATIC_NAMES) -> None:
        super().__init__()
        self.lut = static_lut(tuple(static_names))

    def forward(self, images: Tensor, skips: list[Tensor], label_paths: Sequence[Path] | None) -> Tensor:
        if label_paths is None:
            raise SemvprError("filter=oracle needs ground-truth label maps; only SynthCity provides them")
        maps = [self.lut[np.asarray(Image.open(p))] for p in label_paths]
        return torch.from_numpy(np.stack(maps))[:, None]
