"""What a run prints: semvpr's own stage lines, and none of the known harmless third-party noise.

Long stages (dataset generation, teacher and student training, pseudo-labels, trunk and mask
caching, retriever epochs) report through :class:`Progress` or :class:`EpochLines`: plain lines on
stderr with counts, elapsed time and an ETA, whether or not stderr is a terminal (a sweep's log file
gets the same lines as a console). Every such line goes through :func:`say`, which names the sweep
job printing it (:func:`job_named`: two jobs side by side interleave their lines).
:func:`quiet_third_party` hides what Lightning and its dependencies repeat in every job and that
says nothing about the run: adverts, device banners, warnings about settings semvpr makes on purpose
(a frozen trunk in eval mode, short epochs)."""

from __future__ import annotations

import logging
import re
import sys
import time
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO, TypeVar

import lightning as L

T = TypeVar("T")

#: The sweep job this process runs now (``#2 filter=unet``), named in its stage lines; None outside a sweep.
_JOB: dict[str, str | None] = {"label": None}
#: Longest job name a line carries: a longer one keeps its start and end.
MAX_JOB_NAME = 48


def job_label(num: int, name: str) -> str:
    """How a stage line names a sweep's job: Hydra's job number (as its launch list prints it) and its
    overrides (``hydra.job.override_dirname``: a training job's directory name), a long one cut in the
    middle (``#3 ckpt=outputs/multiru...ckpt,mask=student``)."""
    if len(name) > MAX_JOB_NAME:
        head = (MAX_JOB_NAME - 3) // 2
        name = f"{name[:head]}...{name[head + 3 - MAX_JOB_NAME :]}"
    return f"#{num} {name}"


@contextmanager
def job_named(label: str | None) -> Iterator[None]:
    """Name ``label`` in every line :func:`say` prints inside the block (a sweep job's :func:`job_label`;
    None: no name); the previous name is restored after it."""
    previous, _JOB["label"] = _JOB["label"], label
    try:
        yield
    finally:
        _JOB["label"] = previous


def line(text: str) -> str:
    """``semvpr: <text>``, inside a sweep job ``semvpr: [#2 filter=unet] <text>``."""
    label = _JOB["label"]
    return f"semvpr: [{label}] {text}" if label else f"semvpr: {text}"


#: The log file of the job this process runs now (its stage lines are written there too); None: none.
_LOG: dict[str, TextIO | None] = {"file": None}


@contextmanager
def job_log(path: Path | None) -> Iterator[None]:
    """Inside the block every line :func:`say` prints is also appended to ``path`` (a command's job log,
    ``<run dir>/<command>.log``; None: none), so the run's folder holds what its console showed."""
    if path is None:
        yield
        return
    previous = _LOG["file"]
    with open(path, "a", encoding="utf-8") as fh:
        _LOG["file"] = fh
        try:
            yield
        finally:
            _LOG["file"] = previous


def say(text: str, stream: TextIO | None = None) -> None:
    """Print a stage or warning line (:func:`line`) on ``stream`` (stderr by default), flushed; inside
    :func:`job_log`, append it to the job's log too."""
    shown = line(text)
    print(shown, file=stream or sys.stderr, flush=True)
    if (log := _LOG["file"]) is not None:
        print(shown, file=log, flush=True)


