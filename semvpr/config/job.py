"""A training job's frame and its record: the context ``semvpr.train`` runs its story in (the device, the
ranks, the threads and the precision, with the job's artifacts prepared), the checkpoints it keeps, and the
metrics it writes (``metrics.json``: what ran and what it measured)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from semvpr.config.build import Prepared, prepare
from semvpr.config.plan import JobPlan, Settings, job_device, job_threads, sweep_gpu
from semvpr.core.checkpoint import RunCheckpoint
from semvpr.core.errors import SemvprError
from semvpr.core.io import reclaim_orphans
from semvpr.core.logs import say
from semvpr.core.precision import job_precision, running_precision
from semvpr.reporting.sweep import weights_kind
from semvpr.retrieval.launch import job_ranks
from semvpr.retrieval.retriever import Retriever


@dataclass
class TrainingJob:
    """One training job as its story needs it: the plan (settings, device, threads), what was prepared
    before training, ``join`` (waits for the DDP ranks this process started, once rank 0's own work before
    ``fit`` is done: :func:`~semvpr.retrieval.launch.job_ranks`), and the seconds of each stage."""

    plan: JobPlan
    prepared: Prepared
    join: Callable[[], None]
    start: float
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def settings(self) -> Settings:
        return self.plan.settings

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Count the block's seconds as ``timings[stage]``."""
        tic = time.time()
        yield
        self.timings[stage] = time.time() - tic


@contextmanager
def training_job(settings: Settings, run_dir: Path) -> Iterator[TrainingJob]:
    """The frame of a training job: its GPU leased where a sweep shares several, its precision, its device and
    threads, the artifacts prepared on that device (SynthCity, the teacher, labels, student, trunk caches), and
    its DDP ranks started, for the block's duration (every stage inside runs on ``job.plan.device``)."""
    start, timings = time.time(), {}
    assert settings.training is not None, "a training job's settings hold its recipe (settings_of(cfg, training=True))"
    devices, nodes = settings.ranks
    if devices * nodes > 1 and not HydraConfig.initialized():
        raise SemvprError("trainer=ddp starts its ranks from the command line: run it as python -m semvpr.train")
    overrides = list(HydraConfig.get().overrides.task) if devices * nodes > 1 else []
    mining = settings.training.mining
    batch = mining.batch_size if mining is not None else devices * nodes
    if 0 < batch < devices * nodes:
        say(
            f"recipe.batch_size={batch} is the global batch: "
            f"{devices * nodes - batch} of the {devices * nodes} ranks idle in every step"
        )
    with (
        sweep_gpu(settings, run_dir) as leased,
        job_precision(str(settings.training.trainer.precision), settings.accelerator),
    ):
        device = job_device(settings, leased)
        plan = JobPlan(device, job_threads(settings, device), settings)
        if plan.device.type == "cuda":
            torch.cuda.set_device(plan.device)
        prepared = prepare(plan, timings)
        with job_ranks(devices, nodes, overrides, run_dir, plan.threads.jobs) as join, plan.threads.stage("retriever"):
            yield TrainingJob(plan, prepared, join, start, timings)


def run_checkpoints(run_dir: Path) -> tuple[RunCheckpoint, RunCheckpoint]:
    """The two checkpoints a run keeps in ``run_dir/checkpoints``: the best validation R@5 (Lightning's own
    selection) and ``last.ckpt`` after every epoch (ModelCheckpoint's save_last only refreshes it when the best
    changes). What a killed save left there is removed first (checkpoints are staged there)."""
    reclaim_orphans(run_dir / "checkpoints")
    best = RunCheckpoint(
        dirpath=run_dir / "checkpoints",
        filename="best",
        monitor="val/R@5",
        mode="max",
        auto_insert_metric_name=False,
        enable_version_counter=False,  # best.ckpt is this run's, never an earlier run's beside a best-v1.ckpt
    )
    last = RunCheckpoint(
        dirpath=run_dir / "checkpoints", filename="last", monitor=None, save_top_k=1, enable_version_counter=False
    )
    return best, last


class KeepThreads(L.Callback):
    """Keep the retriever stage's thread count inside fit and test: Lightning's DDP launcher sets its own
    (cores / ranks) when OMP_NUM_THREADS is unset."""

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        torch.set_num_threads(self.threads)


