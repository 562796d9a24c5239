"""Training entry point: ``python -m semvpr.train [overrides]`` (sweeps: ``-m aggregator=a,b mask=c,d``).

One job: build what the aggregator and mask need (cached), init the aggregator, evaluate the untrained
model, fit with triplet mining, test the best checkpoint, and write ``metrics.json``,
``retrievals.json`` and ``maps.npz`` into the run directory for the sweep-end report.
"""
from __future__ import annotations

import json
import signal
import sys
import threading
import time
from dataclasses import dataclass
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

from semvpr.config.build import (Semantic, build_aggregator, build_backbone, build_class_weights, build_mask_source, build_places,
                          build_semantic, check_config, init_aggregator, mask_key)
from semvpr.core.checkpoint import RunCheckpoint, record_of
from semvpr.data.places import PlaceSet
from semvpr.retrieval.datamodule import RetrievalDataModule
from semvpr.retrieval.distributed import sharded
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.retrieval.validation import RecallEvaluation
from semvpr.retrieval.features import PlaceFeatures, choose_storage, place_features, trunk_cached, trunk_shape
from semvpr.core.io import CONF_DIR, atomic_file, write_json
from semvpr.retrieval.launch import job_ranks, launched_rank
from semvpr.retrieval.mining import Mining
from semvpr.models.backbones import Backbone
from semvpr.models.masks import MaskSource
from semvpr.models.aggregators.netvlad import PCAWhitening
from semvpr.retrieval.retriever import Optimization, Retriever
from semvpr.core.precision import lightning_precision
from semvpr.core.logs import quiet_third_party, trainer_kwargs
from semvpr.core.resume import keep_run_record, resumed_config
from semvpr.reporting.sweep import weights_kind


@dataclass
class Prepared:
    """What a job builds (or reads from the cache) before any training: the same on every rank."""

    places: dict[str, PlaceSet]
    backbone: Backbone
    semantic: Semantic
    mask_source: MaskSource | None
    features: dict[str, PlaceFeatures]
    storage: str


def prepare(cfg: DictConfig, timings: dict[str, float]) -> Prepared:
    """Place sets, backbone, the filter's semantic artifacts and the frozen-trunk features; the seconds of
    each stage into ``timings`` (data, semantic = teacher + labels + student, features = trunk and masks)."""
    check_config(cfg)
    tic = time.time()
    places = build_places(cfg)  # generates SynthCity on first use
    timings["data_s"] = time.time() - tic
    backbone = build_backbone(cfg)
    tic = time.time()
    semantic = build_semantic(cfg, places["train"], backbone, timings)
    mask_source = build_mask_source(cfg, backbone, semantic)
    timings["semantic_s"] = time.time() - tic
    tic = time.time()
    storage = feature_storage(cfg, backbone, places)
    features = {split: place_features(
        places[split], backbone, backbone.frozen_identity(), mask_source, mask_key(mask_source, cfg),
        cfg.data.image_size, cfg.paths.cache_dir, storage, cfg.model.eval_batch_size, cfg.data.num_workers,
        weighting=cfg.mask.weights) for split in places}
    timings["features_s"] = time.time() - tic
    return Prepared(places, backbone, semantic, mask_source, features, storage)


def mining_of(cfg: DictConfig) -> Mining:
    """The mining and batching parameters of ``cfg.model`` (``batch_size`` is the global batch)."""
    model = cfg.model
    return Mining(batch_size=int(model.batch_size), cache_refresh=int(model.cache_refresh),
                  queries_per_epoch=model.queries_per_epoch, seed=int(cfg.seed),
                  positive_radius=float(model.positive_radius), negative_radius=float(model.negative_radius),
                  num_negatives=int(model.num_negatives), negative_candidates=int(model.negative_candidates),
                  margin=float(model.margin))


