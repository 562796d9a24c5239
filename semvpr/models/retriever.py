"""The retriever: backbone → (mask) → NetVLAD / SRAL aggregator → global descriptor.

One code path for every aggregator and mask (DESIGN §3): the components are built outside and injected. The
frozen backbone prefix and the mask run once per image (semvpr.features); training, mining and
evaluation work on their cached outputs through :meth:`Retriever.describe`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from semvpr.data.datamodule import ImageDataset
from semvpr.errors import SemvprError
from semvpr.features import TRUNK_DTYPE, FeatureStore, PlaceFeatures, grid_size, store_loader
from semvpr.metrics import RECALL_NS, knn, recall_result
from semvpr.models.masks import ClassWeights, MaskSource
from semvpr.precision import autocast



class Retriever(L.LightningModule):
    """Weakly-supervised VPR model trained with the triplet loss on mined tuples."""

    def __init__(
        self,
        backbone: nn.Module,
        aggregator: nn.Module,
        mask_source: MaskSource | None = None,
        whitening: nn.Module | None = None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        margin: float = 0.1,
        eval_batch_size: int = 64,
        num_workers: int = 0,
        record: dict | None = None,
        class_weights: ClassWeights | None = None,
        class_weights_lr: float | None = None,
    ) -> None:
        super().__init__()
        # What eval needs to rebuild the model: config choices and plain values (semvpr.checkpoint),
        # never code or _target_s; Lightning stores it in the checkpoint's "hyper_parameters".
        self.save_hyperparameters(record or {})
        self.backbone, self.aggregator, self.mask_source = backbone, aggregator, mask_source
        # Learned per-class weights turn the cached class probabilities into the mask (mask.weights=learned).
        self.class_weights, self.class_weights_lr = class_weights, class_weights_lr
        # PCA whitening is fitted on database descriptors after training and used from then on.
        self.whitening = whitening
        self.register_buffer("whitening_fitted", torch.tensor(False))
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.eval_batch_size, self.num_workers = eval_batch_size, num_workers
        self.margin = margin
        self._outputs: list[Tensor] = []
        self.last_eval: dict[str, np.ndarray] = {}

    # ----------------------------------------------------------------- descriptors
    def describe(self, trunk: Tensor, mask: Tensor | None) -> Tensor:
        """Global descriptors from frozen-trunk outputs and grid masks."""
        # float(): trunk features are stored in bf16; autocast (where native) takes them back down.
        local = self.backbone.forward_trainable(trunk.float().contiguous(memory_format=torch.channels_last))
        if self.class_weights is not None and mask is not None:
            mask = self.class_weights(mask)
        desc = self.aggregator(local, mask)
        if self.whitening is not None and bool(self.whitening_fitted):
            desc = self.whitening(desc)
        return desc

    def describe_batch(self, batch: dict[str, Tensor]) -> Tensor:
        """Descriptors of a feature-store batch: cached trunk rows, or images through the frozen prefix."""
        if "image" in batch:
            with torch.no_grad():
                trunk = self.backbone.forward_frozen(batch["image"].contiguous(memory_format=torch.channels_last),
                                                     keep_scales=False)[-1]
                trunk = trunk.to(TRUNK_DTYPE)
        else:
            trunk = batch["trunk"]
        return self.describe(trunk, _mask_or_none(batch["mask"], self.device))

    def fit_whitening(self, db: FeatureStore) -> None:
        """Fit the PCA-whitening layer on (unwhitened) database descriptors."""
        assert self.whitening is not None
        self.whitening_fitted.fill_(False)
        self.whitening.fit(self.describe_store(db))
        self.whitening_fitted.fill_(True)

    def forward(self, images: Tensor, label_paths: Sequence[Path] | None = None) -> Tensor:
        """Full pipeline on [0,1] images (the oracle mask also needs their label maps), in chunks of
        images whose frozen-prefix activations fit ``FORWARD_BYTES`` (memory does not grow with the batch)."""
        keep = self.mask_source is not None and self.mask_source.needs_features
        step = self.backbone.images_per_forward(images.shape[-2:], keep_scales=keep)
        if len(images) > step:
            return torch.cat([self(images[i:i + step], None if label_paths is None else label_paths[i:i + step])
                              for i in range(0, len(images), step)])
        outs = self.backbone.forward_frozen(images.contiguous(memory_format=torch.channels_last), keep_scales=keep)
        mask = None
        if self.mask_source is not None:
            grid = grid_size(self.backbone, images.shape[-2:])
            mask = self.mask_source.grid_mask(images, outs, label_paths, grid, self.weighting)
        return self.describe(outs[-1].to(TRUNK_DTYPE), mask)

    @torch.no_grad()
    def describe_images(self, paths: Sequence[Path], labels: Sequence[Path] | None, image_size: Sequence[int],
                        out: np.ndarray, desc: str = "descriptors") -> None:
        """Descriptors of image files in one pass (decoding in workers), written into ``out`` (N,D)."""
        self.eval()
        loader = DataLoader(ImageDataset(list(paths), tuple(image_size)), batch_size=self.eval_batch_size,
                            num_workers=self.num_workers, pin_memory=self.device.type == "cuda")
        with autocast(self.device):
            for images, index in tqdm(loader, desc=desc, unit="batch", leave=False, disable=None):
                batch_labels = [labels[i] for i in index] if labels is not None else None
                rows = slice(int(index[0]), int(index[-1]) + 1)
                out[rows] = self(images.to(self.device), batch_labels).float().cpu().numpy()

    @torch.no_grad()
    def describe_store(self, store: FeatureStore, index: Sequence[int] | None = None) -> np.ndarray:
        """Descriptors of a feature store (or of its rows ``index``), eval mode, as float32 numpy."""
        was_training = self.training
        self.eval()
        out = []
        with autocast(self.device):
            for batch in store_loader(store, self.eval_batch_size, self.num_workers, index):
                batch = {k: v.to(self.device) for k, v in batch.items()}
                out.append(self.describe_batch(batch).float().cpu())
        self.train(was_training)
        return torch.cat(out).numpy()

    # ------------------------------------------------------------------- training
    def training_step(self, batch: dict[str, Tensor] | None, batch_idx: int) -> Tensor | None:
        if batch is None:
            return None  # no query of this batch had a violating negative (pytorch-NetVlad skips it too)
        loss = triplet_loss(self.describe_batch(batch), batch["tuples"], self.margin)
        b = len(batch["tuples"])
        if not torch.isfinite(loss):
            raise SemvprError(
                f"training loss became {loss.item()} at epoch {self.current_epoch} step "
                f"{self.global_step}; the last good checkpoint is left as it was (lower model.optimizer.lr?)")
        self.log("train/loss", loss, prog_bar=True, batch_size=b)
        return loss

    @property
    def weighting(self) -> str:
        """How the mask source's class probabilities become the mask: binary or learned."""
        return "binary" if self.class_weights is None else "learned"

    def configure_optimizers(self) -> Any:
        if self.optimizer_factory is None:
            raise SemvprError("the retriever was built without an optimizer (model.optimizer)")
        own = {id(p) for p in self.class_weights.parameters()} if self.class_weights is not None else set()
        groups: list[dict[str, Any]] = [{"params": [p for p in self.parameters() if p.requires_grad and id(p) not in own]}]
        if own:
            # A few logits that must travel several units: their own learning rate.
            groups.append({"params": list(self.class_weights.parameters()), "lr": self.class_weights_lr,
                           "weight_decay": 0.0})
        optimizer = self.optimizer_factory(groups)
        if self.scheduler_factory is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": self.scheduler_factory(optimizer)}

    # ----------------------------------------------------------------- evaluation
    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._outputs.append(self.describe_batch(batch).float().cpu())

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
        result = evaluate(desc[:n_db], desc[n_db:], features.places.positives())
        for n, value in result["recalls"].items():
            self.log(f"{stage}/R@{n}", value, prog_bar=n in (1, 5))
        if result["num_without_positives"]:
            for n, value in result["recalls_pos"].items():
                self.log(f"{stage}/R@{n}_pos", value)
        self.last_eval = result


