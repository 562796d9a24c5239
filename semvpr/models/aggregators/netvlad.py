"""NetVLAD aggregation (Arandjelović et al., CVPR'16) and its k-means/α initialisation.

Soft-assignment is a 1×1 conv initialised as w_k = 2α·ĉ_k, b_k = −α‖ĉ_k‖², i.e. a softmax over
−α‖x − ĉ_k‖² (the paper's form, Relja's addLayers.m "vladv2"), from the unit-norm k-means centroids
ĉ_k, with α = −log(0.01) / mean gap of the two best logits (set on them too). Because ĉ_k has unit
norm, the bias is the same −α for every k and cancels in the softmax: this is pytorch-NetVlad's
"vladv1" assignment (weights α₁·ĉ_k, no bias) with its α₁ = 2α. The residuals x − c_k use the raw
means c_k of the clustered unit features (norm < 1), as addLayers.m, pytorch-NetVlad and the VPR
benchmark. Conv and residual centroids are separate learnable parameters.
A mask m (B,1,h,w) weights each location's contribution: V(:,k) = Σ_i m_i·a_k(x_i)·(x_i − c_k).
The aggregation always runs in fp32 (autocast off): α is in the thousands at init, so bf16 logits
would flip assignments.
"""

from __future__ import annotations

import math

import faiss
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.core.precision import fp32
from semvpr.models.aggregators.base import Aggregator, check_weights

MAX_KMEANS_FEATURES = 50_000  # NetVLAD's recipe: cluster a 50k random sample of training local features


def l2_normalise_np(feats: Tensor | np.ndarray) -> np.ndarray:
    """(N,D) features as a contiguous float32 array with unit rows."""
    arr = feats.detach().float().cpu().numpy() if isinstance(feats, Tensor) else np.asarray(feats, np.float32)
    arr = np.ascontiguousarray(arr, dtype=np.float32).copy()
    faiss.normalize_L2(arr)
    return arr


def subsample(feats: np.ndarray, limit: int, seed: int) -> np.ndarray:
    """At most ``limit`` rows, drawn without replacement with a seeded generator."""
    if len(feats) <= limit:
        return feats
    idx = np.random.default_rng(seed).choice(len(feats), limit, replace=False)
    return feats[np.sort(idx)]


def spherical_kmeans(feats: np.ndarray, k: int, seed: int, niter: int = 50) -> np.ndarray:
    """(k,D) unit centroids of unit-norm float32 ``feats`` with seeded faiss k-means."""
    if len(feats) < k:
        raise SemvprError(
            f"k-means needs at least {k} local features for {k} clusters, got {len(feats)}; "
            "use more cluster-init images or fewer clusters"
        )
    # Use every (already subsampled) point and silence faiss' "too few points" warning on tiny sets.
    km = faiss.Kmeans(
        feats.shape[1],
        k,
        niter=niter,
        seed=seed,
        spherical=True,
        verbose=False,
        max_points_per_centroid=1 << 30,
        min_points_per_centroid=1,
    )
    km.train(feats, init_centroids=kmeans_pp_seeds(feats, k, seed))
    return km.centroids.copy()


def kmeans_pp_seeds(feats: np.ndarray, k: int, seed: int) -> np.ndarray:
    """k-means++ seeding (D² sampling); faiss' random seeding merged separated clusters in ~40 % of seeds."""
    rng = np.random.default_rng(seed)
    sq = (feats.astype(np.float64) ** 2).sum(1)
    chosen = [int(rng.integers(len(feats)))]
    dist = np.full(len(feats), np.inf)
    for _ in range(k):
        c = feats[chosen[-1]]
        dist = np.minimum(dist, np.maximum(sq + sq[chosen[-1]] - 2.0 * (feats @ c), 0.0))
        if len(chosen) == k:
            break
        total = dist.sum()
        chosen.append(int(rng.choice(len(feats), p=dist / total)) if total > 0 else int(rng.integers(len(feats))))
    return np.ascontiguousarray(feats[chosen], dtype=np.float32)


def cluster_means(feats: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """(k,D) raw means of the features nearest (largest dot product) to each unit centroid; a cluster
    without members keeps its centroid."""
    nearest = np.argmax(feats @ centroids.T, axis=1)
    counts = np.bincount(nearest, minlength=len(centroids)).astype(np.float64)
    sums = np.zeros(centroids.shape, np.float64)
    np.add.at(sums, nearest, feats.astype(np.float64))
    means = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1.0)[:, None], centroids)
    return means.astype(np.float32)


def alpha_from_features(feats: np.ndarray, centroids: np.ndarray) -> float:
    """α = −log(0.01) / mean gap between the best and second-best assignment logit (2x·c − ‖c‖²)."""
    # The gap is taken on the logit the conv computes (= the squared-distance gap; 2× the dot gap for unit
    # centroids), so at init the nearest centroid gets on average 100× the weight of the second nearest.
    logits = 2.0 * feats @ centroids.T - (centroids**2).sum(1)[None]
    top2 = -np.sort(-logits, axis=1)[:, :2]
    gap = float(np.mean(top2[:, 0] - top2[:, 1]))
    if not gap > 0:
        raise SemvprError("cannot set NetVLAD α: all local features are equidistant to their two nearest centroids")
    return -math.log(0.01) / gap


