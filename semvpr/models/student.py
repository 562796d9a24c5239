"""U-Net student: a small decoder over the frozen backbone prefix that predicts the teacher's classes.

It learns the Cityscapes classes of the teacher's pseudo-labels (cross-entropy, 19 outputs); its
static map is the sum of the static classes' probabilities, which is what the binary filter reads.
"""
from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn
from torch.utils.data import DataLoader

from semvpr.core.cache import build_once
from semvpr.data.classes import IGNORE, NUM_CLASSES, STATIC_NAMES
from semvpr.models.masks import static_vector
from semvpr.core.errors import SemvprError
from semvpr.core.precision import autocast
from semvpr.segmentation.pseudolabels import label_path, read_label
from semvpr.core.logs import Progress, progress

VERSION = 2  # 2: multi-class head (cross-entropy on the teacher's classes); 1: binary


def _block(cin: int, cout: int) -> nn.Sequential:
    """conv3x3-BN-ReLU twice: the U-Net unit."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )  # fmt: skip


class Student(nn.Module):
    """Decoder from the deepest chosen frozen feature up through shallower skips to class logits."""

    def __init__(
        self, frozen_channels: Sequence[int], frozen_strides: Sequence[int],
        strides: Sequence[int] = (4, 8, 16), width: int = 64, static_names: Sequence[str] = STATIC_NAMES,
    ) -> None:  # fmt: skip
        super().__init__()
        self.register_buffer("static_weight", static_vector(static_names),
                             persistent=False)
        # The deepest frozen output of each wanted stride (ResNet's stem and layer1 share none; VGG's do not).
        chosen = {s: i for i, s in enumerate(frozen_strides) if s in set(strides)}
        if not chosen:
            raise SemvprError(
                f"student.strides={list(strides)} match none of the backbone's frozen feature strides "
                f"{list(frozen_strides)}; pick some of those"
            )
        self.skip_indices = [chosen[s] for s in sorted(chosen)]  # shallow → deep
        self.out_stride = min(chosen)
        chans = [frozen_channels[i] for i in self.skip_indices]
        # 1x1 projections first: 3x3 convs on 256-512 raw channels cost ~7x more for no measured gain.
        self.lateral = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, width, 1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True)) for c in chans
        )
        self.bottom = _block(width, width)
        self.ups = nn.ModuleList(_block(2 * width, width) for _ in chans[:-1])
        self.head = nn.Conv2d(width, NUM_CLASSES, 1)

    def forward(self, skips: Sequence[Tensor]) -> Tensor:
        """Class logits (B,C,H/s,W/s) at the shallowest chosen stride, from ``forward_frozen`` outputs."""
        return self.decode([skips[i] for i in self.skip_indices])

    def decode(self, chosen: Sequence[Tensor]) -> Tensor:
        """Logits from just the chosen features (shallow → deep), e.g. a cache of them."""
        feats = [lateral(f.float()) for lateral, f in zip(self.lateral, chosen)]
        h = self.bottom(feats[-1])
        for f, block in zip(reversed(feats[:-1]), self.ups):
            h = F.interpolate(h, size=f.shape[-2:], mode="bilinear", align_corners=False)
            h = block(torch.cat([h, f], 1))
        return self.head(h)

    def class_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Softmax over the classes (B,C,·,·), optionally resized (bilinear) to ``out_hw``."""
        prob = torch.softmax(self.forward(skips).float(), dim=1)
        if out_hw is not None:
            prob = F.interpolate(prob, size=tuple(out_hw), mode="bilinear", align_corners=False)
        return prob

    def static_prob(self, skips: Sequence[Tensor], out_hw: Sequence[int] | None = None) -> Tensor:
        """Σ of the static classes' probabilities (B,1,·,·), optionally resized to ``out_hw``."""
        prob = torch.einsum("bchw,c->bhw", self.class_prob(skips, out_hw), self.static_weight)[:, None]
        return prob


@torch.no_grad()
def cache_skips(
    backbone: nn.Module, indices: Sequence[int], paths: Sequence[Path], image_size: Sequence[int],
    batch_size: int, num_workers: int, bf16: bool = True,
) -> list[Tensor]:  # fmt: skip
    """The chosen frozen features of every image, stored in bf16 (the trunk is frozen: compute them once);
    ``bf16=False`` computes them in fp32 (CPUs without AMX / AVX512-BF16 emulate bf16, several times slower)."""
    from semvpr.segmentation.datamodule import ImageDataset

    device = next(backbone.parameters()).device
    loader = DataLoader(ImageDataset(paths, image_size), batch_size=batch_size, num_workers=num_workers)
    out: list[list[Tensor]] = [[] for _ in indices]
    # The frozen prefix stays in eval mode whatever the backbone's mode (Backbone.train keeps it so).
    with autocast(device, enabled=bf16):
        for images, _ in progress(loader, "student features", len(paths), size=lambda b: len(b[0])):
            skips = backbone.forward_frozen(images.to(device).contiguous(memory_format=torch.channels_last))
            for level, i in enumerate(indices):
                out[level].append(skips[i].to(torch.bfloat16).contiguous())
    return [torch.cat(level) for level in out]


