"""The masks of a mask control (``retrieval.controls``), computed from a side's cached grid masks: no trunk or
segmenter pass of their own."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from semvpr.core.errors import SemvprError
from semvpr.retrieval.controls import REMOVED_CLASSES, MaskControl
from semvpr.retrieval.features import PlaceFeatures


def control_masks(control: MaskControl, cached: Tensor, side: str) -> Tensor:
    """The masks of one side's images (``side``: ``db`` or ``q``) under ``control``, from the source's cached
    masks of them (``cached``: (N,1,h,w) binary, or (N,C,h,w) pooled class probabilities where the control
    :attr:`~MaskControl.needs_classes`)."""
    if control.control == "none":
        return cached
    if control.needs_classes:
        return class_removed(cached, REMOVED_CLASSES[control.control])
    generator = torch.Generator().manual_seed(2 * control.seed + (side == "q"))
    if control.control == "random":
        return random_cells(cached, generator)
    return cached[torch.from_numpy(derangement(len(cached), generator))]


def control_features(features: PlaceFeatures, control: MaskControl) -> PlaceFeatures:
    """A place set's stores under ``control``, as training reads them: the side it leaves unmasked weighted 1
    everywhere (what an aggregator describes as unmasked, ARCHITECTURE §3.3), so that a batch mixing
    database and query images stacks one mask per image."""
    for side in ("db", "q"):
        store = getattr(features, side)
        if store.mask is not None:
            masks = control_masks(control, store.mask, side)
            store.mask = masks if control.masked(side) else torch.ones_like(masks)
    return features


def class_removed(pooled: Tensor, removed: tuple[int, ...], chunk: int = 4096) -> Tensor:
    """(N,1,h,w) binary masks from (N,C,h,w) pooled class probabilities: 0 where the ``removed`` classes'
    probability exceeds 0.5, else 1 (in chunks of images: ``pooled`` may be memory-mapped)."""
    index = torch.tensor(removed)
    out = torch.empty((len(pooled), 1, *pooled.shape[-2:]), dtype=torch.float16)
    for start in range(0, len(pooled), chunk):
        share = pooled[start : start + chunk].index_select(1, index).float().sum(1, keepdim=True)
        out[start : start + chunk] = (share <= 0.5).to(torch.float16)
    return out


def random_cells(binary: Tensor, generator: torch.Generator, chunk: int = 4096) -> Tensor:
    """(N,1,h,w) masks removing, from each image, as many cells drawn at random as ``binary`` removes (its
    cells below 0.5) and keeping the others (in chunks of images, drawn in order from ``generator``)."""
    out = torch.empty(binary.shape, dtype=torch.float16)
    for start in range(0, len(binary), chunk):
        flat = torch.as_tensor(binary[start : start + chunk]).reshape(-1, out[0].numel()).float()
        removed = (flat < 0.5).sum(1, keepdim=True)
        # Each cell's rank in a random order of its image's cells: the first ``removed`` go.
        order = torch.rand(flat.shape, generator=generator).argsort(1)
        rank = torch.empty_like(order).scatter_(1, order, torch.arange(flat.shape[1]).expand_as(order).contiguous())
        out[start : start + chunk] = (rank >= removed).to(torch.float16).reshape(-1, *out.shape[1:])
    return out


def derangement(n: int, generator: torch.Generator) -> np.ndarray:
    """A permutation of ``n`` images with no image in its own place, uniform over such permutations (drawn
    until one has no fixed point: about e draws on average)."""
    if n < 2:
        raise SemvprError(f"mask.control=shuffled needs at least 2 images on a side, got {n}")
    while True:
        order = torch.randperm(n, generator=generator).numpy()
        if not np.any(order == np.arange(n)):
            return order
