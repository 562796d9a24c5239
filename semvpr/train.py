"""Training entry point: ``python -m semvpr.train [overrides]`` (sweeps: ``-m filter=a,b``).

One job: build what the filter needs (cached), k-means/semantic init, evaluate the untrained
model, fit with triplet mining, test the best checkpoint, and write ``metrics.json``,
``retrievals.json`` and ``maps.npz`` into the run directory for the sweep-end report.
"""
from __future__ import annotations

import json
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
from omegaconf import DictConfig

from semvpr.build import (build_backbone, build_class_weights, build_mask_source, build_places, build_semantic,
                          check_config, init_aggregator, mask_key)
from semvpr.checkpoint import RunCheckpoint, record_of
from semvpr.errors import exit_on_user_error
from semvpr.io import CONF_DIR, atomic_file, write_json
from semvpr.features import PlaceFeatures, choose_storage, place_features, trunk_cached, trunk_shape
from semvpr.mining import RetrievalDataModule
from semvpr.models.netvlad import PCAWhitening
from semvpr.models.retriever import Retriever, evaluate
from semvpr.precision import lightning_precision
from semvpr.resume import keep_run_record, resumed_config


def fit_and_test(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run one training job; returns the metrics written to metrics.json."""
    start = time.time()
    timings: dict[str, float] = {}
    check_config(cfg)
    places = build_places(cfg)
    backbone = build_backbone(cfg)
    tic = time.time()
    semantic = build_semantic(cfg, places["train"], backbone)
    mask_source = build_mask_source(cfg, backbone, semantic)
    timings["semantic_s"] = time.time() - tic

    tic = time.time()
    storage = feature_storage(cfg, backbone, places)
    features = {split: place_features(
        places[split], backbone, backbone.frozen_identity(), mask_source, mask_key(mask_source, cfg),
        cfg.data.image_size, cfg.paths.cache_dir, storage, cfg.model.eval_batch_size, cfg.data.num_workers,
        weighting=cfg.filter.get("weights", "binary")) for split in places}
    timings["features_s"] = time.time() - tic

    # Building artifacts in this job draws from the global RNGs; re-seed so that a job gives the
    # same numbers whether its artifacts were built just now or read from the cache.
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    tic = time.time()
    aggregator = instantiate(cfg.filter.aggregator, dim=backbone.out_channels)
    init_info = init_aggregator(cfg, aggregator, backbone, features["train"].db, places["train"], semantic)
    timings["init_s"] = time.time() - tic

    whitening = PCAWhitening(aggregator.output_dim, cfg.model.pca_dim) if cfg.model.pca_dim else None
    class_weights = build_class_weights(cfg)
    retriever = Retriever(backbone, aggregator, mask_source, whitening, instantiate(cfg.model.optimizer),
                          instantiate(cfg.model.scheduler), cfg.model.margin, cfg.model.eval_batch_size,
                          cfg.data.num_workers, record=record_of(cfg), class_weights=class_weights,
                          class_weights_lr=float(cfg.model.class_weights.lr))
    datamodule = RetrievalDataModule(
        features["train"], features["val"], features["test"], cfg.model.batch_size,
        cfg.model.eval_batch_size, cfg.model.cache_refresh, cfg.seed, cfg.model.queries_per_epoch,
        cfg.data.num_workers, positive_radius=cfg.model.positive_radius,
        negative_radius=cfg.model.negative_radius, num_negatives=cfg.model.num_negatives,
        negative_candidates=cfg.model.negative_candidates, margin=cfg.model.margin)

    tic = time.time()
    untrained = evaluate_features(retriever, features["test"])
    timings["untrained_eval_s"] = time.time() - tic

    loggers = [instantiate(node, save_dir=str(run_dir)) for node in cfg.logger.values()]
    checkpoint = RunCheckpoint(dirpath=run_dir / "checkpoints", filename="best", monitor="val/R@5",
                                 mode="max", auto_insert_metric_name=False)
    # last.ckpt after every epoch (ModelCheckpoint's save_last only refreshes it when the best
    # changes, so a killed run would resume from an older epoch).
    latest = RunCheckpoint(dirpath=run_dir / "checkpoints", filename="last", monitor=None, save_top_k=1,
                             enable_version_counter=False)
    trainer: L.Trainer = instantiate(cfg.trainer, default_root_dir=str(run_dir), logger=loggers,
                                     callbacks=[checkpoint, latest],
                                     precision=lightning_precision(str(cfg.trainer.precision), str(cfg.trainer.accelerator)))
    tic = time.time()
    # A resumed checkpoint is read as data too (tensors, numbers, strings): no pickled code runs.
    trainer.fit(retriever, datamodule, ckpt_path=cfg.ckpt_path, weights_only=True)
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
                      int(cfg.num_figure_queries), cfg.filter.mask)
    metrics: dict[str, Any] = {
        "status": "ok", "error": None, "filter": cfg.filter.name, "backbone": cfg.backbone.name,
        "weights": retriever.weighting,
        "class_weights": class_weights.named_weights() if class_weights is not None else None,
        "seed": int(cfg.seed), "data": cfg.data.name,
        **{f"test/R@{n}": v for n, v in tested["recalls"].items()},
        **{f"test/R@{n}_pos": v for n, v in tested["recalls_pos"].items()},
        **{f"untrained/test/R@{n}": v for n, v in untrained["recalls"].items()},
        "recalls": {str(n): v for n, v in tested["curve"].items()},
        "test_queries_without_positives": tested["num_without_positives"],
        "feature_storage": storage,
        "checkpoint": str(tested_ckpt),
        "best/val/R@5": float(checkpoint.best_model_score) if checkpoint.best_model_score is not None else None,
        "best/val/R@1": best_val_r1(run_dir),
        "tuples_per_epoch": datamodule.num_tuples, "aggregator_init": init_info,
        "timings": timings, "wall_time_s": time.time() - start,
    }
    return metrics


def feature_storage(cfg: DictConfig, backbone: Any, places: dict[str, Any]) -> str:
    """How the run holds its frozen-trunk features: ram, disk or stream (semvpr.features)."""
    per_image = 2 * int(np.prod(trunk_shape(backbone, cfg.data.image_size)))  # bf16
    images = sum(len(p.db_paths) + len(p.q_paths) for p in places.values())
    cached = all(trunk_cached(p, backbone.frozen_identity(), cfg.data.image_size, cfg.paths.cache_dir)
                 for p in places.values())
    storage = choose_storage(cfg.features.storage, per_image * images, cfg.paths.cache_dir,
                             float(cfg.features.ram_gb), float(cfg.features.disk_gb), cached)
    print(f"semvpr: frozen-trunk features of {images} images ({per_image * images / 2**30:.2f} GiB): {storage}",
          file=sys.stderr)
    return storage


def best_val_r1(run_dir: Path) -> float | None:
    """Validation R@1 of the epoch whose checkpoint was kept (the val/R@5 maximum), from the CSV log."""
    import csv

    rows = []
    for log in (run_dir / "csv").rglob("metrics.csv"):
        with log.open(newline="") as fh:
            rows += [r for r in csv.DictReader(fh) if r.get("val/R@1") and r.get("val/R@5")]
    if not rows:
        return None
    return float(max(rows, key=lambda r: float(r["val/R@5"]))["val/R@1"])


def evaluate_features(retriever: Retriever, features: PlaceFeatures) -> dict[str, Any]:
    """Recall of the retriever on a place set's feature stores, outside the Lightning loop."""
    return evaluate(retriever.describe_store(features.db), retriever.describe_store(features.q),
                    features.places.positives(25.0))


@torch.no_grad()
def write_figure_data(run_dir: Path, places: Any, features: PlaceFeatures, retriever: Retriever,
                      predictions: np.ndarray, num_queries: int, mask_name: str) -> None:
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
    trunk = features.q.trunk_of(idx, retriever.backbone).float().to(retriever.device)
    local = retriever.backbone.forward_trainable(trunk.contiguous(memory_format=torch.channels_last))
    if hasattr(retriever.aggregator, "attention"):
        arrays["attention"] = retriever.aggregator.attention(local.float())[:, 0].float().cpu().numpy()
    if features.q.mask is not None:
        mask = features.q.mask[torch.from_numpy(idx)].float()
        if retriever.class_weights is not None:  # class probabilities → the learned weight map
            mask = retriever.class_weights(mask.to(retriever.device)).cpu()
        arrays[mask_name] = mask[:, 0].numpy()
    with atomic_file(run_dir / "maps.npz") as fh:
        np.savez(fh, **arrays)


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
            "filter": cfg.filter.get("name"), "backbone": cfg.backbone.get("name"), "seed": cfg.get("seed")})
        if multirun:
            print(f"semvpr: job failed ({run_dir}): {message}", file=sys.stderr)
            return {"status": "failed"}
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    write_json(run_dir / "metrics.json", metrics)
    summary = {k: round(v, 2) for k, v in metrics.items() if k.startswith("test/R@") and not k.endswith("_pos")}
    print(json.dumps({"run_dir": str(run_dir), **summary}))
    return metrics


@hydra.main(config_path=CONF_DIR, config_name="train", version_base="1.3")
@exit_on_user_error
def _hydra_main(cfg: DictConfig) -> None:
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    record = run_dir / ".hydra" / "config.yaml"
    if cfg.ckpt_path and hydra_cfg.output_subdir is None and hydra_cfg.mode == RunMode.RUN and record.is_file():
        cfg = resumed_config(cfg, hydra.compose(config_name="train"), record, list(hydra_cfg.overrides.task))
    run_job(cfg, run_dir, multirun=hydra_cfg.mode == RunMode.MULTIRUN)


def main() -> None:
    """Console entry point; user errors become one line on stderr and exit code 2."""
    sys.argv[1:] = keep_run_record(sys.argv[1:])
    _hydra_main()


if __name__ == "__main__":
    main()
