"""The aggregator protocol: local features (B,D,h,w) and a per-location mask → one global descriptor.

Every aggregator (NetVLAD, SRAL, GeM, MixVPR, SALAD, BoQ) is an :class:`Aggregator`, built from its
``conf/aggregator/<name>.yaml`` with ``dim`` (the backbone's channels) and ``grid`` (the feature grid
(h, w) at the configured image size) added by the caller. train, eval, report and plots use only
this interface:

- ``output_dim``: the descriptor length;
- ``forward(features, weights)``: ``weights`` is the mask (B,1,h,w) in [0, 1] on the feature grid,
  or None (no mask). Each aggregator says in its docstring how the mask enters; a weight of 1
  everywhere gives exactly the unmasked descriptor, and a location of weight 0 has no influence.
  An image whose mask keeps nothing (weights summing to less than ``EMPTY_MASK``: a bus filling the
  frame) is described unmasked: its masked descriptor would be zero, or undefined, and a zero
  descriptor lies at distance 1 from every unit descriptor, so it would be the nearest database
  image of every query with no closer match;
- ``init_sample`` / ``init_from_sample``: what initialisation sample the aggregator needs, if any
  (NetVLAD: k-means on local features; SRAL: the same features with static / dynamic labels), and
  ``init_min_static``: how many sampled locations a labelled init needs to call static;
- ``attention(features)``: an optional per-location map (B,1,h,w) for the report figures;
- ``untrained_form`` / ``untrained_settings``: what the aggregator is with no VPR training (``semvpr.eval
  ckpt=none``: its weights at construction, and its sample initialisation where it has one), or None
  where that would be random layers (MixVPR, SALAD, BoQ).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor, nn

#: The sample an aggregator's initialisation needs: none, local features, or local features with labels.
InitSample = Literal["none", "features", "labelled"]


class Aggregator(nn.Module, ABC):
    """Base class of every aggregator (see the module docstring for the contract)."""

    #: What ``init_from_sample`` needs; "labelled" makes the run build the teacher's pseudo-labels.
    init_sample: ClassVar[InitSample] = "none"
    #: What the aggregator is with no VPR training, in words (``ckpt=none``); None: nothing meaningful (its
    #: layers would be random).
    untrained_form: ClassVar[str | None] = None

    @classmethod
    def untrained_settings(cls, settings: dict[str, Any]) -> dict[str, Any]:
        """The constructor settings of the untrained form, from the configured ones (by default the same)."""
        return dict(settings)

    @property
    def init_min_static(self) -> int:
        """For a "labelled" init: the fewest sampled locations it must be able to treat as static (a weak
        teacher's labels are topped up with the most static locations to reach it)."""
        return 0

    @property
    @abstractmethod
    def output_dim(self) -> int:
        """Descriptor length."""

    @abstractmethod
    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """(B,D,h,w) local features and optional (B,1,h,w) weights → (B,output_dim) descriptor."""

    def init_from_sample(self, feats: Tensor, static: Tensor | None, seed: int) -> dict[str, float | int | str]:
        """Initialise from (N,D) sampled local features (``static``: (N,) bool for "labelled"); returns
        what was used, for metrics.json. Aggregators with ``init_sample == "none"`` are never called."""
        raise NotImplementedError(f"{type(self).__name__} has no sample initialisation")

    def attention(self, x: Tensor) -> Tensor | None:
        """A per-location map (B,1,h,w) worth drawing next to the masks, or None."""
        return None


#: A mask whose weights sum to less than this keeps nothing; its image is described unmasked.
EMPTY_MASK = 1.0e-6


def check_weights(x: Tensor, weights: Tensor | None) -> Tensor | None:
    """``weights`` as float32 after checking it is (B,1,h,w) on the grid of ``x`` (B may be 1), with
    the weights of an image whose mask keeps nothing set to 1 (see the module docstring)."""
    if weights is None:
        return None
    if (
        weights.dim() != 4
        or weights.shape[1] != 1
        or weights.shape[-2:] != x.shape[-2:]
        or weights.shape[0] not in (1, x.shape[0])
    ):
        raise ValueError(
            f"mask must be (B,1,h,w) on the feature grid {tuple(x.shape[-2:])}, got {tuple(weights.shape)}"
        )
    weights = weights.float()
    empty = weights.sum(dim=(1, 2, 3), keepdim=True) < EMPTY_MASK
    return torch.where(empty, torch.ones_like(weights), weights)


#: log of a zero weight: exp(LOG_ZERO) is exactly 0 in float32 while sums of such terms stay finite
#: (an image masked everywhere never gets here: check_weights describes it unmasked).
LOG_ZERO = -1.0e4


def log_weights(weights: Tensor) -> Tensor:
    """log w with zeros mapped to ``LOG_ZERO`` (an additive bias that removes a location exactly)."""
    return weights.clamp_min(0).log().clamp_min(LOG_ZERO)
