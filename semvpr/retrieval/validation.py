"""Recall@N of the retriever on val/test, as a Lightning callback that owns the evaluation results.

The model only turns batches into descriptors (``validation_step`` / ``test_step`` return them);
this callback collects them, gathers them across ranks in order (semvpr.retrieval.distributed), computes
recall once on rank 0, and gives every rank the same numbers to log. The caller reads the results
from here: the last result per stage (:attr:`results`, with the top-k predictions for the figures)
and the validation R@1 and the epoch (1-based) with the best val/R@5, the one ModelCheckpoint keeps
(:attr:`best_val`, saved in the checkpoint so that a resumed run reports it too).
"""

from __future__ import annotations

from typing import Any

import lightning as L
import numpy as np
import torch
from torch import Tensor

from semvpr.retrieval.distributed import Describe, from_rank_zero, gather_rows, world
from semvpr.retrieval.features import PlaceFeatures
from semvpr.retrieval.recall import evaluate


class RecallEvaluation(L.Callback):
    """Val/test recall from the descriptors the model returns (module docstring)."""

    def __init__(self, sets: dict[str, PlaceFeatures], describe: Describe) -> None:
        self.sets, self.describe = sets, describe
        self.results: dict[str, dict[str, Any]] = {}
        self.best_val: dict[str, float | int] | None = None
        self._rows: list[Tensor] = []

    def evaluate(self, features: PlaceFeatures) -> dict[str, Any]:
        """Describe a place set's database and queries and compute recall (outside the Lightning loop)."""
        return self._recall(features, self.describe(features.db, None), self.describe(features.q, None))

    # Lightning hooks: collect each batch's descriptors, then evaluate at the end of the loop.
    def on_validation_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        self._rows.append(outputs)

    on_test_batch_end = on_validation_batch_end

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._end("val", pl_module)

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._end("test", pl_module)

    def _end(self, stage: str, pl_module: L.LightningModule) -> None:
        features = self.sets[stage]
        local = torch.cat(self._rows) if self._rows else torch.zeros(0, 0)
        self._rows.clear()
        desc = gather_rows(local).numpy()
        n_db = len(features.db)
        if len(desc) == n_db + len(features.q):
            result = self._recall(features, desc[:n_db], desc[n_db:])
        else:  # fast_dev_run / limit_*_batches saw part of the set; recall needs all of it.
            result = self.evaluate(features)
        for n, value in result["recalls"].items():
            pl_module.log(f"{stage}/R@{n}", value, prog_bar=n in (1, 5))
        if result["num_without_positives"]:
            for n, value in result["recalls_pos"].items():
                pl_module.log(f"{stage}/R@{n}_pos", value)
        self.results[stage] = result
        if stage == "val" and not pl_module.trainer.sanity_checking:
            # As logged (float32), as ModelCheckpoint compares and keeps its best score.
            r1, r5 = (float(torch.tensor(result["recalls"][n], dtype=torch.float32)) for n in (1, 5))
            if self.best_val is None or r5 > self.best_val["R@5"]:  # strictly better, as ModelCheckpoint
                self.best_val = {"R@1": r1, "R@5": r5, "epoch": int(pl_module.current_epoch) + 1}

    def _recall(self, features: PlaceFeatures, db: np.ndarray, q: np.ndarray) -> dict[str, Any]:
        """Recall computed once, on rank 0, and the same result on every rank."""
        result = evaluate(db, q, features.places.positives()) if world()[0] == 0 else None
        return from_rank_zero(result)

    def state_dict(self) -> dict[str, Any]:
        return {"best_val": self.best_val}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.best_val = state_dict.get("best_val")
