"""Training the segmenters once per setting (cached): the embedded Mask2Former teacher with Lightning on
a segmentation set, and the U-Net student in a plain loop over the frozen trunk's cached features on
the teacher's pseudo-labels. Each lands in the artifact cache (``teacher-*``, ``student-*``) keyed by
everything that changes its weights."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader

from semvpr.core.cache import build_once, config_hash, files_identity
from semvpr.core.errors import SemvprError
from semvpr.core.logs import Progress, progress
from semvpr.core.precision import autocast, compute_key, device_precision
from semvpr.data.classes import IGNORE, NUM_CLASSES
from semvpr.data.images import ImageDataset
from semvpr.data.segmentation import SegmentationSet
from semvpr.models.student import Student, StudentSpec, student_architecture
from semvpr.models.teacher import Teacher, TeacherSpec
from semvpr.models.teacher_folder import teacher_architecture
from semvpr.segmentation.pseudolabels import LabelledImages, TrunkOutputs, label_path, read_label
from semvpr.segmentation.teacher_training import train_teacher

STUDENT_VERSION = 2  # 2: multi-class head (cross-entropy on the teacher's classes); 1: binary


def dataset_identity(seg: SegmentationSet) -> str:
    """Hash of a SegmentationSet's files (name, size and content: ``files_identity``) and label table."""
    paths = [*seg.images, *seg.labels]
    files = files_identity([p.name for p in paths], paths)
    lut = seg.label_lut  # the same PNGs read with another id table are other targets
    return config_hash(files if lut is None else [files, list(lut)])


def training_threads(device: torch.device) -> dict[str, int]:
    """The torch threads a training run on ``device`` gets (the caller's ``Threads.stage``), part of its
    artifact's key on a CPU: a multi-threaded CPU reduction splits its sums by thread, so the same training at
    another thread count ends with other weights (one teacher step's gradients measured to differ at 1 and 2
    threads), and a cached teacher or student must be the one this run's settings would train (frozen passes
    are keyed by the job's frozen-pass count: ``core.threads``). A GPU's sums do not follow the CPU's threads:
    nothing then."""
    return {"threads": torch.get_num_threads()} if device.type == "cpu" else {}


def build_teacher(
    spec: TeacherSpec,
    seg_train: SegmentationSet | None,
    seg_val: SegmentationSet | None,
    cache_dir: str | Path,
    device: torch.device | str = "cpu",
) -> Teacher:
    """Load the pretrained teacher, or train the embedded one once (cached) on ``device`` and load it; eval mode,
    frozen, on ``device``."""
    device = torch.device(device)
    teacher = teacher_architecture(spec)
    if not spec.checkpoint:
        if seg_train is None or seg_val is None:
            raise SemvprError(
                "teacher.checkpoint=null trains the embedded teacher, which needs data.segmentation "
                "train and val sets (Cityscapes format); set them or give a pretrained checkpoint"
            )
        # Only what changes the weights: class lists, labelling batch size etc. must not retrain it.
        key = {
            "version": 1,
            "image_size": list(spec.image_size),
            "model": dict(spec.model),
            "train": {k: v for k, v in dataclasses.asdict(spec.train).items() if k != "val_every"},
            "train_set": dataset_identity(seg_train),
            "val_set": dataset_identity(seg_val),
            **training_threads(device),
            **compute_key(device),
        }
        art = build_once(cache_dir, "teacher", key, lambda tmp: train_teacher(spec, seg_train, seg_val, tmp, device))
        # The architecture comes from the config, only weights from the (possibly shared) cache.
        try:
            teacher.model.load_state_dict(torch.load(art / "model.pt", weights_only=True, map_location="cpu"))
        except Exception as err:  # noqa: BLE001 - a damaged or foreign cache entry
            raise SemvprError(
                f"teacher cache {art} does not hold this teacher's weights ({type(err).__name__}); delete it to rebuild"
            ) from None
        teacher.teacher_key = art.name
    return teacher.to(device).eval().requires_grad_(False)


@torch.no_grad()
def cache_skips(
    backbone: nn.Module,
    indices: Sequence[int],
    paths: Sequence[Path],
    image_size: Sequence[int],
    spec: StudentSpec,
    mirror: bool = False,
) -> list[Tensor]:
    """The chosen frozen features of every image, stored in bf16 (the trunk is frozen: compute them once), in
    batches of the student's ``batch_size`` read by its ``num_workers``; its ``bf16=False`` computes them in fp32
    (CPUs without AMX / AVX512-BF16 emulate bf16, several times slower); ``mirror``: of each image's left-right
    mirror image."""
    device = next(backbone.parameters()).device
    loader = DataLoader(ImageDataset(paths, image_size), batch_size=spec.batch_size, num_workers=spec.num_workers)
    out: list[list[Tensor]] = [[] for _ in indices]
    # The frozen prefix stays in eval mode whatever the backbone's mode (Backbone.train keeps it so).
    with autocast(device, enabled=spec.bf16):
        what = "student features (mirrored)" if mirror else "student features"
        for images, _ in progress(loader, what, len(paths), size=lambda b: len(b[0])):
            images = images.flip(-1) if mirror else images
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
            raise SemvprError(
                f"pseudo-label {label_path(label_dir, p, root)} is {ids.shape}, expected {tuple(image_size)}"
            )
        maps.append(np.where(ids < NUM_CLASSES, ids, IGNORE).astype(np.uint8))
    return torch.from_numpy(np.stack(maps))


