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
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from semvpr.config.build import build_backbone
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.data.camvid import read_camvid
from semvpr.reporting.paired import RESAMPLES
from semvpr.segment import saved_mask_source
from semvpr.segmentation.confusion import mask_scores
from semvpr.segmentation.scoring import frame_counts

KEY = "dynamic_iou"


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
    a, b = (frame_counts(saved_mask_source(d, cfg, backbone), frames, size) for d in (args.a, args.b))
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