def load_targets(paths: Sequence[Path], label_dir: Path, root: Path, image_size: Sequence[int]) -> Tensor:
    """(N,H,W) uint8 trainId targets from pseudo-label PNGs (255 = ignore)."""
    maps = []
    for p in paths:
        ids = read_label(label_dir, p, root)
        if ids.shape != tuple(image_size):
            raise SemvprError(f"pseudo-label {label_path(label_dir, p, root)} is {ids.shape}, expected {tuple(image_size)}")
        maps.append(np.where(ids < NUM_CLASSES, ids, IGNORE).astype(np.uint8))
    return torch.from_numpy(np.stack(maps))


def fit_student(student: Student, skips: list[Tensor], targets: Tensor, cfg: DictConfig) -> dict[str, float]:
    """Train the decoder on cached features with cross-entropy at image resolution; returns final metrics
    (the static-map IoU against the labels' static map is tracked, as that is what the filter uses)."""
    gen = torch.Generator().manual_seed(int(cfg.seed))
    n, bs = len(targets), int(cfg.batch_size)
    steps = max(1, cfg.epochs * math.ceil(n / bs))
    opt = torch.optim.AdamW(student.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=steps, pct_start=0.1)
    device = student.head.weight.device
    student.train()
    inter = union = 0
    bar = Progress("student", steps, unit="steps")
    for epoch in range(cfg.epochs):
        order = torch.randperm(n, generator=gen)
        inter = union = 0
        for start in range(0, n, bs):
            idx = order[start : start + bs]
            target = targets[idx].to(device).long()
            with autocast(device, enabled=bool(cfg.bf16)):
                logits = student.decode([s[idx].to(device) for s in skips])
            logits = F.interpolate(logits.float(), size=target.shape[-2:], mode="bilinear", align_corners=False)
            loss = F.cross_entropy(logits, target, ignore_index=IGNORE)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            valid = target != IGNORE
            static = torch.einsum("bchw,c->bhw", logits.detach().softmax(1), student.static_weight)
            pred, gt = (static >= 0.5) & valid, (student.static_weight[target.clamp(max=NUM_CLASSES - 1)] > 0) & valid
            inter, union = inter + int((pred & gt).sum()), union + int((pred | gt).sum())
            bar.update()
    bar.close()
    student.eval()
    return {"train/loss": float(loss.item()), "train/iou_vs_labels": inter / max(1, union)}


def student_architecture(cfg_student: Mapping[str, Any], backbone: nn.Module) -> Student:
    """An untrained student for this config over this backbone's frozen features."""
    return Student(backbone.frozen_channels, backbone.frozen_strides, strides=list(cfg_student["strides"]),
                   width=int(cfg_student["width"]), static_names=list(cfg_student.get("static_classes", STATIC_NAMES)))


def build_student(
    cfg_student: Mapping[str, Any], backbone: nn.Module, image_paths: Sequence[str | Path],
    label_dir: str | Path, root: str | Path, image_size: Sequence[int], cache_dir: str | Path,
) -> Student:  # fmt: skip
    """Train the student once on pseudo-labels (cached, kind "student") and return it in eval mode."""
    cfg = cfg_student if isinstance(cfg_student, DictConfig) else OmegaConf.create(dict(cfg_student))
    paths, label_dir, root = [Path(p) for p in image_paths], Path(label_dir), Path(root)
    if cfg.get("max_images") and len(paths) > cfg.max_images:
        # The frozen trunk pass dominates the cost; a fixed random subset is plenty for a small decoder.
        keep = torch.randperm(len(paths), generator=torch.Generator().manual_seed(int(cfg.seed)))[: cfg.max_images]
        paths = [paths[i] for i in sorted(keep.tolist())]
    size = [int(image_size[0]), int(image_size[1])]
    key = {"version": VERSION, "student": OmegaConf.to_container(cfg, resolve=True),
           "backbone": backbone.frozen_identity(), "labels": label_dir.name, "image_size": size}  # fmt: skip

    def build(out: Path) -> None:
        torch.manual_seed(int(cfg.seed))
        student = student_architecture(cfg, backbone)
        start = time.perf_counter()
        targets = load_targets(paths, label_dir, root, size)
        skips = cache_skips(backbone, student.skip_indices, paths, size, int(cfg.batch_size), int(cfg.num_workers),
                            bf16=bool(cfg.bf16))
        student.to(next(backbone.parameters()).device)
        metrics = fit_student(student, skips, targets, cfg)
        metrics["train_seconds"] = time.perf_counter() - start
        torch.save(student.cpu().state_dict(), out / "student.pt")
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))

    art = build_once(cache_dir, "student", key, build)
    # The architecture comes from the config, only weights from the (possibly shared) cache.
    student = student_architecture(cfg, backbone)
    try:
        student.load_state_dict(torch.load(art / "student.pt", weights_only=True, map_location="cpu"))
    except Exception as err:  # noqa: BLE001 - a damaged or foreign cache entry
        raise SemvprError(f"student cache {art} does not hold this student's weights ({type(err).__name__}); "
                          f"delete it to rebuild") from None
    student.artifact = art  # type: ignore[attr-defined]  # for the benchmark / logs: metrics.json lives here
    return student.to(next(backbone.parameters()).device).eval()
