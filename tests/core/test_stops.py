"""Stops: a signal Lightning catches during fit is the stop it is, not a finished process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from semvpr.core import stops
from tests.helpers import REPO


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
        executor.submit(os.getpid).result(timeout=600)
        (worker,) = executor._processes.values()

        def killed_pgrep(*args: object, **kwargs: object) -> bytes:
            raise subprocess.CalledProcessError(-signal.SIGTERM, ["pgrep", "-P", str(worker.pid)])

        monkeypatch.setattr(utils.subprocess, "check_output", killed_pgrep)
        utils.kill_process_tree(worker)
        # Killed, the worker is gone within moments (is_alive can still say True just after loky's join).
        deadline = time.monotonic() + 30
        while worker.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not worker.is_alive()
    finally:
        executor.shutdown(wait=False, kill_workers=True)


#: A job whose stop signal comes out as a library's error, as torch's SIGCHLD handler turns it when the same
#: signal to the process group ended a data-loader worker.
_STOPPED_AS_AN_ERROR = """
import os, signal, time

def stopped_as_an_error(*_args, **_kwargs):
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
    except BaseException as err:
        raise RuntimeError("DataLoader worker (pid 1) is killed by signal: Terminated.") from err
    raise AssertionError("SIGTERM was ignored")
"""


def _run_script(body: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1"}
    code = _STOPPED_AS_AN_ERROR + textwrap.dedent(body)
    return subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )


def test_a_stop_that_surfaces_as_a_librarys_error_is_the_commands_one_line(tmp_path: Path) -> None:
    """segment, localize and eval: a signal whose Interrupted a library's error replaced (a DataLoader worker
    killed by the same SIGTERM) is still the stop: one line, exit 2, no traceback."""
    proc = _run_script(
        f"""
        import sys
        from semvpr.config.command import hydra_command
        from semvpr.core.stops import run_stoppable

        task = hydra_command("localize", "localize.json")(stopped_as_an_error)
        sys.argv[1:] = ["hydra.run.dir={tmp_path / "run"}"]
        run_stoppable(task, sys.argv[1:])
        """,
        tmp_path,
    )
    assert proc.returncode == 2 and proc.stderr == "semvpr: error: stopped by SIGTERM\n", proc.stderr[-3000:]


def test_an_eval_sweep_stopped_through_a_librarys_error_is_stopped_not_a_failed_job(tmp_path: Path) -> None:
    """In an eval sweep the same stop ends the sweep with its table, instead of being the job's failed row."""
    sweep = tmp_path / "sweep"
    proc = _run_script(
        f"""
        import sys
        from semvpr import eval as command

        command.evaluate_checkpoint = stopped_as_an_error
        sys.argv[1:] = ["-m", "hydra/launcher=basic", "ckpt=none", "data=synthcity,synthcity",
                        "hydra.sweep.dir={sweep}"]
        command.main()
        """,
        tmp_path,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and lines[-1].startswith("semvpr: error: stopped by SIGTERM; "), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "job failed" not in proc.stderr
    assert not list(sweep.glob("*/eval.json"))  # no job recorded as failed with the library's error
