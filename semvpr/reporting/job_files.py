"""What a training job writes for the sweep report besides metrics.json: the top-k retrievals of a fixed
set of test queries (``retrievals.json``) and their attention and mask maps (``maps.npz``), read back
by ``semvpr.reporting.sweep`` and drawn by ``semvpr.reporting.figures``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from semvpr.core.io import atomic_file, write_json
from semvpr.retrieval.features import PlaceFeatures
from semvpr.retrieval.retriever import Retriever


@torch.no_grad()
def write_job_figure_data(
    run_dir: Path,
    places: Any,
    features: PlaceFeatures,
    retriever: Retriever,
    predictions: np.ndarray,
    num_queries: int,
    mask_name: str,
) -> None:
    """Top-k retrievals and attention / mask maps of ``num_queries`` test queries spread evenly
    over the query traversal (the same queries for every run, so the report can compare runs)."""
    idx = np.unique(np.linspace(0, len(places.q_paths) - 1, num_queries).round().astype(int))
    positives = places.positives()
    queries = []
    for i in idx:
        topk = [
            {
                "path": str(places.db_paths[j]),
                **places.position("db", j),
                "correct": bool(j in set(positives[i].tolist())),
            }
            for j in predictions[i, :5]
        ]
        queries.append({"query": str(places.q_paths[i]), **places.position("q", i), "topk": topk})
    write_json(run_dir / "retrievals.json", {"queries": queries})
    arrays: dict[str, np.ndarray] = {"query_index": idx, "image_paths": np.array([str(places.q_paths[i]) for i in idx])}
    trunk = features.q.trunk_of(idx, retriever.backbone).float().to(retriever.device)
    local = retriever.backbone.forward_trainable(trunk.contiguous(memory_format=torch.channels_last))
    attention = retriever.aggregator.attention(local.float())
    if attention is not None:
        arrays["attention"] = attention[:, 0].float().cpu().numpy()
    if features.q.mask is not None:
        mask = features.q.mask[torch.from_numpy(idx)].float()
        if retriever.class_weights is not None:  # class probabilities → the learned weight map
            mask = retriever.class_weights(mask.to(retriever.device)).cpu()
        arrays[mask_name] = mask[:, 0].numpy()
    with atomic_file(run_dir / "maps.npz") as fh:
        np.savez(fh, **arrays)
