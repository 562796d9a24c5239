"""The device a job runs on, chosen once, and the GPU a sweep job takes.

Every stage of a job (trunk pass, teacher, pseudo-labels, student, k-means sample, evaluation, whitening,
mining distances) runs on the device of the job's backbone, which is built there: ``resolve`` turns the
config's words into that device once, and the builders move every network onto it.

A sweep on a machine with GPUs runs ``jobs_per_gpu`` jobs per GPU at a time (``sweep_jobs``; small jobs
that leave a GPU idle can share it), and each job takes a slot of a GPU no other job holds (``GpuLease``: an
exclusive lock per slot in the sweep directory, named by host, held for the job's life), slots taken GPU
by GPU before any GPU gets a second job, so jobs never stack on ``cuda:0``.
"""

from __future__ import annotations

import fcntl
import os
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from semvpr.core.errors import SemvprError
from semvpr.core.io import open_lock

#: Accelerator names that mean a CUDA GPU (Lightning's and torch's words).
GPU_WORDS = ("gpu", "cuda")


def resolve(word: str | None, index: int | None = None) -> torch.device:
    """The device a setting names: ``cpu``, ``gpu`` / ``cuda`` (GPU ``index``, else the current one),
    ``cuda:N``, or ``auto`` / None (the first GPU where one is visible, else the CPU). A GPU asked for where
    none is visible is one line."""
    text = "auto" if word is None else str(word).lower()
    if text == "cpu":
        return torch.device("cpu")
    if text == "auto":
        return resolve("cuda", index) if torch.cuda.is_available() else torch.device("cpu")
    if text in GPU_WORDS or text.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise SemvprError(f"{word} asks for a CUDA GPU and none is visible here; use cpu (trainer=cpu, device=cpu)")
        if text.startswith("cuda:"):
            if not text.partition(":")[2].isdecimal():
                raise SemvprError(f"device={word!r} must be auto, cpu, cuda or cuda:N")
            index = int(text.partition(":")[2])
        index = torch.cuda.current_device() if index is None else index
        if not 0 <= index < torch.cuda.device_count():
            raise SemvprError(f"{word}: GPU {index} is not one of the {torch.cuda.device_count()} visible here")
        return torch.device("cuda", index)
    raise SemvprError(f"device={word!r} must be auto, cpu, cuda or cuda:N")


def visible_gpus() -> list[int]:
    """The indices of the GPUs this process sees (``CUDA_VISIBLE_DEVICES`` already applied by CUDA)."""
    return list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []


def sweep_jobs(
    accelerator: str, devices: object, cpu_jobs: int, gpus: Sequence[int] | None = None, per_gpu: int = 1
) -> int:
    """How many jobs of a sweep run side by side: ``cpu_jobs`` on the CPU; on GPUs ``per_gpu`` jobs per
    visible GPU for one-device jobs, and one job at a time for a job that takes several (DDP over the GPUs)."""
    if str(accelerator).lower() not in GPU_WORDS:
        return cpu_jobs
    found = len(visible_gpus() if gpus is None else gpus)
    if devices != 1:
        return 1
    return max(1, found) * per_gpu


@dataclass
class GpuLease:
    """A slot of a GPU of ``gpus`` that no other job holds, taken for as long as the lease is open.

    Each GPU has ``slots`` lock files, ``<folder>/<host>-gpu<N>.lock`` and ``...-gpu<N>-slot<K>.lock`` for
    K >= 1; a job takes the first it can lock without waiting, slot 0 of every GPU before slot 1 of any, or
    waits on the first one when all are held (a sweep never runs more jobs than slots, so this happens only
    beside another sweep). The lock goes with the process, so a killed job frees its slot."""

    folder: Path
    gpus: Sequence[int]
    slots: int = 1
    index: int | None = None
    _handle: int | None = None

    def __enter__(self) -> GpuLease:
        self.folder.mkdir(parents=True, exist_ok=True)
        host = socket.gethostname().replace(os.sep, "_")
        slots = [(gpu, slot) for slot in range(self.slots) for gpu in self.gpus]
        for wait in (False, True):
            for gpu, slot in slots:
                fd = open_lock(self.folder / f"{host}-gpu{gpu}{f'-slot{slot}' if slot else ''}.lock")
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
                except BlockingIOError:
                    os.close(fd)
                    continue
                except OSError as err:
                    os.close(fd)
                    raise SemvprError(
                        f"{self.folder} cannot hold the sweep's GPU locks ({err.strerror}): a file system without "
                        "flock; run the sweep's directory (hydra.sweep.dir) on a local or flock-capable disk"
                    ) from None
                self.index, self._handle = gpu, fd
                return self
        raise SemvprError("no GPU to lease")  # unreachable with a non-empty list: the second pass waits

    def __exit__(self, *exc: object) -> None:
        if self._handle is not None:
            os.close(self._handle)
            self._handle = None
