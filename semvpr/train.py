"""Training entry point: ``python -m semvpr.train [overrides]`` (sweeps: ``-m aggregator=a,b mask=c,d``).

One job: build what the aggregator and mask need (cached), init the aggregator, evaluate the untrained
model, fit with the recipe (triplet mining, or GSV-Cities' place batches), test the best checkpoint, and
write ``metrics.json``, ``retrievals.json`` and ``maps.npz`` into the run directory for the sweep-end report.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from lightning.pytorch.callbacks import LearningRateMonitor
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from semvpr.config.build import Prepared, build_datamodule, build_retriever, build_trainer, init_aggregator, prepare
from semvpr.config.checks import check_config, check_overrides_or_exit
from semvpr.config.command import hydra_command, name_swept_keys
from semvpr.config.plan import JobPlan, job_device, job_threads, settings_of, sweep_gpu
from semvpr.config.runs import keep_run_record, resumed_config
from semvpr.core.checkpoint import RunCheckpoint
from semvpr.core.errors import SemvprError
from semvpr.core.io import reclaim_orphans, write_json
from semvpr.core.logs import say
from semvpr.core.precision import job_precision, running_precision
from semvpr.core.stops import (
    Interrupted,
    lightning_stop,
    received_stop,
    run_stoppable,
    stop_on_signals,
    sweep_stopped_line,
)
from semvpr.reporting.job_files import write_job_figure_data
from semvpr.reporting.sweep import weights_kind
from semvpr.reporting.sweep_report import write_report
from semvpr.retrieval.distributed import sharded
from semvpr.retrieval.launch import job_ranks, launched_rank
from semvpr.retrieval.validation import RecallEvaluation


def fit_and_test(cfg: DictConfig, run_dir: Path) -> dict[str, Any] | None:
    """Run one training job: check, build, fit, test, write; returns the metrics to write (None on the
    ranks other than 0)."""
    start, timings = time.time(), {}
    check_config(cfg, run_dir)
    settings = settings_of(cfg, training=True)  # the config, typed once: what every builder below reads
    training, (devices, nodes) = settings.training, settings.ranks
    assert training is not None
    if devices * nodes > 1 and not HydraConfig.initialized():
        raise SemvprError("trainer=ddp starts its ranks from the command line: run it as python -m semvpr.train")
    overrides = list(HydraConfig.get().overrides.task) if devices * nodes > 1 else []
    batch = training.mining.batch_size if training.mining is not None else devices * nodes
    if 0 < batch < devices * nodes:
        say(
            f"recipe.batch_size={batch} is the global batch: "
            f"{devices * nodes - batch} of the {devices * nodes} ranks idle in every step"
        )
    precision = str(training.trainer.precision)
    with sweep_gpu(settings, run_dir) as leased, job_precision(precision, settings.accelerator):
        device = job_device(settings, leased)
        plan = JobPlan(device, job_threads(settings, device), settings)  # every stage below runs on plan.device
        if plan.device.type == "cuda":
            torch.cuda.set_device(plan.device)
        job = prepare(plan, timings)  # SynthCity, the teacher, labels, student, trunk caches
        ranks = job_ranks(devices, nodes, overrides, run_dir, plan.threads.jobs)
        with ranks as join, plan.threads.stage("retriever"):
            measured = train_and_test(plan, run_dir, job, timings, start, join)
    return None if measured is None else job_metrics(cfg, measured)


def train_and_test(
    plan: JobPlan,
    run_dir: Path,
    job: Prepared,
    timings: dict[str, float],
    start: float,
    join: Callable[[], None],
) -> dict[str, Any] | None:
    """Initialise, evaluate untrained (rank 0), fit, test the best checkpoint; on rank 0 the measures
    :func:`job_metrics` records (None on the others). ``join`` waits for the DDP ranks this process started
    (:func:`~semvpr.retrieval.launch.job_ranks`) once rank 0's own work before ``fit`` is done."""
    # Building artifacts in this job draws from the global RNGs (a student's training re-seeds them):
    # seed before the aggregator's random layers are drawn and again before its initialisation, so that a
    # job gives the same numbers whether its artifacts were built just now or read from the cache.
    settings = plan.settings
    training = settings.training
    assert training is not None, "a training job's settings hold its recipe (settings_of(cfg, training=True))"
    L.seed_everything(settings.seed, workers=True, verbose=False)
    retriever = build_retriever(settings, job.backbone, job.mask_source)
    describe = sharded(retriever.describe_store, settings.model.eval_batch_size)
    evaluation = RecallEvaluation({s: job.features[s] for s in ("val", "test")}, describe)
    # Best validation R@5 (Lightning's own selection), and last.ckpt after every epoch
    # (ModelCheckpoint's save_last only refreshes it when the best changes).
    checkpoint = RunCheckpoint(
        dirpath=run_dir / "checkpoints",
        filename="best",
        monitor="val/R@5",
        mode="max",
        auto_insert_metric_name=False,
        enable_version_counter=False,  # best.ckpt is this run's, never an earlier run's beside a best-v1.ckpt
    )
    latest = RunCheckpoint(
        dirpath=run_dir / "checkpoints", filename="last", monitor=None, save_top_k=1, enable_version_counter=False
    )
    threads, device = plan.threads, plan.device
    reclaim_orphans(run_dir / "checkpoints")  # what a killed save left (checkpoints are staged there)
    # The learning rate each epoch, as Lightning's own callback logs it (lr-<optimizer>), beside val/R@N.
    lr = [LearningRateMonitor(logging_interval="epoch")] if training.loggers else []
    callbacks = [evaluation, checkpoint, latest, *lr, KeepThreads(threads.of("retriever"))]
    trainer = build_trainer(plan, run_dir, callbacks)
    datamodule = build_datamodule(settings, job.features, describe)
    leader = trainer.global_rank == 0
    # The other ranks skip the initialisation: DDP gives them rank 0's weights.
    L.seed_everything(settings.seed, workers=True, verbose=False)
    tic = time.time()
    init_info = init_aggregator(settings, retriever, job) if leader else None
    timings["init_s"] = time.time() - tic
    tic = time.time()
    untrained = evaluation.evaluate(job.features["test"]) if leader else None
    timings["untrained_eval_s"] = time.time() - tic
    join()
    tic = time.time()
    # A resumed checkpoint is read as data too (tensors, numbers, strings): no pickled code runs.
    with lightning_stop():
        trainer.fit(retriever, datamodule, ckpt_path=training.ckpt_path, weights_only=True)
    timings["fit_s"] = time.time() - tic
    reason = datamodule.nothing_trained() or retriever.nothing_learned()
    if reason is not None:
        raise SemvprError(f"{reason}; nothing was trained")
    tic = time.time()
    trainer.strategy.barrier("best checkpoint written")
    retriever.to(device)  # Lightning's teardown moved it to the CPU: the whitening fit runs on the job's device
    if checkpoint.best_model_path:
        best = torch.load(checkpoint.best_model_path, map_location="cpu", weights_only=True)
        retriever.load_state_dict(best["state_dict"])
    if retriever.whitening is not None:
        retriever.fit_whitening(job.features["train"].db, describe)
    with lightning_stop():
        trainer.test(retriever, datamodule, verbose=False)
    # The tested model (best weights, fitted whitening): what semvpr.eval should be given.
    tested_ckpt = run_dir / "checkpoints" / "tested.ckpt"
    trainer.save_checkpoint(tested_ckpt, weights_only=True)  # no optimizer state: eval needs none
    timings["test_s"] = time.time() - tic
    if not leader:
        return None
    ran_on = trainer.strategy.root_device  # where fit and test ran (teardown has moved the model to the CPU)
    retriever.to(device)  # the figures' maps are made on the job's device too
    tested = evaluation.results["test"]
    for logger in trainer.loggers:  # TensorBoard's hparams view: the run's labels with its test R@1
        if isinstance(logger, TensorBoardLogger):
            labels = {"aggregator": type(retriever.aggregator).__name__, "mask": settings.model.mask_name}
            labels |= {"seed": settings.seed, "descriptor_dim": retriever.descriptor_dim}
            logger.log_hyperparams(labels, metrics={"hp_metric": tested["recalls"][1]})
    write_job_figure_data(
        run_dir,
        job.places["test"],
        job.features["test"],
        retriever,
        tested["predictions"],
        training.figure_queries,
        settings.model.mask_name,
    )
    class_weights = retriever.class_weights
    return {
        "descriptor_dim": retriever.descriptor_dim,
        "class_weights": class_weights.named_weights() if class_weights is not None else None,
        **{f"test/R@{n}": v for n, v in tested["recalls"].items()},
        **{f"test/R@{n}_pos": v for n, v in tested["recalls_pos"].items()},
        **{f"untrained/test/R@{n}": v for n, v in untrained["recalls"].items()},
        "recalls": {str(n): v for n, v in tested["curve"].items()},
        "test_queries_without_positives": tested["num_without_positives"],
        "feature_storage": job.storage,
        "checkpoint": str(tested_ckpt),
        "best/val/R@5": float(checkpoint.best_model_score) if checkpoint.best_model_score is not None else None,
        "best/val/R@1": evaluation.best_val["R@1"] if evaluation.best_val else None,
        # The epoch the tested weights come from (chosen on val): None for a checkpoint from before it was kept.
        "best/epoch": evaluation.best_val.get("epoch") if evaluation.best_val else None,
        **datamodule.epoch_facts(),
        "aggregator_init": init_info,
        "threads": threads.record(),
        # Where fit and test ran (the builders put every earlier stage on the same device) and how.
        "device": str(ran_on),
        "distributed": {
            "world_size": trainer.world_size,
            "backend": torch.distributed.get_backend() if torch.distributed.is_initialized() else None,
        },
        "precision": running_precision(),
        "timings": timings,
        "wall_time_s": time.time() - start,
    }


