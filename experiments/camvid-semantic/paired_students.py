"""Two saved students' binary masks compared frame by frame on a CamVid split, with a paired bootstrap.

Each student (a directory ``semvpr.segment`` saved, ``<run>/student_efficientnet_lite0``) predicts the
static mask of every frame of the split the way ``semvpr.segment`` scores it (the frozen ImageNet
EfficientNet-Lite0 trunk at ``seg.image_size``, bf16 autocast). The masks' confusion counts are kept per
frame; the dynamic IoU of each student is read off the counts pooled over the frames, and the difference
B − A is resampled over the frames (percentile bootstrap, both students on the same resampled frames).

    python experiments/camvid-semantic/paired_students.py A_DIR B_DIR [--root ../shared/realdata/camvid] [--split val]

Last line: ``split=<s> frames=<n> a=<IoU> b=<IoU> diff=<b-a> low=<2.5 %> high=<97.5 %>``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from semvpr.config.build import build_backbone
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.data.camvid import read_camvid
from semvpr.data.segmentation import SegmentationSet
from semvpr.models.student import load_student
from semvpr.reporting.paired import RESAMPLES
from semvpr.segmentation.confusion import Confusion, binary_pred, mask_scores
from semvpr.segmentation.scoring import loader, student_prob

KEY = "dynamic_iou"


def frame_counts(
    folder: Path, backbone: torch.nn.Module, frames: SegmentationSet, split: str, size: list[int]
) -> np.ndarray:
    """(frames, 19, 3) confusion counts of one student's binary mask, frame by frame."""
    student = load_student(folder, backbone)
    counts = []
    for images, labels, _ in loader(frames, size, batch_size=8, num_workers=0):
        prob = student_prob(student, backbone, images, size, bf16=True)
        for frame, label in enumerate(labels):
            if tuple(label.shape) != tuple(size):
                raise SystemExit(f"{split} frame {frame}: label {tuple(label.shape)} is not seg.image_size {size}")
            confusion = Confusion(2)
            confusion.update(binary_pred(prob[frame : frame + 1, 0]), label[None])
            counts.append(confusion.counts)
    return np.stack(counts)


@exit_on_user_error
def main() -> None:
    """Score both students frame by frame and print the paired difference with its interval."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--root", type=Path, default=Path("../shared/realdata/camvid"))
    ap.add_argument("--split", default="val", choices=["val", "test"])
    ap.add_argument("--resamples", type=int, default=RESAMPLES)
    args = ap.parse_args()
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("segment", overrides=[f"seg.root={args.root.resolve()}"])
    backbone = build_backbone(cfg.backbones.efficientnet_lite0, int(cfg.seed)).eval()
    size, static = [int(v) for v in cfg.seg.image_size], list(cfg.teacher.static_classes)
    frames = read_camvid(args.root, args.split)  # a wrong --root says so before any student is loaded
    a, b = (frame_counts(d, backbone, frames, args.split, size) for d in (args.a, args.b))
    score = lambda counts: mask_scores(counts.sum(0), static)[KEY]  # noqa: E731
    rng = np.random.default_rng(0)
    diffs = []
    for _ in range(args.resamples):
        frames = rng.integers(0, len(a), len(a))
        diffs.append(score(b[frames]) - score(a[frames]))
    low, high = np.percentile(diffs, [2.5, 97.5])
    print(
        f"split={args.split} frames={len(a)} a={score(a):.4f} b={score(b):.4f} diff={score(b) - score(a):+.4f} "
        f"low={low:+.4f} high={high:+.4f}"
    )


if __name__ == "__main__":
    main()
