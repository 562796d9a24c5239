"""What a job decides once from its config, before it builds anything: the device every stage runs on, the
threads of each stage, its DDP ranks, its mask source (:class:`MaskPlan`: the class, its node, the teacher's and
student's typed settings) and whether it needs the semantic side (teacher, pseudo-labels, student).
:func:`job_plan` makes it as the job starts; the builders read it instead of deciding again.

A job runs on one device (``core/device.py``): the CPU, or a GPU: a DDP rank's own (its local rank), the one
a sweep job leases (:func:`sweep_gpu`: a GPU per job where several are visible), else the first.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from semvpr.config.components import component_class
from semvpr.core.device import GPU_WORDS, GpuLease, resolve, visible_gpus
from semvpr.core.threads import JOBS_BESIDE, Threads, standard_start_method, usable_cores
from semvpr.models.masks import MaskSource
from semvpr.models.student import StudentSpec
from semvpr.models.teacher import TeacherSpec
from semvpr.retrieval.launch import local_rank


@dataclass(frozen=True)
class MaskPlan:
    """A config's mask source, looked up once (:func:`mask_plan`): its class (``source``, None without one), the
    node that builds it (``mask.module``), and the ``teacher``'s and ``student``'s settings, what a segmenter
    source is made from."""

    source: type[MaskSource] | None
    module: Any
    teacher: TeacherSpec
    student: StudentSpec

    @property
    def needs(self) -> str | None:
        """What the mask source is made from: ``teacher``, ``student``, ``labels`` (the oracle) or None."""
        return self.source.needs if self.source is not None else None


def mask_plan(cfg: DictConfig) -> MaskPlan:
    """The mask source ``cfg`` asks for (its ``mask``, ``teacher`` and ``student`` groups)."""
    return MaskPlan(component_class(cfg, "mask"), cfg.mask.get("module"), teacher_spec(cfg), student_spec(cfg))


@dataclass(frozen=True)
class JobPlan:
    """One job's decisions: ``device`` (every stage's), ``threads`` (each stage's, adopted for its frozen
    passes), ``ranks`` (DDP processes per node, nodes), ``masks`` (its mask source) and ``semantic`` (whether
    the aggregator's labelled init or the mask needs the teacher)."""

    device: torch.device
    threads: Threads
    ranks: tuple[int, int]
    masks: MaskPlan
    semantic: bool


def job_plan(cfg: DictConfig, device: torch.device | None = None) -> JobPlan:
    """The plan of a training job of ``cfg`` on ``device`` (default: :func:`job_device`'s)."""
    device = device if device is not None else job_device(cfg)
    masks = mask_plan(cfg)
    semantic = component_class(cfg, "aggregator").init_sample == "labelled" or masks.needs in ("teacher", "student")
    threads = thread_plan(cfg, gpu=device.type == "cuda")
    return JobPlan(device, threads, ranks_of(cfg.trainer), masks, semantic)


def student_spec(cfg: DictConfig) -> StudentSpec:
    """The student's settings (``cfg.student``)."""
    return StudentSpec.from_mapping(cfg.student)


def teacher_spec(cfg: DictConfig) -> TeacherSpec:
    """The teacher's settings (``cfg.teacher``)."""
    return TeacherSpec.from_mapping(cfg.teacher)


def ranks_of(trainer_cfg: DictConfig) -> tuple[int, int]:
    """(processes per node, nodes) of a job: trainer.devices (-1: all GPUs) and trainer.num_nodes
    under a DDP strategy; (1, 1) otherwise."""
    if not str(trainer_cfg.get("strategy", "auto")).startswith("ddp"):
        return 1, 1
    devices = int(trainer_cfg.devices)
    if devices == -1:  # Lightning's "all GPUs"
        devices = torch.cuda.device_count()
    return devices, int(trainer_cfg.get("num_nodes", 1))


def job_device(cfg: DictConfig, leased: int | None = None) -> torch.device:
    """The one device of a training job, from its trainer: the CPU, or a GPU: a DDP rank's own
    (:func:`local_rank`), a sweep job's leased one (``leased``), else the first."""
    accelerator = str(cfg.trainer.accelerator)
    if accelerator.lower() not in GPU_WORDS:
        return resolve("cpu")
    if ranks_of(cfg.trainer) != (1, 1):
        return resolve("cuda", local_rank())
    return resolve("cuda", leased)


@contextmanager
def sweep_gpu(cfg: DictConfig, run_dir: Path) -> Iterator[int | None]:
    """The GPU a one-GPU job of a sweep takes for its life where several are visible (``GpuLease`` in the
    sweep directory), so that the jobs a launcher runs side by side never share one; None elsewhere."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    gpus = visible_gpus()
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    gpu_job = str(cfg.trainer.accelerator).lower() in GPU_WORDS and ranks_of(cfg.trainer) == (1, 1)
    if not (multirun and gpu_job and len(gpus) > 1):
        yield None
        return
    with GpuLease(run_dir.parent / ".gpus", gpus) as lease:
        yield lease.index


def launcher_jobs() -> int:
    """How many jobs run side by side with this one: in a sweep, ``hydra.launcher.n_jobs`` under the joblib
    launcher (-1: one per core), else 1; 1 for a job run alone (its config names the sweep launcher all the
    same); for a DDP rank started by its job's rank 0, that job's count (:data:`JOBS_BESIDE`)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    beside = os.environ.get(JOBS_BESIDE, "")
    if beside.isdigit():
        return max(1, int(beside))
    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return 1
    launcher = HydraConfig.get().get("launcher") or {}
    if "joblib" not in str(launcher.get("_target_", "")).lower():
        return 1
    n = launcher.get("n_jobs")
    return usable_cores() if n in (None, -1) else max(1, int(n))


def thread_plan(cfg: DictConfig, gpu: bool | None = None) -> Threads:
    """The threads of this process (``threads``: auto or a number; semvpr.core.threads), given the job's DDP
    ranks on this node and the jobs its launcher runs beside it, and whether its networks run on a GPU
    (``gpu``; by default its trainer's accelerator), adopted as the running job's plan; every command calls
    it (or :func:`job_plan`) as its job starts."""
    ranks = ranks_of(cfg.trainer)[0] if "trainer" in cfg else 1
    if gpu is None:
        gpu = "trainer" in cfg and str(cfg.trainer.accelerator).lower() in GPU_WORDS
    standard_start_method()  # a job in a joblib worker: data loaders need a standard start method
    return Threads.resolve(cfg.get("threads", "auto"), ranks, launcher_jobs(), gpu=gpu).adopt()
