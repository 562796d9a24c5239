"""Each aggregator agrees with its paper's formula re-derived here with plain torch ops (the mask
contract every aggregator keeps is tested on every shipped config in ``test_components.py``)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from semvpr.core.errors import SemvprError
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.aggregators.boq import BoQ
from semvpr.models.aggregators.gem import GeM
from semvpr.models.aggregators.mixvpr import MixVPR
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.aggregators.salad import SALAD
from semvpr.models.aggregators.sral import SRAL

torch.set_num_threads(2)
D, H, W = 32, 4, 5

#: Small instances for the re-derivations.
SMALL = {
    "netvlad": lambda: NetVLAD(num_clusters=4, dim=D),
    "sral": lambda: SRAL(num_clusters=4, dim=D, num_shadows=2),
    "gem": lambda: GeM(dim=D),
    "gem_fc": lambda: GeM(dim=D, fc_dim=7),
    "mixvpr": lambda: MixVPR(dim=D, grid=(H, W), out_channels=8, out_rows=3, mix_depth=2),
    "salad": lambda: SALAD(dim=D, num_clusters=4, cluster_dim=6, token_dim=5),
    "boq": lambda: BoQ(dim=D, proj_channels=64, num_queries=3, num_layers=2, row_dim=2),
}


def _build(name: str) -> Aggregator:
    torch.manual_seed(0)
    agg = SMALL[name]().eval()
    if name == "sral":  # shadows near real features, so β varies across locations
        feats = torch.randn(400, D)
        agg.init_from_sample(feats, torch.arange(400) % 3 != 0, seed=0)
    return agg


def test_gem_matches_radenovic() -> None:
    agg = _build("gem")
    with torch.no_grad():
        agg.p.fill_(2.5)
    x, w = torch.randn(2, D, H, W), torch.rand(2, 1, H, W)
    p = 2.5
    expected = []
    for b in range(2):
        xs = x[b].reshape(D, -1).clamp(min=1e-6)
        ws = w[b].reshape(-1)
        f = ((xs**p * ws).sum(1) / ws.sum()) ** (1 / p)
        expected.append(f / f.norm())
    with torch.no_grad():
        torch.testing.assert_close(agg(x, w), torch.stack(expected))
        unweighted = x.clamp(min=1e-6).pow(p).mean((2, 3)).pow(1 / p)  # the paper's unmasked GeM
        torch.testing.assert_close(agg(x), unweighted / unweighted.norm(dim=1, keepdim=True))
    assert agg.p.requires_grad


def test_gem_head_matches_cosplace() -> None:
    """CosPlace's aggregation: L2-normalise each location, GeM, linear layer, L2-normalise."""
    agg = _build("gem_fc")
    x, w = torch.randn(2, D, H, W), torch.rand(2, 1, H, W)
    with torch.no_grad():
        p = float(agg.p)
        expected = []
        for b in range(2):
            cols = x[b].reshape(D, -1)
            cols = cols / cols.norm(dim=0, keepdim=True)  # each location's feature on the unit sphere
            ws = w[b].reshape(-1)
            pooled = ((cols.clamp(min=1e-6) ** p * ws).sum(1) / ws.sum()) ** (1 / p)
            z = agg.fc.weight @ pooled + agg.fc.bias
            expected.append(z / z.norm())
        torch.testing.assert_close(agg(x, w), torch.stack(expected))
    assert agg.output_dim == 7 and agg.fc.weight.requires_grad


def test_mixvpr_matches_the_paper() -> None:
    agg = _build("mixvpr")
    x = torch.randn(2, D, H, W)
    with torch.no_grad():
        rows = x.reshape(2, D, H * W)
        for layer in agg.mix:  # X ← X + W2 ReLU(W1 LN(X))
            mu, var = rows.mean(-1, keepdim=True), rows.var(-1, unbiased=False, keepdim=True)
            normed = (rows - mu) / torch.sqrt(var + 1e-5) * layer.norm.weight + layer.norm.bias
            rows = rows + (
                torch.relu(normed @ layer.fc1.weight.T + layer.fc1.bias) @ layer.fc2.weight.T + layer.fc2.bias
            )
        z = agg.channel_proj.weight @ rows + agg.channel_proj.bias[:, None]  # (B, out_channels, hw)
        z = z @ agg.row_proj.weight.T  # (B, out_channels, out_rows)
        expected = z.reshape(2, -1)
        torch.testing.assert_close(agg(x), expected / expected.norm(dim=1, keepdim=True), rtol=1e-5, atol=1e-6)
        w = torch.rand(2, 1, H, W)
        torch.testing.assert_close(agg(x, w), agg(x * w))


def test_mixvpr_other_grid_is_pooled_to_the_built_grid() -> None:
    agg = _build("mixvpr")
    x, w = torch.randn(2, D, 2 * H, 2 * W), torch.rand(2, 1, 2 * H, 2 * W)
    pooled = (x * w).reshape(2, D, H, 2, W, 2).mean((3, 5))  # 2×2 block means = adaptive pooling here
    with torch.no_grad():
        torch.testing.assert_close(agg(x, w), agg(pooled), rtol=1e-5, atol=1e-6)


