"""semvpr: semantic-aware visual place recognition.

Importing the package first (every ``python -m semvpr.*`` command does, before torch) makes OpenMP threads
that wait sleep instead of spinning: ``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets another policy.
libgomp reads it once, when torch loads it, so it must be in the environment before ``import torch``; a
program that imports torch before semvpr keeps its own policy. A spinning thread holds a core while it waits
at a barrier, which the job beside it (another sweep job, a DDP rank) needed (semvpr/core/threads.py).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
