"""The retriever: backbone → (mask) → NetVLAD / SRAL aggregator → global descriptor.

One code path for every filter (DESIGN §3): the components are built outside and injected. The
frozen backbone prefix and the mask run once per image (semvpr.features); training, mining and
evaluation work on their cached outputs through :meth:`Retriever.describe`.
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader

from semvpr.errors import SemvprError
from semvpr.features import FeatureStore, PlaceFeatures, autocast_context, grid_size
from semvpr.metrics import knn, recall_result
from semvpr.mining import StoreDataset
from semvpr.models.masks import pool_to_grid

RECALL_NS = (1, 5, 10, 20)


class Retriever(L.LightningModule):
    """Weakly-supervised VPR model trained with the triplet loss on mined tuples."""

    def __init__(
        self,
        backbone: nn.Module,
        aggregator: nn.Module,
        mask_source: nn.Module | None = None,
        whitening: nn.Module | None = None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        margin: float = 0.1,
        eval_batch_size: int = 64,
        config: dict | None = None,
    ) -> None:
        super().__init__()
        # The resolved run config travels in the checkpoint so eval can rebuild the components.
        self.save_hyperparameters({"config": config})
        self.backbone, self.aggregator, self.mask_source = backbone, aggregator, mask_source
        # PCA whitening is fitted on database descriptors after training and used from then on.
        self.whitening = whitening
        self.register_buffer("whitening_fitted", torch.tensor(False))
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.eval_batch_size = eval_batch_size
        # NetVLAD's loss: L2 distances, margin sqrt(m), summed over negatives, mean over queries.
        self.loss_fn = nn.TripletMarginLoss(margin=margin**0.5, p=2, reduction="none")
        self._outputs: list[Tensor] = []
        self.last_eval: dict[str, np.ndarray] = {}

    # ----------------------------------------------------------------- descriptors
    def describe(self, trunk: Tensor, mask: Tensor | None) -> Tensor:
        """Global descriptors from cached frozen-trunk outputs and grid masks."""
        local = self.backbone.forward_trainable(trunk.contiguous(memory_format=torch.channels_last))
        desc = self.aggregator(local, mask)
        if self.whitening is not None and bool(self.whitening_fitted):
            desc = self.whitening(desc)
        return desc

    def fit_whitening(self, db: FeatureStore) -> None:
        """Fit the PCA-whitening layer on (unwhitened) database descriptors."""
        assert self.whitening is not None
        self.whitening_fitted.fill_(False)
        self.whitening.fit(self.describe_store(db))
        self.whitening_fitted.fill_(True)

    def forward(self, images: Tensor) -> Tensor:
        """Full pipeline on [0,1] images (no labels, so not for the oracle mask)."""
        outs = self.backbone.forward_frozen(images)
        mask = None
        if self.mask_source is not None:
            grid = grid_size(self.backbone, images.shape[-2:])
            mask = pool_to_grid(self.mask_source(images, outs, None), grid)
        return self.describe(outs[-1], mask)

    @torch.no_grad()
    def describe_store(self, store: FeatureStore) -> np.ndarray:
        """Descriptors of a whole feature store (eval mode, bf16 autocast), float32 numpy."""
        was_training = self.training
        self.eval()
        loader = DataLoader(StoreDataset(store), batch_size=self.eval_batch_size)
        out = []
        with autocast_context(self.device):
            for trunk, mask in loader:
                out.append(self.describe(trunk.to(self.device), _mask_or_none(mask, self.device)).float())
        self.train(was_training)
        return torch.cat(out).cpu().numpy()

    # ------------------------------------------------------------------- training
    def training_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> Tensor:
        trunk, mask = batch
        b, t = trunk.shape[:2]
        desc = self.describe(trunk.flatten(0, 1), _mask_or_none(mask.flatten(0, 1) if mask.numel() else mask, self.device))
        desc = desc.view(b, t, -1)
        q, p, n = desc[:, :1], desc[:, 1:2], desc[:, 2:]
        loss = self.loss_fn(q.expand_as(n).flatten(0, 1), p.expand_as(n).flatten(0, 1), n.flatten(0, 1))
        loss = loss.view(b, -1).mean(dim=1).mean()
        if not torch.isfinite(loss):
            raise SemvprError(
                f"training loss became {loss.item()} at epoch {self.current_epoch} step "
                f"{self.global_step}; the last good checkpoint is left as it was (lower model.optimizer.lr?)")
        self.log("train/loss", loss, prog_bar=True, batch_size=b)
        return loss

    def configure_optimizers(self) -> Any:
        if self.optimizer_factory is None:
            raise SemvprError("the retriever was built without an optimizer (model.optimizer)")
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = self.optimizer_factory(params)
        if self.scheduler_factory is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": self.scheduler_factory(optimizer)}

    # ----------------------------------------------------------------- evaluation
    def validation_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> None:
        self._outputs.append(self.describe(batch[0], _mask_or_none(batch[1], self.device)).float().cpu())

    test_step = validation_step

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val", self.trainer.datamodule.val)

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test", self.trainer.datamodule.test)

    def _eval_epoch_end(self, stage: str, features: PlaceFeatures) -> None:
        desc = torch.cat(self._outputs).numpy()
        self._outputs.clear()
        n_db = len(features.db)
        if len(desc) != n_db + len(features.q):
            # fast_dev_run / limit_*_batches saw part of the set; recall needs all of it.
            desc = np.concatenate([self.describe_store(features.db), self.describe_store(features.q)])
        result = evaluate(desc[:n_db], desc[n_db:], features.places.positives(25.0))
        for n, value in result["recalls"].items():
            self.log(f"{stage}/R@{n}", value, prog_bar=n in (1, 5))
        self.last_eval = result


def evaluate(db_desc: np.ndarray, q_desc: np.ndarray, positives: Sequence[np.ndarray],
             max_n: int = 20) -> dict[str, Any]:
    """Top-k retrieval and Recall@1..max_n (percent) of queries with at least one positive."""
    k = min(max_n, len(db_desc))
    predictions = knn(db_desc, q_desc, k)
    result = recall_result(predictions, positives, ns=tuple(range(1, k + 1)))
    # A database smaller than N is retrieved whole: Recall@N = Recall@len(db).
    curve = {n: result.recalls[min(n, k)] for n in range(1, max_n + 1)}
    return {"predictions": predictions, "curve": curve,
            "recalls": {n: curve[n] for n in RECALL_NS},
            "num_without_positives": result.num_without_positives}


def _mask_or_none(mask: Tensor, device: torch.device) -> Tensor | None:
    return mask.to(device) if mask.numel() else None