def build_retriever(cfg: DictConfig, job: Prepared) -> Retriever:
    """The retriever with an uninitialised aggregator (:func:`semvpr.config.build.init_aggregator` fills it)."""
    aggregator = build_aggregator(cfg, job.backbone)
    whitening = PCAWhitening(aggregator.output_dim, cfg.model.pca_dim) if cfg.model.pca_dim else None
    optimization = Optimization(instantiate(cfg.model.optimizer), instantiate(cfg.model.scheduler),
                                float(cfg.model.margin), float(cfg.model.class_weights.lr))
    return Retriever(job.backbone, aggregator, job.mask_source, whitening, optimization, cfg.model.eval_batch_size,
                     cfg.data.num_workers, record=record_of(cfg), class_weights=build_class_weights(cfg))


def build_trainer(cfg: DictConfig, run_dir: Path, callbacks: list[L.Callback]) -> L.Trainer:
    """The configured Lightning Trainer with the run's loggers and checkpoints."""
    loggers = [instantiate(node, save_dir=str(run_dir)) for node in cfg.logger.values()]
    return instantiate(cfg.trainer, default_root_dir=str(run_dir), logger=loggers, **trainer_kwargs("retriever", callbacks),
                       precision=lightning_precision(str(cfg.trainer.precision), str(cfg.trainer.accelerator)))


def ranks_of(trainer_cfg: DictConfig) -> tuple[int, int]:
    """(processes per node, nodes) of a job: trainer.devices (-1: all GPUs) and trainer.num_nodes
    under a DDP strategy; (1, 1) otherwise."""
    if not str(trainer_cfg.get("strategy", "auto")).startswith("ddp"):
        return 1, 1
    devices = int(trainer_cfg.devices)
    if devices == -1:  # Lightning's "all GPUs"
        devices = torch.cuda.device_count()
    return devices, int(trainer_cfg.get("num_nodes", 1))


def fit_and_test(cfg: DictConfig, run_dir: Path) -> dict[str, Any] | None:
    """Run one training job; returns the metrics to write (None on the ranks other than 0)."""
    start, timings = time.time(), {}
    devices, nodes = ranks_of(cfg.trainer)
    if devices * nodes > 1 and not HydraConfig.initialized():
        raise SemvprError("trainer=ddp starts its ranks from the command line: run it as python -m semvpr.train")
    overrides = list(HydraConfig.get().overrides.task) if devices * nodes > 1 else []
    if 0 < int(cfg.model.batch_size) < devices * nodes:
        print(f"semvpr: model.batch_size={cfg.model.batch_size} is the global batch: "
              f"{devices * nodes - int(cfg.model.batch_size)} of the {devices * nodes} ranks idle in every step",
              file=sys.stderr)
    job = prepare(cfg, timings)
    with job_ranks(devices, nodes, overrides, run_dir):
        return train_and_test(cfg, run_dir, job, timings, start)


