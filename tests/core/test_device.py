"""One device per job: every stage built where the job runs, precision as asked, the fp32 sections in fp32,
the NCCL-style gather, a sweep's GPUs leased one per job; the ``gpu`` tests run every stage on CUDA."""

from __future__ import annotations

import multiprocessing as mp
import os
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from semvpr.config.build import build_retriever, prepare
from semvpr.config.plan import job_device, job_plan, settings_of
from semvpr.core.device import GpuLease, resolve, sweep_jobs
from semvpr.core.errors import SemvprError
from semvpr.core.precision import (
    autocast,
    bf16_native,
    compute_key,
    fp32,
    job_precision,
    lightning_precision,
    running_precision,
)
from tests.helpers import tiny_config

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def _devices_of(module: torch.nn.Module) -> set[torch.device]:
    return {t.device for t in [*module.parameters(), *module.buffers()]}


def test_every_stage_is_built_on_the_job_device(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """prepare() hands its device to the backbone, and everything built from it (teacher, student, the mask
    source, the retriever) lands there: a stage built elsewhere would show up as a second device."""
    cfg = tiny_config(tmp_path / "cache", "filter=unet", "threads=1")
    seen: list[torch.device] = []
    moved: list[torch.nn.Module] = []
    real = torch.nn.Module.to

    def spy(self: torch.nn.Module, *args: object, **kwargs: object) -> torch.nn.Module:
        for a in [*args, kwargs.get("device")]:
            if isinstance(a, (str, torch.device)) and str(a) not in ("", "None"):
                seen.append(torch.device(a))
                moved.append(self)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(torch.nn.Module, "to", spy)
    from semvpr.segmentation import training

    asked: list[torch.device] = []
    build_teacher = training.build_teacher

    def teacher_spy(*args: object, **kwargs: object) -> object:
        asked.append(torch.device(kwargs.get("device", args[4] if len(args) > 4 else "unset")))
        return build_teacher(*args, **kwargs)

    monkeypatch.setattr(training, "build_teacher", teacher_spy)
    device = job_device(settings_of(cfg))
    assert device == torch.device("cpu")
    job = prepare(job_plan(cfg, device), {})
    # The mask source holds buffers of its own (class weights) besides its segmenter's: the masks of the
    # trunk pass are made before the retriever (which would carry it along) exists, so it is moved itself.
    assert any(m is job.mask_source for m in moved)
    retriever = build_retriever(settings_of(cfg, training=True), job.backbone, job.mask_source)
    assert asked == [device]  # the teacher is built (and would be trained) on the job's device
    assert seen and set(seen) == {device}, seen
    assert _devices_of(retriever) == {device}
    assert job.semantic.teacher is not None and _devices_of(job.semantic.teacher) == {device}


def test_a_gpu_asked_for_where_none_is_visible_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SemvprError, match="asks for a CUDA GPU and none is visible"):
        resolve("gpu")
    assert resolve("auto") == torch.device("cpu") and resolve(None) == torch.device("cpu")
    with pytest.raises(SemvprError, match="must be auto, cpu, cuda or cuda:N"):
        resolve("tpu")


def test_precision_as_asked() -> None:
    assert lightning_precision("32-true", "cpu") == "32-true" and lightning_precision("32", "gpu") == "32-true"
    for half in ("16-true", "bf16-true", "64-true", "transformer-engine"):
        with pytest.raises(SemvprError, match=r"is not supported: semvpr runs bf16-mixed, 16-mixed \(GPU\) or 32-true"):
            lightning_precision(half, "gpu")
    with pytest.raises(SemvprError, match="16-mixed needs a GPU"):
        lightning_precision("16-mixed", "cpu")


def test_bf16_on_a_gpu_without_bf16_units_is_fp16_with_a_scaler(monkeypatch: pytest.MonkeyPatch) -> None:
    """A V100 or T4 reports bf16 'supported' through emulation: only native support counts."""
    from semvpr.core import precision

    precision.bf16_native.cache_clear()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: including_emulation)
    try:
        assert lightning_precision("bf16-mixed", "gpu") == "16-mixed"
    finally:
        precision.bf16_native.cache_clear()


def test_the_project_autocast_follows_the_job_precision() -> None:
    default = running_precision()
    with job_precision("32-true", "cpu") as run:
        assert run == "32-true" and running_precision() == "32-true"
        with autocast("cpu"):
            assert not torch.is_autocast_enabled("cpu")
        assert compute_key("cpu")["compute"] == "cpu/32-true"
    assert running_precision() == default
    as_run = "bf16-mixed" if bf16_native("cpu") else "32-true"  # bf16 asked of a CPU without it runs fp32
    assert compute_key("cpu")["compute"] == f"cpu/{as_run}"


