"""What the Hydra commands (train, eval, localize, segment) share: the frame of their task function, and for the
commands that pass images through a whole trained model (eval, localize, the hub) its device, threads and
precision."""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue

from semvpr.config.plan import lease_folder, thread_plan
from semvpr.config.schema import RunSettings, typed
from semvpr.core.device import GpuLease, resolve, visible_gpus
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR, sole_writer
from semvpr.core.logs import job_label, job_log, job_named, quiet_third_party
from semvpr.core.precision import job_precision
from semvpr.core.spec import unset
from semvpr.core.stops import stop_over_errors
from semvpr.core.threads import Threads
from semvpr.retrieval.launch import launched_rank

Task = Callable[[DictConfig, Path], None]

#: Longest job directory name (bytes): file systems hold 255.
MAX_DIRNAME_BYTES = 200


def one_dir_name(name: str) -> str:
    """A sweep job's directory name made from Hydra's ``override_dirname`` as one path component
    (``conf/train.yaml`` ``hydra.sweep.subdir``): a ``/`` in a value (``data.root=/data/pitts30k``) is written
    ``%2F`` (``%`` itself ``%25``) instead of nesting folders, and a name too long for a file system keeps its
    start and a hash of the whole."""
    name = name.replace("%", "%25").replace("/", "%2F")
    if len(name.encode()) <= MAX_DIRNAME_BYTES:
        return name
    digest = hashlib.sha256(name.encode()).hexdigest()[:16]
    return f"{name.encode()[: MAX_DIRNAME_BYTES - 17].decode(errors='ignore')}-{digest}"


OmegaConf.register_new_resolver("one_dir_name", one_dir_name, replace=True)

#: The keys a job's directory name leaves out (``conf/train.yaml``: set once for a whole sweep).
EXCLUDED_FROM_NAME = "hydra.job.config.override_dirname.exclude_keys"