def evaluate(db_desc: np.ndarray, q_desc: np.ndarray, positives: Sequence[np.ndarray],
             max_n: int = 20) -> dict[str, Any]:
    """Top-k retrieval and Recall@1..max_n in percent: of all queries (``recalls``, ``curve``, as
    pytorch-NetVlad and the benchmark) and of queries with a positive (``recalls_pos``, as MSLS)."""
    k = min(max_n, len(db_desc))
    predictions = knn(db_desc, q_desc, k)
    result = recall_result(predictions, positives, ns=tuple(range(1, k + 1)))
    # A database smaller than N is retrieved whole: Recall@N = Recall@len(db).
    curve = {n: result.recalls[min(n, k)] for n in range(1, max_n + 1)}
    return {"predictions": predictions, "curve": curve,
            "recalls": {n: curve[n] for n in RECALL_NS},
            "recalls_pos": {n: result.recalls_pos[min(n, k)] for n in RECALL_NS},
            "num_without_positives": result.num_without_positives}


def triplet_loss(desc: Tensor, tuples: Tensor, margin: float, eps: float = 1e-6) -> Tensor:
    """NetVLAD's loss: max(0, d(q,p) − d(q,n) + sqrt(margin)) on L2 distances (as
    ``nn.TripletMarginLoss``), averaged over every (query, negative) pair of the batch, as
    pytorch-NetVlad divides by the number of negatives. ``tuples`` (T, 2+N) holds each tuple's rows
    of ``desc``: query, positive, negatives, -1 padded.

    Every row is gathered once: a query repeated per negative would make the backward pass
    accumulate into one row from several threads, whose order (and last bits) vary run to run.
    """
    q, p = desc[tuples[:, 0]], desc[tuples[:, 1]]
    valid = tuples[:, 2:] >= 0
    negatives = desc.new_zeros(*valid.shape, desc.shape[1])
    negatives[valid] = desc[tuples[:, 2:][valid]]
    d_pos = (q - p + eps).norm(dim=1)
    d_neg = (q[:, None] - negatives + eps).norm(dim=2)
    pairs = torch.relu(d_pos[:, None] - d_neg + margin**0.5)
    return pairs[valid].sum() / valid.sum()


def _mask_or_none(mask: Tensor, device: torch.device) -> Tensor | None:
    return mask.to(device) if mask.numel() else None