def _mlp(layers: torch.nn.Sequential, v: torch.Tensor) -> torch.Tensor:
    """Two-layer ReLU MLP (1×1 convs or linears, dropout off) applied on the last axis of v."""
    convs = [m for m in layers if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    w1, b1 = convs[0].weight.reshape(convs[0].weight.shape[0], -1), convs[0].bias
    w2, b2 = convs[1].weight.reshape(convs[1].weight.shape[0], -1), convs[1].bias
    return torch.relu(v @ w1.T + b1) @ w2.T + b2


def test_salad_matches_the_paper() -> None:
    agg = _build("salad")
    with torch.no_grad():
        agg.dust_bin.fill_(0.7)
    x, w = torch.randn(2, D, H, W), torch.rand(2, 1, H, W)
    m, n, iters = 4, H * W, 3
    with torch.no_grad():
        for weights in (None, w):
            out = []
            for b in range(2):
                locs = x[b].reshape(D, n).T  # (n, D)
                wb = torch.ones(n) if weights is None else weights[b].reshape(n)
                f, s = _mlp(agg.cluster_features, locs).T, _mlp(agg.score, locs).T  # (l, n), (m, n)
                s_bar = torch.cat([s, torch.full((1, n), 0.7)])  # dustbin row
                mu = torch.cat([torch.ones(m), torch.tensor([float(n - m)])]) / (m + n)
                nu = wb / (m + n)
                # Sinkhorn on K = exp(S̄): alternately rescale rows to mu and columns to nu
                kmat, r, c = s_bar.exp(), torch.ones(m + 1), torch.ones(n)
                for _ in range(iters):
                    r = mu / (kmat @ c)
                    c = nu / (kmat.T @ r)
                plan = r[:, None] * kmat * c[None] * (m + n)
                v = f @ plan[:m].T  # (l, m)
                v = v / v.norm(dim=0, keepdim=True)
                token = (locs * wb[:, None]).sum(0) / wb.sum()
                g = _mlp(agg.token_features, token)
                desc = torch.cat([g / g.norm(), v.reshape(-1)])
                out.append(desc / desc.norm())
            torch.testing.assert_close(agg(x, weights), torch.stack(out), rtol=1e-4, atol=1e-6)


def test_salad_needs_more_locations_than_clusters() -> None:
    with pytest.raises(SemvprError, match="more feature locations than clusters"):
        SALAD(dim=D, num_clusters=H * W)(torch.randn(1, D, H, W))


def _attention(q_in, k_in, mha: torch.nn.MultiheadAttention, bias: torch.Tensor) -> torch.Tensor:
    """Multi-head scaled dot-product attention with a per-key logit bias, from the module's weights."""
    d, heads = q_in.shape[-1], mha.num_heads
    wq, wk, wv = mha.in_proj_weight.split(d)
    bq, bk, bv = mha.in_proj_bias.split(d)
    q, k, v = q_in @ wq.T + bq, k_in @ wk.T + bk, k_in @ wv.T + bv
    split = lambda t: t.reshape(t.shape[0], heads, d // heads).transpose(0, 1)  # noqa: E731
    logits = split(q) @ split(k).transpose(1, 2) / math.sqrt(d // heads) + bias[None, None, :]
    o = (logits.softmax(-1) @ split(v)).transpose(0, 1).reshape(q_in.shape[0], d)
    return o @ mha.out_proj.weight.T + mha.out_proj.bias


def test_boq_matches_the_paper() -> None:
    agg = _build("boq")
    x, w = torch.randn(2, D, H, W), torch.rand(2, 1, H, W)
    w[0, 0, 0, 0] = 0.0
    ln = lambda t, m: F.layer_norm(t, t.shape[-1:], m.weight, m.bias, m.eps)  # noqa: E731
    with torch.no_grad():
        for weights in (None, w):
            out = []
            for b in range(2):
                bias = torch.zeros(H * W) if weights is None else weights[b].reshape(-1).log().clamp(min=-1e4)
                tokens = x[b].reshape(D, -1).T @ agg.proj_c.weight.reshape(-1, D).T + agg.proj_c.bias
                tokens = ln(tokens, agg.norm_input)
                outs = []
                for blk in agg.blocks:
                    enc = blk.encoder  # post-norm: x ← LN(x + SA(x)); x ← LN(x + W2 ReLU(W1 x))
                    tokens = ln(tokens + _attention(tokens, tokens, enc.self_attn, bias), enc.norm1)
                    ff = (
                        torch.relu(tokens @ enc.linear1.weight.T + enc.linear1.bias) @ enc.linear2.weight.T
                        + enc.linear2.bias
                    )
                    tokens = ln(tokens + ff, enc.norm2)
                    q = blk.queries[0]
                    q = ln(q + _attention(q, q, blk.self_attn, torch.zeros(len(q))), blk.norm_q)
                    outs.append(ln(_attention(q, tokens, blk.cross_attn, bias), blk.norm_out))
                stacked = torch.cat(outs)  # (L·Q, d)
                rows = stacked.T @ agg.fc.weight.T + agg.fc.bias  # (d, row_dim)
                out.append(rows.reshape(-1) / rows.norm())
            torch.testing.assert_close(agg(x, weights), torch.stack(out), rtol=1e-4, atol=1e-5)
