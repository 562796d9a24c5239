"""What a training run's TensorBoard shows beside its scalars: after each validation, a few validation queries
drawn with their first retrieved images (``val/retrievals``: the rows of ``reporting.prediction_images``, framed
green where right and red where wrong, the mask shading them where the model has one), the same queries every
epoch, so the images show what training changes. The grid is written as a JPEG (TensorBoard shows any image its
bytes say it is): ``add_image``'s PNG took about 0.4 s an epoch for these photographs, a JPEG a hundredth of it."""

from __future__ import annotations

import io

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from PIL import Image
from tensorboard.compat.proto.summary_pb2 import Summary

from semvpr.reporting.prediction_images import MaskOf, query_row
from semvpr.retrieval.features import PlaceFeatures
from semvpr.retrieval.retriever import Retriever
from semvpr.retrieval.validation import RecallEvaluation

#: Validation queries drawn per epoch, and retrieved images beside each.
QUERIES, TOP = 4, 4
#: The grid's JPEG quality (TensorBoard's view of thumbnails: no visible loss).
JPEG_QUALITY = 90


class RetrievalImages(L.Callback):
    """Log ``val/retrievals`` to the run's TensorBoard after every validation (rank 0, not the sanity check);
    ``evaluation`` is the run's recall callback (its last validation's predictions), listed before this one."""

    def __init__(
        self, evaluation: RecallEvaluation, features: PlaceFeatures, retriever: Retriever, image_size: tuple[int, int]
    ) -> None:
        self.evaluation, self.features, self.retriever, self.image_size = evaluation, features, retriever, image_size
        places = features.places
        self.queries = np.unique(np.linspace(0, len(places.q_paths) - 1, QUERIES).round().astype(int))

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        boards = [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]
        if not boards or trainer.sanity_checking or not trainer.is_global_zero or "val" not in self.evaluation.results:
            return
        places, top = self.features.places, self.evaluation.results["val"]["predictions"]
        positives, masks = places.positives(), stored_masks(self.features, self.retriever)
        rows = [
            query_row(places, int(i), top[i, :TOP], None, positives[i], self.image_size, masks) for i in self.queries
        ]
        grid = Image.new("RGB", (max(r.width for r in rows), sum(r.height for r in rows)), "white")
        y = 0
        for row in rows:
            grid.paste(row, (0, y))
            y += row.height
        summary = jpeg_summary("val/retrievals", grid)
        for board in boards:
            board.experiment.file_writer.add_summary(summary, trainer.current_epoch)


def jpeg_summary(tag: str, image: Image.Image, quality: int = JPEG_QUALITY) -> Summary:
    """An image summary of ``image`` encoded as a JPEG (what ``SummaryWriter.add_image`` writes, PNG-encoded)."""
    encoded = io.BytesIO()
    image.convert("RGB").save(encoded, format="JPEG", quality=quality)
    picture = Summary.Image(
        height=image.height, width=image.width, colorspace=3, encoded_image_string=encoded.getvalue()
    )
    return Summary(value=[Summary.Value(tag=tag, image=picture)])


def stored_masks(features: PlaceFeatures, retriever: Retriever) -> MaskOf | None:
    """Each image's weight map as the retriever reads it from the feature store (through its learned class
    weights where it has them); None where the store holds no masks."""
    if features.db.mask is None or features.q.mask is None:
        return None

    @torch.no_grad()
    def mask_of(side: str, i: int) -> np.ndarray:
        mask = (features.db if side == "db" else features.q).mask[i : i + 1].float()
        if retriever.class_weights is not None:
            mask = retriever.class_weights(mask.to(retriever.device)).cpu()
        return mask[0, 0].numpy()

    return mask_of
