"""How well each CamVid segmenter's mask finds the pasted objects: on the composites run.sh evaluated, the IoU of
the pixels its binary mask removes against the pasted pixels, beside the same score on CamVid test.

    python experiments/occluded-streets/mask_iou.py OUT --source student=DIR --source teacher=DIR \
        [--camvid ../shared/realdata/camvid] [--cache OUT/cache] [--image-size 270 480] \
        [--out-dir experiments/occluded-streets] \
        [segment config overrides, as the run that saved the segmenters had]

Each source is a directory ``semvpr.segment`` saved, predicting a frame's static mask as that command scores
it (``semvpr.segment.saved_mask_source``: a student on the frozen trunk, a teacher from the images; kept where
the static probability is at least 0.5, as every binary mask here). The composites are run.sh's: every
``occluded-*`` artifact with the objects pasted under the cache (``CACHE``, by default OUT/cache), each image
once per coverage and seed (pairs share their images' draws), read at ``--image-size`` (by default
``data=gardens_point``'s, at which run.sh evaluated them); CamVid test at ``seg.image_size``. Both are scored at
their labels' own size.

The objects are the moving classes (person to bicycle; on the composites, the pasted pixels); every other
labelled pixel counts as one to keep (on CamVid sky too, which the binary mask removes on purpose: the same
definition on both, not ``semvpr.segment``'s ``dynamic_iou``, which leaves sky out). Per source and image set:
``object_iou`` (removed ∩ objects over removed ∪ objects), ``objects_removed`` (the share of the objects'
pixels removed) and ``rest_removed`` (the share of the other pixels removed), pooled over the frames (and the
seeds of a coverage). Writes ``mask_iou.csv``; last line ``<source>=<CamVid test IoU>/<composites' IoU> ...``.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from semvpr.config.build import build_backbone
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import CONF_DIR, read_json, write_csv
from semvpr.data.camvid import read_camvid
from semvpr.data.classes import IGNORE, NUM_CLASSES, TRAIN_ID_NAMES
from semvpr.data.segmentation import SegmentationSet
from semvpr.segment import saved_mask_source
from semvpr.segmentation.confusion import MOVING_NAMES, REMOVED
from semvpr.segmentation.scoring import frame_counts

FIELDS = ("source", "images", "coverage", "seeds", "frames", "object_iou", "objects_removed", "rest_removed")
#: The size data=gardens_point reads its images at (run.sh's evaluations).
EVALUATED_AT = [int(v) for v in OmegaConf.load(Path(CONF_DIR) / "data" / "gardens_point.yaml").image_size]
#: Composite label maps hold trainIds (the pasted classes, building elsewhere).
TRAIN_ID_LUT = tuple(range(NUM_CLASSES)) + (IGNORE,) * (256 - NUM_CLASSES)


def object_scores(counts: np.ndarray) -> dict[str, float]:
    """object_iou, objects_removed and rest_removed of a (19, [removed, kept, other]) confusion."""
    moving = np.isin(TRAIN_ID_NAMES, MOVING_NAMES)
    removed, total = counts[:, REMOVED], counts.sum(1)
    hit, objects, wrong, rest = removed[moving].sum(), total[moving].sum(), removed[~moving].sum(), total[~moving].sum()
    if objects == 0 or rest == 0:
        raise SemvprError("no object pixels or no other pixels to score a mask against")
    return {
        "object_iou": round(float(hit / (objects + wrong)), 4),
        "objects_removed": round(float(hit / objects), 4),
        "rest_removed": round(float(wrong / rest), 4),
    }


def composites(cache: Path) -> dict[tuple[int, int], SegmentationSet]:
    """{(coverage %, seed): the composites with the objects pasted, each image once} under ``cache``."""
    found: dict[tuple[int, int], dict[str, tuple[Path, Path]]] = defaultdict(dict)
    for key_file in sorted(cache.glob("occluded-*/key.json")):
        key, folder = read_json(key_file, "occluders cache key"), key_file.parent
        if not key.get("paste", True):
            continue  # the holes-only control: the frames without objects
        if not isinstance(key.get("coverage"), int | float) or not isinstance(key.get("seed"), int):
            continue  # another experiment's draws (coverage=camvid): not a cell of this one
        cell = (round(100 * float(key["coverage"])), int(key["seed"]))
        record = read_json(folder / "occluders.json", "occluders record")
        names = record.get("images") if isinstance(record, dict) else None
        if not isinstance(names, dict):
            raise SemvprError(f"{folder / 'occluders.json'} is not an occluders record (no images)")
        for name in names:
            if not isinstance(name, str) or Path(name).is_absolute() or ".." in Path(name).parts:
                raise SemvprError(f"{folder / 'occluders.json'} names {name!r}, not an image inside its folder")
            found[cell][name] = (folder / "images" / name, (folder / "labels" / name).with_suffix(".png"))
    if not found:
        raise SemvprError(f"no composites with pasted objects under {cache}; run run.sh first (or give --cache)")
    return {
        cell: SegmentationSet(*zip(*(pairs[n] for n in sorted(pairs))), label_lut=TRAIN_ID_LUT)
        for cell, pairs in sorted(found.items())
    }


def source_arg(text: str) -> tuple[str, Path]:
    name, sep, folder = text.partition("=")
    if not sep or not name or not Path(folder).is_dir():
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=DIR, a directory semvpr.segment saved")
    return name, Path(folder)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the OUT directory of run.sh")
    ap.add_argument("--source", type=source_arg, action="append", required=True, help="NAME=DIR, repeatable")
    ap.add_argument("--camvid", type=Path, default=Path("../shared/realdata/camvid"))
    ap.add_argument("--cache", type=Path, default=None, help="run.sh's CACHE (default OUT/cache)")
    ap.add_argument(
        "--image-size", type=int, nargs=2, default=EVALUATED_AT, help="H W the composites were evaluated at"
    )
    ap.add_argument("--out-dir", type=Path, default=Path(__file__).parent)
    ap.add_argument("overrides", nargs="*", help="overrides of conf/segment.yaml, as the run that saved them had")
    args = ap.parse_intermixed_args()
    sets = composites(args.cache or args.out / "cache")
    camvid = read_camvid(args.camvid, "test")
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("segment", overrides=[f"seg.root={args.camvid.resolve()}", *args.overrides])
    backbone = build_backbone(cfg.backbones.efficientnet_lite0, int(cfg.seed)).eval()
    rows, last = [], []
    for name, folder in args.source:
        predict = saved_mask_source(folder, cfg, backbone)
        counts = frame_counts(predict, camvid, [int(v) for v in cfg.seg.image_size])
        camvid_scores = object_scores(counts.sum(0))
        rows.append({"source": name, "images": "camvid test", "frames": len(counts), **camvid_scores})
        by_coverage: dict[int, list[np.ndarray]] = defaultdict(list)
        for (coverage, _seed), frames in sets.items():
            by_coverage[coverage].append(frame_counts(predict, frames, args.image_size))
        pooled = []
        for coverage, per_seed in sorted(by_coverage.items()):
            counts = np.concatenate(per_seed)
            pooled.append(counts)
            scores = object_scores(counts.sum(0))
            rows.append(
                {
                    "source": name,
                    "images": "composites",
                    "coverage": coverage,
                    "seeds": len(per_seed),
                    "frames": len(counts),
                    **scores,
                }
            )
        composite_iou = object_scores(np.concatenate(pooled).sum(0))["object_iou"]
        last.append(f"{name}={camvid_scores['object_iou']}/{composite_iou}")
    write_csv(args.out_dir / "mask_iou.csv", FIELDS, rows)
    for row in rows:
        print(" ".join(f"{k}={row.get(k, '')}" for k in FIELDS))
    print(" ".join(last))


if __name__ == "__main__":
    main()
