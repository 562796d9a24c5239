"""The ranks of a data-parallel job (``trainer=ddp``): who starts them and when they stop.

- Under a scheduler that starts one task per device (SLURM via hydra-submitit-launcher with
  ``tasks_per_node`` = ``trainer.devices``, or ``torchrun``), the ranks exist already: Lightning's
  cluster environment reads them. ``hydra/launcher=submitit_local`` starts the tasks without SLURM's
  variables; :func:`job_ranks` sets Lightning's (``LOCAL_RANK``, ``NODE_RANK``, ``WORLD_SIZE``,
  ``MASTER_ADDR``, ``MASTER_PORT``) from submitit's job environment.
- Otherwise this process is rank 0 and starts the others for this one job: ``python -m semvpr.train``
  with the job's own overrides (never the sweep's ``-m``) in the job's run directory. Lightning would
  relaunch ``sys.argv`` instead, which re-runs a whole sweep in every rank.

When the job ends the process group is destroyed and the variables are restored, so that the next
job of a sweep starts afresh.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch.distributed as dist

from semvpr.core.errors import SemvprError

_RANK_VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE")
CHILD_TIMEOUT_S = 600  # how long rank 0 waits for the other ranks to exit after its own job ended


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


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _child_command(overrides: list[str], run_dir: Path, rank: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "semvpr.train",
        *overrides,
        f'hydra.run.dir="{run_dir}"',
        "hydra.output_subdir=null",
        f"hydra.job.name=ddp_rank{rank}",
        "hydra/job_logging=stdout",
    ]


@contextmanager
def job_ranks(devices: int, num_nodes: int, overrides: list[str], run_dir: Path) -> Iterator[None]:
    """Make the ranks of one job exist for its duration (module docstring); a no-op for one process."""
    world_size = devices * num_nodes
    saved = {key: os.environ.get(key) for key in _RANK_VARIABLES}
    children: list[subprocess.Popen] = []
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
                children = [
                    subprocess.Popen(
                        _child_command(overrides, run_dir, rank), env={**os.environ, "LOCAL_RANK": str(rank)}
                    )
                    for rank in range(1, world_size)
                ]
        yield
    except BaseException:
        for child in children:
            child.terminate()
        for child in children:
            child.wait()
        raise
    finally:
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
