"""Two saved mask sources' binary masks compared frame by frame on a CamVid split, with a paired bootstrap.

Each source is a directory ``semvpr.segment`` saved: a student (``<run>/student_efficientnet_lite0``) or a
teacher (``<run>/teacher``). It predicts the static mask of every frame of the split the way
``semvpr.segment`` scores it (a student on the frozen ImageNet EfficientNet-Lite0 trunk at ``seg.image_size``,
bf16 autocast; a teacher from the images at ``seg.image_size``, at its own inference size). The masks'
confusion counts are kept per frame; the dynamic IoU of each source is read off the counts pooled over the
frames, and the difference B − A is resampled over the frames (percentile bootstrap, both sources on the same
resampled frames).

    python experiments/camvid-semantic/paired_masks.py A_DIR B_DIR [--root ../shared/realdata/camvid] [--split val] \
        [segment config overrides, e.g. seg.image_size=[360,480]]

Last line: ``split=<s> frames=<n> a=<IoU> b=<IoU> diff=<b-a> low=<2.5 %> high=<97.5 %>``.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig
from torch import Tensor

from semvpr.config.build import build_backbone, teacher_spec
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.data.camvid import read_camvid
from semvpr.data.images import Reading
from semvpr.data.segmentation import SegmentationSet
from semvpr.models.student import load_student
from semvpr.models.teacher_folder import teacher_architecture
from semvpr.reporting.paired import RESAMPLES
from semvpr.segmentation.confusion import Confusion, binary_pred, mask_scores
from semvpr.segmentation.scoring import by_size, loader, student_prob, teacher_outputs

KEY = "dynamic_iou"


def mask_source(folder: Path, cfg: DictConfig, backbone: torch.nn.Module) -> Callable[[Tensor, list[int]], Tensor]:
    """``static probability (B,1,H,W) at size`` of a saved teacher (a folder with config.json) or student."""
    static = list(cfg.teacher.static_classes)
    if (folder / "config.json").is_file():  # a teacher directory (a student's is student.json + weights)
        spec = dataclasses.replace(teacher_spec(cfg), checkpoint=str(folder.resolve()))
        teacher = teacher_architecture(spec).eval()
        return lambda images, size: teacher_outputs(teacher, images, size, static)[1]
    student = load_student(folder, backbone)
    return lambda images, size: student_prob(student, backbone, images, size, bf16=True)


def frame_counts(
    predict: Callable[[Tensor, list[int]], Tensor], frames: SegmentationSet, size: list[int]
) -> np.ndarray:
    """(frames, 19, 3) confusion counts of one source's binary mask, frame by frame, scored at each label's
    size (CamVid: 360x480)."""
    counts: dict[int, np.ndarray] = {}
    for images, labels, index in loader(frames, Reading(size, batch_size=8, num_workers=0)):
        for label_size, pos in by_size(labels).items():  # one group where the labels share a size (CamVid)
            prob = predict(images[pos], list(label_size))
            for row, i in enumerate(pos):
                confusion = Confusion(2)
                confusion.update(binary_pred(prob[row : row + 1, 0]), labels[i][None])
                counts[index[i]] = confusion.counts
    return np.stack([counts[i] for i in range(len(frames))])


@exit_on_user_error
def main() -> None:
    """Score both sources frame by frame and print the paired difference with its interval."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("a", type=Path, help="a teacher or student directory saved by semvpr.segment")
    ap.add_argument("b", type=Path, help="another one, compared with A on the same frames")
    ap.add_argument("--root", type=Path, default=Path("../shared/realdata/camvid"))
    ap.add_argument("--split", default="val", choices=["val", "test"])
    ap.add_argument("--resamples", type=int, default=RESAMPLES)
    ap.add_argument("overrides", nargs="*", help="overrides of conf/segment.yaml, as the run that saved them had")
    args = ap.parse_intermixed_args()  # overrides may follow the options
    if args.resamples < 1:
        ap.error(f"--resamples {args.resamples}: at least 1")
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("segment", overrides=[f"seg.root={args.root.resolve()}", *args.overrides])
    frames = read_camvid(args.root, args.split)  # a wrong --root says so before any model is loaded
    backbone = build_backbone(cfg.backbones.efficientnet_lite0, int(cfg.seed)).eval()
    size, static = [int(v) for v in cfg.seg.image_size], list(cfg.teacher.static_classes)
    a, b = (frame_counts(mask_source(d, cfg, backbone), frames, size) for d in (args.a, args.b))
    score = lambda counts: mask_scores(counts.sum(0), static)[KEY]  # noqa: E731
    rng = np.random.default_rng(0)
    diffs = []
    for _ in range(args.resamples):
        chosen = rng.integers(0, len(a), len(a))
        diffs.append(score(b[chosen]) - score(a[chosen]))
    low, high = np.percentile(diffs, [2.5, 97.5])
    print(
        f"split={args.split} frames={len(a)} a={score(a):.4f} b={score(b):.4f} diff={score(b) - score(a):+.4f} "
        f"low={low:+.4f} high={high:+.4f}"
    )


if __name__ == "__main__":
    main()
