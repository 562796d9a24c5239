"""Training entry point: ``python -m semvpr.train [overrides]`` (sweeps: ``-m filter=a,b``).

One job: build what the filter needs (cached), k-means/semantic init, evaluate the untrained
model, fit with triplet mining, test the best checkpoint, and write ``metrics.json``,
``retrievals.json`` and ``maps.npz`` into the run directory for the sweep-end report.
"""
from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig, OmegaConf

from semvpr.build import (backbone_key, backbone_name, build_backbone, build_mask_source, build_places,
                          build_semantic, check_config, init_aggregator)
from semvpr.errors import SemvprError
from semvpr.features import PlaceFeatures, cached_place_features, grid_size
from semvpr.mining import RetrievalDataModule
from semvpr.models.netvlad import PCAWhitening
from semvpr.models.retriever import Retriever, evaluate

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically (temp name, then rename)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=float))
    os.replace(tmp, path)


def fit_and_test(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run one training job; returns the metrics written to metrics.json."""
    start = time.time()
    timings: dict[str, float] = {}
    check_config(cfg)
    places = build_places(cfg)
    backbone = build_backbone(cfg)
    tic = time.time()
    semantic = build_semantic(cfg, places["train"], backbone)
    mask_source, mask_key = build_mask_source(cfg, semantic)
    timings["semantic_s"] = time.time() - tic

    tic = time.time()
    features = {split: cached_place_features(
        places[split], backbone, backbone_key(cfg), mask_source, mask_key, cfg.data.image_size,
        cfg.paths.cache_dir, cfg.model.eval_batch_size, cfg.data.num_workers) for split in places}
    timings["features_s"] = time.time() - tic

    # Building artifacts in this job draws from the global RNGs; re-seed so that a job gives the
    # same numbers whether its artifacts were built just now or read from the cache.
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    tic = time.time()
    aggregator = instantiate(cfg.filter.aggregator, dim=backbone.out_channels)
    init_info = init_aggregator(cfg, aggregator, backbone, features["train"].db, places["train"], semantic)
    timings["init_s"] = time.time() - tic

    whitening = PCAWhitening(aggregator.output_dim, cfg.model.pca_dim) if cfg.model.pca_dim else None
    retriever = Retriever(backbone, aggregator, mask_source, whitening, instantiate(cfg.model.optimizer),
                          instantiate(cfg.model.scheduler), cfg.model.margin, cfg.model.eval_batch_size,
                          config=OmegaConf.to_container(cfg, resolve=True))
    datamodule = RetrievalDataModule(
        features["train"], features["val"], features["test"], cfg.model.batch_size,
        cfg.model.eval_batch_size, cfg.model.cache_refresh, cfg.seed,
        positive_radius=cfg.model.positive_radius, negative_radius=cfg.model.negative_radius,
        num_negatives=cfg.model.num_negatives, negative_candidates=cfg.model.negative_candidates,
        margin=cfg.model.margin)

    tic = time.time()
    untrained = evaluate_features(retriever, features["test"])
    timings["untrained_eval_s"] = time.time() - tic

    loggers = [instantiate(node, save_dir=str(run_dir)) for node in cfg.logger.values()]
    checkpoint = ModelCheckpoint(dirpath=run_dir / "checkpoints", filename="best", monitor="val/R@5",
                                 mode="max", save_last=True, auto_insert_metric_name=False)
    trainer: L.Trainer = instantiate(cfg.trainer, default_root_dir=str(run_dir), logger=loggers,
                                     callbacks=[checkpoint])
    tic = time.time()
    trainer.fit(retriever, datamodule, ckpt_path=cfg.ckpt_path)
    timings["fit_s"] = time.time() - tic
    tic = time.time()
    if checkpoint.best_model_path:
        best = torch.load(checkpoint.best_model_path, map_location="cpu", weights_only=True)
        retriever.load_state_dict(best["state_dict"])
    if whitening is not None:
        retriever.fit_whitening(features["train"].db)
    trainer.test(retriever, datamodule)
    # The tested model (best weights, fitted whitening): what semvpr.eval should be given.
    tested_ckpt = run_dir / "checkpoints" / "tested.ckpt"
    trainer.save_checkpoint(tested_ckpt)
    timings["test_s"] = time.time() - tic
    tested = retriever.last_eval

    write_figure_data(run_dir, places["test"], features["test"], retriever, tested["predictions"],
                      int(cfg.num_figure_queries))
    metrics: dict[str, Any] = {
        "status": "ok", "error": None, "filter": cfg.filter.name, "backbone": backbone_name(cfg),
        "seed": int(cfg.seed), "data": cfg.data.name,
        **{f"test/R@{n}": v for n, v in tested["recalls"].items()},
        **{f"untrained/test/R@{n}": v for n, v in untrained["recalls"].items()},
        "recalls": {str(n): v for n, v in tested["curve"].items()},
        "test_queries_without_positives": tested["num_without_positives"],
        "checkpoint": str(tested_ckpt),
        "best/val/R@5": float(checkpoint.best_model_score) if checkpoint.best_model_score is not None else None,
        "tuples_per_epoch": datamodule.num_tuples, "aggregator_init": init_info,
        "timings": timings, "wall_time_s": time.time() - start,
    }
    return metrics


def evaluate_features(retriever: Retriever, features: PlaceFeatures) -> dict[str, Any]:
    """Recall of the retriever on cached features, outside the Lightning loop."""
    return evaluate(retriever.describe_store(features.db), retriever.describe_store(features.q),
                    features.places.positives(25.0))


@torch.no_grad()
def write_figure_data(run_dir: Path, places: Any, features: PlaceFeatures, retriever: Retriever,
                      predictions: np.ndarray, num_queries: int) -> None:
    """Top-k retrievals and attention / mask maps of ``num_queries`` test queries spread evenly
    over the query traversal (the same queries for every run, so the report can compare filters)."""
    idx = np.unique(np.linspace(0, len(places.q_paths) - 1, num_queries).round().astype(int))
    positives = places.positives(25.0)
    queries = []
    for i in idx:
        topk = [{"path": str(places.db_paths[j]), "utm": places.db_utm[j].tolist(),
                 "correct": bool(j in set(positives[i].tolist()))} for j in predictions[i, :5]]
        queries.append({"query": str(places.q_paths[i]), "utm": places.q_utm[i].tolist(), "topk": topk})
    write_json(run_dir / "retrievals.json", {"queries": queries})
    arrays: dict[str, np.ndarray] = {"query_index": idx, "image_paths": np.array([str(places.q_paths[i]) for i in idx])}
    trunk = features.q.trunk[torch.from_numpy(idx)]
    local = retriever.backbone.forward_trainable(trunk.float().contiguous(memory_format=torch.channels_last))
    if hasattr(retriever.aggregator, "attention"):
        arrays["attention"] = retriever.aggregator.attention(local.float())[:, 0].float().numpy()
    if features.q.mask is not None:
        arrays[retriever.hparams["config"]["filter"]["mask"]] = features.q.mask[torch.from_numpy(idx), 0].numpy()
    tmp = run_dir / ".maps.tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, run_dir / "maps.npz")


class Interrupted(BaseException):
    """SIGTERM / SIGINT: stop the job and the whole sweep; not a job failure."""


def _interrupt(signum: int, _frame: object) -> None:
    raise Interrupted(f"stopped by {signal.Signals(signum).name}")


def run_job(cfg: DictConfig, run_dir: Path, multirun: bool = False) -> dict[str, Any]:
    """Run a job and always leave a metrics.json; in a sweep a failure never stops the others.

    A signal (scheduler pre-emption, ``kill``, Ctrl-C) raises :class:`Interrupted` instead: it is
    not recorded as a failed job and it ends the sweep. Lightning composes its own SIGTERM handler
    with this one during ``fit``.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    signals = (signal.SIGTERM, signal.SIGINT) if threading.current_thread() is threading.main_thread() else ()
    previous = {sig: signal.signal(sig, _interrupt) for sig in signals}
    try:
        metrics = fit_and_test(cfg, run_dir)
    except Exception as err:  # noqa: BLE001 - every failure is recorded for the report
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        write_json(run_dir / "metrics.json", {
            "status": "failed", "error": f"{type(err).__name__}: {message}",
            "filter": cfg.filter.get("name"), "backbone": backbone_name(cfg), "seed": int(cfg.seed)})
        if multirun:
            print(f"semvpr: job failed ({run_dir}): {message}", file=sys.stderr)
            return {"status": "failed"}
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    write_json(run_dir / "metrics.json", metrics)
    summary = {k: round(v, 2) for k, v in metrics.items() if k.startswith("test/R@")}
    print(json.dumps({"run_dir": str(run_dir), **summary}))
    return metrics


@hydra.main(config_path=CONF_DIR, config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    hydra_cfg = HydraConfig.get()
    try:
        run_job(cfg, Path(hydra_cfg.runtime.output_dir), multirun=hydra_cfg.mode == RunMode.MULTIRUN)
    except SemvprError as err:
        # SystemExit passes through Hydra's own error reporting, which would print a traceback.
        print(f"semvpr: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def main() -> None:
    """Console entry point; user errors become one line on stderr and exit code 2."""
    _hydra_main()


if __name__ == "__main__":
    main()
