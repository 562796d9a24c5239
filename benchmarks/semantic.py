"""Semantic pipeline on SynthCity: teacher training, pseudo-labelling throughput, student training and quality.

Trains the embedded Mask2Former teacher on the SynthCity segmentation split (held-out: seg val), labels the
train database + query images with it, trains the U-Net student over a random-init VGG16's frozen
prefix on those labels, and scores the student on held-out test images against the teacher and the
ground truth (the GT is read here only, never by training). Artifacts go to a fresh cache so every
stage is timed from scratch; SynthCity itself is generated once into --data-cache.

    python benchmarks/semantic.py [--preset default] [--seed 0] [--data-cache outputs/cache] [--eval-images 400]
                                  [--threads N]

Last line: ``teacher_s=.. teacher_miou=.. teacher_static_iou=.. label_img_s=.. student_s=..
student_iou_teacher=.. student_iou_gt=..``
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from PIL import Image
from torch.utils.data import DataLoader
from torchmetrics.classification import MulticlassJaccardIndex

from semvpr.config.schema import typed
from semvpr.core.errors import exit_on_user_error
from semvpr.core.precision import autocast
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES, static_lut
from semvpr.data.images import ImageDataset, Reading
from semvpr.data.synthcity import read_segmentation, read_split
from semvpr.models.backbones import VGG16Backbone
from semvpr.models.student import StudentSpec
from semvpr.models.teacher import TeacherSpec
from semvpr.segmentation.datamodule import SegmentationDataset
from semvpr.segmentation.pseudolabels import LabelledImages, pseudo_labels
from semvpr.segmentation.training import build_student, build_teacher

REPO = Path(__file__).resolve().parents[1]


def load_cfg(image_size: list[int], overrides: list[str]) -> OmegaConf:
    """The shipped teacher and student configs, with the data image size they interpolate, plus
    dotted overrides (e.g. ``teacher.train.epochs=12``)."""
    cfg = OmegaConf.create(
        {
            "data": {"image_size": image_size},
            "teacher": OmegaConf.load(REPO / "conf/teacher/mask2former.yaml"),
            "student": OmegaConf.load(REPO / "conf/student/unet.yaml"),
        }
    )
    return OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides))


class StaticIoU:
    """Running IoU of the static class (prediction bool maps vs target 0/1/255 maps)."""

    def __init__(self) -> None:
        self.inter = self.union = 0

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        valid = target != IGNORE
        p, t = pred & valid, (target == 1) & valid
        self.inter += int((p & t).sum())
        self.union += int((p | t).sum())

    def value(self) -> float:
        return self.inter / max(1, self.union)


@torch.no_grad()
def teacher_held_out(
    teacher: torch.nn.Module, seg_val: object, size: tuple[int, int], lut: torch.Tensor
) -> tuple[float, float]:
    """mIoU over the 19 classes and static IoU of the teacher on the held-out segmentation split."""
    miou = MulticlassJaccardIndex(len(TRAIN_ID_NAMES), ignore_index=IGNORE, average="macro")
    static = StaticIoU()
    for images, ids in DataLoader(SegmentationDataset(seg_val, size), batch_size=16):
        pred = teacher.predict_train_ids(images)
        miou.update(pred, ids)
        static.update(lut[pred] == 1, lut[ids.clamp(0, 255)])
    return float(miou.compute()), static.value()


@torch.no_grad()
def student_scores(student, backbone, teacher, paths, label_paths, size, lut) -> dict[str, float]:
    """Static IoU of the student vs the teacher and vs GT, and of the teacher vs GT, on held-out images."""
    scores = {"student_teacher": StaticIoU(), "student_gt": StaticIoU(), "teacher_gt": StaticIoU()}
    for images, index in DataLoader(ImageDataset(paths, size), batch_size=32):
        with autocast("cpu"):
            skips = backbone.forward_frozen(images.contiguous(memory_format=torch.channels_last))
        pred = student.static_prob(skips, out_hw=size)[:, 0] >= 0.5
        from_teacher = lut[teacher.predict_train_ids(images)]
        gt = lut[torch.from_numpy(np.stack([np.asarray(Image.open(label_paths[i])) for i in index])).long()]
        scores["student_teacher"].update(pred, from_teacher)
        scores["student_gt"].update(pred, gt)
        scores["teacher_gt"].update(from_teacher == 1, gt)
    return {k: v.value() for k, v in scores.items()}


@exit_on_user_error
def main() -> None:
    """Run the three stages from scratch and print their timings and quality."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data-cache", default="outputs/cache", help="where SynthCity is generated (once)")
    ap.add_argument("--backbone-seed", type=int, default=0)
    ap.add_argument("--eval-images", type=int, default=400, help="held-out test images to score the student on")
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads (default: torch's); 1 is far faster while other jobs load the cores",
    )
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. teacher.train.epochs=12")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    train = read_split(args.preset, args.seed, args.data_cache, "train")
    test = read_split(args.preset, args.seed, args.data_cache, "test")
    seg_train = read_segmentation(args.preset, args.seed, args.data_cache, "train")
    seg_val = read_segmentation(args.preset, args.seed, args.data_cache, "val")
    size = Image.open(train.db_paths[0]).size[::-1]
    cfg = load_cfg(list(size), args.overrides)
    lut = torch.full((256,), IGNORE, dtype=torch.long)
    lut[: len(TRAIN_ID_NAMES)] = torch.from_numpy(
        static_lut(tuple(cfg.teacher.static_classes))[: len(TRAIN_ID_NAMES)]
    ).long()
    print(
        f"cpu threads={torch.get_num_threads()} load={os.getloadavg()[0]:.1f} "
        f"seg train/val={len(seg_train)}/{len(seg_val)}"
    )

    with tempfile.TemporaryDirectory(prefix="semvpr-bench-") as cache:
        start = time.perf_counter()
        teacher = build_teacher(typed(TeacherSpec, cfg.teacher, "teacher"), seg_train, seg_val, cache)
        teacher_s = time.perf_counter() - start
        miou, static_iou = teacher_held_out(teacher, seg_val, size, lut)
        print(f"teacher: {teacher_s:.0f} s, held-out mIoU {miou:.3f}, static IoU {static_iou:.3f}")

        images = list(train.db_paths) + list(train.q_paths)
        start = time.perf_counter()
        labels = pseudo_labels(
            teacher,
            images,
            Reading(size, int(cfg.teacher.predict_batch_size)),
            cache,
            train.root,
        )
        label_img_s = len(images) / (time.perf_counter() - start)
        print(f"pseudo-labels: {len(images)} images, {label_img_s:.1f} img/s")

        torch.manual_seed(args.backbone_seed)
        backbone = VGG16Backbone(weights="none", train_from="conv5").eval()
        start = time.perf_counter()
        student = build_student(
            typed(StudentSpec, cfg.student, "student"),
            backbone,
            LabelledImages(images, labels, train.root),
            size,
            cache,
        )
        student_s = time.perf_counter() - start
        n = min(args.eval_images, len(test.db_paths))
        scores = student_scores(student, backbone, teacher, test.db_paths[:n], test.db_labels[:n], size, lut)
        print(
            f"student: {student_s:.0f} s; static IoU on {n} test images: vs teacher {scores['student_teacher']:.3f}, "
            f"vs GT {scores['student_gt']:.3f} (teacher vs GT {scores['teacher_gt']:.3f})"
        )
    print(
        f"teacher_s={teacher_s:.1f} teacher_miou={miou:.3f} teacher_static_iou={static_iou:.3f} "
        f"label_img_s={label_img_s:.1f} student_s={student_s:.1f} student_iou_teacher={scores['student_teacher']:.3f} "
        f"student_iou_gt={scores['student_gt']:.3f} teacher_test_iou_gt={scores['teacher_gt']:.3f}"
    )


if __name__ == "__main__":
    main()
