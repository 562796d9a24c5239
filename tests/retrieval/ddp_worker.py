"""One training epoch (descriptor-cache refresh, mining, one gradient per batch, no optimizer step)
in one process or on W gloo ranks; run by tests/retrieval/test_ddp.py in a subprocess, never in pytest's own.

``python tests/retrieval/ddp_worker.py WORLD OUT``: rank 0 saves to OUT what it saw; every rank's batch is
gathered to rank 0 so the test can check that the slices recombine to the single-process batches.
"""

from __future__ import annotations

import sys
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from semvpr.data.places import PlaceSet
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.retrieval.distributed import sharded
from semvpr.retrieval.features import FeatureStore, PlaceFeatures
from semvpr.retrieval.mining import Mining, MiningPool, TrainingEpoch
from semvpr.retrieval.retriever import Optimization, Retriever

DIM, GRID = 8, (3, 4)


class Trunk(nn.Module):
    """The trainable part of a backbone, on 'trunk features' that are random tensors here."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(DIM, DIM, 1)

    def forward_trainable(self, x: Tensor) -> Tensor:
        return self.conv(x)


class Step(nn.Module):
    """What Lightning's DDP wrapper does: the module's forward is its training_step."""

    def __init__(self, retriever: Retriever) -> None:
        super().__init__()
        self.retriever = retriever

    def forward(self, batch: dict[str, Any]) -> Tensor:
        return self.retriever.training_step(batch, 0)


def features(num_db: int = 40, num_q: int = 14) -> PlaceFeatures:
    """Database every 5 m on a line, queries near every third database image; random trunk features."""
    gen = torch.Generator().manual_seed(0)
    db_utm = np.stack([np.arange(num_db) * 5.0, np.zeros(num_db)], 1)
    q_utm = np.stack([np.arange(num_q) * 15.0 + 1.0, np.zeros(num_q)], 1)
    places = PlaceSet(
        "line",
        tuple(f"/d/db{i}.jpg" for i in range(num_db)),
        tuple(f"/d/q{i}.jpg" for i in range(num_q)),
        db_utm,
        q_utm,
    )

    def store(n: int) -> FeatureStore:
        return FeatureStore(
            tuple(Path(f"x{i}") for i in range(n)), GRID, torch.randn(n, DIM, *GRID, generator=gen), None
        )

    return PlaceFeatures(places, store(num_db), store(num_q))


def run(rank: int, world: int, out: str, port: int) -> None:
    if world > 1:
        dist.init_process_group(
            "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world, timeout=timedelta(seconds=120)
        )
    torch.manual_seed(0)
    torch.set_num_threads(1)
    retriever = Retriever(
        Trunk(), NetVLAD(num_clusters=4, dim=DIM), optimization=Optimization(torch.optim.SGD), eval_batch_size=6
    )
    train = features()
    # Global batches of 3 tuples: uneven slices on 2 ranks, an empty one on 3 ranks; sub-epochs of 7
    # queries end with a 1-query batch, which leaves empty slices on 2 ranks too.
    mining = Mining(batch_size=3, cache_refresh=7, num_negatives=3, negative_candidates=12, margin=0.5)
    pool = MiningPool.of(train, mining)
    describe = sharded(retriever.describe_store, retriever.eval_batch_size)
    seen: dict[str, Any] = {"db_desc": describe(train.db, None), "grads": [], "batches": [], "pairs": []}
    epoch = TrainingEpoch(train, mining, pool, 0, describe)
    step = Step(retriever)
    model = nn.parallel.DistributedDataParallel(step) if world > 1 else step
    params = [p for p in retriever.parameters() if p.requires_grad]
    for batch in epoch:
        retriever.zero_grad()
        if batch is None:
            seen["grads"].append(None)
            continue
        model(batch).backward()
        seen["grads"].append(torch.cat([p.grad.flatten() for p in params]).clone())
        local = (
            batch["trunk"].clone() if "trunk" in batch else torch.zeros(0, DIM, *GRID),
            int((batch["tuples"][:, 2:] >= 0).sum()) if "tuples" in batch else 0,
        )
        slices = [None] * world
        if world > 1:
            dist.all_gather_object(slices, local)
        else:
            slices = [local]
        seen["batches"].append(torch.cat([s[0] for s in slices]))
        seen["pairs"].append([s[1] for s in slices])
    seen["neg_cache"], seen["num_tuples"] = pool.neg_cache.copy(), epoch.num_tuples
    if rank == 0:
        torch.save(seen, out)
    if world > 1:
        dist.destroy_process_group()


def main() -> None:
    world, out = int(sys.argv[1]), sys.argv[2]
    if world == 1:
        run(0, 1, out, 0)
        return
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    torch.multiprocessing.spawn(run, args=(world, out, port), nprocs=world)


if __name__ == "__main__":
    main()
