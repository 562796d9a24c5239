"""GeM: generalised-mean pooling (Radenović, Tolias & Chum, TPAMI 2018), with a per-location mask.

    f_c = ( Σ_i w_i · max(x_ic, ε)^p  /  Σ_i w_i )^(1/p),   then L2 normalisation,

with one learnable exponent p (initialised at 3, as the paper) shared by all channels. Without a
mask w ≡ 1 and this is the paper's GeM (p = 1: average pooling, p → ∞: max pooling); a location of
weight 0 takes no part in the mean. The descriptor has as many dimensions as the backbone has
channels.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.models.aggregator import Aggregator, check_weights


class GeM(Aggregator):
    """Weighted generalised-mean pooling: (B,D,h,w) [+ (B,1,h,w) mask] → (B,D) L2-normalised."""

    def __init__(self, dim: int, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.dim, self.eps = dim, eps
        self.p = nn.Parameter(torch.tensor(float(p)))

    @property
    def output_dim(self) -> int:
        """Descriptor length D (the backbone's channels)."""
        return self.dim

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """Weighted GeM over the grid, in fp32."""
        weights = check_weights(x, weights)
        with torch.autocast(x.device.type, enabled=False):
            p = self.p.float()
            powered = x.float().clamp_min(self.eps).pow(p)
            w = powered.new_ones(1, 1, *x.shape[2:]) if weights is None else weights
            w = w.expand(x.shape[0], 1, *x.shape[2:])
            mean = (powered * w).sum(dim=(2, 3)) / w.sum(dim=(2, 3)).clamp_min(self.eps)
            # A fully masked image has an empty mean: clamp it where x^p could never be (eps^p), not to 0.
            return F.normalize(mean.clamp_min(self.eps ** p).pow(1.0 / p), dim=1)
