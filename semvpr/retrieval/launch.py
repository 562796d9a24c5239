"""The ranks of a data-parallel job (``trainer=ddp``): who starts them and when they stop.

- Under a scheduler that starts one task per device (SLURM via hydra-submitit-launcher with
  ``tasks_per_node`` = ``trainer.devices``, or ``torchrun``), the ranks exist already: Lightning's
  cluster environment reads them. ``hydra/launcher=submitit_local`` starts the tasks without SLURM's
  variables; :func:`job_ranks` sets Lightning's (``LOCAL_RANK``, ``NODE_RANK``, ``WORLD_SIZE``,
  ``MASTER_ADDR``, ``MASTER_PORT``) from submitit's job environment.
- Otherwise this process is rank 0 and starts the others for this one job: ``python -m semvpr.train``
  with the job's own overrides (never the sweep's ``-m``) in the job's run directory. Lightning would
  relaunch ``sys.argv`` instead, which re-runs a whole sweep in every rank.

The ranks this process starts check in with it (a local socket) just before ``fit`` (the ``join`` that
:func:`job_ranks` yields), and wait there for its word to go. Rank 0 does its own work before ``fit`` (the
aggregator's initialisation, the untrained evaluation) while they read their caches and build their model,
then waits for their check-in at its own ``join``, in Python, watching them, and tells them to go: a rank
that exits first (a bad command line, a crash while reading its caches) ends the job at once with one line;
SIGTERM / Ctrl-C stop it; a rank 0 that ends first ends the waiting ranks with one line. Nobody waits in the
process group's rendezvous, which would ignore signals until its timeout, except ranks a scheduler started
(they wait there for rank 0's work before ``fit``: the strategy's timeout covers it).

When the job ends the process group is destroyed and the variables are restored, so that the next
job of a sweep starts afresh.
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import torch.distributed as dist

from semvpr.core.errors import SemvprError
from semvpr.core.threads import JOBS_BESIDE

_RANK_VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE")
CHILD_TIMEOUT_S = 600  # how long rank 0 waits for the other ranks to exit after its own job ended
#: The port of rank 0's check-in socket, for the ranks it starts.
CHECK_IN = "SEMVPR_DDP_CHECK_IN"
#: What rank 0 sends the ranks it started once it is ready to train.
GO = b"go"


def _submitit_ranks(devices: int) -> dict[str, str] | None:
    """Lightning's rank variables from submitit's job environment outside SLURM (submitit_local)."""
    if "SUBMITIT_EXECUTOR" not in os.environ or "SLURM_PROCID" in os.environ:
        return None
    import submitit

    env = submitit.JobEnvironment()
    if env.num_tasks != devices * env.num_nodes:
        raise SemvprError(
            f"trainer=ddp under submitit needs hydra.launcher.tasks_per_node={devices} "
            f"(= trainer.devices), got {env.num_tasks // env.num_nodes} task(s) per node"
        )
    port = 20000 + int("".join(c for c in str(env.job_id) if c.isdigit()) or 0) % 20000
    return {
        "MASTER_ADDR": env.hostnames[0],
        "MASTER_PORT": str(port),
        "NODE_RANK": str(env.node),
        "LOCAL_RANK": str(env.local_rank),
        "WORLD_SIZE": str(env.num_tasks),
    }


def launched_rank() -> int:
    """This process's global rank as its launcher set it (0 where nothing did: the launching process)."""
    for key in ("SLURM_PROCID", "RANK"):
        if key in os.environ:
            return int(os.environ[key])
    if "SUBMITIT_EXECUTOR" in os.environ:
        import submitit

        return int(submitit.JobEnvironment().global_rank)
    return int(os.environ.get("LOCAL_RANK", 0))


def local_rank() -> int:
    """This process's rank on its node as its launcher set it (semvpr's own ranks, torchrun, SLURM, submitit),
    0 where nothing did (the launching process): the GPU a DDP rank takes."""
    for key in ("LOCAL_RANK", "SLURM_LOCALID"):
        if key in os.environ:
            return int(os.environ[key])
    if "SUBMITIT_EXECUTOR" in os.environ:
        import submitit

        return int(submitit.JobEnvironment().local_rank)
    return 0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def hydra_quoted(value: str) -> str:
    """``value`` as a single-quoted Hydra override value that parses back to exactly ``value`` (quotes
    escaped, and the backslashes Hydra would read as escapes: those before a quote or at the end)."""
    body = re.sub(r"(\\+)(?='|$)", lambda m: m.group(1) * 2, value).replace("'", "\\'")
    return f"'{body}'"


def _child_command(overrides: list[str], run_dir: Path, rank: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "semvpr.train",
        *overrides,
        f"hydra.run.dir={hydra_quoted(str(run_dir))}",
        "hydra.output_subdir=null",
        f"hydra.job.name=ddp_rank{rank}",
        "hydra/job_logging=stdout",
    ]