def fit_student(
    student: Student, skips: list[Tensor], targets: Tensor, spec: StudentSpec, mirrored: list[Tensor] | None = None
) -> dict[str, float]:
    """Train the decoder on cached features with cross-entropy at image resolution; returns final metrics
    (the static-map IoU against the labels' static map over the last epoch, as that is what the filter uses;
    it is measured in that epoch only: it reads the logits and nothing else, so training is the same).

    ``mirrored``: the same features of each image's mirror image (``spec.flip``): a random half of each batch
    (drawn from the run's seed) is read from there, its labels mirrored."""
    gen = torch.Generator().manual_seed(int(spec.seed))
    n, bs = len(targets), int(spec.batch_size)
    steps = max(1, spec.epochs * math.ceil(n / bs))
    opt = torch.optim.AdamW(student.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=spec.lr, total_steps=steps, pct_start=0.1)
    device = student.head.weight.device
    # fp16 (a GPU without native bf16: V100, T4) needs its loss scaled, as Lightning's 16-mixed does; bf16 and
    # fp32 do not (the scaler then passes everything through).
    scaler = torch.amp.GradScaler(device.type, enabled=bool(spec.bf16) and device_precision(device.type) == "16-mixed")
    student.train()
    inter = union = 0
    bar = Progress("student", steps, unit="steps")
    for epoch in range(spec.epochs):
        order = torch.randperm(n, generator=gen)
        last = epoch == spec.epochs - 1
        for start in range(0, n, bs):
            idx = order[start : start + bs]
            target = targets[idx].to(device).long()
            chosen = [s[idx].to(device) for s in skips]
            if mirrored is not None:
                flip = torch.rand(len(idx), generator=gen) < 0.5
                target = torch.where(flip[:, None, None].to(device), target.flip(-1), target)
                chosen = [
                    torch.where(flip[:, None, None, None].to(device), m[idx].to(device), s)
                    for m, s in zip(mirrored, chosen, strict=True)
                ]
            with autocast(device, enabled=bool(spec.bf16)):
                logits = student.decode(chosen)
            logits = F.interpolate(logits.float(), size=target.shape[-2:], mode="bilinear", align_corners=False)
            loss = F.cross_entropy(logits, target, ignore_index=IGNORE)
            opt.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(opt)
            scaler.update()
            sched.step()
            if last:
                valid = target != IGNORE
                static = torch.einsum("bchw,c->bhw", logits.detach().softmax(1), student.static_weight)
                pred = (static >= 0.5) & valid
                gt = (student.static_weight[target.clamp(max=NUM_CLASSES - 1)] > 0) & valid
                inter, union = inter + int((pred & gt).sum()), union + int((pred | gt).sum())
            bar.update()
    bar.close()
    student.eval()
    return {"train/loss": float(loss.item()), "train/iou_vs_labels": inter / max(1, union)}


def build_student(
    spec: StudentSpec,
    backbone: nn.Module,
    labelled: LabelledImages,
    image_size: Sequence[int],
    cache_dir: str | Path,
    trunk: TrunkOutputs | None = None,
) -> Student:
    """Train the student once on the pseudo-labels of ``labelled`` (cached, kind "student") and return it in
    eval mode.

    ``trunk``: the images' cached ``forward_frozen`` outputs in the precision :func:`cache_skips` would compute
    them at; the student then reads its skips from there instead of passing the images through the trunk again
    (the same values: the frozen pass gives the same outputs whatever the batch)."""
    paths, label_dir, root = [Path(p) for p in labelled.images], Path(labelled.labels), Path(labelled.root)
    if spec.max_images and len(paths) > spec.max_images:
        # The frozen trunk pass dominates the cost; a fixed random subset is plenty for a small decoder.
        keep = torch.randperm(len(paths), generator=torch.Generator().manual_seed(int(spec.seed)))[: spec.max_images]
        paths = [paths[i] for i in sorted(keep.tolist())]
    size = [int(image_size[0]), int(image_size[1])]
    settings = {k: v for k, v in dataclasses.asdict(spec).items() if k != "checkpoint"}  # read, never trained
    key = {
        "version": STUDENT_VERSION,
        "student": settings,
        "backbone": backbone.frozen_key(),
        "labels": label_dir.name,
        "image_size": size,
        **training_threads(next(backbone.parameters()).device),
    }

    def build(out: Path) -> None:
        torch.manual_seed(int(spec.seed))
        student = student_architecture(spec, backbone)
        start = time.perf_counter()
        targets = load_targets(paths, label_dir, root, size)
        features = partial(cache_skips, backbone, student.skip_indices, paths, size, spec)
        if trunk is not None:
            outputs = trunk(paths)
            skips = [outputs[i].contiguous() for i in student.skip_indices]
        else:
            skips = features()
        mirrored = features(mirror=True) if spec.flip else None
        student.to(next(backbone.parameters()).device)
        metrics = fit_student(student, skips, targets, spec, mirrored)
        metrics["train_seconds"] = time.perf_counter() - start
        torch.save(student.cpu().state_dict(), out / "student.pt")
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))

    art = build_once(cache_dir, "student", key, build)
    # The architecture comes from the config, only weights from the (possibly shared) cache.
    student = student_architecture(spec, backbone)
    try:
        student.load_state_dict(torch.load(art / "student.pt", weights_only=True, map_location="cpu"))
    except Exception as err:  # noqa: BLE001 - a damaged or foreign cache entry
        raise SemvprError(
            f"student cache {art} does not hold this student's weights ({type(err).__name__}); delete it to rebuild"
        ) from None
    student.artifact = art  # type: ignore[attr-defined]  # for the benchmark / logs: metrics.json lives here
    return student.to(next(backbone.parameters()).device).eval()
