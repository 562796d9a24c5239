"""The retriever: backbone → (mask) → aggregator → (PCA whitening) → global descriptor, as a LightningModule.

One code path for every aggregator and mask (ARCHITECTURE §3.4): the components are built outside and injected. The
frozen backbone prefix and the mask run once per image (semvpr.retrieval.features); training, mining and
evaluation work on their cached outputs through :meth:`Retriever.describe`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader

from semvpr.core.errors import SemvprError
from semvpr.core.logs import progress
from semvpr.core.precision import autocast
from semvpr.core.threads import frozen_pass
from semvpr.data.images import ImageDataset, to_unit
from semvpr.models.masks import ClassWeights, MaskSource
from semvpr.retrieval.distributed import Describe, from_rank_zero, world
from semvpr.retrieval.features import TRUNK_DTYPE, FeatureStore, HostWrites, grid_size, store_batches
from semvpr.retrieval.losses import Loss, TripletLoss


@dataclass(frozen=True)
class Optimization:
    """How the retriever trains: optimizer and scheduler factories (Hydra partials), the learning rate of
    the learned class weights, the loss (None: the triplet loss with ``margin``), a linear warm-up over
    the first ``warmup_steps`` optimizer steps, and whether the scheduler steps per ``epoch`` or ``step``."""

    optimizer: Callable[..., torch.optim.Optimizer]
    scheduler: Callable[..., Any] | None = None
    margin: float = 0.1
    class_weights_lr: float | None = None
    loss: Loss | None = None
    warmup_steps: int = 0
    scheduler_interval: str = "epoch"
    #: Training steps between two reads of their losses (:class:`LossWatch`).
    check_loss_every_n_steps: int = 1

    @property
    def loss_fn(self) -> Loss:
        return self.loss if self.loss is not None else TripletLoss(self.margin)


class LossWatch:
    """The training losses since the last check, kept where they were computed: noting one is no wait for the
    device. :meth:`check` reads them at once, every ``every`` losses and whenever the retriever is validated or
    saved, and raises at the first that is not finite (so no checkpoint ever holds what it trained)."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.losses: list[Tensor] = []
        self.at: list[tuple[int, int]] = []  # each loss's epoch and step

    def note(self, loss: Tensor, epoch: int, step: int) -> None:
        self.losses.append(loss.detach())
        self.at.append((epoch, step))
        if len(self.losses) >= self.every:
            self.check()

    def check(self) -> None:
        if not self.losses:
            return
        values, at = torch.stack(self.losses).float().cpu(), self.at
        self.losses, self.at = [], []
        bad = torch.nonzero(~torch.isfinite(values))
        if len(bad):
            first = int(bad[0])
            epoch, step = at[first]
            raise SemvprError(
                f"training loss became {values[first].item()} at epoch {epoch} step {step}; the last good "
                "checkpoint is left as it was (lower recipe.optimizer.lr?)"
            )