def await_ranks(listener: socket.socket, children: list[subprocess.Popen], poll_s: float = 0.5) -> list[socket.socket]:
    """Wait until every started rank (``children``: ranks 1..n) has checked in on ``listener``; a rank
    that exits before is one line. The wait returns to Python every ``poll_s``, so signals are handled.
    Returns the ranks' open connections: each waits on its own until :func:`release_ranks` tells it to go."""
    pending = set(range(1, len(children) + 1))
    joined: list[socket.socket] = []
    try:
        while pending:
            for rank, child in enumerate(children, start=1):
                code = child.poll()
                if rank in pending and code is not None:
                    raise SemvprError(
                        f"rank {rank} of the DDP job exited (code {code}) before joining it; its output above says why"
                    )
            ready, _, _ = select.select([listener], [], [], poll_s)
            if ready:
                conn, _ = listener.accept()
                conn.settimeout(5)
                try:
                    pending.discard(int(conn.recv(16).decode() or -1))
                except (OSError, ValueError):
                    conn.close()
                    continue
                joined.append(conn)
    except BaseException:
        for conn in joined:
            conn.close()
        raise
    return joined


def release_ranks(joined: list[socket.socket]) -> None:
    """Tell the ranks waiting on ``joined`` (:func:`await_ranks`) to start training."""
    for conn in joined:
        with conn, contextlib.suppress(OSError):  # a rank that is gone: its exit code ends the job
            conn.sendall(GO)


def _check_in() -> None:
    """Tell the rank-0 process that started this rank that it is about to train, and wait until rank 0
    is too (its own work before ``fit`` done): in Python, not in the process group's rendezvous. A no-op
    in a rank it did not start, and after the first call."""
    port = os.environ.pop(CHECK_IN, None)
    if port is None:
        return
    word = b""
    try:
        with socket.create_connection(("127.0.0.1", int(port)), timeout=30) as conn:
            conn.sendall(os.environ.get("LOCAL_RANK", "0").encode())
            conn.settimeout(None)
            while len(word) < len(GO) and (part := conn.recv(len(GO) - len(word))):
                word += part
    except OSError:
        pass  # rank 0 is gone (refused or reset): the line below
    if word != GO:
        raise SemvprError("rank 0 of the DDP job ended before training began; its output says why")


@contextmanager
def job_ranks(
    devices: int, num_nodes: int, overrides: list[str], run_dir: Path, jobs_beside: int = 1
) -> Iterator[Callable[[], None]]:
    """Make the ranks of one job exist for its duration (module docstring); a no-op for one process. The ranks
    it starts share the cores as this job does, with ``jobs_beside`` jobs side by side (:data:`JOBS_BESIDE`).

    Yields ``join``, which every rank calls just before ``fit``: rank 0 waits there until the ranks it started
    have checked in and tells them to go; a rank it started checks in there and waits for that word (a no-op
    elsewhere, and after the first call); the block's end joins them if it did not."""
    world_size = devices * num_nodes
    saved = {key: os.environ.get(key) for key in _RANK_VARIABLES}
    children: list[subprocess.Popen] = []
    listener: socket.socket | None = None

    def join() -> None:
        nonlocal listener
        if listener is None:
            _check_in()
            return
        try:
            release_ranks(await_ranks(listener, children))
        finally:
            listener.close()
            listener = None

    externally = "LOCAL_RANK" in os.environ or "SLURM_PROCID" in os.environ
    try:
        if world_size > 1 and not externally:
            found = _submitit_ranks(devices)
            if found is not None:
                os.environ.update(found)
            elif num_nodes > 1:
                raise SemvprError(
                    "trainer.num_nodes > 1 needs a scheduler that starts one task per device "
                    "(SLURM with hydra.launcher.tasks_per_node=trainer.devices, or torchrun)"
                )
            else:
                os.environ.update(
                    {
                        "MASTER_ADDR": "127.0.0.1",
                        "MASTER_PORT": str(_free_port()),
                        "NODE_RANK": "0",
                        "WORLD_SIZE": str(world_size),
                        "LOCAL_RANK": "0",
                    }
                )
                listener = socket.create_server(("127.0.0.1", 0))
                env = {**os.environ, CHECK_IN: str(listener.getsockname()[1]), JOBS_BESIDE: str(jobs_beside)}
                children = [
                    subprocess.Popen(_child_command(overrides, run_dir, rank), env={**env, "LOCAL_RANK": str(rank)})
                    for rank in range(1, world_size)
                ]
        yield join
        join()
    except BaseException:
        for child in children:
            child.terminate()
        for child in children:
            child.wait()
        raise
    finally:
        if listener is not None:
            listener.close()
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    failed = [child.args for child in children if child.wait(timeout=CHILD_TIMEOUT_S) != 0]
    if failed:
        raise SemvprError(f"{len(failed)} of the job's other ranks failed (see their output above)")
