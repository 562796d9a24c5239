"""What a mask costs at evaluation: the teacher's and the student's images/s against the trunk pass alone,
on this CPU, measured in one run.

Evaluation describes each image once: the frozen trunk (EfficientNet-Lite0 to its stride-16 stage, the
default) then the aggregator, and with a mask also the mask source. The student is a U-Net decoder on the
trunk's own skip features, so its mask costs the decoder alone (the trunk pass is shared); the teacher is
a second network (Mask2Former on its own encoder, EfficientNet-Lite2 for CamVid) that sees every image too.
Each is built from the project's configs as ``semvpr.segment`` trains them for CamVid (the teacher model of
``conf/teacher/mask2former.yaml`` with ``conf/segment.yaml``'s ``teacher.model`` over it, the student width
of ``conf/segment.yaml``); speed does not depend on the weights, so they are untrained. Images are
random, at 270x480 (Gardens Point's size in ``data=gardens_point``), under the pipeline's precision (bf16
autocast where the CPU runs it natively). ``--teacher-backbone`` times another encoder for the teacher.

Timed, each the median over ``--repeats`` batches after one warm-up:
- ``trunk``: the trunk pass alone (``forward_frozen``, no skips kept): an evaluation without a mask;
- ``trunk+student``: the trunk pass keeping the skips, the decoder and the grid mask: what an evaluation
  with ``mask=student`` runs per image;
- ``student decoder``: the decoder and grid mask alone on the trunk's skips (the student's own cost);
- ``teacher@HxW``: the teacher's grid mask with the teacher seeing the images at HxW: 270x480 (as given)
  and the size the CamVid teacher trains at (``seg.image_size`` of ``conf/seg/camvid.yaml``: a
  semvpr.segment teacher's ``semvpr.json`` makes it its inference size, and the embedded teacher's is its
  ``image_size``);
- ``espnetv2 s=W``: the grid mask of ESPNetv2 (``teacher=espnetv2``, the widths of its authors' s=2.0 and
  s=1.0 files, untrained) seeing the images at its authors' 1024x512, in fp32 as ``conf/teacher/espnetv2.yaml``
  runs it, beside its own labelling pass on the same images (``predict_train_ids``: what ``semvpr.label`` and the
  pseudo-labels run, the resize in, the network, its softmax resized back and the argmax) and its network alone
  on 1024x512 inputs (the resize in and the scores' resize back and pooling are what the mask adds to it).

    python benchmarks/mask_cost.py [--batch 8] [--repeats 5] [--threads 1] [--teacher-backbone efficientnet_lite0]

Last line: ``name=value`` pairs, ratios of times measured in this run: ``student_over_trunk`` (an
evaluation with the student's mask over one without), ``trunk_share_of_student`` (the part of the
student's pass that is the shared trunk), ``teacher_over_trunk`` (trunk + teacher at 270x480 over the
trunk), ``teacher_inference_over_trunk`` (the same with the teacher at its training size), ``teacher_cut``
(teacher at 270x480 over teacher at its training size), and ``espnetv2_<s>_over_trunk`` (trunk + ESPNetv2 over
the trunk), ``espnetv2_<s>_over_teacher`` (ESPNetv2 over the CamVid teacher at its training size),
``espnetv2_<s>_mask_over_labels`` (its mask over its own labelling pass) and ``espnetv2_<s>_mask_over_network``
(its mask over its network alone).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from semvpr.config.schema import typed
from semvpr.core.errors import exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast, bf16_native
from semvpr.models.backbones import EFFICIENTNET_LITE, IMAGENET_MEAN, IMAGENET_STD, Backbone, EfficientNetLite0Backbone
from semvpr.models.espnetv2 import CITYSCAPES_CHANNELS, ESPNetv2Segmentation
from semvpr.models.masks import StudentMask, TeacherMask
from semvpr.models.student import StudentSpec, student_architecture
from semvpr.models.teacher import Teacher, TeacherSpec, embedded_teacher
from semvpr.retrieval.features import grid_size

SIZE = (270, 480)
#: The size the CamVid teacher trains at (``seg.image_size`` of conf/seg/camvid.yaml), its inference size.
TEACHER_TRAINED_AT = tuple(OmegaConf.load(Path(CONF_DIR) / "seg" / "camvid.yaml").image_size)


def seconds_per_image(run: Callable[[], object], batch: int, repeats: int) -> float:
    """Median seconds per image of ``run`` (one batch), after one warm-up call."""
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        with torch.no_grad():
            run()
        if i:
            times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2] / batch


def camvid_student(backbone: Backbone) -> tuple[StudentMask, StudentSpec]:
    """An untrained student of the CamVid student's spec (``conf/segment.yaml``'s width) over ``backbone``."""
    conf = Path(CONF_DIR)
    node = OmegaConf.load(conf / "student" / "unet.yaml")
    node.width = OmegaConf.load(conf / "segment.yaml").student.width
    del node["static_classes"]  # the teacher's list there; the default list here
    spec = typed(StudentSpec, node, "student")
    return StudentMask(student_architecture(spec, backbone)), spec


def camvid_teacher_node(encoder: str | None = None) -> DictConfig:
    """The CamVid teacher's config (``conf/teacher/mask2former.yaml`` with ``conf/segment.yaml``'s model over
    it; ``encoder``: another EfficientNet-Lite for its pixel encoder)."""
    conf = Path(CONF_DIR)
    node = OmegaConf.load(conf / "teacher" / "mask2former.yaml")
    node.image_size = list(TEACHER_TRAINED_AT)
    node.model = OmegaConf.merge(node.model, OmegaConf.load(conf / "segment.yaml").teacher.get("model", {}))
    if encoder:
        node.model.backbone = encoder
    return node


def camvid_teacher(inference_size: Sequence[int], encoder: str | None = None) -> TeacherMask:
    """An untrained teacher of the CamVid teacher's model, seeing images at ``inference_size``."""
    node = camvid_teacher_node(encoder)
    spec = typed(TeacherSpec, {**OmegaConf.to_container(node), "inference_size": list(inference_size)}, "teacher")
    return TeacherMask(embedded_teacher(spec))