class Retriever(L.LightningModule):
    """VPR model trained with its recipe's loss: the triplet loss on mined tuples, or the multi-similarity
    loss on place batches (``Optimization.loss``)."""

    def __init__(
        self,
        backbone: nn.Module,
        aggregator: nn.Module,
        mask_source: MaskSource | None = None,
        whitening: nn.Module | None = None,
        optimization: Optimization | None = None,
        eval_batch_size: int = 64,
        num_workers: int = 0,
        record: dict | None = None,
        class_weights: ClassWeights | None = None,
    ) -> None:
        super().__init__()
        # What eval needs to rebuild the model: config choices and plain values (semvpr.core.checkpoint),
        # never code or _target_s; Lightning stores it in the checkpoint's "hyper_parameters".
        self.save_hyperparameters(record or {})
        self.backbone, self.aggregator, self.mask_source = backbone, aggregator, mask_source
        # Learned per-class weights turn the cached class probabilities into the mask (mask.weights=learned).
        self.class_weights = class_weights
        # PCA whitening is fitted on database descriptors after training and used from then on.
        self.whitening = whitening
        self.register_buffer("whitening_fitted", torch.tensor(False))
        self.optimization = optimization
        self.eval_batch_size, self.num_workers = eval_batch_size, num_workers
        # What this process's fit did: optimiser steps, whether any gave a parameter a non-zero gradient, and
        # the first loss (a fit whose loss never had a gradient learned nothing: nothing_learned).
        self.steps, self.had_gradient, self.first_loss = 0, False, None
        self.loss_watch = LossWatch(optimization.check_loss_every_n_steps if optimization is not None else 1)

    # ----------------------------------------------------------------- descriptors
    @property
    def descriptor_dim(self) -> int:
        """Length of the global descriptor (after PCA whitening, if any)."""
        return self.whitening.out_dim if self.whitening is not None else self.aggregator.output_dim

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
            with torch.no_grad(), frozen_pass():
                trunk = self.backbone.forward_frozen(
                    to_unit(batch["image"]).contiguous(memory_format=torch.channels_last), keep_scales=False
                )[-1]
                trunk = trunk.to(TRUNK_DTYPE)
        else:
            trunk = batch["trunk"]
        return self.describe(trunk, _mask_or_none(batch["mask"], self.device))

    def fit_whitening(self, db: FeatureStore, describe: Describe | None = None) -> None:
        """Fit the PCA-whitening layer on (unwhitened) database descriptors; ``describe`` (default
        :meth:`describe_store`) is how they are computed, e.g. sharded across ranks. Under DDP every rank takes
        part in describing them, rank 0 alone decomposes them and the others take its fitted layer."""
        assert self.whitening is not None
        self.whitening_fitted.fill_(False)
        descriptors = (describe or self.describe_store)(db, None)
        fitted = None
        if world()[0] == 0:
            fitted = {k: v.cpu() for k, v in self.whitening.fit(descriptors).state_dict().items()}
        self.whitening.load_state_dict(from_rank_zero(fitted))
        self.whitening_fitted.fill_(True)

    def forward(self, images: Tensor, label_paths: Sequence[Path] | None = None) -> Tensor:
        """Full pipeline on [0,1] images (the oracle mask also needs their label maps), in chunks of
        images whose frozen-prefix activations fit ``forward_bytes`` (memory does not grow with the batch)."""
        keep = self.mask_source is not None and bool(self.mask_source.trunk_levels(images.shape[-2:]))
        step = self.backbone.images_per_forward(images.shape[-2:], keep_scales=keep, device=self.device)
        if len(images) > step:
            return torch.cat(
                [
                    self(images[i : i + step], None if label_paths is None else label_paths[i : i + step])
                    for i in range(0, len(images), step)
                ]
            )
        outs = self.backbone.forward_frozen(images.contiguous(memory_format=torch.channels_last), keep_scales=keep)
        mask = None
        if self.mask_source is not None:
            grid = grid_size(self.backbone, images.shape[-2:])
            mask = self.mask_source.grid_mask(images, outs, label_paths, grid, self.weighting)
        return self.describe(outs[-1].to(TRUNK_DTYPE), mask)

    @torch.no_grad()
    def describe_images(
        self,
        paths: Sequence[Path],
        labels: Sequence[Path] | None,
        image_size: Sequence[int],
        out: np.ndarray,
        desc: str = "descriptors",
        resize: str = "bilinear",
    ) -> None:
        """Descriptors of image files in one pass (decoding in workers, resizing as ``resize`` says:
        ``data.images.RESIZES``), written into ``out`` (N,D)."""
        self.eval()
        loader = DataLoader(
            ImageDataset(list(paths), tuple(image_size), resize, eight_bit=True),  # made floats on the device
            batch_size=self.eval_batch_size,
            num_workers=self.num_workers,
            pin_memory=self.device.type == "cuda",
        )
        with autocast(self.device):
            for images, index in progress(loader, desc, len(paths), size=lambda b: len(b[1])):
                batch_labels = [labels[i] for i in index] if labels is not None else None
                rows = slice(int(index[0]), int(index[-1]) + 1)
                out[rows] = self(to_unit(images.to(self.device, non_blocking=True)), batch_labels).float().cpu().numpy()

    @torch.no_grad()
    def describe_store(
        self, store: FeatureStore, index: Sequence[int] | None = None, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Descriptors of a feature store (or of its rows ``index``), eval mode, as float32 numpy (N, D).

        Each batch's rows are written into ``out`` as they come (a memory-mapped array keeps them out of RAM);
        without it, into an array allocated at the first batch. Returns the array written."""
        was_training = self.training
        self.eval()
        rows = len(store) if index is None else len(index)
        done = 0
        writes = HostWrites(self.device)  # on a GPU, each batch's copy back overlaps the next batch's work
        with autocast(self.device):
            for batch in store_batches(store, self.eval_batch_size, self.num_workers, index, self.device):
                desc = self.describe_batch(batch).float()
                if out is None:
                    out = np.empty((rows, desc.shape[1]), np.float32)
                writes.put(out, slice(done, done + len(desc)), desc)
                writes.chunk_done()
                done += len(desc)
        writes.flush()
        self.train(was_training)
        return out if out is not None else np.zeros((0, self.descriptor_dim), np.float32)

    # ------------------------------------------------------------------- training
    def training_step(self, batch: dict[str, Any] | None, batch_idx: int) -> Tensor | None:
        """The recipe's loss of this rank's batch. Tuples: the triplet loss summed and divided by
        ``batch["pairs"]`` (semvpr.retrieval.mining: the global pair count over the world size, so DDP's
        averaged gradient is the single-process one). Places: the multi-similarity loss of the batch."""
        if batch is None:
            return None  # no query of this batch had a violating negative (pytorch-NetVlad skips it too)
        if "pairs" in batch and "tuples" not in batch:
            # An empty slice of a global batch: a zero loss through every trainable parameter, so that
            # this rank's zero gradients still join DDP's all-reduce.
            return sum(p.sum() for p in self.parameters() if p.requires_grad) * 0.0
        assert self.optimization is not None
        loss = self.optimization.loss_fn(self.describe_batch(batch), batch)
        self.loss_watch.note(loss, self.current_epoch, self.global_step)
        if self.first_loss is None:
            self.first_loss = float(loss.detach())
        rows = batch["tuples"] if "tuples" in batch else batch["labels"]
        self.log("train/loss", loss, prog_bar=True, batch_size=len(rows))
        return loss

    def on_validation_start(self) -> None:
        self.loss_watch.check()

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.loss_watch.check()

    def on_train_end(self) -> None:
        self.loss_watch.check()

    def on_before_optimizer_step(self, optimizer: Any) -> None:
        """Count the step, and until one is found, look for a non-zero gradient (after DDP's all-reduce and
        the mixed-precision unscale: what the optimiser is about to apply)."""
        self.steps += 1
        if not self.had_gradient:
            self.had_gradient = any(
                p.grad is not None and bool(p.grad.ne(0).any()) for g in optimizer.param_groups for p in g["params"]
            )

    def nothing_learned(self) -> str | None:
        """Why the fit that ended learned nothing, or None: it took optimiser steps and none of them had a
        non-zero gradient (a loss constant from the first step: nothing it could move)."""
        if self.steps == 0 or self.had_gradient:
            return None
        return (
            f"the loss gave no parameter a gradient in any of {self.steps} optimiser step(s) (its first value "
            f"{self.first_loss}): it is constant from the first step; check the recipe's loss settings"
        )

    def optimizer_step(self, epoch: int, batch_idx: int, optimizer: Any, optimizer_closure: Any = None) -> None:
        """The step, its learning rates scaled by (step + 1) / warmup_steps during the warm-up (as
        gsv-cities, MixVPR and BoQ warm up: every group from its configured rate; the scheduler takes
        over from the rate the warm-up ends at)."""
        warmup = self.optimization.warmup_steps if self.optimization is not None else 0
        if self.trainer.global_step < warmup:
            scale = min(1.0, (self.trainer.global_step + 1) / warmup)
            for group, base in zip(optimizer.param_groups, self._base_lrs):
                group["lr"] = scale * base
        super().optimizer_step(epoch, batch_idx, optimizer, optimizer_closure)

    @property
    def weighting(self) -> str:
        """How the mask source's class probabilities become the mask: binary or learned."""
        return "binary" if self.class_weights is None else "learned"

    def configure_optimizers(self) -> Any:
        if self.optimization is None:
            raise SemvprError("the retriever was built without an optimizer (recipe.optimizer)")
        own = {id(p) for p in self.class_weights.parameters()} if self.class_weights is not None else set()
        groups: list[dict[str, Any]] = [
            {"params": [p for p in self.parameters() if p.requires_grad and id(p) not in own]}
        ]
        if own:
            # A few logits that must travel several units: their own learning rate.
            groups.append(
                {
                    "params": list(self.class_weights.parameters()),
                    "lr": self.optimization.class_weights_lr,
                    "weight_decay": 0.0,
                }
            )
        optimizer = self.optimization.optimizer(groups)
        self._base_lrs = [group["lr"] for group in optimizer.param_groups]
        if self.optimization.scheduler is None:
            return optimizer
        scheduler = self.optimization.scheduler(optimizer)
        if self.optimization.scheduler_interval == "epoch":
            return {"optimizer": optimizer, "lr_scheduler": scheduler}
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ----------------------------------------------------------------- evaluation
    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """Descriptors of a val/test batch; semvpr.retrieval.validation gathers them and computes recall."""
        return self.describe_batch(batch).float().cpu()

    test_step = validation_step


def _mask_or_none(mask: Tensor, device: torch.device) -> Tensor | None:
    return mask.to(device) if mask.numel() else None
