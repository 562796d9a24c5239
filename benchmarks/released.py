"""What a mask costs on each released architecture: images/s without a mask, with a student's and with the
teacher's, at the author's evaluation size, on this CPU, measured in one run.

Each architecture is semvpr's re-derivation of a release (``semvpr/models/released.py``) with random
weights of the release's shapes (speed does not depend on the weights): pytorch-NetVlad's VGG16 + NetVLAD
(64 × 512) and CosPlace / EigenPlaces' ResNet50 layer4 + GeM + FC (512) at 480x640 (Pitts30k's size: both
evaluate images at their own size), MixVPR's ResNet50 layer3 + MixVPR (1024 × 4) at 320x320, BoQ's
ResNet50 layer3 + BoQ (512 × 32) at 384x384, and the DINOv2 releases at 322x322: BoQ's ViT-B/14 (no
final norm) + BoQ (384 × 32) and SALAD's ViT-B/14 with its class token + SALAD (64 × 128 + 256). The
student is a U-Net decoder of the CamVid student's width on that trunk's skips (a student trained on that
trunk would cost the same; none decodes DINOv2's token maps, so those rows have no student time); the
teacher is the CamVid teacher (``benchmarks/mask_cost.py``'s) seeing the images at its training size.
Timed, each the fastest of ``--repeats`` batches after one warm-up round, the three interleaved (so that
other processes on the cores slow them alike), under the pipeline's precision (bf16 autocast where the CPU
runs it natively):

- ``none``: trunk then aggregator;
- ``student``: trunk keeping the skips, the decoder's grid mask, the masked aggregator;
- ``teacher``: the teacher's grid mask, then trunk and masked aggregator.

    python benchmarks/released.py [--batch 2] [--repeats 3] [--threads 1] [--only mixvpr boq] [--out FILE.json]

One line per architecture; the last line ``name=value`` pairs: each architecture's ``student_over_none``
(where a student applies) and ``teacher_over_none`` (time ratios measured in this run). ``--out`` writes
every time as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import torch
from mask_cost import TEACHER_TRAINED_AT, camvid_student, camvid_teacher
from torch import nn

from semvpr.core.errors import exit_on_user_error
from semvpr.core.precision import autocast, bf16_native
from semvpr.models.aggregators.boq import BoQ
from semvpr.models.aggregators.gem import GeM
from semvpr.models.aggregators.mixvpr import MixVPR
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.aggregators.salad import SALAD
from semvpr.models.backbones import Backbone, ResNet50Backbone, VGG16Backbone
from semvpr.models.dinov2 import DINOv2Backbone
from semvpr.models.masks import TeacherMask
from semvpr.retrieval.features import grid_size

#: layout -> (trunk, aggregator, the author's evaluation size)
ARCHITECTURES: dict[str, Callable[[], tuple[Backbone, nn.Module, tuple[int, int]]]] = {
    "netvlad": lambda: (VGG16Backbone(), NetVLAD(64, 512), (480, 640)),
    "mixvpr": lambda: (ResNet50Backbone("layer3", train_from=None), MixVPR(1024, (20, 20), 1024, 4), (320, 320)),
    "cosplace": lambda: (ResNet50Backbone("layer4", train_from=None), GeM(2048, fc_dim=512), (480, 640)),
    "boq": lambda: (ResNet50Backbone("layer3", train_from=None), BoQ(1024, 512, 64, 2, 32, 3), (384, 384)),
    "boq_dinov2": lambda: (DINOv2Backbone(final_norm=False), BoQ(768, 384, 64, 2, 32, 3), (322, 322)),
    "salad": lambda: (
        DINOv2Backbone(class_token=True),
        SALAD(768, 64, 128, 256, global_token="class"),
        (322, 322),
    ),
}


def time_architecture(
    name: str, teacher: TeacherMask, batch: int, repeats: int
) -> tuple[dict[str, float], tuple[int, int]]:
    """Seconds per image of ``name`` without a mask, with a student's (where one decodes the trunk) and with
    ``teacher``'s, and its size."""
    torch.manual_seed(0)
    backbone, aggregator, size = ARCHITECTURES[name]()
    backbone, aggregator = backbone.eval(), aggregator.eval()
    student = camvid_student(backbone)[0] if backbone.image_maps else None
    images = torch.rand(batch, 3, *size, generator=torch.Generator().manual_seed(0))
    images = images.contiguous(memory_format=torch.channels_last)
    grid = grid_size(backbone, size)

    def describe(trunk: list[torch.Tensor], mask: torch.Tensor | None) -> torch.Tensor:
        return aggregator(backbone.forward_trainable(trunk[-1]), mask)

    def with_student() -> torch.Tensor:
        trunk = backbone.forward_frozen(images)
        return describe(trunk, student.grid_mask(images, trunk, None, grid))

    def with_teacher() -> torch.Tensor:
        mask = teacher.grid_mask(images, [], None, grid)
        return describe(backbone.forward_frozen(images, keep_scales=False), mask)

    runs = {
        "none": lambda: describe(backbone.forward_frozen(images, keep_scales=False), None),
        **({"student": with_student} if student is not None else {}),
        "teacher": with_teacher,
    }
    times: dict[str, list[float]] = {k: [] for k in runs}
    for i in range(repeats + 1):  # interleaved, so that other processes on the cores slow each timing alike
        for k, run in runs.items():
            t0 = time.perf_counter()
            with torch.no_grad(), autocast("cpu"):
                run()
            if i:  # the first round warms up
                times[k].append(time.perf_counter() - t0)
    return {k: min(v) / batch for k, v in times.items()}, size


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--only", nargs="+", choices=sorted(ARCHITECTURES), default=sorted(ARCHITECTURES))
    ap.add_argument("--out", type=Path, help="write the times as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bf16 = bf16_native("cpu")
    teacher = camvid_teacher(TEACHER_TRAINED_AT)
    load = os.getloadavg()[0]
    print(
        f"batch {args.batch}, {args.repeats} repeats, {'bf16' if bf16 else 'fp32'}, {args.threads} thread(s), "
        f"{cpu_name()} (load {load:.1f}); teacher at {TEACHER_TRAINED_AT[0]}x{TEACHER_TRAINED_AT[1]}"
    )
    results: dict[str, dict[str, float | list[int]]] = {}
    for name in args.only:
        t, size = time_architecture(name, teacher, args.batch, args.repeats)
        results[name] = {
            "image_size": list(size),
            **{f"{k}_s_per_image": round(v, 4) for k, v in t.items()},
            **{f"{k}_images_per_s": round(1 / v, 3) for k, v in t.items()},
            **{f"{k}_over_none": round(t[k] / t["none"], 3) for k in ("student", "teacher") if k in t},
        }
        print(
            f"{name:>10} at {size[0]}x{size[1]}: "
            + " ".join(f"{k} {1 / v:6.2f} images/s" for k, v in t.items())
            + "".join(f"  {k}/none {t[k] / t['none']:.2f}" for k in ("student", "teacher") if k in t),
            flush=True,
        )
    if args.out is not None:
        meta = {"batch": args.batch, "repeats": args.repeats, "threads": args.threads, "bf16": bf16, "cpu": cpu_name()}
        # Other processes on the cores slow every pass: the 1-minute load average at the start and the end.
        meta["load_average"] = [round(load, 2), round(os.getloadavg()[0], 2)]
        args.out.write_text(json.dumps({"settings": meta, "architectures": results}, indent=1) + "\n")
    print(
        " ".join(
            f"{name}.{k}={r[k]}"
            for name, r in results.items()
            for k in ("student_over_none", "teacher_over_none")
            if k in r
        )
    )


if __name__ == "__main__":
    main()
