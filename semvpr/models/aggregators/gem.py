"""GeM: generalised-mean pooling (Radenović, Tolias & Chum, TPAMI 2018), with a per-location mask.

    f_c = ( Σ_i w_i · max(x_ic, ε)^p  /  Σ_i w_i )^(1/p),   then L2 normalisation,

with one learnable exponent p (initialised at 3, as the paper) shared by all channels. Without a
mask w ≡ 1 and this is the paper's GeM (p = 1: average pooling, p → ∞: max pooling); a location of
weight 0 takes no part in the mean. The descriptor has as many dimensions as the backbone has
channels.

``fc_dim`` adds CosPlace's head (Berton, Masone & Caputo, CVPR 2022; the benchmark's "gem" with a
fully connected layer): each location's feature is L2-normalised over channels first, then pooled
as above, projected by a learned linear layer to ``fc_dim`` and L2-normalised. On a frozen trunk
the plain GeM learns only p; the head gives it a learned projection, as NetVLAD, MixVPR, SALAD and
BoQ have.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.precision import fp32
from semvpr.models.aggregators.base import Aggregator, check_weights


class GeM(Aggregator):
    """Weighted generalised-mean pooling: (B,D,h,w) [+ (B,1,h,w) mask] → (B,D) L2-normalised, or
    (B,fc_dim) with CosPlace's head."""

    untrained_form = "the plain GeM at its initial p (3), no head"

    @classmethod
    def untrained_settings(cls, settings: dict[str, Any]) -> dict[str, Any]:
        """The plain GeM: the head is a linear layer that only VPR training makes meaningful."""
        return {**settings, "fc_dim": None}

    def __init__(self, dim: int, p: float = 3.0, eps: float = 1e-6, fc_dim: int | None = None) -> None:
        super().__init__()
        self.dim, self.eps = dim, eps
        self.p = nn.Parameter(torch.tensor(float(p)))
        self.fc = nn.Linear(dim, fc_dim) if fc_dim else None

    @property
    def output_dim(self) -> int:
        """Descriptor length: fc_dim with the head, else D (the backbone's channels)."""
        return self.fc.out_features if self.fc is not None else self.dim

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """Weighted GeM over the grid (in fp32), then the head if any."""
        weights = check_weights(x, weights)
        with fp32(x.device.type):
            x = x.float()
            if self.fc is not None:
                x = F.normalize(x, dim=1)
            p = self.p.float()
            powered = x.clamp_min(self.eps).pow(p)
            w = powered.new_ones(1, 1, *x.shape[2:]) if weights is None else weights
            w = w.expand(x.shape[0], 1, *x.shape[2:])
            mean = (powered * w).sum(dim=(2, 3)) / w.sum(dim=(2, 3)).clamp_min(self.eps)
            # check_weights leaves every image some weight, so the mean of values >= eps^p is > 0.
            pooled = mean.pow(1.0 / p)
            return F.normalize(self.fc(pooled) if self.fc is not None else pooled, dim=1)
