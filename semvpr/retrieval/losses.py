"""Training losses of the retriever."""

from __future__ import annotations

import torch
from torch import Tensor


def triplet_loss(desc: Tensor, tuples: Tensor, margin: float, pairs: float | None = None, eps: float = 1e-6) -> Tensor:
    """NetVLAD's loss: max(0, d(q,p) − d(q,n) + sqrt(margin)) on L2 distances (as
    ``nn.TripletMarginLoss``), summed over every (query, negative) pair of the batch and divided by
    ``pairs`` (default: their number, the mean, as pytorch-NetVlad divides by the number of
    negatives). ``tuples`` (T, 2+N) holds each tuple's rows of ``desc``: query, positive,
    negatives, -1 padded.

    Every row is gathered once: a query repeated per negative would make the backward pass
    accumulate into one row from several threads, whose order (and last bits) vary run to run.
    """
    q, p = desc[tuples[:, 0]], desc[tuples[:, 1]]
    valid = tuples[:, 2:] >= 0
    negatives = desc.new_zeros(*valid.shape, desc.shape[1])
    negatives[valid] = desc[tuples[:, 2:][valid]]
    d_pos = (q - p + eps).norm(dim=1)
    d_neg = (q[:, None] - negatives + eps).norm(dim=2)
    losses = torch.relu(d_pos[:, None] - d_neg + margin**0.5)[valid]
    return losses.sum() / (valid.sum() if pairs is None else pairs)
