"""How a run or a sweep stops early: a signal (scheduler pre-emption, ``kill``, Ctrl-C) or, in a sweep, a
job's worker process killed under the launcher ends it as :class:`Interrupted`, which the commands turn
into one line (and, for a sweep, its final report); it is never recorded as a job's failure.

A sweep's parent process (the one running Hydra's launcher) takes the signals too
(:func:`stop_on_signals`, from the report callbacks' ``on_multirun_start``): raised there, the launcher
abandons its jobs and ends its worker processes, so none is left running or writing after the line.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any


class Interrupted(BaseException):
    """A stop, not a failure: ``run_dir`` is the job it stopped, ``sweep_dir`` the sweep (None where not
    known)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.run_dir: Path | None = None
        self.sweep_dir: Path | None = None


#: The signals that stop a run or a sweep.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


#: The stop signals this process received: raised inside a library (a checkpoint being written, say), the
#: stop can surface as that library's own error, which must not be recorded as the job's failure.
RECEIVED: list[int] = []
#: The sweep this process launches (set when its parent installs the handlers), for a stop raised elsewhere.
SWEEP: list[Path] = []


def received_stop() -> Interrupted | None:
    """The stop this process received, if any, as the :class:`Interrupted` it raised (naming the sweep this
    process launches, if any)."""
    if not RECEIVED:
        return None
    stop = Interrupted(f"stopped by {signal.Signals(RECEIVED[-1]).name}")
    stop.sweep_dir = SWEEP[0] if SWEEP else None
    return stop


@contextmanager
def stop_over_errors() -> Iterator[None]:
    """Around a command's job: an error raised after a stop signal arrived is that stop. A signal to the
    command's process group also ends its data-loader workers, and torch's SIGCHLD handler then reports the
    dead worker (``RuntimeError: DataLoader worker ... is killed by signal: Terminated``) while the stop's
    :class:`Interrupted` unwinds, replacing it; a library that catches the stop (torch writing a file) raises
    its own error the same way."""
    try:
        yield
    except Exception:
        if (stop := received_stop()) is None:
            raise
        raise stop from None


def stop_on_signals(sweep_dir: Path | None = None) -> dict[int, Any]:
    """Make SIGTERM and SIGINT raise :class:`Interrupted` (naming ``sweep_dir``) in this process's main
    thread, forgetting the stops received before; returns the handlers they replace."""
    RECEIVED.clear()
    if sweep_dir is not None:
        SWEEP[:] = [sweep_dir]

    def interrupt(signum: int, _frame: object) -> None:
        RECEIVED.append(signum)
        if len(RECEIVED) > 1:  # the stop is under way: another signal must not break off its clean-up
            return
        stop = Interrupted(f"stopped by {signal.Signals(signum).name}")
        stop.sweep_dir = sweep_dir
        raise stop

    return {sig: signal.signal(sig, interrupt) for sig in STOP_SIGNALS}


def run_stoppable(
    main: Callable[[], None],
    argv: Sequence[str],
    line: Callable[[Interrupted], str] | None = None,
    handlers: bool = True,
) -> None:
    """Run a command's Hydra main with SIGTERM and SIGINT raising :class:`Interrupted` wherever they land, and a
    stop (a killed sweep worker too: :func:`killed_workers_stop`) printed as ``line(stop)`` (default: why it
    stopped) on stderr, exit code 2. ``handlers=False``: the command installs them itself (``semvpr.train``, per
    job in ``train.run_job``, as its job records and resume line need)."""
    if handlers:
        stop_on_signals()
    try:
        with killed_workers_stop(argv):
            main()
    except Interrupted as stop:  # one line, not the traceback of wherever the signal landed
        for sig in STOP_SIGNALS:  # more signals change nothing now: the stop is being finished
            signal.signal(sig, signal.SIG_IGN)
        end_descendants()
        print(line(stop) if line is not None else f"semvpr: error: {stop}", file=sys.stderr)
        raise SystemExit(2) from None


def _tracker(process: Any) -> bool:
    """Whether ``process`` is joblib's resource tracker: it runs no job, ends with this process, and ended
    before it, it is relaunched with a traceback."""
    try:
        return any("resource_tracker" in part for part in process.cmdline())
    except Exception:  # noqa: BLE001 - gone already, or not ours to read: nothing to spare
        return False


def end_descendants(grace_s: float = 5.0) -> None:
    """End every process this one started that is still running (a sweep's workers, their data-loader
    workers; not joblib's resource tracker: :func:`_tracker`): SIGTERM, then SIGKILL after ``grace_s`` for
    those still there, so none writes a result after the stop's line."""
    import psutil

    try:
        alive = [p for p in psutil.Process().children(recursive=True) if not _tracker(p)]
    except psutil.Error:
        return
    for process in alive:
        with suppress(psutil.Error):
            process.terminate()
    _, alive = psutil.wait_procs(alive, timeout=grace_s)
    for process in alive:
        with suppress(psutil.Error):
            process.kill()
    psutil.wait_procs(alive, timeout=grace_s)


@contextmanager
def lightning_stop() -> Iterator[None]:
    """Around a Lightning ``fit`` or ``test``: Lightning's own SIGTERM handler ends its loops with
    ``SIGTERMException``, a ``SystemExit`` of code None, so the process would exit 0 as if the job had finished
    (what a scheduler records); here it is the :class:`Interrupted` it is."""
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    try:
        yield
    except SIGTERMException:
        RECEIVED.append(signal.SIGTERM)
        raise received_stop() from None


def sweep_stopped_line(stop: Interrupted, write_report: Callable[[Path], Path], resume: str = "") -> str:
    """The one line of a stopped sweep (``stop.sweep_dir`` set): why, and where its report is, written now
    from what the jobs left (those that finished, those that did not, those that never started); ``resume``:
    how to go on with a stopped job."""
    assert stop.sweep_dir is not None
    try:
        where = f"its report, naming the jobs that did not finish or never started: {write_report(stop.sweep_dir)}"
    except Exception as err:  # noqa: BLE001 - the jobs' own files are the results; the line must still come
        where = f"its report was not written ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"
    return f"semvpr: error: {stop}; {where}{'; ' + resume if resume else ''}"


@contextmanager
def killed_workers_stop(argv: Sequence[str]) -> Iterator[None]:
    """Around a command's Hydra main: in a sweep (``-m``), a job's worker process killed under joblib (the
    out-of-memory killer, ``kill -9``) comes out of the launcher as ``TerminatedWorkerError``, which Hydra
    would print as a traceback; here it is raised (``HYDRA_FULL_ERROR``) and becomes :class:`Interrupted`
    naming the sweep, so the command gives its one line and the final report. Joblib cannot go on with the
    other jobs once one of its workers is gone."""
    if not {"-m", "--multirun"} & set(argv):
        yield
        return
    previous = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        yield
    except Exception as err:
        if type(err).__name__ != "TerminatedWorkerError" or not SWEEP:
            raise
        codes = str(err).rpartition("exit codes of the workers are ")[2].split("\n")[0].strip(" {}")
        stop = Interrupted(f"a job's worker process was killed ({codes or 'no exit code'}), so the sweep stopped")
        stop.sweep_dir = SWEEP[0]
        raise stop from None
    finally:
        if previous is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = previous
