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
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from lightning.pytorch.callbacks import LearningRateMonitor
from omegaconf import DictConfig

from semvpr.config.build import build_datamodule, build_retriever, build_trainer, init_aggregator
from semvpr.config.checks import check_config, check_overrides_or_exit
from semvpr.config.command import hydra_command, name_swept_keys
from semvpr.config.job import (
    KeepThreads,
    TrainingJob,
    job_metrics,
    log_hyperparams,
    run_checkpoints,
    run_labels,
    tested_facts,
    training_job,
)
from semvpr.config.plan import settings_of
from semvpr.config.runs import keep_run_record, resumed_config
from semvpr.core.errors import SemvprError
from semvpr.core.io import write_json
from semvpr.core.stops import (
    Interrupted,
    lightning_stop,
    received_stop,
    run_stoppable,
    stop_on_signals,
    sweep_stopped_line,
)
from semvpr.reporting.job_files import write_job_figure_data
from semvpr.reporting.sweep_report import write_report
from semvpr.reporting.tensorboard import RetrievalImages
from semvpr.retrieval.distributed import sharded
from semvpr.retrieval.launch import launched_rank
from semvpr.retrieval.validation import RecallEvaluation


def fit_and_test(cfg: DictConfig, run_dir: Path) -> dict[str, Any] | None:
    """Run one training job: check, build, fit, test; the metrics to write (None on the ranks other than 0)."""
    check_config(cfg, run_dir)
    settings = settings_of(cfg, training=True)  # the config, typed once: what every builder below reads
    with training_job(settings, run_dir) as job:  # device, precision, threads, ranks; the artifacts prepared
        measured = train_and_test(job, run_dir)
    return None if measured is None else job_metrics(cfg, measured)


def train_and_test(job: TrainingJob, run_dir: Path) -> dict[str, Any] | None:
    """Initialise, evaluate untrained (rank 0), fit, test the best checkpoint; on rank 0 what the job measured
    (None on the others)."""
    settings, training, prepared = job.settings, job.settings.training, job.prepared
    assert training is not None, "a training job's settings hold its recipe (settings_of(cfg, training=True))"
    # Building artifacts in this job draws from the global RNGs (a student's training re-seeds them): seed
    # before the aggregator's random layers are drawn and again before its initialisation, so that a job gives
    # the same numbers whether its artifacts were built just now or read from the cache.
    L.seed_everything(settings.seed, workers=True, verbose=False)
    retriever = build_retriever(settings, prepared.backbone, prepared.mask_source)
    describe = sharded(retriever.describe_store, settings.model.eval_batch_size)
    evaluation = RecallEvaluation({s: prepared.features[s] for s in ("val", "test")}, describe)
    best, last = run_checkpoints(run_dir)
    # The learning rate each epoch, as Lightning's own callback logs it (lr-<optimizer>), and a few validation
    # queries' retrievals as images, beside val/R@N.
    size = settings.data.image_size
    logged = [
        LearningRateMonitor(logging_interval="epoch"),
        RetrievalImages(evaluation, prepared.features["val"], retriever, size),
    ]
    callbacks = [
        evaluation,
        best,
        last,
        *(logged if training.loggers else []),
        KeepThreads(job.plan.threads.of("retriever")),
    ]
    trainer = build_trainer(job.plan, run_dir, callbacks)
    datamodule = build_datamodule(settings, prepared.features, describe)
    leader = trainer.global_rank == 0  # the other ranks skip the initialisation: DDP gives them rank 0's weights
    L.seed_everything(settings.seed, workers=True, verbose=False)
    with job.timed("init_s"):
        init_info = init_aggregator(settings, retriever, prepared) if leader else None
    with job.timed("untrained_eval_s"):
        untrained = evaluation.evaluate(prepared.features["test"]) if leader else None
    job.join()
    with job.timed("fit_s"), lightning_stop():  # a resumed checkpoint is read as data: no pickled code runs
        trainer.fit(retriever, datamodule, ckpt_path=training.ckpt_path, weights_only=True)
    if (reason := datamodule.nothing_trained() or retriever.nothing_learned()) is not None:
        raise SemvprError(f"{reason}; nothing was trained")
    with job.timed("test_s"):
        trainer.strategy.barrier("best checkpoint written")
        retriever.to(job.plan.device)  # Lightning's teardown moved it to the CPU: whitening fits on the device
        if best.best_model_path:
            retriever.load_state_dict(
                torch.load(best.best_model_path, map_location="cpu", weights_only=True)["state_dict"]
            )
        if retriever.whitening is not None:
            retriever.fit_whitening(prepared.features["train"].db, describe)
        with lightning_stop():
            trainer.test(retriever, datamodule, verbose=False)
        # The tested model (best weights, fitted whitening, no optimizer state): what semvpr.eval should be given.
        tested_ckpt = run_dir / "checkpoints" / "tested.ckpt"
        trainer.save_checkpoint(tested_ckpt, weights_only=True)
    if not leader:
        return None
    tested = evaluation.results["test"]
    log_hyperparams(trainer, retriever, settings, tested["recalls"][1])
    retriever.to(job.plan.device)  # the figures' maps are made on the job's device too
    write_job_figure_data(
        run_dir,
        prepared.places["test"],
        prepared.features["test"],
        retriever,
        tested["predictions"],
        training.figure_queries,
        settings.model.mask_name,
    )
    facts = tested_facts(job, trainer, retriever, tested, untrained, best, evaluation.best_val)
    return {**facts, "checkpoint": str(tested_ckpt), **datamodule.epoch_facts(), "aggregator_init": init_info}


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
