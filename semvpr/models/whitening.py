"""PCA whitening of global descriptors (NetVLAD's 4096-D reduction), fitted on database descriptors."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from semvpr.core.errors import SemvprError


class PCAWhitening(nn.Module):
    """PCA + whitening + L2, fitted on database descriptors (NetVLAD's 4096-D reduction)."""

    def __init__(self, in_dim: int, out_dim: int, eps: float = 1e-9) -> None:
        super().__init__()
        if not 1 <= out_dim <= in_dim:
            raise SemvprError(
                f"model.pca_dim={out_dim}: PCA reduces the aggregator's {in_dim}-D descriptor to at most {in_dim} "
                "dims; lower it, or model.pca_dim=null for no whitening"
            )
        self.in_dim, self.out_dim, self.eps = in_dim, out_dim, eps
        self.register_buffer("mean", torch.zeros(in_dim))
        self.register_buffer("projection", torch.eye(out_dim, in_dim))

    @torch.no_grad()
    def fit(self, db: Tensor | np.ndarray) -> PCAWhitening:
        """Fit mean and whitened top-``out_dim`` principal directions on (N,in_dim) descriptors, on the device the
        layer is on (the Gram matrix in float32, its eigendecomposition in float64)."""
        x = db.float() if isinstance(db, Tensor) else torch.from_numpy(np.array(db, dtype=np.float32))
        x = x.to(self.mean.device)
        n = x.shape[0]
        if x.ndim != 2 or x.shape[1] != self.in_dim:
            raise ValueError(f"expected (N,{self.in_dim}) descriptors, got {tuple(x.shape)}")
        if self.out_dim > min(n - 1, self.in_dim):
            raise SemvprError(
                f"PCA whitening to {self.out_dim} dims needs more than {self.out_dim} database "
                f"descriptors of at least that width, got {n}×{self.in_dim}; lower the PCA dimension"
            )
        mean = x.mean(0)
        xc = x - mean
        # Eigen-decompose the smaller Gram matrix (N×N when N < D): same spectrum, far cheaper than a D×D SVD.
        if n < self.in_dim:
            evals, evecs = torch.linalg.eigh((xc @ xc.T).double())
            evals, evecs = evals.flip(0)[: self.out_dim], evecs.flip(1)[:, : self.out_dim]
            dirs = (xc.T.double() @ evecs) / evals.clamp_min(1e-30).sqrt()  # (D,out) unit principal axes
        else:
            evals, evecs = torch.linalg.eigh((xc.T @ xc).double())
            evals, dirs = evals.flip(0)[: self.out_dim], evecs.flip(1)[:, : self.out_dim]
        scale = (evals.clamp_min(0) / (n - 1) + self.eps).rsqrt()
        self.mean.copy_(mean)
        self.projection.copy_((dirs * scale[None]).T.float())
        return self

    def forward(self, x: Tensor) -> Tensor:
        """(B,in_dim) → (B,out_dim) whitened, L2-normalised."""
        return F.normalize((x.float() - self.mean) @ self.projection.T, dim=1)