def log_hyperparams(trainer: L.Trainer, retriever: Retriever, settings: Settings, test_r1: float) -> None:
    """TensorBoard's hparams view: the run's labels with its test R@1 (``hp_metric``)."""
    for logger in trainer.loggers:
        if isinstance(logger, TensorBoardLogger):
            labels = {"aggregator": type(retriever.aggregator).__name__, "mask": settings.model.mask_name}
            labels |= {"seed": settings.seed, "descriptor_dim": retriever.descriptor_dim}
            logger.log_hyperparams(labels, metrics={"hp_metric": test_r1})


def tested_facts(
    job: TrainingJob,
    trainer: L.Trainer,
    retriever: Retriever,
    tested: dict[str, Any],
    untrained: dict[str, Any],
    best: RunCheckpoint,
    best_val: dict[str, Any] | None,
) -> dict[str, Any]:
    """What a finished job measured, as ``metrics.json`` keeps it: the test recalls of the tested model and of
    the untrained one, the best epoch chosen on val, and where and how the job ran."""
    class_weights = retriever.class_weights
    return {
        "descriptor_dim": retriever.descriptor_dim,
        "class_weights": class_weights.named_weights() if class_weights is not None else None,
        **{f"test/R@{n}": v for n, v in tested["recalls"].items()},
        **{f"test/R@{n}_pos": v for n, v in tested["recalls_pos"].items()},
        **{f"untrained/test/R@{n}": v for n, v in untrained["recalls"].items()},
        "recalls": {str(n): v for n, v in tested["curve"].items()},
        "test_queries_without_positives": tested["num_without_positives"],
        "feature_storage": job.prepared.storage,
        "best/val/R@5": float(best.best_model_score) if best.best_model_score is not None else None,
        "best/val/R@1": best_val["R@1"] if best_val else None,
        # The epoch the tested weights come from (chosen on val): None for a checkpoint from before it was kept.
        "best/epoch": best_val.get("epoch") if best_val else None,
        "threads": job.plan.threads.record(),
        # Where fit and test ran (the builders put every earlier stage on the same device) and how.
        "device": str(trainer.strategy.root_device),
        "distributed": {
            "world_size": trainer.world_size,
            "backend": torch.distributed.get_backend() if torch.distributed.is_initialized() else None,
        },
        "precision": running_precision(),
        "timings": job.timings,
        "wall_time_s": time.time() - job.start,
    }


def job_metrics(cfg: DictConfig, measured: dict[str, Any]) -> dict[str, Any]:
    """The job's metrics.json: what ran (``cfg``'s labels, its data and recipe) and what ``measured`` holds."""
    return {
        "status": "ok",
        "error": None,
        **run_labels(cfg),
        "data": cfg.data.name,
        # The recipe's settings as this run resolved them (each aggregator's schedule under recipe=gsv).
        "recipe_settings": {
            k: v for k, v in OmegaConf.to_container(cfg.recipe, resolve=True).items() if k != "default"
        },
        **measured,
    }


def run_labels(cfg: DictConfig) -> dict[str, Any]:
    """What the report groups a run by: aggregator, the recipe it trained with, mask, its weighting and
    control, backbone and what its weights are (imagenet, none or file), seed; ``filter`` is the preset the config
    started from (an explicit aggregator= or mask= may have replaced its choices)."""
    return {
        "aggregator": cfg.aggregator.get("name"),
        "recipe": cfg.recipe.get("name"),
        "baseline_aggregator": bool(cfg.aggregator.get("baseline", False)),
        "mask": cfg.mask.get("name"),
        "weights": cfg.mask.get("weights"),
        "mask_upper_bound": bool(cfg.mask.get("upper_bound", False)),
        # The mask's control (retrieval.controls): none and both for the source's own mask on every image.
        "mask_control": cfg.mask.get("control"),
        "mask_apply": cfg.mask.get("apply"),
        "mask_control_seed": cfg.mask.get("control_seed"),
        "backbone": cfg.backbone.get("name"),
        "backbone_weights": weights_kind(cfg.backbone.get("weights")),
        "filter": cfg.filter.get("name"),
        "seed": _seed_of(cfg),
    }


def _seed_of(cfg: DictConfig) -> int | str | None:
    """The seed as recorded: a whole number, or as given when it is not one (a refused job's record)."""
    try:
        return int(cfg.get("seed"))
    except (TypeError, ValueError):
        return None if cfg.get("seed") is None else str(cfg.get("seed"))
