"""semvpr: semantic-aware visual place recognition.

A process that runs one of semvpr's commands (``python -m semvpr.<command>`` or a ``semvpr-*`` console script:
:func:`runs_a_command`) gets two process-wide defaults when the package is first imported, before torch, each
only where the environment has not set its own. Importing the library anywhere else (the hub, a user's program,
the tests) leaves the process as it was.

- OpenMP threads that wait sleep instead of spinning: ``OMP_WAIT_POLICY=PASSIVE``. libgomp reads it once,
  when torch loads it, so it must be in the environment before ``import torch``. A spinning thread holds a
  core while it waits at a barrier, which the job beside it (another sweep job, a DDP rank) needed
  (semvpr/core/threads.py).
- glibc's allocator keeps freed memory for the next allocation (:func:`_keep_freed_memory`).

Both are in the environment the command's own processes inherit (sweep workers, DDP ranks, loader workers).
"""

import ctypes
import os
import sys
from collections.abc import Sequence
from pathlib import PurePath

#: glibc ``mallopt`` parameters and the values semvpr's commands give them: a frozen pass over a batch of images
#: may use up to ``semvpr.models.backbones.FORWARD_BYTES`` (2 GiB) of activations, and the heap holds all of it.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 2**30
TRIM_THRESHOLD = 2 * 2**30
#: glibc's environment variables for the same two settings, which a process reads as it starts.
_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": MMAP_THRESHOLD, "MALLOC_TRIM_THRESHOLD_": TRIM_THRESHOLD}


def runs_a_command(argv: Sequence[str]) -> bool:
    """Whether an interpreter's command line (``sys.orig_argv``) runs one of semvpr's commands: a module of the
    package with ``-m``, or a ``semvpr-*`` console script (the interpreter's own options skipped)."""
    rest = list(argv[1:])
    while rest:
        arg = rest.pop(0)
        if arg.startswith("-m"):
            module = arg[2:] or (rest[0] if rest else "")
            return module == "semvpr" or module.startswith("semvpr.")
        if arg.startswith("-c"):
            return False
        if arg in ("-X", "-W", "--check-hash-based-pycs"):  # an option with its value as the next argument
            rest = rest[1:]
        elif not arg.startswith("-") or arg == "-":
            return PurePath(arg).name.startswith("semvpr-")
    return False


def _keep_freed_memory() -> None:
    """Keep blocks up to :data:`MMAP_THRESHOLD` in the heap and up to :data:`TRIM_THRESHOLD` of free memory at
    its top, in this process (``mallopt``) and in the processes it starts (glibc's environment variables).
    glibc's defaults hand every block above a dynamic threshold (at most 32 MiB) back to the kernel when freed
    and trim the heap's top beyond 128 KiB, so each batch of a pass over images (decoded images, activations)
    is written into fresh pages that the kernel must fault in and zero. Both values cover a frozen pass's
    activation budget: with less (256 MiB and 512 MiB), an fp32 pass's largest activations (a padded
    96-channel map of 64 images at 180x240: 258 MiB) were mapped afresh for every batch and its freed top
    trimmed, and a cold default job under the AVX2 cap made 4 to 8 million page faults instead of 0.7
    (``benchmarks/kernel_time.py``, ``benchmarks/results/kernel_time*.json``), with equal recalls. Left alone
    where the environment sets glibc's own (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``,
    ``GLIBC_TUNABLES``: a process this one started has them already) and where the C library is not glibc."""
    if any(k in os.environ for k in (*_MALLOC_ENV, "GLIBC_TUNABLES")):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc: its allocator has its own policy
        return
    mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    os.environ.update({k: str(v) for k, v in _MALLOC_ENV.items()})


if runs_a_command(getattr(sys, "orig_argv", [])):
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    _keep_freed_memory()

__version__ = "0.1.0"
