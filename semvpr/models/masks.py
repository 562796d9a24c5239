"""Mask sources: per-class probabilities of each pixel, reduced to a weight map on the feature grid.

Every source (teacher, student, oracle) gives Cityscapes-class probabilities (B,C,H,W) at image
resolution. On the local-feature grid (ARCHITECTURE §3.2) they become either

- ``binary``: the static classes' probabilities summed per pixel, area-pooled and thresholded at
  0.5, one channel (the seed paper's filter); or
- ``learned``: the class probabilities area-pooled to the grid (C channels), which
  :class:`ClassWeights` turns into Σ_c p_c·w_c with one learnable weight per class.

The aggregator uses the result to weight each location's contribution, never to zero features.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor, nn

from semvpr.core.cache import config_hash, state_hash
from semvpr.core.errors import SemvprError
from semvpr.core.precision import compute_key
from semvpr.data.classes import IGNORE, NUM_CLASSES, STATIC_NAMES, TRAIN_ID_NAMES, static_lut

WEIGHTINGS = ("binary", "learned")
#: The backbone's ``forward_frozen`` outputs of a batch; a source reads its :meth:`MaskSource.trunk_levels`
#: (the others may be None).
Skips = Sequence[Tensor | None]
#: The ground-truth label maps of a batch's images, where the set has them.
LabelPaths = Sequence[Path] | None


def static_vector(static_names: Sequence[str]) -> Tensor:
    """(C,) 1 for static classes, 0 for the others."""
    return torch.from_numpy(static_lut(tuple(static_names))[:NUM_CLASSES])


def weighted_classes(class_prob: Tensor, weights: Tensor) -> Tensor:
    """Σ_c p_c·w_c of (B,C,H,W) class probabilities, as (B,1,H,W)."""
    return torch.einsum("bchw,c->bhw", class_prob.float(), weights)[:, None]


def pool_to_grid(static_prob: Tensor, grid_hw: tuple[int, int], threshold: float = 0.5) -> Tensor:
    """Area-pool a static probability map to the feature grid and binarise it."""
    pooled = F.adaptive_avg_pool2d(static_prob.float(), grid_hw)
    return (pooled >= threshold).float()


def _windows(size: int, cells: int) -> tuple[Tensor, Tensor]:
    """Start and end of each of ``cells`` adaptive-pooling windows over ``size`` (``F.adaptive_avg_pool2d``'s:
    floor(i·size/cells) to ceil((i+1)·size/cells); neighbouring windows overlap where ``cells`` does not divide
    ``size``)."""
    i = torch.arange(cells)
    return (i * size) // cells, ((i + 1) * size + cells - 1) // cells


def class_shares(labels: Tensor, grid_hw: tuple[int, int]) -> Tensor:
    """The share of each class's pixels in each grid cell, (B,C,h,w) float32, from (B,H,W) class ids (any id
    of ``NUM_CLASSES`` or above belongs to no class): the one-hot class maps area-pooled to the grid, without
    them. Per column window, the class counts of every row (a bincount), summed over each row window by a
    cumulative sum; a cell's share is its count over its window's pixels."""
    batch, height, width = labels.shape
    ids = labels.long().clamp(max=NUM_CLASSES)
    rows, cols = ([w.to(ids.device) for w in _windows(n, cells)] for n, cells in zip((height, width), grid_hw))
    where = (torch.arange(batch, device=ids.device)[:, None] * height + torch.arange(height, device=ids.device))[
        ..., None
    ] * (NUM_CLASSES + 1)  # (B,H,1): the first count of each image's row
    shares = []
    for start, end in zip(cols[0].tolist(), cols[1].tolist()):
        counts = torch.bincount(
            (where + ids[:, :, start:end]).reshape(-1), minlength=batch * height * (NUM_CLASSES + 1)
        )
        running = F.pad(counts.view(batch, height, NUM_CLASSES + 1).cumsum(1), (0, 0, 1, 0))  # (B,H+1,C+1)
        cell = running[:, rows[1]] - running[:, rows[0]]  # (B,h,C+1): the counts of each row window
        area = ((rows[1] - rows[0]) * (end - start))[None, :, None]
        shares.append(cell[..., :NUM_CLASSES].float() / area.float())
    return torch.stack(shares, -1).permute(0, 2, 1, 3).contiguous()


#: What a mask source is built from: the teacher, the student (each built or loaded first, then given to
#: its constructor as ``segmenter=``), or the place set's ground-truth label maps.
Needs = Literal["teacher", "student", "ground_truth"]


class MaskSource(nn.Module):
    """Gives class probabilities (B,C,H,W) of a batch; ``grid_mask`` reduces them to the grid.

    A mask source is one class and one ``conf/mask/*.yaml`` whose ``_target_`` names it; ``needs``
    says what the builder must provide.
    """

    needs: ClassVar[Needs]
    #: Whether it can describe images that come without label maps (a folder of queries, the hub).
    describes_new_images: ClassVar[bool] = True

    def __init__(self, static_names: Sequence[str] = STATIC_NAMES) -> None:
        super().__init__()
        # Derived from the config, so not part of the state dict.
        self.register_buffer("static_weight", static_vector(static_names), persistent=False)

    def forward(
        self, images: Tensor | None, skips: Skips, label_paths: LabelPaths, out_hw: Sequence[int] | None = None
    ) -> Tensor:
        """Class probabilities (B,C,H,W) at ``out_hw`` (default: the images' size). ``skips`` are the backbone's
        ``forward_frozen`` outputs (only the :meth:`trunk_levels` are read; the others may be None);
        ``images`` may be None where :meth:`reads_pixels` is False."""
        raise NotImplementedError

    def trunk_levels(self, image_size: Sequence[int]) -> tuple[int, ...]:
        """Which ``forward_frozen`` outputs it reads for images of ``image_size`` (none: the frozen pass can be
        skipped for it)."""
        return ()

    def reads_pixels(self, image_size: Sequence[int]) -> bool:
        """Whether it reads the images themselves (else cached trunk outputs, or label maps, are enough)."""
        return True

    @property
    def segmenter(self) -> nn.Module | None:
        """The network that makes the probabilities (its ``trained_on`` says on what data), None for
        ground truth."""
        return None

    def input_size(self, image_size: Sequence[int]) -> tuple[int, int] | None:
        """The size the segmenter sees images of ``image_size`` at, where it resizes them; None: as given."""
        return None

    def identity(self, image_size: Sequence[int]) -> dict[str, object]:
        """What the output depends on besides the weights (which a cache key hashes with the state dict):
        the class, the static classes and the segmenter's input size."""
        seen = self.input_size(image_size)
        return {
            "source": type(self).__name__,
            "static": [float(v) for v in self.static_weight.tolist()],
            "input_size": list(seen) if seen is not None else None,
            **self.arithmetic(image_size),
        }

    def arithmetic(self, image_size: Sequence[int]) -> dict[str, str]:
        """How the output is computed where that moves its last bits (a teacher reading the trunk's features
        instead of its own encoder's): part of every cache key of its masks and descriptors; {} by default."""
        return {}

    def cache_key(self, image_size: Sequence[int]) -> str:
        """The key of its masks of images at ``image_size``: its weights, :meth:`identity` and, where a network
        computes them, the arithmetic it runs in (``precision.compute_key``: device, precision, CPU threads); the
        one key training's and evaluation's mask caches share."""
        computed = compute_key(self.static_weight.device) if self.segmenter is not None else {}
        return config_hash([state_hash(self.state_dict()), self.identity(image_size), computed])

    def static_prob(self, class_prob: Tensor) -> Tensor:
        """Probability of a static class, (B,1,H,W)."""
        return weighted_classes(class_prob, self.static_weight)

    def grid_mask(
        self,
        images: Tensor | None,
        skips: Skips,
        label_paths: LabelPaths,
        grid_hw: tuple[int, int],
        weighting: str = "binary",
        out_hw: Sequence[int] | None = None,
    ) -> Tensor:
        """The mask the aggregator reads: (B,1,h,w) binary, or (B,C,h,w) pooled class probabilities. A source
        whose classes are label maps (:meth:`label_maps`) is pooled straight from them, without a (B,C,H,W)
        one-hot tensor (label maps of real frames are large): binary, the static table gathered by label and
        pooled; learned, each grid cell's class shares counted from its labels. Both equal pooling the one-hot
        classes."""
        if weighting not in WEIGHTINGS:
            raise SemvprError(f"mask.weights={weighting!r} is not one of {list(WEIGHTINGS)}")
        labels = self.label_maps(label_paths)
        if labels is not None:
            labels = labels.clamp(max=NUM_CLASSES).to(self.static_weight.device)
            if weighting == "learned":
                return class_shares(labels, grid_hw)
            table = torch.cat([self.static_weight.float(), self.static_weight.new_zeros(1).float()])  # ignore → 0
            return pool_to_grid(table[labels][:, None], grid_hw)
        class_prob = self(images, skips, label_paths, out_hw)
        if weighting == "learned":
            return F.adaptive_avg_pool2d(class_prob.float(), grid_hw)
        return pool_to_grid(self.static_prob(class_prob), grid_hw)

    def label_maps(self, label_paths: LabelPaths) -> Tensor | None:
        """(B,H,W) class ids where the source's classes are the batch's label maps; None (the default) where a
        network gives probabilities."""
        return None


class SegmenterMask(MaskSource):
    """Class probabilities from a frozen segmentation network, held under the attribute its ``needs`` names
    (``teacher`` or ``student``: the prefix of its keys in a checkpoint's state dict)."""

    def __init__(self, segmenter: nn.Module, static_names: Sequence[str] = STATIC_NAMES) -> None:
        super().__init__(static_names)
        setattr(self, self.needs, segmenter.eval().requires_grad_(False))

    @property
    def segmenter(self) -> nn.Module:
        return getattr(self, self.needs)

    @torch.no_grad()
    def forward(
        self, images: Tensor | None, skips: Skips, label_paths: LabelPaths, out_hw: Sequence[int] | None = None
    ) -> Tensor:
        size = (int(out_hw[0]), int(out_hw[1])) if out_hw is not None else tuple(images.shape[-2:])
        return self.class_prob(images, skips, size)

    def class_prob(self, images: Tensor | None, skips: Skips, size: tuple[int, int]) -> Tensor:
        """The network's class probabilities (B,C,H,W) at ``size``."""
        raise NotImplementedError


class TeacherMask(SegmenterMask):
    """Class probabilities from the teacher (Mask2Former or ESPNetv2), run on the images themselves, or on the
    trunk's frozen outputs where its pixel encoder is that trunk (``Teacher.link_trunk``)."""

    needs = "teacher"

    def class_prob(self, images: Tensor | None, skips: Skips, size: tuple[int, int]) -> Tensor:
        if self.segmenter.on_trunk(size) and skips:
            return self.segmenter.trunk_class_prob(skips, size)
        assert images is not None, "the teacher reads the images at this size"
        return self.segmenter.class_prob(images)

    def trunk_levels(self, image_size: Sequence[int]) -> tuple[int, ...]:
        return tuple(self.segmenter.trunk_levels) if self.segmenter.on_trunk(image_size) else ()

    def reads_pixels(self, image_size: Sequence[int]) -> bool:
        return not self.segmenter.on_trunk(image_size)

    def arithmetic(self, image_size: Sequence[int]) -> dict[str, str]:
        if self.segmenter.on_trunk(image_size):
            return {"encoder": "trunk"}
        # A per-pixel network's softmax is taken as given (no class shares) and resized before the trainId sum.
        return {} if self.segmenter.is_mask2former else {"scores": "softmax, resized first"}

    def input_size(self, image_size: Sequence[int]) -> tuple[int, int] | None:
        size = getattr(self.segmenter, "inference_size", None)
        if size is None or [int(v) for v in size] == [int(v) for v in image_size]:
            return None
        return int(size[0]), int(size[1])


class StudentMask(SegmenterMask):
    """Class probabilities from the U-Net student over the backbone's own multi-scale features."""

    needs = "student"

    def class_prob(self, images: Tensor | None, skips: Skips, size: tuple[int, int]) -> Tensor:
        return self.segmenter.class_prob(skips, out_hw=size)

    def trunk_levels(self, image_size: Sequence[int]) -> tuple[int, ...]:
        return tuple(self.segmenter.skip_indices)

    def reads_pixels(self, image_size: Sequence[int]) -> bool:
        return False


class OracleMask(MaskSource):
    """One-hot ground-truth classes from a set's label PNGs: SynthCity's, or those of the objects pasted by
    ``data.occluders`` (upper bound; never in training data)."""

    needs = "ground_truth"
    describes_new_images = False

    def forward(
        self, images: Tensor | None, skips: Skips, label_paths: LabelPaths, out_hw: Sequence[int] | None = None
    ) -> Tensor:
        labels = self.label_maps(label_paths)
        one_hot = F.one_hot(labels.clamp(max=NUM_CLASSES), NUM_CLASSES + 1)[..., :NUM_CLASSES]  # ignore → zeros
        assert IGNORE >= NUM_CLASSES
        return one_hot.permute(0, 3, 1, 2).float().to(self.static_weight.device)

    def label_maps(self, label_paths: LabelPaths) -> Tensor:
        if label_paths is None:
            raise SemvprError(
                "mask=oracle needs ground-truth label maps: SynthCity's, or a frame-aligned set's with data.occluders"
            )
        return torch.from_numpy(np.stack([np.asarray(Image.open(p)) for p in label_paths]).astype(np.int64))

    def reads_pixels(self, image_size: Sequence[int]) -> bool:
        return False


class ClassWeights(nn.Module):
    """Σ_c p_c·w_c per grid location, w_c = sigmoid(θ_c) learned with the triplet loss.

    Initialised at the binary filter's values as far as a sigmoid allows: θ_c = +init_logit for
    static classes (w ≈ 0.98 for 4) and −init_logit for the others (w ≈ 0.02).
    """

    def __init__(self, static_names: Sequence[str] = STATIC_NAMES, init_logit: float = 4.0) -> None:
        super().__init__()
        static = static_vector(static_names) > 0
        self.theta = nn.Parameter(torch.where(static, init_logit, -init_logit))

    @property
    def weights(self) -> Tensor:
        """w_c in (0, 1), one per Cityscapes class."""
        return torch.sigmoid(self.theta)

    def forward(self, class_prob: Tensor) -> Tensor:
        """(B,C,h,w) pooled class probabilities → (B,1,h,w) contribution weights."""
        return weighted_classes(class_prob, self.weights)

    def named_weights(self) -> dict[str, float]:
        """{class name: w_c} for reports."""
        return {name: float(w) for name, w in zip(TRAIN_ID_NAMES, self.weights.detach().cpu())}
