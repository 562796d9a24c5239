"""semvpr: semantic-aware visual place recognition.

Importing the package first (every ``python -m semvpr.*`` command does, before torch) sets two process-wide
defaults, each only where the environment has not set its own:

- OpenMP threads that wait sleep instead of spinning: ``OMP_WAIT_POLICY=PASSIVE``. libgomp reads it once,
  when torch loads it, so it must be in the environment before ``import torch``; a program that imports
  torch before semvpr keeps its own policy. A spinning thread holds a core while it waits at a barrier,
  which the job beside it (another sweep job, a DDP rank) needed (semvpr/core/threads.py).
- glibc's allocator keeps freed memory for the next allocation (:func:`_keep_freed_memory`).
"""

import ctypes
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

#: glibc ``mallopt`` parameters and the values semvpr gives them: a frozen pass over a batch of images may use
#: up to ``semvpr.models.backbones.FORWARD_BYTES`` (2 GiB) of activations, and the heap holds all of it.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 2**30
TRIM_THRESHOLD = 2 * 2**30


def _keep_freed_memory() -> None:
    """Keep blocks up to :data:`MMAP_THRESHOLD` in the heap and up to :data:`TRIM_THRESHOLD` of free memory at
    its top. glibc's defaults hand every block above a dynamic threshold (at most 32 MiB) back to the kernel
    when freed and trim the heap's top beyond 128 KiB, so each batch of a pass over images (decoded images,
    activations) is written into fresh pages that the kernel must fault in and zero. Both values cover a
    frozen pass's activation budget: with less (256 MiB and 512 MiB), an fp32 pass's largest activations
    (a padded 96-channel map of 64 images at 180x240: 258 MiB) were mapped afresh for every batch and its
    freed top trimmed, and a cold default job under the AVX2 cap made 4 to 8 million page faults instead
    of 0.7 (``benchmarks/kernel_time.py``, ``benchmarks/results/kernel_time*.json``), with equal recalls.
    Left alone where the environment sets glibc's own (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``,
    ``GLIBC_TUNABLES``) and where the C library is not glibc."""
    if any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc: its allocator has its own policy
        return
    mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)


_keep_freed_memory()

__version__ = "0.1.0"
