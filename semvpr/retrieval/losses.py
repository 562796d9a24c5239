"""Training losses of the retriever, one per recipe: each says which batches it trains on (``batches``:
``tuples`` mined by semvpr.retrieval.mining, or ``places``, P places × K images by
semvpr.retrieval.places), so the builder picks the datamodule from the loss the recipe names."""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from semvpr.core.precision import fp32


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


class Loss:
    """A recipe's loss: ``loss(descriptors, batch)`` for a batch of the kind ``batches`` names."""

    batches: ClassVar[str]

    def __call__(self, desc: Tensor, batch: dict[str, Any]) -> Tensor:
        raise NotImplementedError


class TripletLoss(Loss):
    """:func:`triplet_loss` on a batch of mined tuples (``tuples``, ``pairs``: semvpr.retrieval.mining)."""

    batches = "tuples"

    def __init__(self, margin: float = 0.1) -> None:
        self.margin = float(margin)

    def __call__(self, desc: Tensor, batch: dict[str, Any]) -> Tensor:
        return triplet_loss(desc, batch["tuples"], self.margin, batch["pairs"])


class MultiSimilarity(Loss):
    """GSV-Cities' loss: pytorch-metric-learning's ``MultiSimilarityLoss`` (dot-product similarity) on the
    pairs its ``MultiSimilarityMiner`` (cosine similarity, margin ``epsilon``) mines from the batch,
    every image of a place a positive of the others and every other place's a negative (``labels``: the
    place of each row). The descriptors are L2-normalised, so both similarities are the cosine. Miner and
    loss run in float32 outside autocast: bf16 similarities (a step of 2^-7 near 1) would move exp(β·s),
    β = 50, by a factor of e^0.4 and blur the miner's ε = 0.1."""

    batches = "places"

    def __init__(self, alpha: float = 1.0, beta: float = 50.0, base: float = 0.0, epsilon: float = 0.1) -> None:
        from pytorch_metric_learning import distances, losses, miners

        self.alpha, self.beta, self.base, self.epsilon = float(alpha), float(beta), float(base), float(epsilon)
        self.loss = losses.MultiSimilarityLoss(
            alpha=self.alpha, beta=self.beta, base=self.base, distance=distances.DotProductSimilarity()
        )
        self.miner = miners.MultiSimilarityMiner(epsilon=self.epsilon, distance=distances.CosineSimilarity())

    def __call__(self, desc: Tensor, batch: dict[str, Any]) -> Tensor:
        labels = batch["labels"]
        with fp32(desc.device.type):
            desc = desc.float()
            return self.loss(desc, labels, self.miner(desc, labels))