def train_and_test(cfg: DictConfig, run_dir: Path, job: Prepared, timings: dict[str, float],
                   start: float) -> dict[str, Any] | None:
    """Initialise, evaluate untrained (rank 0), fit, test the best checkpoint; metrics on rank 0."""
    retriever = build_retriever(cfg, job)
    describe = sharded(retriever.describe_store, int(cfg.model.eval_batch_size))
    evaluation = RecallEvaluation({s: job.features[s] for s in ("val", "test")}, describe)
    # Best validation R@5 (Lightning's own selection), and last.ckpt after every epoch
    # (ModelCheckpoint's save_last only refreshes it when the best changes).
    checkpoint = RunCheckpoint(dirpath=run_dir / "checkpoints", filename="best", monitor="val/R@5",
                               mode="max", auto_insert_metric_name=False)
    latest = RunCheckpoint(dirpath=run_dir / "checkpoints", filename="last", monitor=None, save_top_k=1,
                           enable_version_counter=False)
    trainer = build_trainer(cfg, run_dir, [evaluation, checkpoint, latest])
    datamodule = RetrievalDataModule(job.features, mining_of(cfg), describe, int(cfg.model.eval_batch_size),
                                     int(cfg.data.num_workers))
    leader = trainer.global_rank == 0
    # Building artifacts in this job draws from the global RNGs; re-seed so that a job gives the
    # same numbers whether its artifacts were built just now or read from the cache. The other
    # ranks skip the initialisation: DDP gives them rank 0's weights.
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    tic = time.time()
    init_info = init_aggregator(cfg, retriever.aggregator, job.backbone, job.features["train"].db,
                                job.places["train"], job.semantic) if leader else None
    timings["init_s"] = time.time() - tic
    tic = time.time()
    untrained = evaluation.evaluate(job.features["test"]) if leader else None
    timings["untrained_eval_s"] = time.time() - tic
    tic = time.time()
    # A resumed checkpoint is read as data too (tensors, numbers, strings): no pickled code runs.
    trainer.fit(retriever, datamodule, ckpt_path=cfg.ckpt_path, weights_only=True)
    timings["fit_s"] = time.time() - tic
    tic = time.time()
    trainer.strategy.barrier("best checkpoint written")
    if checkpoint.best_model_path:
        best = torch.load(checkpoint.best_model_path, map_location="cpu", weights_only=True)
        retriever.load_state_dict(best["state_dict"])
    if retriever.whitening is not None:
        retriever.fit_whitening(job.features["train"].db, describe)
    trainer.test(retriever, datamodule, verbose=False)
    # The tested model (best weights, fitted whitening): what semvpr.eval should be given.
    tested_ckpt = run_dir / "checkpoints" / "tested.ckpt"
    trainer.save_checkpoint(tested_ckpt, weights_only=True)  # no optimizer state: eval needs none
    timings["test_s"] = time.time() - tic
    if not leader:
        return None
    tested = evaluation.results["test"]
    write_figure_data(run_dir, job.places["test"], job.features["test"], retriever, tested["predictions"],
                      int(cfg.num_figure_queries), cfg.mask.name)
    return job_metrics(cfg, retriever, job, tested, untrained, {
        "checkpoint": str(tested_ckpt),
        "best/val/R@5": float(checkpoint.best_model_score) if checkpoint.best_model_score is not None else None,
        "best/val/R@1": evaluation.best_val["R@1"] if evaluation.best_val else None,
        "tuples_per_epoch": datamodule.num_tuples, "aggregator_init": init_info,
        "timings": timings, "wall_time_s": time.time() - start})


