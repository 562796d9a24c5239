"""Data-parallel speed and exactness: 2 processes x 1 thread (gloo) against 1 process x 1 thread,
with the same global batch, on VGG16's trainable conv5 block + NetVLAD (64 x 512) over cached
conv4 trunk features of 240x320 images (random weights and features: timing needs no data).

- refresh: describe a database of ``--db`` trunk rows (semvpr.retrieval.distributed.sharded: whole eval
  batches per rank, gathered), as the descriptor-cache refresh does;
- step: ``--steps`` training steps of global batches of ``--batch`` tuples (1 query, 1 positive,
  ``--negatives`` negatives each), each rank on its slice (semvpr.retrieval.mining), loss over the global pair
  count (Retriever.training_step), DDP's gradient all-reduce included, no optimizer step;
- grad_rel_err: ||g_ddp - g_1|| / ||g_1|| of the first step's gradient.

python benchmarks/ddp.py [--db 192] [--batch 4] [--negatives 2] [--steps 2] [--reps 3]
Last line: world=2 grad_rel_err=<e> refresh_speedup=<s> step_speedup=<s>
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
import time
import warnings
from datetime import timedelta
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from semvpr.core.errors import exit_on_user_error
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.backbones import VGG16Backbone
from semvpr.retrieval.distributed import rank_slice, sharded
from semvpr.retrieval.features import FeatureStore
from semvpr.retrieval.mining import TupleImages, collate_tuples
from semvpr.retrieval.retriever import Optimization, Retriever

GRID = (15, 20)  # conv4 output of a 240x320 image
WORLD = 2


class Training(nn.Module):
    """Lightning's DDP wrapper in short: the forward pass is the retriever's training step."""

    def __init__(self, retriever: Retriever) -> None:
        super().__init__()
        self.retriever = retriever

    def forward(self, batch: dict) -> torch.Tensor:
        return self.retriever.training_step(batch, 0)


def workload(args: argparse.Namespace) -> tuple[Retriever, FeatureStore, list[list[tuple[int, int, np.ndarray]]]]:
    """The model, a store of random trunk rows, and the global batches of tuples (same on every rank)."""
    torch.manual_seed(0)
    backbone = VGG16Backbone(weights="none", train_from="conv5")
    retriever = Retriever(
        backbone, NetVLAD(num_clusters=64, dim=512), optimization=Optimization(torch.optim.SGD), eval_batch_size=16
    )
    trunk = torch.randn(args.db, 512, *GRID, generator=torch.Generator().manual_seed(1)).to(torch.bfloat16)
    store = FeatureStore(tuple(Path(f"x{i}") for i in range(args.db)), GRID, trunk, None)
    rng = np.random.default_rng(0)
    batches = [
        [
            (int(rng.integers(args.db)), int(rng.integers(args.db)), rng.choice(args.db, args.negatives, replace=False))
            for _ in range(args.batch)
        ]
        for _ in range(args.steps)
    ]
    return retriever, store, batches


def measure(rank: int, world: int, args: argparse.Namespace, port: int, out: str) -> None:
    """Time the refresh and the steps in this process (one rank of ``world``); rank 0 saves the result."""
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", message=".*self.log.*")  # the step runs outside a Trainer
    if world > 1:
        dist.init_process_group(
            "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world, timeout=timedelta(seconds=600)
        )
    retriever, store, batches = workload(args)
    describe = sharded(retriever.describe_store, retriever.eval_batch_size)
    trainable = [p for p in retriever.parameters() if p.requires_grad]
    training = Training(retriever)
    wrapped = nn.parallel.DistributedDataParallel(training) if world > 1 else training
    images = TupleImages(store, store)
    slices = []
    for tuples in batches:
        mine = tuples[rank_slice(len(tuples), rank, world)]
        batch = collate_tuples([images[t] for t in mine]) or {}
        slices.append({**batch, "pairs": sum(len(t[2]) for t in tuples) / world})

    def steps() -> torch.Tensor:
        first = None
        for batch in slices:
            retriever.zero_grad()
            wrapped(batch).backward()  # DDP all-reduces the gradients during the backward pass
            if first is None:
                first = torch.cat([p.grad.flatten() for p in trainable]).clone()
        assert first is not None
        return first

    def timed(fn):  # type: ignore[no-untyped-def]
        best, value = float("inf"), None
        for _ in range(args.reps):
            if world > 1:
                dist.barrier()
            tic = time.perf_counter()
            value = fn()
            best = min(best, time.perf_counter() - tic)
        return best, value

    refresh_s, desc = timed(lambda: describe(store, None))
    step_s, grad = timed(steps)
    if rank == 0:
        torch.save({"refresh_s": refresh_s, "step_s": step_s, "grad": grad, "desc": desc}, out)
    if world > 1:
        dist.destroy_process_group()


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", type=int, default=192)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--negatives", type=int, default=2)
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory() as tmp:
        single, ranks = Path(tmp) / "single.pt", Path(tmp) / "ranks.pt"
        measure(0, 1, args, 0, str(single))
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        torch.multiprocessing.spawn(measure, args=(WORLD, args, port, str(ranks)), nprocs=WORLD)
        one, two = torch.load(single, weights_only=False), torch.load(ranks, weights_only=False)
    err = float((two["grad"] - one["grad"]).norm() / one["grad"].norm())
    print(
        f"one process: refresh {one['refresh_s']:.2f} s, {args.steps} steps {one['step_s']:.2f} s; "
        f"{WORLD} processes: refresh {two['refresh_s']:.2f} s, steps {two['step_s']:.2f} s; "
        f"descriptors bit-identical: {np.array_equal(one['desc'], two['desc'])}"
    )
    print(
        f"world={WORLD} grad_rel_err={err:.2e} refresh_speedup={one['refresh_s'] / two['refresh_s']:.2f} "
        f"step_speedup={one['step_s'] / two['step_s']:.2f}"
    )


if __name__ == "__main__":
    main()