def vlad_aggregate(x: Tensor, weights: Tensor, centroids: Tensor) -> Tensor:
    """Intra- and L2-normalised Σ_i w_ik·(x_i − c_k) for x (B,D,h,w), weights (B,K,h,w), centroids (K,D)."""
    b, d = x.shape[:2]
    xf = x.reshape(b, d, -1)
    wf = weights.reshape(b, weights.shape[1], -1)
    vlad = torch.bmm(wf, xf.transpose(1, 2)) - wf.sum(-1, keepdim=True) * centroids[None]
    vlad = F.normalize(vlad, dim=2)
    return F.normalize(vlad.flatten(1), dim=1)


class NetVLAD(Aggregator):
    """NetVLAD layer: (B,D,h,w) local features [+ mask] → (B,K·D) L2-normalised descriptor.

    The mask scales each location's soft-assignment mass (features are never zeroed); initialised by
    k-means on a sample of training local features.
    """

    init_sample = "features"
    untrained_form = "k-means centroids of a training set's local features"

    def __init__(self, num_clusters: int = 64, dim: int = 512) -> None:
        super().__init__()
        self.num_clusters, self.dim = num_clusters, dim
        self.centroids = nn.Parameter(torch.empty(num_clusters, dim))
        self.conv = nn.Conv2d(dim, num_clusters, kernel_size=1, bias=True)
        self.register_buffer("alpha", torch.tensor(0.0))
        # Random unit centroids until init_from_features; α=1 keeps the softmax soft and untrained-safe.
        gen = torch.Generator().manual_seed(0)
        self.set_centroids(F.normalize(torch.randn(num_clusters, dim, generator=gen), dim=1), alpha=1.0)

    @property
    def output_dim(self) -> int:
        """Descriptor length K·D."""
        return self.num_clusters * self.dim

    @torch.no_grad()
    def set_centroids(self, centroids: Tensor, alpha: float, residual: Tensor | None = None) -> None:
        """Set the assignment conv to w = 2α·c, b = −α‖c‖² and the residual centroids to ``residual``
        (default: ``centroids``)."""
        c = centroids.to(self.centroids.device, torch.float32)
        self.centroids.copy_(c if residual is None else residual.to(self.centroids.device, torch.float32))
        self.conv.weight.copy_((2.0 * alpha * c)[:, :, None, None])
        self.conv.bias.copy_(-alpha * (c**2).sum(1))
        self.alpha.fill_(alpha)

    def init_from_features(self, feats: Tensor | np.ndarray, seed: int = 0, niter: int = 50) -> float:
        """Spherical k-means on ≤50k L2-normalised (N,D) local features: the assignment conv and α from
        the unit centroids, the residual centroids = the clusters' raw means; returns α."""
        arr = subsample(self._features(feats), MAX_KMEANS_FEATURES, seed)
        centroids = spherical_kmeans(arr, self.num_clusters, seed, niter)
        alpha = alpha_from_features(arr, centroids)
        self.set_centroids(torch.from_numpy(centroids), alpha, torch.from_numpy(cluster_means(arr, centroids)))
        return alpha

    def init_from_sample(self, feats: Tensor, static: Tensor | None, seed: int) -> dict[str, float | int | str]:
        """k-means / α initialisation from the sampled local features (labels unused)."""
        alpha = self.init_from_features(feats, seed=seed)
        return {"init": "kmeans", "features": len(feats), "alpha": float(alpha)}

    def _features(self, feats: Tensor | np.ndarray) -> np.ndarray:
        if feats.ndim != 2 or feats.shape[1] != self.dim:
            raise ValueError(f"expected (N,{self.dim}) local features, got {tuple(feats.shape)}")
        return l2_normalise_np(feats)

    def _prepare(self, x: Tensor) -> Tensor:
        return F.normalize(x.float(), dim=1)

    def _weights(self, x: Tensor) -> Tensor:
        """Per-location, per-cluster contribution weights (B,K,h,w) of normalised features."""
        return F.softmax(self.conv(x), dim=1)

    def assignment(self, x: Tensor) -> Tensor:
        """Soft-assignment a_k(x_i), (B,K,h,w)."""
        with fp32(x.device.type):
            return F.softmax(self.conv(self._prepare(x)), dim=1)

    def forward(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """(B,D,h,w) features and optional (B,1,h,w) contribution weights → (B,K·D) descriptor."""
        mask = check_weights(x, mask)
        with fp32(x.device.type):
            x = self._prepare(x)
            weights = self._weights(x)
            if mask is not None:
                weights = weights * mask
            return vlad_aggregate(x, weights, self.centroids.float())
