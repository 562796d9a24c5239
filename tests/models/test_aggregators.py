"""Each aggregator against an independent re-derivation of its authors' forward pass, written here from
the authors' code (pytorch-NetVlad, cirtorch / CosPlace, MixVPR, SALAD, Bag-of-Queries; SRAL, which has
no published code, from its formula), with the module's weights copied across, at the sizes the
shipped ``conf/aggregator/*.yaml`` configure on the default trunk's features (112 channels on a 12x15
grid). The masked forms re-derive what each module's docstring says the mask does. The mask contract
every aggregator keeps is tested on every shipped config in ``test_components.py``."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.config.components import build_component
from semvpr.core.errors import SemvprError
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.aggregators.boq import BoQ
from semvpr.models.aggregators.mixvpr import MixVPR
from semvpr.models.aggregators.netvlad import NetVLAD, alpha_from_features
from semvpr.models.aggregators.salad import SALAD, log_sinkhorn
from tests.helpers import config

torch.set_num_threads(2)
#: The default trunk (EfficientNet-Lite0 stage4 at 180x240): 112 channels on a 12x15 grid.
D, H, W = 112, 12, 15
N = H * W


def shipped(name: str, *overrides: str) -> Aggregator:
    """The aggregator ``conf/aggregator/<name>.yaml`` builds (default config, ``overrides`` on top) for the
    default trunk's features, in eval mode, initialised from a random sample where its class asks for one."""
    node = config(f"aggregator={name}", *overrides).aggregator
    torch.manual_seed(0)
    agg = build_component(node, "aggregator", dim=D, **({"grid": [H, W]} if "grid" in node else {})).eval()
    assert isinstance(agg, Aggregator)
    if agg.init_sample != "none":
        feats = torch.randn(3000, D)
        agg.init_from_sample(feats, torch.arange(3000) % 3 != 0 if agg.init_sample == "labelled" else None, seed=0)
    return agg


