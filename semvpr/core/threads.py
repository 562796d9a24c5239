"""How many threads each stage of a job runs: one ``threads`` setting (``auto`` or a whole number).

A job may use the cores of its CPU affinity (``os.sched_getaffinity``), shared with the other processes it
starts (DDP ranks on the node) and with the jobs a launcher runs beside it (in a sweep, Hydra's joblib
launcher's ``hydra.launcher.n_jobs``; a job run alone has none beside it): each process gets
``cores // (ranks x jobs)`` (at least 1), its *share*.

- ``threads=N``: the job's N threads split the same way (``N // (ranks x jobs)``), never over the share.
- ``threads=auto`` (the default): each stage takes what it was measured to gain from, within the share:
  passes of conv networks over batches of images (the frozen trunk, the teacher's and the student's inference,
  training the teacher and the student) take the whole share; the retriever's training and evaluation on
  cached features, small steps of a few tuples each, take 1 thread (two threads measured no faster, and
  twice as slow beside another job). A job whose networks run on a GPU gives every stage its whole share:
  what stays on the CPU there is data loading and k-means, not small steps. An ``OMP_NUM_THREADS`` set in the
  environment caps ``auto``.

Data-loader workers decode images single-threaded (torch's default in a worker). A loader that feeds a GPU
starts at most ``share`` of them; one that feeds a CPU stage at most the cores the stage's threads leave free
(none under ``auto``, which gives a frozen pass the whole share): a worker beside busy compute threads only
takes turns with them, and forking it write-protects the job's whole heap, so that every page the job writes
next faults (in one pair of cold default jobs on 2 cores, starting none left about a quarter of the page
faults, with the same recalls and no slower).

A job that Hydra's joblib launcher runs lives in a loky worker, whose default start method (``loky``) a
data loader cannot start its workers with; :func:`standard_start_method` gives such a job the platform's
standard one before its first loader.

The frozen passes (trunk, masks, pseudo-labels) give other bits at other thread counts wherever the
arithmetic splits a reduction by thread (fp32 convolutions on every CPU measured; bf16 ones were invariant
on the AVX512-BF16 CPUs measured), and the same bits at any batch size. So a job runs every frozen pass at
one count, its plan's ``frozen`` stage (:func:`frozen_pass`, also where images stream through the trunk
inside the retriever's one-thread steps), and the caches of CPU passes are keyed by that count
(:func:`frozen_threads`, read by ``precision.compute_key``): a cache holds what this job's settings compute.

Threads that wait must not spin: OpenMP's wait policy is passive (``semvpr/__init__.py`` sets
``OMP_WAIT_POLICY=PASSIVE`` before torch loads libgomp), so a thread blocked at a barrier sleeps instead of
taking a core from the job beside it.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from semvpr.core.errors import SemvprError

#: The running job's plan, once adopted (:meth:`Threads.adopt`): its frozen passes' threads, its loaders' workers.
_JOB: dict[str, Threads | None] = {"plan": None}

#: The environment variable that gives a DDP rank started by its job's rank 0 that job's count of jobs side by
#: side (a rank runs alone as Hydra sees it, but shares the cores as its job does).
JOBS_BESIDE = "SEMVPR_JOBS_SIDE_BY_SIDE"

#: ``threads=auto`` per stage: None = the whole share, else that many threads (within the share).
AUTO: dict[str, int | None] = {
    "frozen": None,  # the trunk pass, skips, masks, pseudo-labels, eval descriptors of images
    "teacher": None,  # training the embedded teacher
    "student": None,  # training the student
    "retriever": 1,  # aggregator init, fit, untrained and tested evaluation on cached features
}


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity; all of them where the platform has none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def parse_setting(value: object) -> int | None:
    """``threads`` as None (auto) or a whole number >= 1; anything else is one line naming the key."""
    if value is None or value == "auto":
        return None
    if isinstance(value, int) and not isinstance(value, bool) and value >= 1:
        return value
    raise SemvprError(f"threads={value!r} must be auto or a whole number >= 1")


@dataclass(frozen=True)
class Threads:
    """The threads of one process of a job: its ``setting`` (None = auto), its ``share`` of the cores, shared
    by ``processes`` (its DDP ranks on the node times the ``jobs`` side by side)."""

    setting: int | None
    share: int
    cores: int
    processes: int
    env_cap: int | None = None
    gpu: bool = False
    jobs: int = 1

    @classmethod
    def resolve(
        cls, setting: object, ranks: int = 1, jobs: int = 1, cores: int | None = None, gpu: bool = False
    ) -> Threads:
        """The plan for one process of a job of ``ranks`` processes among ``jobs`` jobs side by side; ``gpu``: its
        networks run on a GPU, so its CPU work (data loading, k-means, recall) takes the whole share."""
        cores = usable_cores() if cores is None else cores
        processes = max(1, ranks) * max(1, jobs)
        share = max(1, cores // processes)
        chosen = parse_setting(setting)
        env = os.environ.get("OMP_NUM_THREADS", "")
        env_cap = int(env) if env.isdigit() and int(env) >= 1 and chosen is None else None
        return cls(chosen, share, cores, processes, env_cap, gpu, max(1, jobs))

    def of(self, stage: str) -> int:
        """Threads of ``stage`` (a key of :data:`AUTO`)."""
        if stage not in AUTO:
            raise KeyError(stage)
        if self.setting is not None:
            return max(1, min(self.share, self.setting // self.processes or 1))
        wanted = self.share if self.gpu else AUTO[stage] or self.share
        return max(1, min(wanted, self.share, self.env_cap or self.share))

    def workers(self, requested: int, stage: str = "frozen") -> int:
        """Data-loader workers for a loader that feeds ``stage``, asked to use ``requested``: on a GPU at most the
        share; on the CPU at most the cores that the stage's own threads leave free (module docstring)."""
        free = self.share if self.gpu else self.share - self.of(stage)
        return max(0, min(int(requested), free))

    @contextmanager
    def stage(self, name: str) -> Iterator[int]:
        """Run a stage with its threads (restored after); yields the count."""
        n = self.of(name)
        before = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            yield n
        finally:
            torch.set_num_threads(before)

    def adopt(self) -> Threads:
        """Make this the running job's plan: its frozen passes run at ``of("frozen")`` threads, its image loaders
        start :meth:`workers` (returns self)."""
        _JOB["plan"] = self
        return self

    def record(self) -> dict[str, object]:
        """What a run's metrics record: the setting, the cores, the processes sharing them, each stage's count."""
        return {
            "setting": "auto" if self.setting is None else self.setting,
            "cores": self.cores,
            "processes": self.processes,
            "share": self.share,
            "omp_num_threads": self.env_cap,
            "wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "gpu": self.gpu,
            "stages": {name: self.of(name) for name in AUTO},
        }