def name_swept_keys(argv: list[str], config_name: str) -> list[str]:
    """Hydra's command line with every swept key in its jobs' directory names: ``conf/<config_name>.yaml``
    leaves keys out of them that a sweep usually sets once (``paths.cache_dir``, ``trainer.max_epochs``), and a
    sweep over one of those (``trainer.max_epochs=2,4``) put all its jobs in one directory. A command line
    that sets the excluded keys itself is left as it is."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    positions = [i for i, arg in enumerate(argv) if not arg.startswith("-")]
    if not positions or any(argv[i].lstrip("+~").startswith(f"{EXCLUDED_FROM_NAME}=") for i in positions):
        return argv
    config = OmegaConf.load(Path(CONF_DIR) / f"{config_name}.yaml")
    excluded = list(OmegaConf.select(config, EXCLUDED_FROM_NAME, default=None) or [])
    try:
        overrides = OverridesParser.create().parse_overrides([argv[i] for i in positions])
    except Exception:  # noqa: BLE001 - Hydra refuses it in its own line (config.checks.check_overrides)
        return argv
    swept = {o.key_or_group for o in overrides if o.is_sweep_override()}
    kept = [key for key in excluded if key not in swept]
    if kept == excluded:
        return argv
    at = positions[-1] + 1  # among the overrides: Hydra's parser takes -m only before or after them all
    return [*argv[:at], f"{EXCLUDED_FROM_NAME}=[{','.join(kept)}]", *argv[at:]]


def hydra_command(
    config_name: str, record: str, prepare: Callable[[DictConfig, Path], DictConfig] | None = None
) -> Callable[[Task], Callable[[], None]]:
    """Make ``task(cfg, run_dir)`` a Hydra command over ``conf/<config_name>.yaml``: third-party logging
    quietened, called with the job's output directory (held by this process: :func:`~semvpr.core.io.sole_writer`),
    a user error one line on stderr and exit code 2
    (:func:`~semvpr.core.errors.exit_on_user_error`; a value left unset among them: :func:`named_unset`), an
    error raised after a stop signal that stop (:func:`~semvpr.core.stops.stop_over_errors`). Hydra names the job
    after ``task``'s module. In a sweep, the job's stage lines name it
    (``semvpr: [#2 filter=unet] retriever: epoch 3/16 ...``: :func:`~semvpr.core.logs.job_named`).

    ``record`` is the file that says a job there ended (``metrics.json``, ``eval.json``): an earlier job's is
    removed as this one starts, so it never stands beside this job's files as if they were complete; before
    that, ``prepare(cfg, run_dir)`` makes the config the task runs (a resume's, from the run's own record), so a
    command refused there leaves the run as it was."""

    def command(task: Task) -> Callable[[], None]:
        @functools.wraps(task)
        def task_function(cfg: DictConfig) -> None:
            quiet_third_party()
            hydra_cfg = HydraConfig.get()
            run_dir = Path(hydra_cfg.runtime.output_dir)
            if launched_rank() != 0:  # another rank of a DDP job works beside rank 0 in its directory
                with stop_over_errors(), named_unset(cfg):
                    task(prepare(cfg, run_dir) if prepare else cfg, run_dir)
                return
            multirun = hydra_cfg.mode == RunMode.MULTIRUN
            sweep_job = job_label(hydra_cfg.job.num, hydra_cfg.job.override_dirname) if multirun else None
            with (
                sole_writer(run_dir, "hydra.run.dir"),
                job_named(sweep_job),
                job_log(_hydra_log_file(run_dir)),
                stop_over_errors(),
                named_unset(cfg),
            ):
                cfg = prepare(cfg, run_dir) if prepare else cfg
                (run_dir / record).unlink(missing_ok=True)
                task(cfg, run_dir)

        main = hydra.main(config_path=CONF_DIR, config_name=config_name, version_base="1.3")
        return main(exit_on_user_error(task_function))

    return command


def _hydra_log_file(run_dir: Path) -> Path | None:
    """The job's log file Hydra opened in its run dir (``<command>.log``, its job logging's file handler), where
    the stage lines go too; None where Hydra's job logging writes none there."""
    for handler in logging.getLogger().handlers:
        if (
            isinstance(handler, logging.FileHandler)
            and Path(handler.baseFilename).resolve().parent == run_dir.resolve()
        ):
            return Path(handler.baseFilename)
    return None


@contextmanager
def named_unset(cfg: DictConfig) -> Iterator[None]:
    """A value ``cfg`` leaves unset (``???``: ``ckpt``, ``queries``, a dataset's ``data.root``) read while the job
    runs is one line naming the key to set (:func:`~semvpr.core.spec.unset`), not OmegaConf's traceback."""
    try:
        yield
    except (MissingMandatoryValue, InterpolationToMissingValueError) as err:
        raise unset(OmegaConf.to_container(cfg, resolve=False), str(err.full_key)) from None


@contextmanager
def model_pass(cfg: DictConfig) -> Iterator[Threads]:
    """The threads and precision (``trainer.precision``) of a command that passes images through a whole model on
    its ``device``, adopted while it runs (yields the threads): the trunk pass dominates, so it runs as the
    ``frozen`` stage. A sweep's job with ``device=auto`` or ``cuda`` where several GPUs are visible takes one
    no other job holds (:func:`leased_gpu`), as a training sweep's job does."""
    with leased_gpu(cfg):
        device = resolve(cfg.get("device"))
        threads = thread_plan(cfg, gpu=device.type == "cuda")
        with threads.stage("frozen"), job_precision(str(cfg.trainer.precision), device.type):
            yield threads


@contextmanager
def leased_gpu(cfg: DictConfig) -> Iterator[None]:
    """In a sweep where several GPUs are visible, ``device=auto`` or ``cuda`` becomes ``cuda:N`` for the job's
    life, N a GPU with a slot (of ``jobs_per_gpu``) that no other job of this or another sweep on the cache
    holds (``core.device.GpuLease`` in ``config.plan.lease_folder``). Elsewhere ``cfg`` is left as it is."""
    gpus = visible_gpus()
    word = str(cfg.get("device") or "auto")
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    if not (multirun and word in ("auto", "cuda") and len(gpus) > 1):
        yield
        return
    sweep_dir = Path(str(HydraConfig.get().sweep.dir))
    slots = typed(RunSettings, cfg, part=True).jobs_per_gpu
    with GpuLease(lease_folder(Path(str(cfg.paths.cache_dir)), sweep_dir), gpus, slots) as lease, open_dict(cfg):
        cfg.device = f"cuda:{lease.index}"
        try:
            yield
        finally:
            cfg.device = word


#: The precision an author's release file is evaluated in unless the command line sets ``trainer.precision``:
#: its authors' arithmetic, fp32 (on a GPU without TF32), which their published numbers come from.
RELEASE_PRECISION = "32-true"


@dataclass(frozen=True)
class Arithmetic:
    """The precision a pass through a model asks for (a ``trainer.precision`` value) and whether its fp32 matmuls
    and convolutions on a GPU may use TF32 (``precision.job_precision``)."""

    precision: str
    tf32: bool

    @contextmanager
    def run(self, device: str) -> Iterator[str]:
        """Adopt it on ``device`` (a device type: ``cpu``, ``cuda``) while the block runs; yields the precision as
        run (``precision.lightning_precision``)."""
        with job_precision(self.precision, device, self.tf32) as precision:
            yield precision


def model_arithmetic(cfg: DictConfig, merged: DictConfig, explicit: set[str]) -> Arithmetic:
    """How eval, localize and the hub pass images through ``merged``'s model: a semvpr checkpoint (or
    ``ckpt=none``) in ``trainer.precision``, as the job runs; an author's release file (``merged.release``) in its
    authors' fp32 (:data:`RELEASE_PRECISION`), unless the command line sets ``trainer.precision``."""
    if merged.get("release") and "trainer.precision" not in explicit:
        return Arithmetic(RELEASE_PRECISION, tf32=False)
    return Arithmetic(str(cfg.trainer.precision), tf32=True)