def features(batch: int = 2, seed: int = 1) -> tuple[Tensor, Tensor]:
    """Signed local features (B,D,H,W) and a mask (B,1,H,W) with soft weights and a few zeros."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, D, H, W, generator=gen)
    w = torch.rand(batch, 1, H, W, generator=gen) * 0.9 + 0.1
    w[torch.rand(batch, 1, H, W, generator=gen) < 0.3] = 0.0
    w[:, :, 0, 0] = 0.0  # a corner, so the border's renormalisation is exercised under a mask too
    return x, w


def l2(v: Tensor, dim: int = -1) -> Tensor:
    return v / v.norm(dim=dim, keepdim=True)


def locations(x: Tensor) -> Tensor:
    """(D,H,W) → (N,D) local features in row-major order (index h·W + w)."""
    return x.reshape(x.shape[0], -1).T


def mlp(layers: nn.Sequential, v: Tensor) -> Tensor:
    """A two-layer ReLU MLP of 1x1 convs or linears (dropout off) on the last axis of v, from its weights."""
    lin = [m for m in layers if isinstance(m, (nn.Conv2d, nn.Linear))]
    assert len(lin) == 2
    w1, w2 = (m.weight.reshape(m.weight.shape[0], -1).double() for m in lin)
    return torch.relu(v @ w1.T + lin[0].bias.double()) @ w2.T + lin[1].bias.double()


# ------------------------------------------------------------------------------------------ NetVLAD


def pytorch_netvlad(x: Tensor, conv_w: Tensor, conv_b: Tensor, centroids: Tensor, w: Tensor | None) -> Tensor:
    """pytorch-NetVlad's forward in float64: L2 over channels, 1x1 conv, softmax over clusters, residuals
    to the raw centroids cluster by cluster, intra-L2, flatten (index k·D + d), L2. With a mask, each
    location's soft-assignment is multiplied by its weight (semvpr's extension)."""
    out = []
    for b in range(x.shape[0]):
        loc = l2(locations(x[b]).double())  # (N, D)
        assign = (loc @ conv_w.double().T + conv_b.double()).softmax(dim=1)  # (N, K)
        if w is not None:
            assign = assign * w[b].reshape(-1, 1).double()
        vlad = torch.stack([(assign[:, k : k + 1] * (loc - c)).sum(0) for k, c in enumerate(centroids.double())])
        out.append(l2(l2(vlad).reshape(-1)))
    return torch.stack(out)


@pytest.mark.parametrize("name", ["netvlad", "sral (no shadows)"])
def test_netvlad_matches_pytorch_netvlad(name: str) -> None:
    agg = shipped("netvlad") if name == "netvlad" else shipped("sral", "model.num_shadows=0")
    x, w = features()
    conv_w, conv_b = agg.conv.weight[:, :, 0, 0], agg.conv.bias
    with torch.no_grad():
        for weights in (None, w):
            expected = pytorch_netvlad(x, conv_w, conv_b, agg.centroids, weights)
            torch.testing.assert_close(agg(x, weights).double(), expected, rtol=1e-5, atol=1e-6)


def test_netvlad_alpha_is_half_of_vladv1s_and_the_assignment_is_vladv1s() -> None:
    """With unit centroids, semvpr's α (the squared-distance gap) is pytorch-NetVlad vladv1's α (the
    dot-product gap) / 2, and the soft-assignment 2α·c·x − α‖c‖² equals vladv1's α_v1·ĉ·x (no bias)."""
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(3000, D, generator=gen) + 0.5  # trunk-like: correlated, not centred
    unit_x = l2(feats)

    def vladv1(unit_c: Tensor) -> tuple[float, Tensor]:
        """vladv1's α = −ln(0.01) / mean(top1 − top2 of ĉ·x) and its assignment softmax_k(α·ĉ_k·x)."""
        dots = unit_x.double() @ unit_c.double().T
        top2 = dots.topk(2, dim=1).values
        alpha_v1 = -math.log(0.01) / float((top2[:, 0] - top2[:, 1]).mean())
        return alpha_v1, (alpha_v1 * dots).softmax(dim=1)

    # Given unit centroids (the helper, then the layer set from it), and the layer's own k-means init.
    given = l2(unit_x[torch.randperm(3000, generator=gen)[:32]] + 0.1 * torch.randn(32, D, generator=gen))
    alpha = alpha_from_features(unit_x.numpy(), given.numpy())
    set_from_given = NetVLAD(num_clusters=32, dim=D)
    set_from_given.set_centroids(given, alpha)
    own_kmeans = NetVLAD(num_clusters=32, dim=D)
    own_kmeans.init_from_features(feats, seed=0)
    for agg in (set_from_given, own_kmeans):
        alpha = float(agg.alpha)
        unit_c = agg.conv.weight[:, :, 0, 0].detach() / (2 * alpha)
        torch.testing.assert_close(unit_c.norm(dim=1), torch.ones(32), rtol=0, atol=1e-5)
        alpha_v1, assign_v1 = vladv1(unit_c)
        assert alpha == pytest.approx(alpha_v1 / 2, rel=1e-5)
        with torch.no_grad():
            assign = agg.assignment(feats.T.reshape(1, D, 1, -1))[0, :, 0].T  # (N, K)
        torch.testing.assert_close(assign.double(), assign_v1, rtol=0, atol=5e-5)  # fp32 logits up to ~2α
        assert assign_v1.max(dim=1).values.mean() > 0.3  # a sharp assignment, not a uniform one


# ------------------------------------------------------------------------------------------ SRAL


def test_sral_matches_its_formula() -> None:
    """a_k softmax over the representatives' logits; β_k = e^{l_k} / (e^{l_k} + Σ_j e^{l_kj}) over the
    cluster's representative and shadows; V(:,k) = Σ_i w_i·a_k·β_k·(x_i − c_k); intra-L2; L2."""
    agg = shipped("sral")
    k, s = agg.num_clusters, agg.num_shadows
    assert (k, s) == (32, 4)
    x, w = features()
    with torch.no_grad():
        for weights in (None, w):
            out = []
            for b in range(2):
                loc = l2(locations(x[b]).double())
                rep = loc @ agg.conv.weight[:, :, 0, 0].double().T + agg.conv.bias.double()  # (N, K)
                shadow = torch.einsum("nd,ksd->nks", loc, agg.shadow_weight.double()) + agg.shadow_bias.double()
                beta = rep.exp() / (rep.exp() + shadow.exp().sum(2))
                mass = rep.softmax(dim=1) * beta
                if weights is not None:
                    mass = mass * weights[b].reshape(-1, 1).double()
                vlad = torch.stack([(mass[:, j : j + 1] * (loc - agg.centroids[j].double())).sum(0) for j in range(k)])
                out.append(l2(l2(vlad).reshape(-1)))
            torch.testing.assert_close(agg(x, weights).double(), torch.stack(out), rtol=1e-5, atol=1e-6)
            assert agg.attention(x).min() < 0.9  # the shadows are near real features: β varies


