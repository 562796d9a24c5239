"""How a data-parallel job (``trainer=ddp``) shares its work between ranks.

Every helper here is a no-op in a single process, so the same code path serves one process and
many. Work is split the same way everywhere:

- description (descriptor-cache refresh, val/test): rank r takes a contiguous block of *whole*
  eval batches and the descriptors are gathered in rank order. A batch is never split, so the
  gathered rows are the single-process ones bit for bit on the same hardware (a row's value can
  depend on the batch it was computed in, by ~1e-6);
- training: each global batch of tuples is cut into ``world`` consecutive slices
  (:func:`rank_slice`); the loss is normalised by the global pair count (semvpr.retrieval.mining).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.distributed as dist

if TYPE_CHECKING:  # features' loaders read the world size from here
    from semvpr.retrieval.features import FeatureStore

Describe = Callable[["FeatureStore", np.ndarray | None], np.ndarray]


def world() -> tuple[int, int]:
    """(rank, world size) of this process: (0, 1) without a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def rank_slice(n: int, rank: int, world_size: int) -> slice:
    """Rank ``rank``'s consecutive share of ``n`` items: sizes differ by at most one, the first
    ranks take the larger shares, and the shares of ranks 0..world-1 concatenate to range(n)."""
    base, extra = divmod(n, world_size)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (rank < extra))


def batch_block(n: int, batch_size: int, rank: int, world_size: int) -> slice:
    """Rows of rank ``rank``'s contiguous block of whole ``batch_size`` batches of ``n`` rows."""
    batches = rank_slice(-(-n // batch_size), rank, world_size)
    return slice(min(n, batches.start * batch_size), min(n, batches.stop * batch_size))


def collective_device() -> torch.device:
    """Where the process group's collectives take their tensors: this rank's GPU under NCCL (which has no CPU
    backend), the CPU under gloo."""
    if dist.is_available() and dist.is_initialized() and dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def gather_rows(rows: torch.Tensor, device: torch.device | None = None) -> torch.Tensor:
    """Concatenate every rank's 2-D ``rows`` (N_r, D) in rank order; N_r may differ and be 0 (a
    rank with no rows may pass any (0, x) tensor: the width is taken from the others). The collectives run
    on ``device`` (by default :func:`collective_device`); the result is on ``rows``' device."""
    size = world()[1]
    if size == 1:
        return rows
    home, device = rows.device, device or collective_device()
    rows = rows.to(device)
    shapes = [torch.zeros(2, dtype=torch.long, device=device) for _ in range(size)]
    dist.all_gather(shapes, torch.tensor(rows.shape[:2], device=device))
    most, width = (int(max(s[i].item() for s in shapes)) for i in (0, 1))
    padded = rows.new_zeros(most, width)
    if len(rows):
        padded[: len(rows)] = rows
    parts = [torch.empty_like(padded) for _ in range(size)]
    dist.all_gather(parts, padded)
    return torch.cat([part[: int(s[0].item())] for part, s in zip(parts, shapes)]).to(home)


def from_rank_zero(obj: Any) -> Any:
    """Rank 0's ``obj`` on every rank (a picklable object)."""
    rank, size = world()
    if size == 1:
        return obj
    box = [obj if rank == 0 else None]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def sharded(describe: Describe, batch_size: int) -> Describe:
    """``describe`` with its rows split by whole batches across ranks and gathered (see module doc)."""

    def run(store: FeatureStore, index: np.ndarray | None) -> np.ndarray:
        rank, size = world()
        if size == 1:
            return describe(store, index)
        rows = np.arange(len(store)) if index is None else np.asarray(index)
        mine = rows[batch_block(len(rows), batch_size, rank, size)]
        local = describe(store, mine) if len(mine) else np.zeros((0, 0), np.float32)
        return gather_rows(torch.from_numpy(local)).numpy()

    return run
