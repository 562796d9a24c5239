"""Calibrate SynthCity: does an oracle static mask help an untrained VGG16 + NetVLAD retriever?

Random-init VGG16 trunk (conv5_3 local features, fixed seed), NetVLAD with k-means centroids from
train-split features, evaluated on the test split twice: without a mask, and with the ground-truth
static pixels area-pooled to the feature grid (threshold 0.5) as the NetVLAD contribution weights.
The benchmark is useful when the oracle gains >= 10 R@1 points while unmasked R@1 is 20-80 %.

    python benchmarks/calibrate_synthcity.py [--preset default] [--seed 0] [--cache-dir outputs/cache]

Last line: ``none_R@1=<x> oracle_R@1=<y> gain=<y-x>`` (percent).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Sequence

import faiss
import numpy as np
import torch
from PIL import Image

from semvpr.data.classes import static_lut
from semvpr.data.synthcity import ensure_synthcity, read_split
from semvpr.models.backbones import VGG16Backbone
from semvpr.models.masks import pool_to_grid
from semvpr.models.netvlad import NetVLAD

STATIC = torch.from_numpy(static_lut())


def load_batch(paths: Sequence[Path]) -> torch.Tensor:
    """(B,3,H,W) float [0,1] images."""
    arr = np.stack([np.asarray(Image.open(p).convert("RGB")) for p in paths])
    return torch.from_numpy(arr).permute(0, 3, 1, 2).float().div(255)


def oracle_mask(label_paths: Sequence[Path], grid: tuple[int, int]) -> torch.Tensor:
    """Ground-truth static pixels, area-pooled to the feature grid and binarised at 0.5."""
    labels = torch.from_numpy(np.stack([np.asarray(Image.open(p)) for p in label_paths])).long()
    return pool_to_grid(STATIC[labels][:, None], grid)


@torch.no_grad()
def local_features(trunk: VGG16Backbone, images: torch.Tensor) -> torch.Tensor:
    """conv5_3 features in bf16 autocast + channels_last (AMX), returned as fp32."""
    with torch.autocast("cpu", dtype=torch.bfloat16):
        return trunk(images.contiguous(memory_format=torch.channels_last))[-1].float()


@torch.no_grad()
def descriptors(trunk, vlad, paths, labels, batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Unmasked and oracle-masked NetVLAD descriptors of a list of images."""
    plain, masked = [], []
    for i in range(0, len(paths), batch):
        feats = local_features(trunk, load_batch(paths[i:i + batch]))
        mask = oracle_mask(labels[i:i + batch], tuple(feats.shape[-2:]))
        plain.append(vlad(feats).numpy())
        masked.append(vlad(feats, mask).numpy())
    return np.concatenate(plain), np.concatenate(masked)


def recall_at(db: np.ndarray, q: np.ndarray, positives: list[np.ndarray], ns=(1, 5, 10)) -> dict[int, float]:
    """Recall@N (percent) with faiss exact L2 search; queries without positives are skipped."""
    index = faiss.IndexFlatL2(db.shape[1])
    index.add(np.ascontiguousarray(db, np.float32))
    _, pred = index.search(np.ascontiguousarray(q, np.float32), max(ns))
    valid = [i for i, p in enumerate(positives) if len(p)]
    return {n: 100.0 * np.mean([np.isin(pred[i, :n], positives[i]).any() for i in valid]) for n in ns}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seed", type=int, default=0, help="dataset seed")
    ap.add_argument("--model-seed", type=int, default=0, help="seed of the random VGG16 init")
    ap.add_argument("--cache-dir", default="outputs/cache")
    ap.add_argument("--coverage", type=float, default=None)
    ap.add_argument("--lighting", type=float, default=None)
    ap.add_argument("--clusters", type=int, default=32)
    ap.add_argument("--init-images", type=int, default=300, help="train database images for k-means")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.time()
    root = ensure_synthcity(args.cache_dir, args.preset, args.seed, args.coverage, args.lighting)
    test = read_split(args.preset, args.seed, args.cache_dir, "test", args.coverage, args.lighting)
    train = read_split(args.preset, args.seed, args.cache_dir, "train", args.coverage, args.lighting)
    stats = json.loads((root / "stats.json").read_text())
    print(f"dataset {root} ({time.time() - t0:.1f}s): measured dynamic fraction {stats['dynamic_fraction']}, "
          f"sky {stats['sky_fraction']}")

    torch.manual_seed(args.model_seed)
    trunk = VGG16Backbone(weights="none", train_from=None).eval().to(memory_format=torch.channels_last)
    pick = np.random.default_rng(args.model_seed).permutation(len(train.db_paths))[: args.init_images]
    init = [train.db_paths[i] for i in sorted(pick)]
    feats = torch.cat([local_features(trunk, load_batch(init[i:i + 64])) for i in range(0, len(init), 64)])
    vlad = NetVLAD(args.clusters, trunk.out_channels)
    alpha = vlad.init_from_features(feats.permute(0, 2, 3, 1).reshape(-1, feats.shape[1]), seed=args.model_seed)
    print(f"k-means on {len(init)} train images ({feats.shape[-2]}x{feats.shape[-1]} grid), alpha={alpha:.0f}")

    db_plain, db_masked = descriptors(trunk, vlad, test.db_paths, test.db_labels)
    q_plain, q_masked = descriptors(trunk, vlad, test.q_paths, test.q_labels)
    positives = test.positives(25.0)
    none = recall_at(db_plain, q_plain, positives)
    oracle = recall_at(db_masked, q_masked, positives)
    mask_frac = float(np.mean([(STATIC[torch.from_numpy(np.asarray(Image.open(p))).long()]).mean()
                               for p in test.q_labels]))
    n = len(test.q_paths)
    print(f"test: {len(test.db_paths)} database, {n} queries; measured dynamic fraction (test queries) "
          f"{1 - mask_frac:.3f}; one std-error of R@1 ~ {100 * np.sqrt(0.25 / n):.1f} points")
    for name, rec in (("none", none), ("oracle", oracle)):
        print(f"{name:>7}: " + "  ".join(f"R@{k}={v:.1f}" for k, v in rec.items()))
    print(f"total {time.time() - t0:.0f}s")
    print(f"none_R@1={none[1]:.1f} oracle_R@1={oracle[1]:.1f} gain={oracle[1] - none[1]:.1f}")


if __name__ == "__main__":
    main()