def frozen_threads() -> int:
    """The thread count of the running job's frozen passes: its adopted plan's, else torch's current count."""
    plan = _JOB["plan"]
    return plan.of("frozen") if plan is not None else torch.get_num_threads()


def frozen_workers(requested: int) -> int:
    """Workers of a loader that feeds the running job's frozen passes, asked to use ``requested``: its adopted
    plan's :meth:`Threads.workers`, else ``requested``."""
    plan = _JOB["plan"]
    return plan.workers(requested) if plan is not None else max(0, int(requested))


@contextmanager
def frozen_pass() -> Iterator[int]:
    """Run a frozen pass at the job's frozen thread count (restored after), wherever it happens; yields it."""
    n, before = frozen_threads(), torch.get_num_threads()
    if n != before:
        torch.set_num_threads(n)
    try:
        yield n
    finally:
        if n != before:
            torch.set_num_threads(before)


def standard_start_method() -> None:
    """Give a job started by a third-party launcher's process pool (joblib's ``loky`` workers) the standard
    start method for the processes it starts (data-loader workers): ``fork`` on Linux, ``spawn`` elsewhere
    (Python's defaults). A process already on a standard method keeps it."""
    if multiprocessing.get_start_method(allow_none=True) in (None, "fork", "spawn", "forkserver"):
        return
    multiprocessing.set_start_method("fork" if sys.platform == "linux" else "spawn", force=True)