class KeepThreads(L.Callback):
    """Keep the retriever stage's thread count inside fit and test: Lightning's DDP launcher sets its own
    (cores / ranks) when OMP_NUM_THREADS is unset."""

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        torch.set_num_threads(self.threads)


def job_metrics(cfg: DictConfig, measured: dict[str, Any]) -> dict[str, Any]:
    """The job's metrics.json: what ran (``cfg``'s labels, its data and recipe) and what ``measured`` holds
    (:func:`train_and_test`'s: the test recalls, trained and untrained, and the run's facts)."""
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


def interrupted_line(stop: Interrupted) -> str:
    """The one line a stopped job or sweep leaves: why, how to resume a job that has a last.ckpt, and for a
    sweep its report, written now."""
    resume = "python -m semvpr.train ckpt_path=last hydra.run.dir="
    if stop.sweep_dir is not None:
        return sweep_stopped_line(stop, write_report, f"resume a stopped job that has a last.ckpt: {resume}<its dir>")
    if stop.run_dir is None:
        return f"semvpr: error: {stop}"
    if (stop.run_dir / "checkpoints" / "last.ckpt").is_file():
        return f"semvpr: error: {stop}; resume it: {resume}{stop.run_dir}"
    return f"semvpr: error: {stop} before its first epoch ended ({stop.run_dir}: nothing to resume)"


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
    previous = stop_on_signals() if threading.current_thread() is threading.main_thread() else {}
    try:
        metrics = fit_and_test(cfg, run_dir)
    except Interrupted as stop:
        stop.run_dir = stop.run_dir or run_dir
        raise
    except Exception as err:  # noqa: BLE001 - every failure is recorded for the report
        if (stop := received_stop()) is not None:  # the signal surfaced as a library's error: still a stop
            stop.run_dir = run_dir
            raise stop from None
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        write_json(
            run_dir / "metrics.json",
            {"status": "failed", "error": f"{type(err).__name__}: {message}", **run_labels(cfg)},
        )
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


