"""Memory and throughput of the real eval path as the dataset grows (ARCHITECTURE §5: nothing may need RAM in
proportion to the dataset; decoding must hide behind the trunk).

Writes N placeholder JPEGs (480x640 by default) in the @UTM@ layout, 80 % database and 20 % queries,
and runs ``python -m semvpr.eval data=folder`` on them in a fresh process per N with an untrained
VGG16 + NetVLAD (K=64) checkpoint, reading each process's peak RSS. End-to-end images/s comes from
the difference of the two runs' wall times (start-up cancels out); trunk-only images/s is the
backbone alone on already decoded tensors of the same size and batch, in this process.

    python benchmarks/scale.py [--sizes 250 1000] [--image-size 480 640] [--batch 24]

Last line: ``rss_ratio=<peak RSS at the largest N / at the smallest> pipeline_ratio=<end-to-end
images/s / trunk-only images/s>`` (targets: rss_ratio <= 1.2, pipeline_ratio >= 0.8).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from semvpr.config.build import build_backbone, build_mask_source, build_retriever
from semvpr.config.plan import mask_plan, settings_of
from semvpr.core.errors import exit_on_user_error
from semvpr.core.precision import autocast

REPO = Path(__file__).resolve().parents[1]


def compose(*overrides: str):
    """The project's train config with overrides."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return hydra_compose(config_name="train", overrides=list(overrides))


def write_checkpoint(path: Path, clusters: int) -> None:
    """An untrained VGG16 + NetVLAD checkpoint in the format a run writes."""
    cfg = compose("backbone=vgg16", "backbone.weights=none", f"model.num_clusters={clusters}")
    backbone = build_backbone(cfg.backbone, cfg.seed)
    retriever = build_retriever(settings_of(cfg), backbone, build_mask_source(mask_plan(cfg), backbone))
    torch.save({"state_dict": retriever.state_dict(), "hyper_parameters": dict(retriever.hparams)}, path)


def write_images(root: Path, n: int, hw: tuple[int, int], seed: int = 0) -> None:
    """Placeholder street-sized JPEGs (smooth random patterns, so they compress like photos)."""
    rng = np.random.default_rng(seed)
    num_db = int(0.8 * n)
    for i in range(n):
        side = "database" if i < num_db else "queries"
        east = 585000.0 + 10.0 * (i if i < num_db else i - num_db)
        folder = root / "images" / "test" / side
        folder.mkdir(parents=True, exist_ok=True)
        coarse = rng.integers(0, 255, (hw[0] // 16, hw[1] // 16, 3), dtype=np.uint8)
        image = Image.fromarray(coarse).resize((hw[1], hw[0]), Image.BILINEAR)
        image.save(folder / f"@{east:.2f}@4477000.00@17@T@@@@@@@@@@@.jpg", quality=90)


def run_eval(ckpt: Path, data: Path, work: Path, hw: tuple[int, int], batch: int, workers: int) -> tuple[float, float]:
    """Wall time (s) and peak RSS (MiB) of one ``semvpr.eval`` process."""
    cmd = [
        sys.executable,
        "-m",
        "semvpr.eval",
        f"ckpt={ckpt}",
        "data=folder",
        f"data.root={data}",
        f"data.image_size=[{hw[0]},{hw[1]}]",
        f"data.num_workers={workers}",
        f"model.eval_batch_size={batch}",
        f"paths.cache_dir={work / 'cache'}",
        f"hydra.run.dir={work / 'run'}",
    ]
    out, err = work / "stdout.txt", work / "stderr.txt"
    work.mkdir(parents=True, exist_ok=True)
    with out.open("w") as stdout, err.open("w") as stderr:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=stdout, stderr=stderr)
        # wait4: this child's own peak RSS (its decoding workers are separate processes).
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"semvpr.eval failed:\n{err.read_text()[-2000:]}")
    print(f"  {out.read_text().strip().splitlines()[-1]}")
    return wall, usage.ru_maxrss / 1024  # Linux reports KiB


@torch.no_grad()
def trunk_images_per_s(hw: tuple[int, int], batch: int, reps: int = 2) -> float:
    """The VGG16 trunk alone on decoded tensors, with the eval path's precision and memory format."""
    cfg = compose("backbone.weights=none")
    backbone = build_backbone(cfg.backbone, cfg.seed).eval()
    x = torch.rand(batch, 3, *hw).contiguous(memory_format=torch.channels_last)
    with autocast("cpu"):
        backbone(x)
        start = time.perf_counter()
        for _ in range(reps):
            backbone(x)
    return reps * batch / (time.perf_counter() - start)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs=2, default=(250, 1000))
    ap.add_argument("--image-size", type=int, nargs=2, default=(480, 640))
    ap.add_argument("--batch", type=int, default=24, help="eval batch size (pytorch-NetVlad's cacheBatchSize)")
    ap.add_argument("--workers", type=int, default=2, help="decoding workers")
    ap.add_argument("--clusters", type=int, default=64)
    args = ap.parse_args()
    hw = tuple(args.image_size)
    with tempfile.TemporaryDirectory(prefix="semvpr-scale-") as tmp:
        tmp = Path(tmp)
        write_checkpoint(tmp / "model.ckpt", args.clusters)
        runs = {}
        for n in sorted(args.sizes):
            write_images(tmp / f"data{n}", n, hw)
            print(f"N={n}: eval of {int(0.8 * n)} database + {n - int(0.8 * n)} query images at {hw[0]}x{hw[1]}")
            runs[n] = run_eval(tmp / "model.ckpt", tmp / f"data{n}", tmp / f"work{n}", hw, args.batch, args.workers)
            print(f"  wall {runs[n][0]:.1f} s, peak RSS {runs[n][1]:.0f} MiB")
    (small, (t_small, rss_small)), (large, (t_large, rss_large)) = sorted(runs.items())
    pipeline = (large - small) / (t_large - t_small)
    trunk = trunk_images_per_s(hw, args.batch)
    print(
        f"end-to-end {pipeline:.2f} images/s (decode, resize, trunk, NetVLAD, descriptor cache); "
        f"trunk alone {trunk:.2f} images/s; peak RSS {rss_small:.0f} -> {rss_large:.0f} MiB"
    )
    print(f"rss_ratio={rss_large / rss_small:.3f} pipeline_ratio={pipeline / trunk:.3f}")


if __name__ == "__main__":
    main()
