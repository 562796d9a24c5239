"""Training the embedded teacher: Mask2Former's own loss on Cityscapes trainId maps with Lightning, AdamW
with a linear warm-up and a cosine decay, the pixel-level backbone at its own learning rate, 19-class and
static / dynamic IoU on held-out images (``segmentation.training.build_teacher`` caches the result)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torchmetrics.classification import MulticlassJaccardIndex

from semvpr.core.errors import SemvprError
from semvpr.core.logs import trainer_kwargs
from semvpr.core.precision import lightning_precision
from semvpr.core.stops import lightning_stop
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES
from semvpr.data.segmentation import SegmentationSet
from semvpr.models.teacher import Teacher, TeacherSpec, TeacherTraining, embedded_teacher
from semvpr.segmentation.datamodule import SegmentationDataModule


def targets_from_train_ids(train_ids: Tensor, train_to_model: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """Per-image Mask2Former targets: one binary mask and one class index per present class."""
    mask_labels, class_labels = [], []
    for ids in train_ids:
        model_ids = train_to_model[ids.long().clamp(0, 255)]  # ignore / unknown classes → -1
        classes = model_ids.unique()
        classes = classes[classes >= 0]
        mask_labels.append((model_ids[None] == classes[:, None, None]).float())
        class_labels.append(classes)
    return mask_labels, class_labels


#: The first transformers release whose Mask2Former starts from the original model's init: query and level
#: embeddings N(0, 1), the mask MLP's default nn.Linear init. Earlier releases start them at N(0, 0.02) and
#: zero, from which the embedded teacher trains far worse (experiments/camvid-semantic measures it).
MASK2FORMER_ORIGINAL_INIT = "5.23"


def transformers_version() -> str:
    """The installed transformers release."""
    from importlib.metadata import version

    return version("transformers")


def check_mask2former_init() -> None:
    """Refuse, in one line, to train the embedded teacher from a transformers release that does not start
    Mask2Former from the original init."""
    from packaging.version import Version

    found = transformers_version()
    if Version(found) < Version(MASK2FORMER_ORIGINAL_INIT):
        raise SemvprError(
            f"transformers {found} starts Mask2Former's queries at N(0, 0.02) and its level embeddings at 0, not "
            f"at the original model's N(0, 1), and the embedded teacher trains far worse from there; install "
            f"transformers>={MASK2FORMER_ORIGINAL_INIT} (pip install -U 'transformers>={MASK2FORMER_ORIGINAL_INIT}')"
        )


class TeacherFit(L.LightningModule):
    """The teacher network under training: its Mask2Former loss, optimiser groups and validation IoU."""

    def __init__(self, teacher: Teacher, settings: TeacherTraining) -> None:
        super().__init__()
        self.teacher = teacher
        self.settings = settings
        # The pixel-level backbone's learning rate is lr x backbone_lr_factor (Mask2Former's recipe: 0.1 for an
        # ImageNet backbone); 0 freezes it: no gradient flows into it, so training skips its backward pass.
        if settings.backbone_lr_factor == 0:
            teacher.model.model.pixel_level_module.encoder.requires_grad_(False)
        self.val_miou = MulticlassJaccardIndex(len(TRAIN_ID_NAMES), ignore_index=IGNORE, average="macro")
        self.val_binary = MulticlassJaccardIndex(2, ignore_index=IGNORE, average="none")

    def training_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> Tensor:
        """Mask2Former loss (Hungarian-matched CE + mask BCE + dice) on trainId maps."""
        images, train_ids = batch
        if self.settings.flip:
            # Street scenes are left-right symmetric; a batch-level flip is free, unlike per-sample kornia.
            mirror = torch.rand(len(images), device=images.device) < 0.5
            images = torch.where(mirror[:, None, None, None], images.flip(-1), images)
            train_ids = torch.where(mirror[:, None, None], train_ids.flip(-1), train_ids)
        mask_labels, class_labels = targets_from_train_ids(train_ids, self.teacher.train_to_model)
        loss = self.teacher.model(
            pixel_values=self.teacher.pixels(images), mask_labels=mask_labels, class_labels=class_labels
        ).loss
        self.log("train/loss", loss, prog_bar=True, batch_size=len(images))
        return loss

    def validation_step(self, batch: tuple[Tensor, Tensor], batch_idx: int) -> None:
        """Accumulate 19-class and static/dynamic IoU on held-out images."""
        images, train_ids = batch
        pred = self.teacher.predict_train_ids(images)
        self.val_miou.update(pred, train_ids)
        lut = self.teacher.binary_lut
        self.val_binary.update(lut[pred], lut[train_ids.long().clamp(0, 255)])

    def on_validation_epoch_end(self) -> None:
        """Log val/mIoU, val/static_iou and val/dynamic_iou."""
        binary = self.val_binary.compute()
        self.log_dict(
            {"val/mIoU": self.val_miou.compute(), "val/static_iou": binary[1], "val/dynamic_iou": binary[0]},
            prog_bar=True,
        )
        self.val_miou.reset()
        self.val_binary.reset()

    def configure_optimizers(self) -> Any:
        """AdamW with linear warm-up then cosine decay per step (from-scratch transformers need warm-up);
        the pixel-level backbone at ``backbone_lr_factor`` x lr."""
        model, train = self.teacher.model, self.settings
        encoder = {id(p) for p in model.model.pixel_level_module.encoder.parameters()}
        rest = [p for p in model.parameters() if id(p) not in encoder and p.requires_grad]
        backbone = [p for p in model.parameters() if id(p) in encoder and p.requires_grad]
        groups = [{"params": rest}] + (
            [{"params": backbone, "lr": train.lr * train.backbone_lr_factor}] if backbone else []
        )
        opt = torch.optim.AdamW(groups, lr=train.lr, weight_decay=train.weight_decay)
        total = max(1, int(self.trainer.estimated_stepping_batches))
        warm = min(train.warmup_steps, total // 2)

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            return 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, total - warm)))

        return {
            "optimizer": opt,
            "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.LambdaLR(opt, factor), "interval": "step"},
        }


def train_teacher(
    spec: TeacherSpec, seg_train: SegmentationSet, seg_val: SegmentationSet, out: Path, device: torch.device
) -> None:
    """Train the embedded teacher with Lightning and save its weights, config and val metrics in ``out``."""
    from lightning.pytorch.loggers import CSVLogger

    check_mask2former_init()
    train = spec.train
    L.seed_everything(train.seed, workers=True, verbose=False)
    accelerator = "gpu" if device.type == "cuda" else "cpu"
    teacher = embedded_teacher(spec)
    fit = TeacherFit(teacher, train)
    data = SegmentationDataModule(seg_train, seg_val, tuple(spec.image_size), train)
    trainer = L.Trainer(
        accelerator=accelerator,
        devices=[device.index or 0] if device.type == "cuda" else 1,
        precision=lightning_precision("bf16-mixed" if train.bf16 else "32-true", accelerator),
        max_epochs=train.epochs,
        check_val_every_n_epoch=train.val_every or train.epochs,
        num_sanity_val_steps=0,
        logger=CSVLogger(out, name="logs", version=""),
        enable_checkpointing=False,
        log_every_n_steps=10,
        default_root_dir=out,
        **trainer_kwargs("teacher", ()),
    )
    start = time.perf_counter()
    with lightning_stop():
        trainer.fit(fit, datamodule=data)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    metrics["train_seconds"] = time.perf_counter() - start
    torch.save(teacher.model.state_dict(), out / "model.pt")
    (out / "config.json").write_text(teacher.model.config.to_json_string())
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
