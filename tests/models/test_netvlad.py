"""NetVLAD: equals the naive loop, mask semantics, k-means/α init, PCA whitening."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from semvpr.core.errors import SemvprError
from semvpr.models.aggregators.netvlad import NetVLAD, alpha_from_features
from semvpr.models.whitening import PCAWhitening

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def layer() -> NetVLAD:
    torch.manual_seed(0)
    net = NetVLAD(num_clusters=8, dim=32)
    net.init_from_features(torch.relu(torch.randn(2000, 32)), seed=0)
    return net


def published_netvlad(
    x: np.ndarray, weight: np.ndarray, bias: np.ndarray, centroids: np.ndarray, mask: np.ndarray | None = None
) -> np.ndarray:
    """NetVLAD as Arandjelović et al. (CVPR'16) define it, written from the paper in float64 NumPy:
    L2-normalise each local descriptor; soft-assign with a 1x1 conv of weights w_k and biases b_k
    (decoupled from the centroids c_k, initialised as w_k = 2αĉ_k, b_k = −α‖ĉ_k‖²) followed by a
    softmax over k; V(j,k) = Σ_i a_k(x_i)(x_i(j) − c_k(j)) (here each location's term times its mask
    weight); intra-normalise each V(:,k); L2-normalise the whole."""
    b, d, h, w = x.shape
    local = x.reshape(b, d, h * w).transpose(0, 2, 1).astype(np.float64)  # (B, N, D)
    local = local / np.linalg.norm(local, axis=2, keepdims=True)
    c = centroids.astype(np.float64)
    logits = local @ weight.astype(np.float64).T + bias.astype(np.float64)  # (B, N, K)
    logits -= logits.max(2, keepdims=True)
    assign = np.exp(logits) / np.exp(logits).sum(2, keepdims=True)
    weight = np.ones((b, h * w)) if mask is None else mask.reshape(b, h * w).astype(np.float64)
    out = np.zeros((b, len(c), d))
    for n in range(b):
        for k in range(len(c)):
            out[n, k] = ((local[n] - c[k]) * (assign[n, :, k] * weight[n])[:, None]).sum(0)
    out /= np.linalg.norm(out, axis=2, keepdims=True)
    out = out.reshape(b, -1)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def test_matches_the_published_formula(layer: NetVLAD) -> None:
    x = torch.randn(3, 32, 5, 7)  # signed, like conv5_3 before its ReLU
    mask = (torch.rand(3, 1, 5, 7) > 0.4).float() * torch.rand(3, 1, 5, 7)
    params = (
        layer.conv.weight[:, :, 0, 0].detach().numpy(),
        layer.conv.bias.detach().numpy(),
        layer.centroids.detach().numpy(),
    )
    with torch.no_grad():
        out, masked = layer(x), layer(x, mask)
    assert out.shape == (3, 8 * 32)
    np.testing.assert_allclose(out.numpy(), published_netvlad(x.numpy(), *params), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(
        masked.numpy(), published_netvlad(x.numpy(), *params, mask.numpy()), rtol=1e-4, atol=1e-5
    )
    assign = layer.assignment(x)
    assert assign.shape == (3, 8, 5, 7)
    torch.testing.assert_close(assign.sum(1), torch.ones(3, 5, 7))


def test_mask_ones_equals_no_mask(layer: NetVLAD) -> None:
    x = torch.randn(2, 32, 4, 6)
    torch.testing.assert_close(layer(x, torch.ones(2, 1, 4, 6)), layer(x), rtol=0, atol=0)


def test_zero_mask_drops_contributions_not_features(layer: NetVLAD) -> None:
    x = torch.relu(torch.randn(1, 32, 4, 6))
    mask = torch.ones(1, 1, 4, 6)
    mask[..., 4:] = 0
    dropped = layer(x[..., :4])  # the same grid without the masked columns
    torch.testing.assert_close(layer(x, mask), dropped, rtol=1e-5, atol=1e-6)
    zeroed = x.clone()
    zeroed[..., 4:] = 0  # a zero feature still adds −a_k(0)·c_k: must NOT be what the mask does
    assert (layer(zeroed) - dropped).abs().max() > 1e-3


def test_bf16_autocast_and_channels_last(layer: NetVLAD) -> None:
    x = torch.randn(2, 32, 4, 6).bfloat16()
    ref = layer(x.float())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = layer(x.contiguous(memory_format=torch.channels_last))
    assert out.dtype == torch.float32  # aggregation runs in fp32 regardless of autocast
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)


def test_init_recovers_separated_clusters() -> None:
    rng = np.random.default_rng(0)
    centres = np.eye(16, dtype=np.float32)[:4] * 3
    feats = np.concatenate([c + 0.05 * rng.standard_normal((300, 16)) for c in centres]).astype(np.float32)
    net = NetVLAD(num_clusters=4, dim=16)
    alpha = net.init_from_features(torch.from_numpy(feats), seed=1)
    # The assignment conv holds 2α·ĉ_k for unit centroids ĉ_k, one per blob.
    unit = (net.conv.weight[:, :, 0, 0] / (2 * float(net.alpha))).detach().numpy()
    assert np.allclose(np.linalg.norm(unit, axis=1), 1.0, atol=1e-5)
    assert np.allclose(np.sort((unit @ np.eye(16)[:4].T).max(1)), 1.0, atol=0.01)
    assert sorted((unit @ np.eye(16)[:4].T).argmax(1).tolist()) == [0, 1, 2, 3]
    # α by hand: logits 2x·ĉ − ‖ĉ‖² of the normalised features, mean gap between best and second best.
    x = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    logits = np.sort(2 * x @ unit.T - (unit**2).sum(1), axis=1)
    assert alpha == pytest.approx(-math.log(0.01) / np.mean(logits[:, -1] - logits[:, -2]), rel=1e-4)
    assert float(net.alpha) == pytest.approx(alpha)
    torch.testing.assert_close(net.conv.bias, -alpha * torch.ones(4), rtol=1e-5, atol=1e-4 * alpha)
    # Residual centroids: the raw means of each blob's normalised features (pytorch-NetVlad), norm < 1.
    blob = np.repeat(np.arange(4), 300)
    means = np.stack([x[blob == (unit @ np.eye(16)[:4].T).argmax(1)[k]].mean(0) for k in range(4)])
    np.testing.assert_allclose(net.centroids.detach().numpy(), means, atol=1e-5)
    assert (np.linalg.norm(means, axis=1) < 0.999).all()


def test_alpha_exact_case() -> None:
    # Points on orthonormal centroids: best logit 2·1−1 = 1, second 0−1 = −1, gap 2 → α = ln(100)/2.
    eye = np.eye(4, dtype=np.float32)
    assert alpha_from_features(eye, eye) == pytest.approx(math.log(100) / 2)


def test_too_few_features_is_user_error() -> None:
    with pytest.raises(SemvprError, match="at least 8 local features"):
        NetVLAD(8, 4).init_from_features(torch.randn(5, 4))


def test_gradients_reach_parameters() -> None:
    layer = NetVLAD(num_clusters=8, dim=32)
    layer.set_centroids(F.normalize(torch.randn(8, 32), dim=1), alpha=5.0)
    x = torch.randn(2, 32, 3, 3, requires_grad=True)
    (layer(x) * torch.randn(2, 256)).sum().backward()
    for name, p in layer.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_pca_whitening() -> None:
    gen = torch.Generator().manual_seed(0)
    mix = torch.randn(12, 12, generator=gen)
    db = torch.randn(500, 12, generator=gen) @ mix + 3.0
    pca = PCAWhitening(12, 6).fit(db)
    proj = (db - pca.mean) @ pca.projection.T
    torch.testing.assert_close(proj.T @ proj / 499, torch.eye(6), rtol=1e-3, atol=1e-3)
    out = pca(db[:5])
    assert out.shape == (5, 6)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(5))
    # Gram (N < D) and covariance paths agree up to the sign of each axis.
    wide = torch.randn(20, 40, generator=gen)
    a = PCAWhitening(40, 5).fit(wide).projection
    b = PCAWhitening(40, 5)
    b.fit(torch.cat([wide, wide.mean(0, keepdim=True).expand(30, -1)]))  # N ≥ D, same principal axes
    torch.testing.assert_close(
        (a * b.projection).sum(1).abs() / (a.norm(dim=1) * b.projection.norm(dim=1)),
        torch.ones(5),
        rtol=1e-3,
        atol=1e-3,
    )
    with pytest.raises(SemvprError, match="PCA whitening to 40 dims"):
        PCAWhitening(40, 40).fit(wide)
