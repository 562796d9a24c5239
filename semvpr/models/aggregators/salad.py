"""SALAD: Sinkhorn Algorithm for Locally Aggregated Descriptors (Izquierdo & Civera, CVPR 2024),
with a per-location mask.

Each of the n locations x_i gets a local feature f_i = MLP_f(x_i) ∈ R^l and scores S_ki =
MLP_s(x_i)_k for m clusters. A dustbin row (one learnable score z for every location) is appended
and the (m+1)×n matrix is made a transport plan by ``iters`` log-domain Sinkhorn iterations between
the cluster masses a = (1, …, 1, n − m) / (m + n) and the location masses b = (1, …, 1) / (m + n)
(SuperGlue's formulation, as the authors). The plan times (m + n) gives P; the dustbin row is dropped:

    V(:,k) = Σ_i P_ki f_i   (intra-normalised),   descriptor = L2[ L2(g) , V flattened ],

with g = MLP_g(t) the global scene token. ``global_token`` says what t is: ``mean``, the mask-weighted
mean of the local features, t = Σ_i w_i x_i / Σ_i w_i (for a trunk without a class token), or ``class``, the
authors' t: a ViT's class token, which the backbone gives after the ``dim`` patch channels of its local
features, the same at every location (``DINOv2Backbone(class_token=True)``). The class token has attended
to every patch in the trunk, so a mask does not reach it.

Mask: the weight scales each location's mass, b_i = w_i / (m + n) (log b_i = log w_i − log(m + n));
the dustbin's mass is unchanged. The iterations start from the column masses (v = log w, u = 0; the
authors' u = v = 0 when w ≡ 1), so a location of weight 0 takes no part in any normalisation, from
the first row update on, and receives no transport.
The cluster MLPs use dropout (0.3 as the authors) in training only.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError
from semvpr.core.precision import fp32
from semvpr.models.aggregators.base import Aggregator, check_weights, log_weights

#: What the global scene token is made of: the masked mean feature, or the trunk's class token.
GLOBAL_TOKENS = ("mean", "class")


def log_sinkhorn(scores: Tensor, log_a: Tensor, log_b: Tensor, iters: int) -> Tensor:
    """log of the transport plan of (B,M,N) scores between row masses exp(log_a) (B,M) and column
    masses exp(log_b) (B,N), after ``iters`` alternating row/column normalisations in log space.

    u starts at 0 and v at the log column masses relative to the largest, log_b − max log_b: 0 where
    all column masses are equal (u = v = 0, the authors' start, bit for bit), and a column of mass 0
    is out of the first row normalisation already (exp(v) = 0), so it has no influence on the plan.
    A constant added to v's start moves through u and back and leaves the plan unchanged."""
    u = torch.zeros_like(log_a)
    v = log_b - log_b.amax(dim=1, keepdim=True)
    for _ in range(iters):
        u = log_a - torch.logsumexp(scores + v[:, None, :], dim=2)
        v = log_b - torch.logsumexp(scores + u[:, :, None], dim=1)
    return scores + u[:, :, None] + v[:, None, :]


def _mlp(conv: bool, dim: int, hidden: int, out: int, dropout: float) -> nn.Sequential:
    layer = (lambda i, o: nn.Conv2d(i, o, 1)) if conv else nn.Linear
    drop = [nn.Dropout(dropout)] if dropout > 0 else []
    return nn.Sequential(layer(dim, hidden), *drop, nn.ReLU(), layer(hidden, out))


class SALAD(Aggregator):
    """SALAD: (B,D,h,w) [+ mask] → (B, token_dim + num_clusters·cluster_dim) L2-normalised."""

    def __init__(
        self,
        dim: int,
        num_clusters: int = 32,
        cluster_dim: int = 64,
        token_dim: int = 256,
        dropout: float = 0.3,
        iters: int = 3,
        hidden_dim: int = 512,
        global_token: str = "mean",
    ) -> None:
        """``hidden_dim``: width of the three MLPs (the authors' 512, for DINOv2's 768 channels);
        ``global_token``: ``mean`` or ``class`` (the module docstring)."""
        super().__init__()
        if global_token not in GLOBAL_TOKENS:
            raise SemvprError(f"aggregator.global_token={global_token!r} is not one of {list(GLOBAL_TOKENS)}")
        self.dim, self.global_token = dim, global_token
        self.num_clusters, self.cluster_dim, self.token_dim, self.iters = num_clusters, cluster_dim, token_dim, iters
        self.token_features = _mlp(False, dim, hidden_dim, token_dim, 0.0)
        self.cluster_features = _mlp(True, dim, hidden_dim, cluster_dim, dropout)
        self.score = _mlp(True, dim, hidden_dim, num_clusters, dropout)
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    @property
    def output_dim(self) -> int:
        """Descriptor length token_dim + num_clusters · cluster_dim."""
        return self.token_dim + self.num_clusters * self.cluster_dim

    def assignment(self, scores: Tensor, weights: Tensor | None) -> Tensor:
        """P (B,m,n): the Sinkhorn plan of (B,m,n) scores times (m + n), dustbin row dropped."""
        b, m, n = scores.shape
        if n <= m:
            raise SemvprError(
                f"SALAD needs more feature locations than clusters (the dustbin's mass is n − m), "
                f"got {n} locations for {m} clusters; lower aggregator.num_clusters"
            )
        norm = -math.log(m + n)
        log_a = scores.new_full((b, m + 1), norm)
        log_a[:, m] = math.log(n - m) + norm
        log_b = scores.new_full((b, n), norm)
        if weights is not None:
            log_b = log_b + log_weights(weights).flatten(1).expand(b, n)
        couplings = torch.cat([scores, self.dust_bin.float().expand(b, 1, n)], dim=1)
        return (log_sinkhorn(couplings, log_a, log_b, self.iters) - norm).exp()[:, :m]

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        """Optimal-transport aggregation in fp32 (exp of log-plans)."""
        weights = check_weights(x, weights)
        with fp32(x.device.type):
            x = x.float()
            if self.global_token == "class":
                if x.shape[1] != 2 * self.dim:
                    raise SemvprError(
                        f"SALAD with global_token=class needs the backbone's class token after its {self.dim} "
                        f"channels (backbone.class_token=true), got {x.shape[1]} channels"
                    )
                x, token = x[:, : self.dim], x[:, self.dim :, 0, 0]
            else:
                w = x.new_ones(1, 1, *x.shape[2:]) if weights is None else weights
                w = w.expand(x.shape[0], 1, *x.shape[2:])
                token = (x * w).sum(dim=(2, 3)) / w.sum(dim=(2, 3)).clamp_min(1e-12)
            f = self.cluster_features(x).flatten(2)  # (B, l, n)
            p = self.assignment(self.score(x).flatten(2), weights)  # (B, m, n)
            local = F.normalize(torch.einsum("bln,bmn->blm", f, p), dim=1).flatten(1)
            g = F.normalize(self.token_features(token), dim=1)
            return F.normalize(torch.cat([g, local], dim=1), dim=1)
