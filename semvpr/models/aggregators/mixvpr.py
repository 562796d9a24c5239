"""MixVPR: feature-mixing aggregation (Ali-bey, Chaib-draa & Giguère, WACV 2023), with a per-location mask.

The (B,C,h,w) map is flattened to C rows of h·w values; L Feature-Mixer layers each add an MLP of
the row (LayerNorm → Linear(hw, r·hw) → ReLU → Linear(r·hw, hw)) to it; a channel projection
(Linear C → out_channels) and a row projection (Linear hw → out_rows), both with a bias, give an
out_channels × out_rows matrix, flattened (index c·out_rows + r) and L2-normalised (descriptor
out_channels · out_rows). Initialisation as the authors: the mixers' linears are truncated-normal
with std 0.02 and a zero bias; the LayerNorms and the two projections keep PyTorch's defaults.

Mask: the weight multiplies each location's features before the mixer (x_i ← w_i·x_i), so a
location of weight 0 enters as a zero feature whatever it held.

Grid: the mixer's rows have the fixed length h·w of the grid it was built for (the backbone's grid
at the configured image size). A feature map of another size (eval at another image size) is
adaptive-average-pooled to that grid after the mask is applied; the descriptor is then that of
the pooled map.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.models.aggregators.base import Aggregator, check_weights

MIXER_INIT_STD = 0.02  # the authors' truncated-normal std for the mixers' linears


class FeatureMixer(nn.Module):
    """One Feature-Mixer layer on rows of length ``width``: x + MLP(LayerNorm(x))."""

    def __init__(self, width: int, mlp_ratio: float) -> None:
        super().__init__()
        hidden = int(width * mlp_ratio)
        self.norm = nn.LayerNorm(width)
        self.fc1, self.fc2 = nn.Linear(width, hidden), nn.Linear(hidden, width)
        for linear in (self.fc1, self.fc2):
            nn.init.trunc_normal_(linear.weight, std=MIXER_INIT_STD)
            nn.init.zeros_(linear.bias)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.fc2(F.relu(self.fc1(self.norm(x))))


class MixVPR(Aggregator):
    """MixVPR on a fixed feature grid: (B,C,h,w) [+ mask] → (B, out_channels·out_rows)."""

    def __init__(
        self,
        dim: int,
        grid: Sequence[int],
        out_channels: int = 512,
        out_rows: int = 4,
        mix_depth: int = 4,
        mlp_ratio: float = 1.0,
    ) -> None:
        super().__init__()
        if len(grid) != 2:
            raise SemvprError(f"aggregator.grid={list(grid)} is not [h, w], the feature grid MixVPR mixes")
        self.dim, self.grid = dim, (int(grid[0]), int(grid[1]))
        self.out_channels, self.out_rows = out_channels, out_rows
        width = self.grid[0] * self.grid[1]
        self.mix = nn.Sequential(*[FeatureMixer(width, mlp_ratio) for _ in range(mix_depth)])
        self.channel_proj = nn.Linear(dim, out_channels)
        self.row_proj = nn.Linear(width, out_rows)

    @property
    def output_dim(self) -> int:
        """Descriptor length out_channels · out_rows."""
        return self.out_channels * self.out_rows

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """Mask the features, pool to the built grid if needed, mix, project, L2-normalise."""
        weights = check_weights(x, weights)
        if weights is not None:
            x = x * weights.to(x.dtype)
        if tuple(x.shape[-2:]) != self.grid:
            x = F.adaptive_avg_pool2d(x, self.grid)
        rows = self.mix(x.flatten(2))  # (B, C, hw)
        proj = self.channel_proj(rows.transpose(1, 2)).transpose(1, 2)  # (B, out_channels, hw)
        return F.normalize(self.row_proj(proj).flatten(1), dim=1)  # (B, out_channels·out_rows)