# Informational lines Lightning logs once per Trainer (so once per job of a sweep).
NOISE_LINES = (
    "💡 Tip:",  # litlogger / litmodels adverts
    "GPU available:",
    "TPU available:",
    "HPU available:",
    "Using bfloat16 Automatic Mixed Precision",
    "Using 16bit Automatic Mixed Precision",
    "`Trainer.fit` stopped:",  # semvpr's epoch lines say when training ends
    "Loading `train_dataloader` to estimate number of stepping batches",
    # transformers' Mask2Former lists only Swin as a backbone; timm's EfficientNet-Lite0 works through
    # its TimmBackbone (tests/models/test_teacher.py checks its features and a save/load round trip).
    "Backbone timm_backbone is not a supported model",
    # Lightning's signal handler, before semvpr's own line for the stop (semvpr.train.interrupted_line).
    "Received SIGTERM:",
    "Received SIGINT:",
)
# Warnings about settings semvpr makes on purpose, with the reason each is harmless.
NOISE_WARNINGS = (
    r"Found \d+ module\(s\) in eval mode",  # the frozen trunk stays in eval mode (fixed BatchNorm)
    r"The number of training batches \(\d+\) is smaller than the logging interval",  # short CPU epochs
    r"Precision .* is not supported by the model summary",
    r"`isinstance\(treespec, LeafSpec\)` is deprecated",  # Lightning on newer torch
    r".*does not have many workers which may be a bottleneck",  # num_workers=0 on purpose (tiny sets)
)


class _DropNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        # Lightning prefixes some lines with the rank: "[rank: 0] Received SIGTERM: 15".
        return not re.sub(r"^\[rank: \d+\] ", "", str(record.getMessage())).startswith(NOISE_LINES)


_FILTER = _DropNoise()


def quiet_third_party() -> None:
    """Hide the known harmless third-party lines and warnings (idempotent; other output is kept)."""
    for name in (
        "lightning.pytorch",
        "lightning.pytorch.utilities.rank_zero",
        "lightning.fabric",
        "lightning.fabric.utilities.rank_zero",
        "transformers.models.mask2former.configuration_mask2former",
    ):
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
        for handler in logger.handlers:
            if _FILTER not in handler.filters:
                handler.addFilter(_FILTER)
    for pattern in NOISE_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)


@contextmanager
def no_hf_progress_bars() -> Iterator[None]:
    """Hide transformers' progress bars (``Loading weights: 100%|...`` at every checkpoint load, once per
    evaluation with a teacher mask; ``Writing model shards`` at a save) for the block; the previous setting
    is restored."""
    from transformers.utils import logging as hf_logging

    shown = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        if shown:
            hf_logging.enable_progress_bar()


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