def test_a_gpu_key_names_the_gpu_its_precision_and_tf32_and_no_cpu_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two GPU models, or fp32 with and without TF32, give other bits: each its own cache entry."""
    from semvpr.core import precision

    monkeypatch.setattr(precision, "bf16_native", lambda device_type: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")
    with job_precision("bf16-mixed", "gpu"):
        assert compute_key("cuda") == {"compute": "cuda/NVIDIA H200/bf16-mixed/tf32"}
    with job_precision("32-true", "gpu", tf32=False):
        assert compute_key("cuda:0") == {"compute": "cuda/NVIDIA H200/32-true"}
        assert torch.get_float32_matmul_precision() == "highest" and not torch.backends.cudnn.allow_tf32
    assert torch.backends.cudnn.allow_tf32  # restored
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA A100-SXM4-80GB")
    with job_precision("bf16-mixed", "gpu"):
        assert compute_key("cuda") == {"compute": "cuda/NVIDIA A100-SXM4-80GB/bf16-mixed/tf32"}


def test_the_fp32_sections_turn_autocast_and_tf32_off_and_restore_them() -> None:
    """Inside: autocast off, no TF32 for matmuls or convs; after: the job's settings again, and torch can still
    report them (Lightning asks on a GPU)."""
    with job_precision("bf16-mixed", "gpu"):
        assert torch.get_float32_matmul_precision() == "high"
        with torch.autocast("cpu", dtype=torch.bfloat16), fp32("cpu"):
            assert not torch.is_autocast_enabled("cpu")
            assert torch.get_float32_matmul_precision() == "highest" and not torch.backends.cuda.matmul.allow_tf32
            assert not torch.backends.cudnn.allow_tf32
            x = torch.randn(4, 4)
            assert (x @ x).dtype == torch.float32
        assert torch.get_float32_matmul_precision() == "high" and torch.backends.cudnn.allow_tf32
    assert torch.get_float32_matmul_precision() == "highest"


def test_a_gpu_job_gives_its_cpu_stages_the_share(monkeypatch: pytest.MonkeyPatch) -> None:
    from semvpr.core.threads import Threads

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # a cap in the environment would bound both

    cpu, gpu = Threads.resolve("auto", cores=8), Threads.resolve("auto", cores=8, gpu=True)
    assert cpu.of("retriever") == 1 and gpu.of("retriever") == 8 and gpu.record()["gpu"] is True


def test_a_sweep_runs_one_job_per_visible_gpu() -> None:
    assert sweep_jobs("cpu", 1, 2, gpus=[0, 1, 2, 3]) == 2
    assert sweep_jobs("gpu", 1, 2, gpus=[0, 1, 2, 3]) == 4
    assert sweep_jobs("gpu", 1, 2, gpus=[0]) == 1
    assert sweep_jobs("gpu", -1, 2, gpus=[0, 1]) == 1  # DDP over every GPU: one job at a time
    assert sweep_jobs("gpu", 1, 2, gpus=[0, 1], per_gpu=3) == 6  # small jobs sharing each GPU
    assert sweep_jobs("gpu", -1, 2, gpus=[0, 1], per_gpu=3) == 1
    assert sweep_jobs("cpu", 1, 2, gpus=[0, 1], per_gpu=3) == 2


def test_a_lease_with_slots_fills_every_gpu_before_sharing_one(tmp_path: Path) -> None:
    """With two slots per GPU the jobs held at once get 3, 5, 3, 5 (never two on one while another is idle);
    a freed slot is the next job's."""
    from contextlib import ExitStack

    with ExitStack() as held:
        taken = [held.enter_context(GpuLease(tmp_path, [3, 5], slots=2)).index for _ in range(4)]
        assert taken == [3, 5, 3, 5]
        assert len(list(tmp_path.glob("*.lock"))) == 4
    with GpuLease(tmp_path, [3, 5], slots=2) as first, GpuLease(tmp_path, [3, 5], slots=2) as second:
        assert (first.index, second.index) == (3, 5)


def _lease(folder: str, gpus: list[int], start: mp.synchronize.Barrier, queue: mp.Queue) -> None:
    with GpuLease(Path(folder), gpus) as lease:
        queue.put(lease.index)
        start.wait(timeout=600)  # hold it until every job has taken one


def test_sweep_jobs_side_by_side_lease_distinct_gpus(tmp_path: Path) -> None:
    """Jobs running at once (separate processes, as the launchers start them) each get a GPU of their own
    from a fake visible list; a job that ends frees its GPU for the next."""
    ctx = mp.get_context("spawn")
    gpus = [3, 5, 7]
    start, queue = ctx.Barrier(len(gpus)), ctx.Queue()
    jobs = [ctx.Process(target=_lease, args=(str(tmp_path), gpus, start, queue)) for _ in gpus]
    for job in jobs:
        job.start()
    taken = sorted(queue.get(timeout=600) for _ in jobs)
    for job in jobs:
        job.join(timeout=600)
    assert taken == gpus
    with GpuLease(tmp_path, gpus) as lease:
        assert lease.index == 3


