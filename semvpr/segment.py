"""Segmenters on a segmentation set: ``python -m semvpr.segment seg=camvid seg.root=DIR [overrides]``.

Trains the embedded Mask2Former teacher on the set's train split (cached; its settings were chosen
on val), scores it on val and test and saves it in Hugging Face format (``<run dir>/teacher``, for
``teacher.checkpoint=``; given ``teacher.checkpoint=DIR``, or ``teacher=espnetv2 teacher.checkpoint=FILE``, it
scores that teacher instead and leaves it where it is); labels the train images with it and trains one U-Net
student per entry of ``backbones`` on those pseudo-labels, scored against the ground truth, and saves each as
``<run dir>/student_<backbone>`` (for ``student.checkpoint=``; no entry, ``~backbone@backbones.<name>``: no
pseudo-labels, no student). Both directories record the data they
were trained on. Writes ``results.json``, ``figure_masks.png`` and CSV / TensorBoard logs into
``outputs/segment/<date>/<time>``; the last stdout line is a JSON summary naming the directories.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from semvpr.config.build import build_backbone
from semvpr.config.checks import check_config, check_overrides_or_exit
from semvpr.config.command import hydra_command
from semvpr.config.components import instantiate_node
from semvpr.config.plan import student_spec, teacher_spec, thread_plan
from semvpr.core.device import resolve
from semvpr.core.io import atomic_dir, write_json
from semvpr.core.logs import no_hf_progress_bars
from semvpr.core.provenance import TrainedOn, data_domain
from semvpr.core.stops import run_stoppable
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES, static_lut
from semvpr.data.images import Reading, load_image
from semvpr.data.places import common_root
from semvpr.data.segmentation import SegmentationSet, load_train_ids
from semvpr.models.backbones import Backbone
from semvpr.models.student import Student, StudentSpec, load_student, save_student
from semvpr.models.teacher import Teacher
from semvpr.models.teacher_folder import teacher_architecture, write_teacher_record
from semvpr.segmentation.confusion import binary_pred
from semvpr.segmentation.pseudolabels import LabelledImages
from semvpr.segmentation.scoring import score_student, score_teacher, student_prob, teacher_outputs
from semvpr.segmentation.training import build_student, build_teacher

SPLITS = ("train", "val", "test")
#: Keys of the last stdout line, per model.
SUMMARY_KEYS = ("miou", "dynamic_iou", "nonstatic_iou", "static_removed", "train_s")


def dataset_classes(seg: SegmentationSet) -> list[int]:
    """trainIds the set's labels can hold: mIoU is averaged over these (CamVid has 11 of the 19)."""
    if seg.label_lut is None:
        return list(range(len(TRAIN_ID_NAMES)))
    return sorted({v for v in seg.label_lut if v != IGNORE})


def save_teacher(teacher: Any, out: Path, image_size: list[int], trained_on: TrainedOn) -> None:
    """Hugging Face format (config.json, model.safetensors, preprocessor_config.json) and semvpr.json (the
    size it was trained at, its training data), renamed into place when complete."""
    from transformers import Mask2FormerImageProcessor

    with atomic_dir(out) as tmp, no_hf_progress_bars():
        teacher.model.save_pretrained(tmp)
        Mask2FormerImageProcessor(
            image_mean=teacher.mean.flatten().tolist(),
            image_std=teacher.std.flatten().tolist(),
            size={"height": image_size[0], "width": image_size[1]},
            ignore_index=IGNORE,
            do_reduce_labels=False,
        ).save_pretrained(tmp)
        write_teacher_record(tmp, image_size, trained_on)


def saved_mask_source(
    folder: Path, cfg: DictConfig, backbone: Backbone
) -> Callable[[torch.Tensor, list[int]], torch.Tensor]:
    """``static probability (B,1,H,W) at size`` of images, from a directory this command saved: a teacher (a
    folder with config.json) from the images, or a student on ``backbone``'s frozen outputs (in bf16 autocast
    where ``student.bf16`` says so), as the run scored them; on ``backbone``'s device."""
    static, device = list(cfg.teacher.static_classes), next(backbone.parameters()).device
    if (folder / "config.json").is_file():  # a teacher directory (a student's is student.json + weights)
        spec = dataclasses.replace(teacher_spec(cfg), checkpoint=str(folder.resolve()))
        teacher = teacher_architecture(spec).to(device).eval()
        return lambda images, size: teacher_outputs(teacher, images.to(device), size, static)[1]
    student, bf16 = load_student(folder, backbone).to(device), student_spec(cfg).bf16
    return lambda images, size: student_prob(student, backbone, images, size, bf16=bf16)


def replay_log(csv_path: Path, loggers: list[Any], prefix: str) -> None:
    """Copy a cached artifact's training curve (Lightning CSV) into this run's loggers under ``prefix``."""
    if not csv_path.is_file():
        return
    with csv_path.open() as handle:
        for row in csv.DictReader(handle):
            values = {f"{prefix}/{k}": float(v) for k, v in row.items() if k not in ("epoch", "step") and v}
            for logger in loggers:
                logger.log_metrics(values, step=int(row["step"]))


