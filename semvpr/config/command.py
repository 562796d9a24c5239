"""What the Hydra commands (train, eval, localize, segment) share: the frame of their task function, and for the
commands that pass images through a whole trained model (eval, localize) its device, threads and precision."""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from semvpr.config.plan import thread_plan
from semvpr.core.device import resolve
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR, sole_writer
from semvpr.core.logs import quiet_third_party
from semvpr.core.precision import job_precision
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


def hydra_command(config_name: str, record: str) -> Callable[[Task], Callable[[], None]]:
    """Make ``task(cfg, run_dir)`` a Hydra command over ``conf/<config_name>.yaml``: third-party logging
    quietened, called with the job's output directory (held by this process: :func:`~semvpr.core.io.sole_writer`),
    a user error one line on stderr and exit code 2
    (:func:`~semvpr.core.errors.exit_on_user_error`). Hydra names the job after ``task``'s module.

    ``record`` is the file that says a job there ended (``metrics.json``, ``eval.json``): an earlier job's is
    removed as this one starts, so it never stands beside this job's files as if they were complete."""

    def command(task: Task) -> Callable[[], None]:
        @functools.wraps(task)
        def task_function(cfg: DictConfig) -> None:
            quiet_third_party()
            run_dir = Path(HydraConfig.get().runtime.output_dir)
            if launched_rank() != 0:  # another rank of a DDP job works beside rank 0 in its directory
                task(cfg, run_dir)
                return
            with sole_writer(run_dir, "hydra.run.dir"):
                (run_dir / record).unlink(missing_ok=True)
                task(cfg, run_dir)

        main = hydra.main(config_path=CONF_DIR, config_name=config_name, version_base="1.3")
        return main(exit_on_user_error(task_function))

    return command


@contextmanager
def model_pass(cfg: DictConfig) -> Iterator[Threads]:
    """The threads and precision (``trainer.precision``) of a command that passes images through a whole model on
    its ``device``, adopted while it runs (yields the threads): the trunk pass dominates, so it runs as the
    ``frozen`` stage."""
    device = resolve(cfg.get("device"))
    threads = thread_plan(cfg, gpu=device.type == "cuda")
    with threads.stage("frozen"), job_precision(str(cfg.trainer.precision), device.type):
        yield threads
