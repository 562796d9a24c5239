"""semvpr's stage lines and the hiding of known third-party noise."""

from __future__ import annotations

import io
import logging
import re
import warnings
from types import SimpleNamespace

import pytest

from semvpr.core import logs


def test_progress_lines_have_count_rate_and_eta(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = iter([0.0, 10.0, 20.0, 40.0, 100.0])
    monkeypatch.setattr(logs.time, "monotonic", lambda: next(clock))
    out = io.StringIO()
    bar = logs.Progress("pseudo-labels", 100, every_s=15, stream=out)  # start: t=0
    bar.update(10)  # t=10: under every_s, no line
    bar.update(10)  # t=20: 20 images in 20 s -> 1.0/s, 80 left -> ETA 80 s
    bar.update(20)  # t=40: 40 in 40 s, 20 s since the last line -> a line, ETA 60 s
    bar.close()  # t=100
    lines = out.getvalue().splitlines()
    assert lines == [
        "semvpr: pseudo-labels: 0/100 images",
        "semvpr: pseudo-labels: 20/100 images (1.0/s, 20 s elapsed, ETA 80 s)",
        "semvpr: pseudo-labels: 40/100 images (1.0/s, 40 s elapsed, ETA 60 s)",
        "semvpr: pseudo-labels: 40/100 images in 1.7 min",
    ]


def test_progress_says_when_everything_was_cached() -> None:
    out = io.StringIO()
    bar = logs.Progress("trunk features", 5, done=5, stream=out)
    bar.close()
    assert out.getvalue().splitlines() == ["semvpr: trunk features: 5/5 images (cached)"]


def test_lines_inside_a_sweep_job_name_it_and_a_long_name_keeps_both_ends() -> None:
    out = io.StringIO()
    long_name = "ckpt=outputs%2Fmultiruns%2F2026-01-01%2F10-00-00%2Ffilter=unet%2Fckpt.ckpt,mask=student"
    with logs.job_named(logs.job_label(2, "filter=unet")):
        logs.Progress("pseudo-labels", 3, stream=out).close()
        with logs.job_named(logs.job_label(11, long_name)):
            logs.say("cache: waited 3 s", out)
        logs.say("warning: one", out)
    logs.say("outside", out)
    assert out.getvalue().splitlines() == [
        "semvpr: [#2 filter=unet] pseudo-labels: 0/3 images",
        "semvpr: [#2 filter=unet] pseudo-labels: 0/3 images in 0 s",
        "semvpr: [#11 ckpt=outputs%2Fmultiru...Fckpt.ckpt,mask=student] cache: waited 3 s",
        "semvpr: [#2 filter=unet] warning: one",
        "semvpr: outside",
    ]
    assert len(logs.job_label(11, long_name)) == len("#11 ") + logs.MAX_JOB_NAME


def test_epoch_lines_show_metrics_and_eta(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = iter([0.0, 30.0])
    monkeypatch.setattr(logs.time, "monotonic", lambda: next(clock))
    out = io.StringIO()
    cb = logs.EpochLines("retriever", stream=out)
    trainer = SimpleNamespace(
        current_epoch=0,
        max_epochs=4,
        sanity_checking=False,
        is_global_zero=True,
        callback_metrics={"train/loss": 0.25, "val/R@1": 31.25},
    )
    cb.on_fit_start(trainer, None)  # type: ignore[arg-type]
    cb.on_train_epoch_end(trainer, None)  # type: ignore[arg-type]
    assert out.getvalue().strip() == (
        "semvpr: retriever: epoch 1/4: train/loss 0.25, val/R@1 31.2 (30 s elapsed, ETA 1.5 min)"
    )


def test_long_epochs_get_step_lines_with_an_eta(monkeypatch: pytest.MonkeyPatch) -> None:
    # fit start t=0; steps end at t=30 (under every_s), 70 (a line), 100 (under every_s since 70), 140 (the
    # epoch's last step: the epoch line follows instead), epoch end t=150; epoch 2's first step t=215.
    clock = iter([0.0, 30.0, 70.0, 100.0, 140.0, 150.0, 215.0])
    monkeypatch.setattr(logs.time, "monotonic", lambda: next(clock))
    out = io.StringIO()
    cb = logs.EpochLines("teacher", stream=out, every_s=60)
    trainer = SimpleNamespace(
        current_epoch=0,
        max_epochs=3,
        num_training_batches=4,
        sanity_checking=False,
        is_global_zero=True,
        callback_metrics={},
    )
    cb.on_fit_start(trainer, None)  # type: ignore[arg-type]
    cb.on_train_start(trainer, None)  # type: ignore[arg-type]
    for step in range(4):
        cb.on_train_batch_end(trainer, None, None, None, step)  # type: ignore[arg-type]
    cb.on_train_epoch_end(trainer, None)  # type: ignore[arg-type]
    trainer.current_epoch = 1
    cb.on_train_batch_end(trainer, None, None, None, 0)  # type: ignore[arg-type]
    assert out.getvalue().splitlines() == [
        "semvpr: teacher: 3 epochs of 4 steps",
        # 2 of 12 steps in 70 s: 10 left at 35 s each
        "semvpr: teacher: epoch 1/3: step 2/4 (70 s elapsed, ETA 5.8 min)",
        "semvpr: teacher: epoch 1/3 (2.5 min elapsed, ETA 5.0 min)",
        # 5 of 12 steps in 215 s: 7 left at 43 s each
        "semvpr: teacher: epoch 2/3: step 1/4 (3.6 min elapsed, ETA 5.0 min)",
    ]


def test_known_noise_is_hidden_and_the_rest_kept(caplog: pytest.LogCaptureFixture) -> None:
    logs.quiet_third_party()
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    with caplog.at_level(logging.INFO, logger="lightning.pytorch.utilities.rank_zero"):
        logger.info("💡 Tip: For seamless cloud logging and experiment tracking, try installing litlogger")
        logger.info("GPU available: False, used: False")
        logger.info("Something the user should see")
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["Something the user should see"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        logs.quiet_third_party()  # filters go in front of the "default" one
        warnings.warn("Found 38 module(s) in eval mode at the start of training.", UserWarning, stacklevel=1)
        warnings.warn("a real problem", UserWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["a real problem"]


def test_a_trainer_built_with_trainer_kwargs_prints_only_stage_lines(
    tmp_path, capfd: pytest.CaptureFixture[str]
) -> None:
    import lightning as L
    import torch
    from torch.utils.data import DataLoader, TensorDataset

    class Tiny(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.lin = torch.nn.Linear(2, 1)

        def training_step(self, batch, _):  # type: ignore[no-untyped-def]
            loss = self.lin(batch[0]).pow(2).mean()
            self.log("train/loss", loss)
            return loss

        def configure_optimizers(self):  # type: ignore[no-untyped-def]
            return torch.optim.SGD(self.parameters(), lr=0.1)

    data = DataLoader(TensorDataset(torch.randn(8, 2)), batch_size=4)
    trainer = L.Trainer(
        max_epochs=2,
        logger=False,
        enable_checkpointing=False,
        default_root_dir=tmp_path,
        accelerator="cpu",
        **logs.trainer_kwargs("tiny"),
    )
    trainer.fit(Tiny(), data)
    captured = capfd.readouterr()
    lines = [line for line in (captured.out + captured.err).splitlines() if line.strip()]
    assert lines[0] == "semvpr: tiny: 2 epochs of 2 steps", lines
    assert len(lines) == 3 and all(re.match(r"semvpr: tiny: epoch [12]/2: train/loss ", line) for line in lines[1:]), (
        lines
    )


def test_saving_and_loading_a_teacher_print_no_transformers_progress_bar(
    tmp_path, capfd: pytest.CaptureFixture[str]
) -> None:
    from transformers.utils import logging as hf_logging

    from semvpr.models.teacher_folder import load_pretrained
    from tests.helpers import write_teacher_dir

    capfd.readouterr()
    folder = write_teacher_dir(tmp_path / "teacher")  # saved by semvpr.segment's save_teacher
    load_pretrained(str(folder))
    captured = capfd.readouterr()
    assert "Writing model shards" not in captured.err + captured.out, captured.err
    assert "Loading weights" not in captured.err + captured.out, captured.err
    assert hf_logging.is_progress_bar_enabled()  # restored for whatever else the process loads


def test_building_a_teacher_on_a_timm_backbone_prints_nothing() -> None:
    """transformers notes that Mask2Former's backbone is not Swin whenever its config is built on a timm
    backbone; building the teacher (in a fresh process, from any script, not only the entry points) hides it."""
    import subprocess
    import sys

    code = (
        "from semvpr.models.teacher import embedded_model\n"
        "embedded_model({'backbone': 'efficientnet_lite0', 'backbone_weights': 'none', 'hidden_dim': 32,"
        " 'num_attention_heads': 2, 'encoder_layers': 1, 'decoder_layers': 1, 'num_queries': 4,"
        " 'train_num_points': 64})\n"
        "print('built')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True)
    assert done.stdout.strip() == "built"
    assert "not a supported model" not in done.stderr, done.stderr