#: The level widths of ESPNetv2's authors' Cityscapes files, by scale.
ESPNETV2_WIDTHS = {"2.0": [32, 128, 256, 512], "1.0": [32, 64, 128, 256]}


def espnetv2_teacher(scale: str) -> TeacherMask:
    """An untrained ESPNetv2 of the authors' widths at ``scale``, as ``conf/teacher/espnetv2.yaml`` builds it."""
    node = OmegaConf.load(Path(CONF_DIR) / "teacher" / "espnetv2.yaml")
    model = ESPNetv2Segmentation(ESPNETV2_WIDTHS[scale], len(CITYSCAPES_CHANNELS)).eval()
    teacher = Teacher(
        model,
        IMAGENET_MEAN,
        IMAGENET_STD,
        inference_size=list(node.inference_size),
        bf16=bool(node.train.bf16),
        id2label=dict(enumerate(CITYSCAPES_CHANNELS)),
        antialias=True,
    )
    return TeacherMask(teacher)


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--teacher-backbone",
        choices=sorted(EFFICIENTNET_LITE),
        help="the teacher's encoder (default: conf/segment.yaml's, the CamVid teacher's)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bf16 = bf16_native("cpu")
    backbone = EfficientNetLite0Backbone(weights="imagenet").eval()
    student, student_spec = camvid_student(backbone)
    teachers = {size: camvid_teacher(size, args.teacher_backbone) for size in (SIZE, TEACHER_TRAINED_AT)}
    teacher_node = camvid_teacher_node(args.teacher_backbone)
    images = torch.rand(args.batch, 3, *SIZE, generator=torch.Generator().manual_seed(0)).contiguous(
        memory_format=torch.channels_last
    )
    grid = grid_size(backbone, SIZE)
    with autocast("cpu"):
        skips = backbone.forward_frozen(images)
    print(
        f"{args.batch} images at {SIZE[0]}x{SIZE[1]}, grid {grid}, {'bf16' if bf16 else 'fp32'}, "
        f"{args.threads} thread(s); student width {student_spec.width}; teacher on {teacher_node.model.backbone}"
    )

    def timed(label: str, run: Callable[[], object]) -> float:
        def under_autocast() -> object:
            with autocast("cpu"):
                return run()

        s = seconds_per_image(under_autocast, args.batch, args.repeats)
        print(f"{label:>28}: {1 / s:7.2f} images/s ({1000 * s:7.1f} ms per image)")
        return s

    t = {
        "trunk": timed("trunk", lambda: backbone.forward_frozen(images, keep_scales=False)),
        "trunk+student": timed(
            "trunk+student (mask=student)",
            lambda: student.grid_mask(images, backbone.forward_frozen(images), None, grid),
        ),
        "student": timed("student decoder alone", lambda: student.grid_mask(images, skips, None, grid)),
    }
    for size, teacher in teachers.items():
        t[f"teacher@{size[0]}x{size[1]}"] = timed(
            f"teacher seeing {size[0]}x{size[1]}", lambda teacher=teacher: teacher.grid_mask(images, [], None, grid)
        )
    at_its_size = torch.rand(len(images), 3, 512, 1024)
    for scale in ESPNETV2_WIDTHS:
        espnet = espnetv2_teacher(scale)
        t[f"espnetv2_{scale}"] = timed(
            f"espnetv2 s={scale} at 1024x512", lambda m=espnet: m.grid_mask(images, [], None, grid)
        )
        labels = espnet.segmenter.predict_train_ids
        t[f"espnetv2_{scale}_labels"] = timed("its labels of the images", lambda label=labels: label(images))
        network = espnet.segmenter.model
        t[f"espnetv2_{scale}_network"] = timed("its network alone on 1024x512", lambda n=network: n(at_its_size))
    teacher_full = t[f"teacher@{SIZE[0]}x{SIZE[1]}"]
    teacher_small = t[f"teacher@{TEACHER_TRAINED_AT[0]}x{TEACHER_TRAINED_AT[1]}"]
    print(
        f"trunk_ips={1 / t['trunk']:.2f} student_ips={1 / t['trunk+student']:.2f} "
        f"teacher_ips={1 / (t['trunk'] + teacher_full):.2f} "
        f"teacher_inference_ips={1 / (t['trunk'] + teacher_small):.2f} "
        f"student_over_trunk={t['trunk+student'] / t['trunk']:.2f} "
        f"trunk_share_of_student={t['trunk'] / t['trunk+student']:.2f} "
        f"teacher_over_trunk={(t['trunk'] + teacher_full) / t['trunk']:.2f} "
        f"teacher_inference_over_trunk={(t['trunk'] + teacher_small) / t['trunk']:.2f} "
        f"teacher_cut={teacher_full / teacher_small:.2f} "
        + " ".join(
            f"espnetv2_{s}_over_trunk={(t['trunk'] + t[f'espnetv2_{s}']) / t['trunk']:.2f} "
            f"espnetv2_{s}_over_teacher={t[f'espnetv2_{s}'] / teacher_small:.2f} "
            f"espnetv2_{s}_ips={1 / t[f'espnetv2_{s}']:.2f} "
            f"espnetv2_{s}_mask_over_labels={t[f'espnetv2_{s}'] / t[f'espnetv2_{s}_labels']:.2f} "
            f"espnetv2_{s}_mask_over_network={t[f'espnetv2_{s}'] / t[f'espnetv2_{s}_network']:.2f}"
            for s in ESPNETV2_WIDTHS
        )
    )


if __name__ == "__main__":
    main()
