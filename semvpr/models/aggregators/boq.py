"""BoQ: Bag-of-Queries aggregation (Ali-bey, Chaib-draa & Giguère, CVPR 2024), with a per-location mask.

The (B,C,h,w) map is projected to d channels by a k×k convolution (the authors' 3×3, padding 1, with
a bias) and layer-normalised into n = h·w tokens X⁰. Each of L blocks runs a Transformer encoder
layer on the tokens (post-norm, ReLU MLP of width 4d, no dropout: PyTorch's
``TransformerEncoderLayer`` as the authors), then lets Q learnable queries attend to them:

    X^l = Encoder(X^{l−1});   Q̂ = LN(Q + SelfAttn(Q, Q, Q));   O^l = LN(CrossAttn(Q̂, X^l, X^l)).

The L·Q outputs are stacked (B, L·Q, d), a linear layer maps the L·Q axis to ``row_dim`` rows, and
the flattened d·row_dim matrix is L2-normalised.

Mask: log w_i is added to the attention logit of every key i, in the cross-attention and in the
encoder's self-attention (otherwise a masked token would still reach the others through the
encoder), so each softmax over locations becomes w_i·exp(s_i) / Σ_j w_j·exp(s_j). A weight of 0
removes the location exactly (its bias is −10⁴, whose exp is 0 in float32). A k×k projection (k > 1)
is a normalised convolution (in fp32), so that a masked location cannot leak into its neighbours'
tokens either:

    P(x)_p = b + K * (w ⊙ x)_p · |N_p| / Σ_{q ∈ N_p} w_q,

with N_p the in-image locations of p's window (zero padding, as the authors). With w ≡ 1 the ratio is
exactly 1, at the border too, and this is the authors' convolution. ``proj_kernel=1`` is a
per-location projection instead (no renormalisation needed).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.core.precision import fp32
from semvpr.models.aggregators.base import Aggregator, check_weights, log_weights

HEAD_DIM = 64  # the authors' heads: d // 64 of them
#: A projection window whose mean weight is below this is masked out whole: its token is the bias.
WINDOW_EPS = 1.0e-6


class EncoderLayer(nn.Module):
    """PyTorch's post-norm ``TransformerEncoderLayer`` (ReLU MLP, no dropout), with the same parameter
    names, written out: its inference fast path (eval mode, an even number of heads, no autocast) turns
    a float attention mask into NaNs, and the mask is how BoQ removes a location."""

    def __init__(self, dim: int, heads: int, dim_feedforward: int) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.linear1, self.linear2 = nn.Linear(dim, dim_feedforward), nn.Linear(dim_feedforward, dim)
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(self, x: Tensor, attn_mask: Tensor) -> Tensor:
        """x ← LN(x + SelfAttn(x)); x ← LN(x + W2 ReLU(W1 x)), with ``attn_mask`` added to the logits."""
        x = self.norm1(x + self.self_attn(x, x, x, attn_mask=attn_mask, need_weights=False)[0])
        return self.norm2(x + self.linear2(F.relu(self.linear1(x))))


class BoQBlock(nn.Module):
    """Encoder layer on the tokens, then Q learnable queries cross-attending to them."""

    def __init__(self, dim: int, num_queries: int) -> None:
        super().__init__()
        heads = max(1, dim // HEAD_DIM)
        self.encoder = EncoderLayer(dim, heads, dim_feedforward=4 * dim)
        self.queries = nn.Parameter(torch.randn(1, num_queries, dim))
        self.self_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: Tensor, key_bias: Tensor) -> tuple[Tensor, Tensor]:
        """Tokens (B,n,d) and the per-key logit bias (B,n) → new tokens, query outputs (B,Q,d)."""
        b, n, _ = x.shape
        heads = self.cross_attn.num_heads
        q = self.queries.expand(b, -1, -1)
        bias = key_bias[:, None, None, :].expand(b, heads, 1, n)
        x = self.encoder(x, bias.expand(b, heads, n, n).reshape(b * heads, n, n))
        q = self.norm_q(q + self.self_attn(q, q, q, need_weights=False)[0])
        cross_bias = bias.expand(b, heads, q.shape[1], n).reshape(b * heads, q.shape[1], n)
        out = self.cross_attn(q, x, x, attn_mask=cross_bias, need_weights=False)[0]
        return x, self.norm_out(out)


class BoQ(Aggregator):
    """Bag-of-Queries: (B,C,h,w) [+ mask] → (B, proj_channels·row_dim) L2-normalised."""

    def __init__(
        self,
        dim: int,
        proj_channels: int = 256,
        num_queries: int = 32,
        num_layers: int = 2,
        row_dim: int = 8,
        proj_kernel: int = 3,
    ) -> None:
        """``proj_kernel``: the input projection's odd kernel size (3: the authors' 3×3, as a normalised
        convolution under a mask; 1: per location)."""
        super().__init__()
        if proj_kernel < 1 or proj_kernel % 2 == 0:
            raise SemvprError(f"aggregator.proj_kernel must be an odd kernel size (1 or 3), got {proj_kernel}")
        self.proj_channels, self.row_dim, self.proj_kernel = proj_channels, row_dim, proj_kernel
        self.proj_c = nn.Conv2d(dim, proj_channels, kernel_size=proj_kernel, padding=proj_kernel // 2)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.blocks = nn.ModuleList([BoQBlock(proj_channels, num_queries) for _ in range(num_layers)])
        self.fc = nn.Linear(num_layers * num_queries, row_dim)

    @property
    def output_dim(self) -> int:
        """Descriptor length proj_channels · row_dim."""
        return self.proj_channels * self.row_dim

    def project(self, x: Tensor, weights: Tensor | None) -> Tensor:
        """The input projection (B,d,h,w) of (B,C,h,w) features: the plain convolution for a 1×1 kernel,
        else the normalised convolution of the module docstring (w ≡ 1 without a mask)."""
        if self.proj_kernel == 1:
            return self.proj_c(x)
        # In fp32 (autocast off): the renormalisation divides by window weights down to WINDOW_EPS, which
        # would magnify bf16 rounding.
        with fp32(x.device.type):
            x = x.float()
            w = x.new_ones(1, 1, *x.shape[2:]) if weights is None else weights
            k = self.proj_kernel
            # Σ_{q∈N_p} w_q / |N_p|: the window's mean weight over its in-image locations (1 exactly for w ≡ 1).
            mean_w = F.avg_pool2d(w, k, stride=1, padding=k // 2, count_include_pad=False)
            y = self.proj_c(x * w)  # b + K * (w ⊙ x)
            # b + (y − b) / mean_w, written so that y stays untouched (bit for bit) where mean_w = 1.
            return y + (y - self.proj_c.bias[:, None, None]) * (1.0 / mean_w.clamp_min(WINDOW_EPS) - 1.0)

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """Tokens through the blocks with the mask as a key bias, query outputs → rows → L2."""
        weights = check_weights(x, weights)
        tokens = self.norm_input(self.project(x, weights).flatten(2).transpose(1, 2))  # (B, n, d)
        b, n, _ = tokens.shape
        # Without a mask the bias is 0 everywhere: one code path, so w ≡ 1 is the unmasked model exactly.
        key_bias = tokens.new_zeros(b, n) if weights is None else log_weights(weights).flatten(1).expand(b, n)
        key_bias = key_bias.to(tokens.dtype)
        outs = []
        for block in self.blocks:
            tokens, out = block(tokens, key_bias)
            outs.append(out)
        rows = self.fc(torch.cat(outs, dim=1).transpose(1, 2))  # (B, d, row_dim)
        return F.normalize(rows.flatten(1), dim=1)
