"""SRAL: semantic-reinforced attention on NetVLAD (SRALNet, Peng et al. ICRA'21; TCSVT'23 re-implementation).

There is no official code; this is the formulation we implement. Each of K clusters has a representative
centroid c_k and S shadow centroids s_kj. With the NetVLAD logit l_k(x) = 2α x·c_k − α‖c_k‖² (1×1 conv)
and shadow logits l_kj(x) = 2α x·s_kj − α‖s_kj‖² (a second conv, same α at init):

    a_k(x) = softmax_k l_k(x)                                   (NetVLAD assignment over representatives)
    β_k(x) = exp l_k / (exp l_k + Σ_j exp l_kj) = σ(l_k − logsumexp_j l_kj)   (softmax within the cluster,
                                                                               read at the representative)
    V(:,k) = Σ_i m_i · a_k(x_i) · β_k(x_i) · (x_i − c_k),  then intra-normalisation and L2.

A feature close to a shadow (e.g. a car) keeps its cluster assignment a_k but gets a small β_k, so it
barely contributes; attention(x) = Σ_k a_k β_k ∈ [0,1]. With S = 0, β ≡ 1 and SRAL is NetVLAD exactly.
Semantic-constrained init: k-means on static-class features → representatives (+ NetVLAD's α, and
the clusters' raw means as residual centroids, as NetVLAD); k-means
on dynamic-class features → min(K·S, N_dynamic) shadow candidates; each cluster takes the S candidates
nearest its representative. Without enough dynamic features (fewer than S) the shadows start "far":
s_kj = −4·c_k, outside the unit sphere, so l_kj ≤ −8α < −3α ≤ l_k for unit features; β ≈ 1 and SRAL
starts as NetVLAD (the shadows stay learnable, but learn slowly from there since ∂β ∝ β(1 − β)).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.precision import fp32
from semvpr.models.aggregators.netvlad import (
    MAX_KMEANS_FEATURES,
    NetVLAD,
    alpha_from_features,
    cluster_means,
    spherical_kmeans,
    subsample,
)

FAR_SHADOW = -4.0  # shadow = −4·c_k when there are no dynamic features: never wins against the representative
MIN_STATIC_PER_CLUSTER = 10  # static k-means sample the semantic init needs at the least, per cluster


class SRAL(NetVLAD):
    """NetVLAD with per-cluster shadow centroids that down-weight features near dynamic content.

    The mask enters as in NetVLAD (it scales each location's assignment mass); initialised from a
    sample of local features labelled static / dynamic by the teacher's pseudo-labels.
    """

    init_sample = "labelled"
    untrained_form = "semantic k-means of a training set's local features, labelled by the teacher"

    def __init__(self, num_clusters: int = 64, dim: int = 512, num_shadows: int = 4) -> None:
        super().__init__(num_clusters, dim)
        self.num_shadows = num_shadows
        self.shadow_weight = nn.Parameter(torch.empty(num_clusters, num_shadows, dim))
        self.shadow_bias = nn.Parameter(torch.empty(num_clusters, num_shadows))
        self.set_shadows(FAR_SHADOW * self.centroids.detach()[:, None].expand(-1, num_shadows, -1), float(self.alpha))

    @property
    def init_min_static(self) -> int:
        """At least ``MIN_STATIC_PER_CLUSTER`` static sample locations per representative."""
        return MIN_STATIC_PER_CLUSTER * self.num_clusters

    @torch.no_grad()
    def set_shadows(self, shadows: Tensor, alpha: float) -> None:
        """Set shadow logits from (K,S,D) shadow centroids: w = 2α·s, b = −α‖s‖²."""
        s = shadows.to(self.shadow_weight.device, torch.float32)
        self.shadow_weight.copy_(2.0 * alpha * s)
        self.shadow_bias.copy_(-alpha * (s**2).sum(-1))

    def _beta(self, x: Tensor, logits: Tensor) -> Tensor:
        """Intra-cluster weight β (B,K,h,w) of normalised features given representative logits."""
        b, _, h, w = x.shape
        k, s = self.num_clusters, self.num_shadows
        # All K·S shadows as one 1×1 conv, so there is no loop over clusters.
        shadow = F.conv2d(x, self.shadow_weight.reshape(k * s, -1, 1, 1), self.shadow_bias.reshape(-1))
        return torch.sigmoid(logits - torch.logsumexp(shadow.view(b, k, s, h, w), dim=2))

    def _weights(self, x: Tensor) -> Tensor:
        logits = self.conv(x)
        assign = F.softmax(logits, dim=1)
        if self.num_shadows == 0:
            return assign  # bit-identical to NetVLAD
        return assign * self._beta(x, logits)

    def attention(self, x: Tensor) -> Tensor:
        """Σ_k a_k β_k per location, (B,1,h,w) in [0,1]."""
        with fp32(x.device.type):
            return self._weights(self._prepare(x)).sum(1, keepdim=True).clamp(0.0, 1.0)

    def init_from_sample(self, feats: Tensor, static: Tensor | None, seed: int) -> dict[str, float | int | str]:
        """Semantic-constrained init: ``static`` (N,) marks the static locations of ``feats``."""
        assert static is not None, "SRAL's init needs the sample's static labels"
        counts = self.init_semantic(feats[static], feats[~static], seed=seed)
        return {"init": "semantic", **{k: (float(v) if isinstance(v, float) else v) for k, v in counts.items()}}

    def init_from_features(self, feats: Tensor | np.ndarray, seed: int = 0, niter: int = 50) -> float:
        """Representatives from unlabelled features; shadows at the antipodes (no semantics available)."""
        return float(self.init_semantic(feats, None, seed, niter)["alpha"])

    def init_semantic(
        self,
        static_feats: Tensor | np.ndarray,
        dynamic_feats: Tensor | np.ndarray | None,
        seed: int = 0,
        niter: int = 50,
    ) -> dict[str, float]:
        """Semantic-constrained init from (N_s,D) static and (N_d,D) dynamic local features; returns counts used."""
        static = subsample(self._features(static_feats), MAX_KMEANS_FEATURES, seed)
        reps = spherical_kmeans(static, self.num_clusters, seed, niter)
        alpha = alpha_from_features(static, reps)
        self.set_centroids(torch.from_numpy(reps), alpha, torch.from_numpy(cluster_means(static, reps)))
        num_dynamic = 0 if dynamic_feats is None else len(dynamic_feats)
        num_candidates = 0
        if self.num_shadows and num_dynamic >= self.num_shadows:
            dynamic = subsample(self._features(dynamic_feats), MAX_KMEANS_FEATURES, seed)
            num_candidates = min(self.num_clusters * self.num_shadows, len(dynamic))
            cands = spherical_kmeans(dynamic, num_candidates, seed + 1, niter)
            nearest = np.argsort(-(reps @ cands.T), axis=1, kind="stable")[:, : self.num_shadows]
            shadows = torch.from_numpy(cands[nearest])  # (K,S,D); candidates may be shared between clusters
        else:
            shadows = FAR_SHADOW * torch.from_numpy(reps)[:, None].expand(-1, self.num_shadows, -1)
        self.set_shadows(shadows, alpha)
        return {
            "static_features": len(static),
            "dynamic_features": num_dynamic,
            "shadow_candidates": num_candidates,
            "alpha": alpha,
        }