class Progress:
    """Stage lines for a count-based stage: a first line, one at most every ``every_s`` seconds with
    the count, rate and ETA, and a last line with the total time.

    ``semvpr: pseudo-labels: 120/402 images (3.1/s, 39 s elapsed, ETA 1.5 min)``
    """

    def __init__(
        self,
        stage: str,
        total: int,
        unit: str = "images",
        every_s: float = 30.0,
        stream: TextIO | None = None,
        done: int = 0,
    ) -> None:
        self.stage, self.total, self.unit, self.every_s = stage, int(total), unit, float(every_s)
        self.stream = stream
        self.start = time.monotonic()
        self.initial = self.count = int(done)
        self.last = self.start
        self._print(f"{self.count}/{self.total} {self.unit}" + (" (cached)" if done and done >= total else ""))

    def _print(self, text: str) -> None:
        say(f"{self.stage}: {text}", self.stream)

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units; print a line when ``every_s`` has passed since the last."""
        self.count += int(n)
        now = time.monotonic()
        if now - self.last >= self.every_s and self.count < self.total:
            self.last = now
            self._print(self.status(now))

    def status(self, now: float | None = None) -> str:
        """``count/total unit (rate, elapsed, ETA)`` at ``now``."""
        elapsed = (time.monotonic() if now is None else now) - self.start
        rate = (self.count - self.initial) / elapsed if elapsed > 0 else 0.0
        eta = (self.total - self.count) / rate if rate > 0 else float("nan")
        eta_text = _duration(eta) if eta == eta else "?"
        return f"{self.count}/{self.total} {self.unit} ({rate:.1f}/s, {_duration(elapsed)} elapsed, ETA {eta_text})"

    def close(self) -> None:
        """The last line: how many units in how long."""
        if self.count > self.initial or self.initial < self.total:
            self._print(f"{self.count}/{self.total} {self.unit} in {_duration(time.monotonic() - self.start)}")


def progress(
    items: Iterable[T], stage: str, total: int, unit: str = "images", every_s: float = 30.0, size: Any = None
) -> Iterator[T]:
    """Iterate ``items`` with stage lines; ``size(item)`` counts units per item (default 1)."""
    bar = Progress(stage, total, unit, every_s)
    for item in items:
        yield item
        bar.update(size(item) if size is not None else 1)
    bar.close()


class EpochLines(L.Callback):
    """Stage lines for a Lightning fit: what it will run, then one line per epoch (the logged metrics,
    elapsed time, ETA) and, inside an epoch, one at most every ``every_s`` seconds with the step.

    ``semvpr: teacher: 16 epochs of 92 steps``
    ``semvpr: teacher: epoch 1/16: step 40/92 (2.0 min elapsed, ETA 1.2 h)``
    ``semvpr: retriever: epoch 2/4: train/loss 0.231, val/R@1 31.2, val/R@5 52.0 (1.2 min elapsed, ETA 1.2 min)``
    """

    def __init__(
        self,
        stage: str,
        keys: tuple[str, ...] = ("train/loss", "val/R@1", "val/R@5"),
        stream: TextIO | None = None,
        every_s: float = 60.0,
    ) -> None:
        self.stage, self.keys, self.stream, self.every_s = stage, keys, stream, float(every_s)
        self.start = self.last = 0.0
        self.first_epoch = 0

    def _print(self, text: str) -> None:
        say(f"{self.stage}: {text}", self.stream)

    def _timing(self, now: float, done: float, total: float | None) -> str:
        """``elapsed[, ETA]`` after ``done`` of ``total`` units of work since the fit started."""
        elapsed = now - self.start
        eta = elapsed / done * (total - done) if total and done > 0 else None
        return f"{_duration(elapsed)} elapsed" + (f", ETA {_duration(eta)}" if eta is not None else "")

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.start = self.last = time.monotonic()
        self.first_epoch = trainer.current_epoch

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # After the loaders are set up: the step count is known.
        steps = trainer.num_training_batches
        if trainer.is_global_zero and trainer.max_epochs and trainer.max_epochs > 0 and 0 < steps < float("inf"):
            epochs = trainer.max_epochs - self.first_epoch
            self._print(f"{epochs} epoch{'s' if epochs != 1 else ''} of {int(steps)} step{'s' if steps != 1 else ''}")

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        now = time.monotonic()
        steps = trainer.num_training_batches
        if not trainer.is_global_zero or now - self.last < self.every_s or not 0 < steps < float("inf"):
            return
        if batch_idx + 1 >= steps:  # the epoch line follows
            return
        self.last = now
        epoch, total = trainer.current_epoch + 1, trainer.max_epochs
        done = (trainer.current_epoch - self.first_epoch) * steps + batch_idx + 1
        planned = (total - self.first_epoch) * steps if total and total > 0 else None
        self._print(
            f"epoch {epoch}/{total if total and total > 0 else '?'}: step {batch_idx + 1}/{int(steps)} "
            f"({self._timing(now, done, planned)})"
        )

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Runs after the epoch's validation, so val metrics of this epoch are in callback_metrics.
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        now = time.monotonic()
        self.last = now
        epoch, total = trainer.current_epoch + 1, trainer.max_epochs
        metrics = trainer.callback_metrics
        shown = ", ".join(f"{k} {float(metrics[k]):.3g}" for k in self.keys if k in metrics)
        planned = total - self.first_epoch if total and total > 0 else None
        self._print(
            f"epoch {epoch}/{total if total and total > 0 else '?'}"
            f"{': ' + shown if shown else ''} ({self._timing(now, epoch - self.first_epoch, planned)})"
        )


def trainer_kwargs(stage: str, callbacks: Iterable[L.Callback] = ()) -> dict[str, Any]:
    """Trainer arguments for a semvpr fit: no progress bar or model summary (both repeat in every job
    of a sweep), :class:`EpochLines` after ``callbacks``; the known noise hidden."""
    quiet_third_party()
    return {"enable_progress_bar": False, "enable_model_summary": False, "callbacks": [*callbacks, EpochLines(stage)]}