def _resumed(cfg: DictConfig, run_dir: Path) -> DictConfig:
    """A resume's config (``ckpt_path`` into a run whose record is kept): the run's own, checked, so that a
    contradicting override or a checkpoint it cannot resume from is refused before anything of the run is
    touched (``ckpt_path=last`` where the run has no ``last.ckpt`` too: Lightning would train from scratch over
    it); any other job's as given (Hydra has replaced its record already)."""
    hydra_cfg = HydraConfig.get()
    record = run_dir / ".hydra" / "config.yaml"
    if cfg.ckpt_path and hydra_cfg.output_subdir is None and hydra_cfg.mode == RunMode.RUN and record.is_file():
        cfg = resumed_config(
            cfg,
            record,
            list(hydra_cfg.overrides.task),
            lambda overrides: hydra.compose(config_name="train", overrides=overrides),
        )
        check_config(cfg, run_dir)
    if cfg.get("ckpt_path") == "last" and not (run_dir / "checkpoints" / "last.ckpt").is_file():
        raise SemvprError(
            f"ckpt_path=last: {run_dir} has no checkpoints/last.ckpt to resume from (a finished run keeps "
            "tested.ckpt only; a job stopped before its first epoch ended left none); a new run: drop ckpt_path"
        )
    return cfg


@hydra_command("train", "metrics.json", prepare=_resumed)
def _hydra_main(cfg: DictConfig, run_dir: Path) -> None:
    run_job(cfg, run_dir, multirun=HydraConfig.get().mode == RunMode.MULTIRUN)


def main() -> None:
    """Console entry point; user errors and a stopping signal become one line on stderr and exit code 2."""
    check_overrides_or_exit(sys.argv[1:], "train")
    sys.argv[1:] = name_swept_keys(keep_run_record(sys.argv[1:]), "train")
    run_stoppable(_hydra_main, sys.argv[1:], interrupted_line, handlers=False)  # run_job installs them per job


if __name__ == "__main__":
    main()