def test_a_file_system_without_flock_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fcntl

    def no_flock(fd: int, op: int) -> None:
        raise OSError(38, "Function not implemented")

    monkeypatch.setattr(fcntl, "flock", no_flock)
    with pytest.raises(SemvprError, match="a file system without flock"), GpuLease(tmp_path, [0, 1]):
        pass


def _gather(rank: int, port: int, queue: mp.Queue) -> None:
    import torch.distributed as dist

    from semvpr.retrieval.distributed import gather_rows

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=2)
    rows = torch.full((rank + 1, 3), float(rank))
    out = gather_rows(rows, device=torch.device("cpu"))
    queue.put((rank, out.tolist(), str(out.device)))
    dist.destroy_process_group()


def test_the_gather_runs_on_the_collective_device_and_returns_to_the_rows_device() -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_gather, args=(r, port, queue)) for r in range(2)]
    for p in procs:
        p.start()
    results = dict((r, (rows, dev)) for r, rows, dev in (queue.get(timeout=600) for _ in procs))
    for p in procs:
        p.join(timeout=600)
    expected = [[0.0] * 3, [1.0] * 3, [1.0] * 3]
    assert results[0] == (expected, "cpu") and results[1] == (expected, "cpu")


@pytest.mark.gpu
@CUDA
def test_a_tiny_gpu_job_runs_every_stage_on_cuda(tmp_path: Path) -> None:
    cfg = tiny_config(tmp_path / "cache", "filter=unet", "threads=1", "trainer=gpu")
    with job_precision("bf16-mixed", "gpu"):
        device = job_device(settings_of(cfg))
        job = prepare(job_plan(cfg, device), {})
        retriever = build_retriever(settings_of(cfg, training=True), job.backbone, job.mask_source)
    assert device.type == "cuda" and _devices_of(retriever) == {device}
    assert _devices_of(job.semantic.student) == {device}


def test_a_cache_on_a_file_system_without_flock_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fcntl

    from semvpr.core.cache import build_once

    def no_flock(fd: object, op: int) -> None:
        raise OSError(38, "Function not implemented")

    monkeypatch.setattr(fcntl, "flock", no_flock)
    with pytest.raises(SemvprError, match="cannot lock .* point paths.cache_dir at a local or flock-capable folder"):
        build_once(tmp_path, "thing", {"k": 1}, lambda out: (out / "x").write_text("1"))
    assert not any(p.name.startswith("thing-") for p in tmp_path.iterdir())


def test_a_ddp_rank_takes_the_gpu_of_its_local_rank(monkeypatch: pytest.MonkeyPatch) -> None:
    """semvpr's own ranks and torchrun set LOCAL_RANK, SLURM sets SLURM_LOCALID: either picks the rank's GPU."""
    from semvpr.retrieval.launch import local_rank

    for key in ("LOCAL_RANK", "SLURM_LOCALID", "SUBMITIT_EXECUTOR"):
        monkeypatch.delenv(key, raising=False)
    assert local_rank() == 0
    monkeypatch.setenv("SLURM_LOCALID", "3")
    assert local_rank() == 3
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert local_rank() == 1
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    cfg = tiny_config(Path("/nonexistent"), "trainer=ddp", "trainer.devices=4")
    assert job_device(settings_of(cfg)) == torch.device("cuda", 1)


def test_an_evaluation_sweeps_job_takes_a_gpu_no_job_of_any_sweep_on_the_cache_holds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """eval -m and localize -m put every job on cuda:0, and two sweeps side by side both took GPU 0 (the locks
    were per sweep): with a fake list of three GPUs and GPU 0 held by another sweep's job on the same cache, the
    job takes GPU 1 for its life, and device=cpu or a job outside a sweep is left alone."""
    import semvpr.config.command as command
    from semvpr.config.plan import lease_folder

    cache = tmp_path / "cache"
    monkeypatch.setattr(command, "visible_gpus", lambda: [0, 1, 2])

    class Sweep:
        mode = command.RunMode.MULTIRUN
        sweep = OmegaConf.create({"dir": str(tmp_path / "this-sweep")})

    monkeypatch.setattr(command.HydraConfig, "initialized", staticmethod(lambda: True))
    monkeypatch.setattr(command.HydraConfig, "get", staticmethod(lambda: Sweep))
    run = {"seed": 0, "jobs_per_gpu": 1, "paths": {"cache_dir": str(cache)}}
    cfg = OmegaConf.create({"device": "auto", **run})
    OmegaConf.set_struct(cfg, True)
    with GpuLease(lease_folder(cache, tmp_path / "other-sweep"), [0, 1, 2]) as other:
        assert other.index == 0
        with command.leased_gpu(cfg):
            assert cfg.device == "cuda:1"
    assert cfg.device == "auto"
    cpu = OmegaConf.create({"device": "cpu", **run})
    with command.leased_gpu(cpu):
        assert cpu.device == "cpu"
    Sweep.mode = command.RunMode.RUN
    with command.leased_gpu(cfg):
        assert cfg.device == "auto"
