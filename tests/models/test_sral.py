"""SRAL: reduces to NetVLAD without shadows, semantic init placement, attention, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.aggregators.sral import SRAL

torch.set_num_threads(2)
EYE = np.eye(32, dtype=np.float32)


def _blobs(directions: list[int], n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([EYE[d] + 0.05 * rng.standard_normal((n, 32)) for d in directions]).astype(np.float32)


def test_zero_shadows_equals_netvlad() -> None:
    torch.manual_seed(0)
    net = NetVLAD(8, 32)
    net.init_from_features(torch.randn(1000, 32), seed=0)
    sral = SRAL(8, 32, num_shadows=0)
    sral.load_state_dict(net.state_dict(), strict=False)
    x, mask = torch.randn(2, 32, 4, 5), torch.rand(2, 1, 4, 5)
    assert torch.equal(sral(x), net(x)) and torch.equal(sral(x, mask), net(x, mask))
    torch.testing.assert_close(sral.attention(x), torch.ones(2, 1, 4, 5))


def test_semantic_init_places_representatives_and_shadows() -> None:
    static, dynamic = _blobs([0, 1, 2, 3], 200, 0), _blobs([20, 21], 150, 1)
    sral = SRAL(4, 32, num_shadows=2)
    counts = sral.init_semantic(torch.from_numpy(static), torch.from_numpy(dynamic), seed=0)
    assert counts["static_features"] == 800 and counts["dynamic_features"] == 300
    assert counts["shadow_candidates"] == 8 and counts["alpha"] == pytest.approx(float(sral.alpha))
    reps = sral.centroids.detach().numpy()
    assert sorted((reps @ EYE[:4].T).argmax(1).tolist()) == [0, 1, 2, 3]
    assert (reps @ EYE[:4].T).max(1).min() > 0.95
    # Shadow centroids are recovered from w = 2α·s; every one lies on a dynamic direction.
    shadows = (sral.shadow_weight.detach() / (2 * sral.alpha)).numpy().reshape(-1, 32)
    assert (shadows @ EYE[[20, 21]].T).max(1).min() > 0.9
    assert np.abs(shadows @ EYE[:4].T).max() < 0.2


def test_attention_suppresses_dynamic_features() -> None:
    sral = SRAL(4, 32, num_shadows=2)
    sral.init_semantic(torch.from_numpy(_blobs([0, 1, 2, 3], 200, 0)), torch.from_numpy(_blobs([20], 200, 1)))
    x = torch.from_numpy(EYE[[0, 2, 20, 20]]).T.reshape(1, 32, 2, 2)
    att = sral.attention(x)
    assert att.shape == (1, 1, 2, 2) and att.min() >= 0 and att.max() <= 1
    assert att[0, 0, 0].min() > 0.9 and att[0, 0, 1].max() < 0.1
    # The dynamic locations barely count: SRAL is much closer than NetVLAD to a mask that drops them.
    net = NetVLAD(4, 32)
    net.load_state_dict({k: v for k, v in sral.state_dict().items() if not k.startswith("shadow")})
    drop = torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]]])
    assert (sral(x) * sral(x, drop)).sum() > 0.95 and (net(x) * net(x, drop)).sum() < 0.6


def test_no_dynamic_features_starts_as_netvlad() -> None:
    static = torch.from_numpy(_blobs([0, 1, 2, 3], 200, 0))
    sral = SRAL(4, 32, num_shadows=3)
    counts = sral.init_semantic(static, None)
    assert counts["dynamic_features"] == 0 and counts["shadow_candidates"] == 0
    net = NetVLAD(4, 32)
    net.load_state_dict({k: v for k, v in sral.state_dict().items() if not k.startswith("shadow")})
    x = static[:20].T.reshape(1, 32, 4, 5)
    assert sral.attention(x).min() > 0.99
    torch.testing.assert_close(sral(x), net(x), rtol=1e-4, atol=1e-4)


def test_gradients_reach_all_parameters_and_attention_range() -> None:
    torch.manual_seed(0)
    sral = SRAL(6, 16, num_shadows=3)
    sral.set_centroids(F.normalize(torch.randn(6, 16), dim=1), alpha=2.0)
    sral.set_shadows(F.normalize(torch.randn(6, 3, 16), dim=2), alpha=2.0)
    x = torch.randn(2, 16, 3, 4)
    mask = torch.rand(2, 1, 3, 4)
    (sral(x, mask) * torch.randn(2, 96)).sum().backward()
    names = {n for n, _ in sral.named_parameters()}
    assert names == {"centroids", "conv.weight", "conv.bias", "shadow_weight", "shadow_bias"}
    for name, p in sral.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    att = sral.attention(x)
    assert att.shape == (2, 1, 3, 4) and att.min() >= 0 and att.max() <= 1 and att.min() < 0.99
    torch.testing.assert_close(sral(x, torch.ones(2, 1, 3, 4)), sral(x), rtol=0, atol=0)
