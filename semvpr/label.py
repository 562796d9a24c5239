"""A teacher's labels of a folder of images: ``python -m semvpr.label images=DIR teacher=... teacher.checkpoint=...``.

Any trained teacher (ESPNetv2 from its authors' file, a saved semvpr.segment teacher, a Mask2Former directory)
labels every image below DIR at the image's own size: ``train_ids/<name>.png`` (Cityscapes trainIds, a palette
PNG in Cityscapes' colours, 255 where the teacher's class has no trainId), ``static/<name>.png`` (the binary
static mask the retriever reads: 255 kept, 0 removed) and ``label.json`` (the teacher and each image's share of
each class and of removed pixels), all in the run directory ``outputs/label/<date>/<time>``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image

from semvpr.config.checks import check_overrides_or_exit
from semvpr.config.command import hydra_command
from semvpr.config.plan import teacher_spec, thread_plan
from semvpr.core.device import resolve
from semvpr.core.errors import SemvprError
from semvpr.core.io import write_json
from semvpr.core.logs import progress
from semvpr.core.stops import run_stoppable
from semvpr.data.classes import IGNORE, TRAIN_ID_COLOURS, TRAIN_ID_NAMES
from semvpr.data.images import load_image
from semvpr.data.places import folder_images
from semvpr.models.teacher import Teacher
from semvpr.models.teacher_folder import teacher_architecture
from semvpr.segmentation.confusion import REMOVED, binary_pred
from semvpr.segmentation.scoring import teacher_outputs

#: A palette of 256 RGB entries: trainId i in its Cityscapes colour, everything else black.
PALETTE = [v for colour in TRAIN_ID_COLOURS for v in colour] + [0] * (3 * (256 - len(TRAIN_ID_COLOURS)))


def label_pngs(train_ids: np.ndarray, static: np.ndarray) -> tuple[Image.Image, Image.Image]:
    """(H,W) trainIds as a palette PNG image and an (H,W) bool static mask as a 0/255 grey image."""
    ids = Image.fromarray(train_ids.astype(np.uint8), mode="P")
    ids.putpalette(PALETTE)
    return ids, Image.fromarray(np.where(static, 255, 0).astype(np.uint8), mode="L")


def image_summary(train_ids: np.ndarray, static: np.ndarray) -> dict[str, Any]:
    """One image's share of each trainId it holds (and of pixels with none), and of pixels the mask removes."""
    values, counts = np.unique(train_ids, return_counts=True)
    names = {i: n for i, n in enumerate(TRAIN_ID_NAMES)} | {IGNORE: "none"}
    shares = {names[int(v)]: round(int(c) / train_ids.size, 4) for v, c in zip(values, counts, strict=True)}
    return {"classes": shares, "removed": round(1.0 - float(static.mean()), 4)}


@torch.no_grad()
def label_folder(teacher: Teacher, paths: list[Path], root: Path, out: Path, static_names: list[str]) -> list[dict]:
    """Write each image's label PNGs under ``out`` (its path below ``root`` kept); returns their summaries."""
    rows = []
    for path in progress(paths, "labels", len(paths)):
        image = load_image(path)
        ids, prob = teacher_outputs(teacher, image[None].to(teacher.device), image.shape[-2:], static_names)
        train_ids = ids[0].cpu().numpy()
        static = (binary_pred(prob[0, 0]) != REMOVED).cpu().numpy()
        name = path.relative_to(root).with_suffix(".png")
        for folder, png in zip(("train_ids", "static"), label_pngs(train_ids, static), strict=True):
            (out / folder / name).parent.mkdir(parents=True, exist_ok=True)
            png.save(out / folder / name)
        rows.append({"image": str(name.with_suffix(path.suffix)), **image_summary(train_ids, static)})
    return rows


def build_labelling_teacher(cfg: DictConfig) -> Teacher:
    """The trained teacher the config names, on its device, eval mode; the embedded teacher (no checkpoint)
    is refused: this command trains nothing."""
    spec = teacher_spec(cfg)
    if spec.name == "mask2former" and not spec.checkpoint:
        raise SemvprError(
            "teacher.checkpoint=null: semvpr.label labels with a trained teacher; give teacher.checkpoint=DIR "
            "(<semvpr.segment run>/teacher or a Mask2Former directory), or teacher=espnetv2 teacher.checkpoint=FILE"
        )
    return teacher_architecture(spec).to(resolve(cfg.get("device"))).eval().requires_grad_(False)


@hydra_command("label", "label.json")
def _hydra_main(cfg: DictConfig, run_dir: Path) -> None:
    root = Path(str(cfg.images))
    paths = folder_images(root, "images")
    with thread_plan(cfg, gpu=resolve(cfg.get("device")).type == "cuda").stage("teacher"):
        teacher = build_labelling_teacher(cfg)
        static_names = list(cfg.teacher.static_classes)
        rows = label_folder(teacher, paths, root, run_dir, static_names)
    trained_on = teacher.trained_on.describe() if teacher.trained_on is not None else "unknown"
    record = {
        "teacher": str(cfg.teacher.name),
        "checkpoint": str(cfg.teacher.checkpoint),
        "trained_on": trained_on,
        "images": len(rows),
        "removed": round(float(np.mean([r["removed"] for r in rows])), 4),
        "per_image": rows,
    }
    write_json(run_dir / "label.json", record)
    print(json.dumps({"run_dir": str(run_dir), "images": len(rows), "removed": record["removed"]}))


def main() -> None:
    """Console entry point."""
    check_overrides_or_exit(sys.argv[1:], "label")
    run_stoppable(_hydra_main, sys.argv[1:])


if __name__ == "__main__":
    main()