def job_metrics(cfg: DictConfig, retriever: Retriever, job: Prepared, tested: dict[str, Any],
                untrained: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    """The job's metrics.json: what ran, the test recalls (trained and untrained), and ``run``'s facts."""
    class_weights = retriever.class_weights
    return {
        "status": "ok", "error": None, **run_labels(cfg),
        "descriptor_dim": retriever.whitening.out_dim if retriever.whitening is not None else retriever.aggregator.output_dim,
        "class_weights": class_weights.named_weights() if class_weights is not None else None,
        "data": cfg.data.name,
        **{f"test/R@{n}": v for n, v in tested["recalls"].items()},
        **{f"test/R@{n}_pos": v for n, v in tested["recalls_pos"].items()},
        **{f"untrained/test/R@{n}": v for n, v in untrained["recalls"].items()},
        "recalls": {str(n): v for n, v in tested["curve"].items()},
        "test_queries_without_positives": tested["num_without_positives"],
        "feature_storage": job.storage, **run,
    }


def run_labels(cfg: DictConfig) -> dict[str, Any]:
    """What the report groups a run by: aggregator, mask, its weighting, backbone and what its weights are
    (imagenet, none or file), seed; ``filter`` is the preset the config started from (an explicit
    aggregator= or mask= may have replaced its choices)."""
    return {"aggregator": cfg.aggregator.get("name"), "baseline_aggregator": bool(cfg.aggregator.get("baseline", False)),
            "mask": cfg.mask.get("name"), "weights": cfg.mask.get("weights"),
            "mask_upper_bound": bool(cfg.mask.get("upper_bound", False)), "backbone": cfg.backbone.get("name"),
            "backbone_weights": weights_kind(cfg.backbone.get("weights")),
            "filter": cfg.filter.get("name"), "seed": _seed_of(cfg)}


def _seed_of(cfg: DictConfig) -> int | str | None:
    """The seed as recorded: a whole number, or as given when it is not one (a refused job's record)."""
    try:
        return int(cfg.get("seed"))
    except (TypeError, ValueError):
        return None if cfg.get("seed") is None else str(cfg.get("seed"))


def feature_storage(cfg: DictConfig, backbone: Any, places: dict[str, Any]) -> str:
    """How the run holds its frozen-trunk features: ram, disk or stream (semvpr.retrieval.features). Under DDP
    every rank on a node holds its own copy in RAM, so ``auto`` gives each a share of
    ``features.ram_gb`` (beyond it the memory-mapped store is shared through the page cache)."""
    per_image = 2 * int(np.prod(trunk_shape(backbone, cfg.data.image_size)))  # bf16
    images = sum(len(p.db_paths) + len(p.q_paths) for p in places.values())
    cached = all(trunk_cached(p, backbone.frozen_identity(), cfg.data.image_size, cfg.paths.cache_dir)
                 for p in places.values())
    storage = choose_storage(cfg.features.storage, per_image * images, cfg.paths.cache_dir,
                             float(cfg.features.ram_gb) / ranks_of(cfg.trainer)[0], float(cfg.features.disk_gb),
                             cached)
    print(f"semvpr: frozen-trunk features of {images} images ({per_image * images / 2**30:.2f} GiB): {storage}",
          file=sys.stderr)
    return storage


@torch.no_grad()
def write_figure_data(run_dir: Path, places: Any, features: PlaceFeatures, retriever: Retriever,
                      predictions: np.ndarray, num_queries: int, mask_name: str) -> None:
    """Top-k retrievals and attention / mask maps of ``num_queries`` test queries spread evenly
    over the query traversal (the same queries for every run, so the report can compare runs)."""
    idx = np.unique(np.linspace(0, len(places.q_paths) - 1, num_queries).round().astype(int))
    positives = places.positives()
    queries = []
    for i in idx:
        topk = [{"path": str(places.db_paths[j]), "utm": places.db_utm[j].tolist(),
                 "correct": bool(j in set(positives[i].tolist()))} for j in predictions[i, :5]]
        queries.append({"query": str(places.q_paths[i]), "utm": places.q_utm[i].tolist(), "topk": topk})
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


class Interrupted(BaseException):
    """SIGTERM / SIGINT: stop the job and the whole sweep; not a job failure."""


def _interrupt(signum: int, _frame: object) -> None:
    raise Interrupted(f"stopped by {signal.Signals(signum).name}")


def run_job(cfg: DictConfig, run_dir: Path, multirun: bool = False) -> dict[str, Any]:
    """Run a job and always leave a metrics.json; in a sweep a failure never stops the others.

    A signal (scheduler pre-emption, ``kill``, Ctrl-C) raises :class:`Interrupted` instead: it is
    not recorded as a failed job and it ends the sweep. Lightning composes its own SIGTERM handler
    with this one during ``fit``. In a DDP job only rank 0 writes; the other ranks return ``{}``.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    if launched_rank() != 0:  # another rank of a DDP job: rank 0 writes and records failures
        fit_and_test(cfg, run_dir)
        return {}
    signals = (signal.SIGTERM, signal.SIGINT) if threading.current_thread() is threading.main_thread() else ()
    previous = {sig: signal.signal(sig, _interrupt) for sig in signals}
    try:
        metrics = fit_and_test(cfg, run_dir)
    except Exception as err:  # noqa: BLE001 - every failure is recorded for the report
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        write_json(run_dir / "metrics.json", {
            "status": "failed", "error": f"{type(err).__name__}: {message}", **run_labels(cfg)})
        if multirun:
            print(f"semvpr: job failed ({run_dir}): {message}", file=sys.stderr)
            return {"status": "failed"}
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    assert metrics is not None  # rank 0
    write_json(run_dir / "metrics.json", metrics)
    summary = {k: round(v, 2) for k, v in metrics.items() if k.startswith("test/R@") and not k.endswith("_pos")}
    print(json.dumps({"run_dir": str(run_dir), **summary}))
    return metrics


@hydra.main(config_path=CONF_DIR, config_name="train", version_base="1.3")
@exit_on_user_error
def _hydra_main(cfg: DictConfig) -> None:
    quiet_third_party()
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
