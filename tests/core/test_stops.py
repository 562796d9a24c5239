"""Stops: a signal Lightning catches during fit is the stop it is, not a finished process."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from semvpr.core import stops


class _Line(L.LightningModule):
    def __init__(self) -> None:
        super().__init__()
        self.w = torch.nn.Linear(2, 1)

    def training_step(self, batch: tuple[torch.Tensor], _: int) -> torch.Tensor:
        return self.w(batch[0]).pow(2).mean()

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)


class _SigtermAtStep(L.Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer: L.Trainer, *_: object) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


def test_a_sigterm_lightning_catches_in_fit_is_a_stop_not_exit_0(tmp_path: Path) -> None:
    """Lightning's own SIGTERM handler ends fit with SIGTERMException, a SystemExit of code None: the process
    would exit 0 as if the job had finished (the teacher's training under semvpr.segment did)."""
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(64, 2)), batch_size=4)
    trainer = L.Trainer(
        max_epochs=50,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
        callbacks=[_SigtermAtStep(3)],
    )
    before = signal.getsignal(signal.SIGTERM)
    stops.RECEIVED.clear()
    try:
        with pytest.raises(stops.Interrupted, match="^stopped by SIGTERM$"), stops.lightning_stop():
            trainer.fit(_Line(), data)
    finally:
        signal.signal(signal.SIGTERM, before)
    assert trainer.global_step < 10 and trainer.interrupted
    assert str(stops.received_stop()) == "stopped by SIGTERM"
    stops.RECEIVED.clear()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_command_stopped_anywhere_is_one_line_and_exit_2(sig: signal.Signals, capsys: pytest.CaptureFixture) -> None:
    """eval, localize and segment: a signal landing anywhere (here in a sleep) is one line, exit 2, not
    Python's KeyboardInterrupt traceback or a silent 143; the handlers are the command's for its whole run."""

    def command() -> None:
        os.kill(os.getpid(), sig)
        time.sleep(5)
        raise AssertionError("the signal was ignored")

    before = {s: signal.getsignal(s) for s in stops.STOP_SIGNALS}
    try:
        with pytest.raises(SystemExit) as stopped:
            stops.run_stoppable(command, ["experiment=tiny"])
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
    assert stopped.value.code == 2
    assert capsys.readouterr().err == f"semvpr: error: stopped by {sig.name}\n"
    stops.RECEIVED.clear()


def test_a_sweeps_worker_is_ended_even_when_a_second_signal_kills_a_helper(monkeypatch: pytest.MonkeyPatch) -> None:
    """joblib's loky ends a stopped sweep's workers. Without psutil it asks `pgrep` for their children; a second
    signal to the process group (a scheduler's, a second Ctrl-C) killed pgrep, loky's fallback called a kill() its
    Popen lacks, its manager thread died, the worker ran on and the sweep never exited."""
    import subprocess

    from joblib.externals.loky import ProcessPoolExecutor
    from joblib.externals.loky.backend import utils

    executor = ProcessPoolExecutor(max_workers=1)
    try:
        executor.submit(os.getpid).result(timeout=60)
        (worker,) = executor._processes.values()

        def killed_pgrep(*args: object, **kwargs: object) -> bytes:
            raise subprocess.CalledProcessError(-signal.SIGTERM, ["pgrep", "-P", str(worker.pid)])

        monkeypatch.setattr(utils.subprocess, "check_output", killed_pgrep)
        utils.kill_process_tree(worker)
        assert not worker.is_alive()
    finally:
        executor.shutdown(wait=False, kill_workers=True)