def log_scores(loggers: list[Any], name: str, split: str, scores: dict[str, Any]) -> None:
    """Scalar scores as ``<split>/<model>/<metric>`` (per-class IoU as ``.../iou_<class>``)."""
    values = {f"{split}/{name}/{k}": float(v) for k, v in scores.items() if isinstance(v, (int, float))}
    values.update({f"{split}/{name}/iou_{c}": float(v) for c, v in scores.get("class_iou", {}).items()})
    for logger in loggers:
        logger.log_metrics(values, step=0)


@torch.no_grad()
def figure_rows(
    seg: SegmentationSet,
    teacher: Teacher,
    students: dict[str, tuple[Student, Backbone]],
    static_names: list[str],
    image_size: list[int],
    num_images: int,
    bf16: bool,
) -> list[tuple[np.ndarray, str, dict[str, np.ndarray]]]:
    """Image, ground-truth static mask and each model's binary mask for test images spread over the split."""
    lut = static_lut(tuple(static_names))
    idx = np.unique(np.linspace(0, len(seg) - 1, num_images).round().astype(int))
    rows = []
    for i in idx.tolist():
        ids = load_train_ids(seg.labels[i], from_label_ids=True, lut=seg.label_lut).numpy()
        size = ids.shape
        image = load_image(seg.images[i], image_size)[None]
        masks = {"gt": np.where(ids == IGNORE, np.nan, lut[np.clip(ids, 0, 255)])}
        masks["teacher"] = (
            binary_pred(teacher_outputs(teacher, image, size, static_names)[1][0, 0]).float().cpu().numpy()
        )
        for name, (student, backbone) in students.items():
            prob = student_prob(student, backbone, image, size, bf16)
            masks[name] = binary_pred(prob[0, 0]).float().cpu().numpy()
        native = (load_image(seg.images[i]).permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        rows.append((native, seg.images[i].name, masks))
    return rows


@dataclass(frozen=True)
class StudentRun:
    """What every student of a segment run shares: the teacher's labels it learns, how the sets are read to score
    it against the teacher's static classes, the splits scored (the last one's numbers at the top level of its
    entry), the data it is trained on, where it is saved, the cache and the loggers."""

    labelled: LabelledImages
    reading: Reading
    static_names: list[str]
    scored: tuple[str, ...]
    trained_on: TrainedOn
    run_dir: Path
    cache_dir: str
    loggers: list[Any]


def train_students(
    spec: StudentSpec,
    backbones: dict[str, tuple[Backbone, str]],
    sets: dict[str, SegmentationSet],
    run: StudentRun,
) -> tuple[dict[str, Any], dict[str, tuple[Student, Backbone]]]:
    """A student per frozen backbone (with the name of its weights), scored and saved as
    ``run_dir/student_<name>``; returns each one's results entry and each one with its backbone (for the
    figure), by name."""
    entries, students = {}, {}
    for name, (backbone, weights) in backbones.items():
        tic = time.time()
        student = build_student(spec, backbone, run.labelled, run.reading.image_size, run.cache_dir)
        entry: dict[str, Any] = {"backbone": name, "weights": weights, "build_s": time.time() - tic}
        fitted = json.loads((student.artifact / "metrics.json").read_text())
        entry.update(train_s=fitted["train_seconds"], train_iou_vs_labels=fitted["train/iou_vs_labels"])
        for split in run.scored:
            scores = score_student(student, backbone, sets[split], run.reading, run.static_names, spec.bf16)
            log_scores(run.loggers, f"student_{name}", split, scores)
            entry[split] = scores
        entry.update(entry[run.scored[-1]])
        if run.scored[-1] == "test":
            del entry["test"]
        size = list(run.reading.image_size)
        folder = save_student(
            student, spec, name, backbone.frozen_identity(), size, run.trained_on, run.run_dir / f"student_{name}"
        )
        entry["checkpoint"] = str(folder)
        entries[f"student_{name}"] = entry
        students[f"student_{name}"] = (student, backbone)
    return entries, students


def run(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Check, build the teacher, pseudo-labels and students, score them, draw the figure; returns what
    results.json holds."""
    from semvpr.reporting.figures import mask_figure
    from semvpr.segmentation.pseudolabels import pseudo_labels

    start = time.time()
    check_config(cfg)
    sets = {split: instantiate_node(cfg.seg[split]) for split in SPLITS}
    teacher_settings, student_settings = teacher_spec(cfg), student_spec(cfg)
    size = [int(v) for v in cfg.seg.image_size]
    classes = dataset_classes(sets["train"])
    static_names = list(teacher_settings.static_classes)
    workers, batch = int(cfg.seg.num_workers), int(cfg.eval_batch_size)
    run_dir.mkdir(parents=True, exist_ok=True)
    loggers = [instantiate_node(node, save_dir=str(run_dir)) for node in cfg.logger.values()]

    device = resolve(cfg.get("device"))
    threads = thread_plan(cfg, gpu=device.type == "cuda")
    # The students' trunks first: a setting none of them takes is one line now, not after the teacher has trained.
    backbones = {
        name: (build_backbone(node, int(cfg.seed), device=device).eval(), str(node.get("weights", "none")))
        for name, node in (cfg.get("backbones") or {}).items()
    }
    tic = time.time()
    with threads.stage("teacher"):
        teacher = build_teacher(teacher_settings, sets["train"], sets["val"], cfg.paths.cache_dir, device)
    build_s = time.time() - tic
    trained_on = TrainedOn(str(cfg.seg.name), data_domain(cfg.seg.get("domain")))
    # A given teacher (teacher.checkpoint=) is scored and distilled here, not trained; it stays where it is.
    checkpoint, train_s = teacher_settings.checkpoint, None
    if not checkpoint:
        artifact = Path(cfg.paths.cache_dir) / teacher.teacher_key
        train_s = json.loads((artifact / "metrics.json").read_text())["train_seconds"]
        replay_log(artifact / "logs" / "metrics.csv", loggers, "teacher")
        checkpoint = run_dir / "teacher"
        save_teacher(teacher, checkpoint, size, trained_on)
    results: dict[str, Any] = {"teacher": {"train_s": train_s, "build_s": build_s, "checkpoint": str(checkpoint)}}
    reading = Reading(size, batch, workers)
    scored = ("val", "test") if cfg.score_test else ("val",)
    for split in scored:
        with threads.stage("frozen"):
            scores = score_teacher(teacher, sets[split], reading, classes, static_names)
        log_scores(loggers, "teacher", split, scores)
        results["teacher"][split] = scores
    # The last scored split's numbers at the top level (test, or val when settings are being chosen).
    results["teacher"].update(results["teacher"][scored[-1]])
    if cfg.score_test:
        del results["teacher"]["test"]

    students: dict[str, tuple[Student, Backbone]] = {}
    if backbones:  # none (~backbone@backbones.<name>): the teacher is scored, nothing is distilled from it
        tic = time.time()
        root = common_root(list(sets["train"].images))
        with threads.stage("frozen"):
            labels = pseudo_labels(
                teacher,
                list(sets["train"].images),
                Reading(size, teacher_settings.predict_batch_size, workers),
                cfg.paths.cache_dir,
                root,
            )
        results["pseudo_labels"] = {"dir": str(labels), "images": len(sets["train"]), "build_s": time.time() - tic}
        with threads.stage("student"):
            student_run = StudentRun(
                LabelledImages(list(sets["train"].images), labels, root),
                reading,
                static_names,
                scored,
                trained_on,
                run_dir,
                cfg.paths.cache_dir,
                loggers,
            )
            entries, students = train_students(student_settings, backbones, sets, student_run)
        results.update(entries)

    columns = {
        "gt": "ground truth\n(bright = static)",
        "teacher": "teacher mask",
        **{k: f"student mask\n({k.removeprefix('student_')})" for k in students},
    }
    rows = figure_rows(
        sets[scored[-1]], teacher, students, static_names, size, int(cfg.num_figure_images), bool(student_settings.bf16)
    )
    mask_figure(
        rows,
        columns,
        run_dir / "figure_masks.png",
        f"{cfg.seg.name} {scored[-1]}: static masks (bright = kept, dark = removed; unlabelled = image only)",
    )
    for logger in loggers:
        logger.finalize("success")
    results.update(
        {
            "dataset": {
                "name": cfg.seg.name,
                "root": str(cfg.seg.root),
                "image_size": size,
                "classes": [TRAIN_ID_NAMES[c] for c in classes],
                **{s: len(sets[s]) for s in SPLITS},
            },
            "scored_on": "test (val under each model's 'val')" if cfg.score_test else "val only (test not scored)",
            "threads": threads.record(),
            "config": OmegaConf.to_container(cfg, resolve=True),
            "wall_time_s": time.time() - start,
        }
    )
    write_json(run_dir / "results.json", results)
    return results


def summary(results: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """The last stdout line: run dir, the headline test numbers per model and the directory each model is
    saved in (``teacher.checkpoint=`` / ``student.checkpoint=``)."""
    line: dict[str, Any] = {"run_dir": str(run_dir)}
    for model, entry in results.items():
        if model == "teacher" or model.startswith("student_"):
            line.update({f"{model}/{k}": round(float(entry[k]), 3) for k in SUMMARY_KEYS if entry.get(k) is not None})
            line[f"{model}/checkpoint"] = entry["checkpoint"]
    return line


@hydra_command("segment", "results.json")
def _hydra_main(cfg: DictConfig, run_dir: Path) -> None:
    print(json.dumps(summary(run(cfg, run_dir), run_dir)))


def main() -> None:
    """Console entry point; user errors and a stop (SIGTERM, Ctrl-C) become one line on stderr and exit code 2."""
    check_overrides_or_exit(sys.argv[1:], "segment")
    run_stoppable(_hydra_main, sys.argv[1:])


if __name__ == "__main__":
    main()