# ------------------------------------------------------------------------------------------ GeM


def cirtorch_gem(x: Tensor, p: float, eps: float, w: Tensor | None) -> Tensor:
    """GeM as cirtorch: avg_pool over the whole map of clamp(x, eps)^p, then ^(1/p); with a mask, the
    mean is weighted (semvpr's extension)."""
    powered = x.double().clamp(min=eps) ** p
    if w is None:
        return F.avg_pool2d(powered, (x.shape[-2], x.shape[-1])).flatten(1) ** (1 / p)
    w = w.double()
    return ((powered * w).sum((2, 3)) / w.sum((2, 3))) ** (1 / p)


def test_gem_matches_cirtorch() -> None:
    agg = shipped("gem", "aggregator.fc_dim=null")
    with torch.no_grad():
        agg.p.fill_(2.5)
    x, w = features()
    assert agg.output_dim == D and agg.p.requires_grad
    with torch.no_grad():
        for weights in (None, w):
            expected = l2(cirtorch_gem(x, 2.5, 1e-6, weights))
            torch.testing.assert_close(agg(x, weights).double(), expected, rtol=1e-5, atol=1e-6)


def test_gem_head_matches_cosplace() -> None:
    """CosPlace's aggregation: L2Norm over channels, GeM, Flatten, Linear, L2Norm."""
    agg = shipped("gem")
    assert agg.output_dim == 512 and agg.fc.weight.requires_grad
    x, w = features()
    with torch.no_grad():
        for weights in (None, w):
            pooled = cirtorch_gem(l2(x.double(), dim=1), float(agg.p), 1e-6, weights)
            expected = l2(pooled @ agg.fc.weight.double().T + agg.fc.bias.double())
            torch.testing.assert_close(agg(x, weights).double(), expected, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------ MixVPR


def authors_mixvpr(agg: MixVPR, x: Tensor) -> Tensor:
    """MixVPR's forward in float64: rows of hw values, each mixer X ← X + W2 ReLU(W1 LN(X) + b1) + b2,
    channel projection (with bias) over C, row projection (with bias) over hw, flatten (c·rows + r), L2."""
    rows = x.double().flatten(2)  # (B, C, hw)
    for layer in agg.mix:
        normed = F.layer_norm(rows, rows.shape[-1:], layer.norm.weight.double(), layer.norm.bias.double(), 1e-5)
        hidden = torch.relu(normed @ layer.fc1.weight.double().T + layer.fc1.bias.double())
        rows = rows + hidden @ layer.fc2.weight.double().T + layer.fc2.bias.double()
    g = rows.transpose(1, 2) @ agg.channel_proj.weight.double().T + agg.channel_proj.bias.double()  # (B, hw, C')
    o = g.transpose(1, 2) @ agg.row_proj.weight.double().T + agg.row_proj.bias.double()  # (B, C', rows)
    return l2(o.flatten(1))


def test_mixvpr_matches_the_authors() -> None:
    agg = shipped("mixvpr")
    assert (agg.output_dim, len(agg.mix)) == (512 * 4, 4)
    with torch.no_grad():
        agg.row_proj.bias.copy_(torch.randn(4))  # a bias that matters, whatever its init
    x, w = features()
    with torch.no_grad():
        torch.testing.assert_close(agg(x).double(), authors_mixvpr(agg, x), rtol=1e-5, atol=1e-6)
        # the mask multiplies the features before the mixer
        torch.testing.assert_close(agg(x, w).double(), authors_mixvpr(agg, x * w), rtol=1e-5, atol=1e-6)


def test_mixvpr_initialises_as_the_authors() -> None:
    """The mixers' linears: truncated normal (std 0.02, limits ±2), zero bias; the LayerNorms and both
    projections: PyTorch's defaults (uniform within ±1/√fan_in, biases included)."""
    agg = shipped("mixvpr")
    for layer in agg.mix:
        for linear in (layer.fc1, layer.fc2):
            assert linear.weight.std().item() == pytest.approx(0.02, rel=0.03)
            assert linear.weight.abs().max() <= 2.0 and linear.weight.mean().abs() < 1e-3
            assert torch.equal(linear.bias, torch.zeros_like(linear.bias))
        assert torch.equal(layer.norm.weight, torch.ones(N)) and torch.equal(layer.norm.bias, torch.zeros(N))
    for proj, fan_in in ((agg.channel_proj, D), (agg.row_proj, N)):
        bound = 1 / math.sqrt(fan_in)
        assert proj.weight.abs().max() <= bound and proj.weight.std().item() == pytest.approx(bound / 3**0.5, rel=0.1)
        assert proj.bias is not None and proj.bias.abs().max() <= bound and proj.bias.abs().max() > bound / 4


def test_mixvpr_other_grid_is_pooled_to_the_built_grid() -> None:
    agg = shipped("mixvpr")
    x, w = torch.randn(2, D, 2 * H, 2 * W), torch.rand(2, 1, 2 * H, 2 * W)
    pooled = (x * w).reshape(2, D, H, 2, W, 2).mean((3, 5))  # 2×2 block means = adaptive pooling here
    with torch.no_grad():
        torch.testing.assert_close(agg(x, w), agg(pooled), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------ SALAD


def authors_log_ot(scores: Tensor, log_a: Tensor, log_b: Tensor, iters: int, v0: Tensor | None = None) -> Tensor:
    """SALAD's log-domain optimal transport (from SuperGlue / OpenGlue) on one (M,N) score matrix: u and
    v start at 0 (``v0``: another start for v), each iteration a row update then a column update."""
    u = torch.zeros_like(log_a)
    v = torch.zeros_like(log_b) if v0 is None else v0
    for _ in range(iters):
        u = log_a - torch.logsumexp(scores + v[None, :], dim=1)
        v = log_b - torch.logsumexp(scores + u[:, None], dim=0)
    return scores + u[:, None] + v[None, :]


def authors_salad(agg: SALAD, x: Tensor, w: Tensor | None) -> Tensor:
    """SALAD's forward in float64 for each image: scores with a dustbin ROW of the learnable scalar, row
    masses (1, …, 1, n − m)/(m + n), column masses 1/(m + n), 3 iterations from u = v = 0, the plan
    times (m + n), dustbin dropped, V = Σ_i f_i P_ki, intra-L2 over the cluster dim, flatten (c·m + k),
    after the L2-normed token, L2.

    With a mask: a location of weight 0 is left out of the problem (its column is not there), the
    others' column masses are w_i/(m + n) and v starts at log w_i (0 for w ≡ 1: the authors' start).
    The token is the mask-weighted mean feature (semvpr's stand-in for the ViT's class token)."""
    m = agg.num_clusters
    norm = -math.log(m + N)
    out = []
    for b in range(x.shape[0]):
        loc = locations(x[b]).double()  # (n, D)
        weight = torch.ones(N, dtype=torch.float64) if w is None else w[b].reshape(-1).double()
        keep = weight > 0
        f, s = mlp(agg.cluster_features, loc).T, mlp(agg.score, loc).T  # (l, n), (m, n)
        scores = torch.cat([s, torch.full((1, N), float(agg.dust_bin), dtype=torch.float64)])[:, keep]
        log_a = torch.full((m + 1,), norm, dtype=torch.float64)
        log_a[m] = norm + math.log(N - m)
        log_w = weight[keep].log()
        plan = (authors_log_ot(scores, log_a, norm + log_w, agg.iters, v0=log_w) - norm).exp()[:m]
        v = l2(f[:, keep] @ plan.T, dim=0)  # (l, m)
        token = (loc * weight[:, None]).sum(0) / weight.sum()
        out.append(l2(torch.cat([l2(mlp(agg.token_features, token)), v.reshape(-1)])))
    return torch.stack(out)


def trained_like_salad(std: float = 5.0) -> tuple[SALAD, Tensor, Tensor]:
    """The shipped SALAD with its score layer scaled so the cluster scores have std ≈ ``std`` (a trained
    model's scale; the random init gives ≈ 0.2), and features with a mask."""
    agg = shipped("salad")
    x, w = features()
    with torch.no_grad():
        scale = std / agg.score(x).std().item()
        agg.score[-1].weight.mul_(scale)
        agg.score[-1].bias.mul_(scale)
        assert agg.score(x).std().item() == pytest.approx(std, rel=1e-3)
    return agg, x, w


def test_salad_matches_the_authors() -> None:
    agg, x, w = trained_like_salad()
    assert (agg.num_clusters, agg.cluster_dim, agg.token_dim, agg.iters, agg.output_dim) == (32, 64, 256, 3, 2304)
    with torch.no_grad():
        torch.testing.assert_close(agg(x).double(), authors_salad(agg, x, None), rtol=1e-5, atol=1e-6)


def test_salad_masked_locations_are_out_of_the_transport() -> None:
    """A location of weight 0 is as if it were not there, from the first row normalisation on."""
    agg, x, w = trained_like_salad()
    with torch.no_grad():
        torch.testing.assert_close(agg(x, w).double(), authors_salad(agg, x, w), rtol=1e-5, atol=1e-6)
        binary = (w > 0).float()
        torch.testing.assert_close(agg(x, binary).double(), authors_salad(agg, x, binary), rtol=1e-5, atol=1e-6)


def test_salad_sinkhorn_without_a_mask_is_the_authors_start_bit_for_bit() -> None:
    """Equal column masses start v at 0: the same plan as u = v = 0, to the last bit."""
    gen = torch.Generator().manual_seed(0)
    m, n = 33, N
    scores = 5.0 * torch.randn(2, m, n, generator=gen)
    log_a = torch.full((2, m), -math.log(m + n))
    log_a[:, -1] += math.log(n - m)
    log_b = torch.full((2, n), -math.log(m + n))
    expected = torch.stack([authors_log_ot(scores[b], log_a[b], log_b[b], 3) for b in range(2)])
    assert torch.equal(log_sinkhorn(scores, log_a, log_b, 3), expected)


def test_salad_class_token_is_the_global_token_and_no_mask_reaches_it() -> None:
    """``global_token=class``: g is the token MLP of the channels after the patch channels (the trunk's class
    token); a mask moves the clusters' part only."""
    x, w = features()
    token = torch.randn(2, D, generator=torch.Generator().manual_seed(3))
    with_token = torch.cat([x, token[:, :, None, None].expand_as(x)], dim=1)
    agg = SALAD(dim=D, num_clusters=8, hidden_dim=64, global_token="class").eval()
    g = agg.token_dim
    with torch.no_grad():
        plain, masked = agg(with_token), agg(with_token, w)
        expected_g = F.normalize(agg.token_features(token), dim=1)
    norm = plain[:, :g].norm(dim=1, keepdim=True)  # the global part's share of the unit descriptor
    torch.testing.assert_close(plain[:, :g] / norm, expected_g, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(masked[:, :g], plain[:, :g], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(masked[:, g:], plain[:, g:], atol=1e-4)
    with pytest.raises(SemvprError, match="needs the backbone's class token"):
        agg(x)


def test_salad_needs_more_locations_than_clusters() -> None:
    with pytest.raises(SemvprError, match="more feature locations than clusters"):
        SALAD(dim=D, num_clusters=N)(torch.randn(1, D, H, W))


# ------------------------------------------------------------------------------------------ BoQ


class AuthorsBoQBlock(nn.Module):
    """BoQ's block as the authors build it from PyTorch modules (parameter names as semvpr's, so the
    weights load with strict=True)."""

    def __init__(self, dim: int, num_queries: int) -> None:
        super().__init__()
        heads = dim // 64
        self.encoder = nn.TransformerEncoderLayer(dim, heads, 4 * dim, dropout=0.0, batch_first=True)
        self.queries = nn.Parameter(torch.randn(1, num_queries, dim))
        self.self_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        x = self.encoder(x)
        q = self.queries.repeat(x.shape[0], 1, 1)
        q = self.norm_q(q + self.self_attn(q, q, q)[0])
        return x, self.norm_out(self.cross_attn(q, x, x)[0])  # no residual around the cross-attention


class AuthorsBoQ(nn.Module):
    """BoQ as the authors build it: a kxk input convolution (3x3, padding 1, with bias), LayerNorm over
    channels, the blocks in cascade, their outputs stacked, a linear layer over the L·Q axis, flatten
    (d·row_dim + r), L2."""

    def __init__(self, dim: int, proj: int, num_queries: int, num_layers: int, row_dim: int, kernel: int) -> None:
        super().__init__()
        self.proj_c = nn.Conv2d(dim, proj, kernel_size=kernel, padding=kernel // 2)
        self.norm_input = nn.LayerNorm(proj)
        self.blocks = nn.ModuleList([AuthorsBoQBlock(proj, num_queries) for _ in range(num_layers)])
        self.fc = nn.Linear(num_layers * num_queries, row_dim)

    def forward(self, x: Tensor) -> Tensor:
        x = self.norm_input(self.proj_c(x).flatten(2).permute(0, 2, 1))
        outs = []
        for block in self.blocks:
            x, out = block(x)
            outs.append(out)
        rows = self.fc(torch.cat(outs, dim=1).permute(0, 2, 1))
        return F.normalize(rows.flatten(1), dim=-1)


def authors_boq(agg: BoQ, kernel: int) -> AuthorsBoQ:
    """The authors' BoQ at the module's sizes with the module's weights copied across (strict), in float64.
    Train mode: every dropout is 0, and PyTorch's inference fast path is not taken."""
    ref = AuthorsBoQ(D, agg.proj_channels, agg.blocks[0].queries.shape[1], len(agg.blocks), agg.row_dim, kernel)
    ref.load_state_dict(agg.state_dict(), strict=True)
    return ref.double().train()


def normalised_conv(x: Tensor, weight: Tensor, bias: Tensor, w: Tensor) -> Tensor:
    """(D,H,W) → (H,W,d): b + Σ_o K_o·w_{p+o}·x_{p+o} · |N_p| / Σ_{q∈N_p} w_q over the in-image window N_p,
    offset by offset."""
    k = weight.shape[-1]
    r = k // 2
    xp, wp = F.pad(x * w, (r, r, r, r)), F.pad(w, (r, r, r, r))
    inside = F.pad(torch.ones_like(w), (r, r, r, r))
    acc = torch.zeros(H, W, weight.shape[0], dtype=x.dtype)
    count, wsum = torch.zeros(H, W, dtype=x.dtype), torch.zeros(H, W, dtype=x.dtype)
    for dy in range(k):
        for dx in range(k):
            acc += xp[:, dy : dy + H, dx : dx + W].permute(1, 2, 0) @ weight[:, :, dy, dx].T
            count += inside[0, dy : dy + H, dx : dx + W]
            wsum += wp[0, dy : dy + H, dx : dx + W]
    return bias + acc * (count / wsum.clamp(min=1e-6))[..., None]


def attention(q_in: Tensor, k_in: Tensor, mha: nn.MultiheadAttention, bias: Tensor) -> Tensor:
    """Multi-head scaled dot-product attention with a per-key logit bias, from the module's weights."""
    d, heads = q_in.shape[-1], mha.num_heads
    wq, wk, wv = mha.in_proj_weight.double().split(d)
    bq, bk, bv = mha.in_proj_bias.double().split(d)
    q, k, v = q_in @ wq.T + bq, k_in @ wk.T + bk, k_in @ wv.T + bv
    split = lambda t: t.reshape(t.shape[0], heads, d // heads).transpose(0, 1)  # noqa: E731
    logits = split(q) @ split(k).transpose(1, 2) / math.sqrt(d // heads) + bias[None, None, :]
    o = (logits.softmax(-1) @ split(v)).transpose(0, 1).reshape(q_in.shape[0], d)
    return o @ mha.out_proj.weight.double().T + mha.out_proj.bias.double()


def masked_boq(agg: BoQ, x: Tensor, w: Tensor) -> Tensor:
    """The masked BoQ written out: the normalised kxk projection, log w on every attention key."""
    ln = lambda t, m: F.layer_norm(t, t.shape[-1:], m.weight.double(), m.bias.double(), m.eps)  # noqa: E731
    out = []
    for b in range(x.shape[0]):
        bias = w[b].reshape(-1).double().log().clamp(min=-1e4)
        conv = agg.proj_c
        projected = normalised_conv(x[b].double(), conv.weight.double(), conv.bias.double(), w[b].double())
        tokens = ln(projected.reshape(N, -1), agg.norm_input)
        outs = []
        for blk in agg.blocks:
            enc = blk.encoder  # post-norm: x ← LN(x + SA(x)); x ← LN(x + W2 ReLU(W1 x))
            tokens = ln(tokens + attention(tokens, tokens, enc.self_attn, bias), enc.norm1)
            hidden = torch.relu(tokens @ enc.linear1.weight.double().T + enc.linear1.bias.double())
            tokens = ln(tokens + hidden @ enc.linear2.weight.double().T + enc.linear2.bias.double(), enc.norm2)
            q = blk.queries[0].double()
            q = ln(q + attention(q, q, blk.self_attn, torch.zeros(len(q), dtype=torch.float64)), blk.norm_q)
            outs.append(ln(attention(q, tokens, blk.cross_attn, bias), blk.norm_out))
        rows = torch.cat(outs).T @ agg.fc.weight.double().T + agg.fc.bias.double()  # (d, row_dim)
        out.append(l2(rows.reshape(-1)))
    return torch.stack(out)


@pytest.mark.parametrize("kernel", [3, 1])
def test_boq_matches_the_authors(kernel: int) -> None:
    agg = shipped("boq", f"aggregator.proj_kernel={kernel}")
    assert (agg.proj_kernel, agg.proj_c.weight.shape[-2:], agg.output_dim) == (kernel, (kernel, kernel), 128 * 16)
    x, w = features()
    with torch.no_grad():
        expected = authors_boq(agg, kernel)(x.double())
        torch.testing.assert_close(agg(x).double(), expected, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(agg(x, w).double(), masked_boq(agg, x, w), rtol=1e-5, atol=1e-6)
        # the written-out reference is the authors' model too where the mask keeps everything
        torch.testing.assert_close(masked_boq(agg, x, torch.ones_like(w)), expected, rtol=1e-9, atol=1e-10)


def test_boq_projection_with_weights_of_one_is_the_authors_convolution_bit_for_bit() -> None:
    """w ≡ 1 renormalises by exactly 1, at the zero-padded border too."""
    agg = shipped("boq", "aggregator.proj_kernel=3")
    x = features()[0]
    plain = F.conv2d(x, agg.proj_c.weight, agg.proj_c.bias, padding=1)
    with torch.no_grad():
        assert torch.equal(agg.project(x, None), plain)
        assert torch.equal(agg.project(x, torch.ones(2, 1, H, W)), plain)


def test_boq_projection_keeps_a_masked_location_out_of_its_neighbours() -> None:
    agg = shipped("boq", "aggregator.proj_kernel=3")
    x, w = features()
    moved = x.clone()
    moved[:, :, 5, 7] += 10.0 * torch.randn(2, D)
    w[:, :, 5, 7] = 0.0
    with torch.no_grad():
        assert torch.equal(agg.project(moved, w), agg.project(x, w))
        ones = torch.ones_like(w)
        assert (agg.project(moved, ones) - agg.project(x, ones))[:, :, 4:7, 6:9].abs().min() > 0


def test_boq_projection_kernel_must_be_odd() -> None:
    with pytest.raises(SemvprError, match="proj_kernel"):
        BoQ(dim=D, proj_kernel=2)
