"""Training-step cost of each aggregator on the default trunk's feature grid, measured in one run.

One step = forward and backward of a batch of (B, 112, 12, 15) local features (the frozen ImageNet
EfficientNet-Lite0's stride-16 stage at 180x240) with a random binary mask, under the trainer's
precision (bf16 autocast where the CPU runs it natively). Each aggregator is built from its
``conf/aggregator/*.yaml``; SALAD (MLPs 512 wide) and BoQ (256 channels x 8 rows) are also timed at
the widths they had before, the papers' scaled to a 2,048-D descriptor, to show what the
configured widths save.

    python benchmarks/aggregator_cost.py [--batch 64] [--repeats 5] [--threads 1]

Prints one line per aggregator (ms per step, descriptor size); last line:
``salad_512_over_128=<ratio> boq_256_over_128=<ratio>`` (step time at the former width over the
configured one).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from semvpr.config.components import build_component, options
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast, bf16_native

DIM, GRID = 112, (12, 15)


def build(name: str, **overrides: object) -> torch.nn.Module:
    """The aggregator of ``conf/aggregator/<name>.yaml`` for the default trunk, with its values overridden."""
    node = OmegaConf.load(Path(CONF_DIR) / "aggregator" / f"{name}.yaml")
    node.merge_with({"num_clusters": 32} if "num_clusters" in node else {}, overrides)
    extra = {"grid": GRID} if "grid" in node else {}
    return build_component(node, "aggregator", dim=DIM, **extra).train()


def step_ms(agg: torch.nn.Module, batch: int, repeats: int, bf16: bool) -> float:
    """Median milliseconds of one forward + backward."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(batch, DIM, *GRID, generator=gen)
    w = (torch.rand(batch, 1, *GRID, generator=gen) > 0.3).float()
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        with autocast("cpu", enabled=bf16):
            out = agg(x, w)
        out.float().sum().backward()
        if i:  # the first step warms up
            times.append(time.perf_counter() - t0)
    return 1000.0 * sorted(times)[len(times) // 2]


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bf16 = bf16_native("cpu")
    print(f"batch {args.batch}, grid {GRID}, {DIM} channels, {'bf16' if bf16 else 'fp32'}, {args.threads} thread(s)")
    ms = {}
    variants = {name: (name, {}) for name in options("aggregator") if name != "sral"}  # SRAL: NetVLAD's cost
    variants["salad (hidden 512)"] = ("salad", {"hidden_dim": 512})
    variants["boq (256 channels)"] = ("boq", {"proj_channels": 256, "row_dim": 8})  # 2,048-D too
    for label, (name, overrides) in variants.items():
        agg = build(name, **overrides)
        ms[label] = step_ms(agg, args.batch, args.repeats, bf16)
        print(f"{label:>20}: {ms[label]:8.1f} ms per step, descriptor {agg.output_dim}")
    print(
        f"salad_512_over_128={ms['salad (hidden 512)'] / ms['salad']:.1f} "
        f"boq_256_over_128={ms['boq (256 channels)'] / ms['boq']:.1f}"
    )


if __name__ == "__main__":
    main()
