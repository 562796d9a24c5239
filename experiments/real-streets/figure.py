"""The masks on real streets: a few Gardens Point frames, day and night, with each mask source's grid mask.

    python experiments/real-streets/figure.py OUT GARDENS_ROOT [--frames 25 100 175] [--out-png PNG]

Each mask is the one the retriever reads (``MaskSource.grid_mask``, binary, bright = static = kept), from
the checkpoints and segmenters run.sh wrote under OUT: the SynthCity student (seed 0 of ``filter=unet``),
the SynthCity teacher (seed 0 of ``filter=mask2former``), the CamVid student and the CamVid teacher (on
the untrained GeM model: a mask source does not depend on the aggregator). The frames are spread evenly
over the route, fixed before anything was looked at.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from semvpr.config.restore import load_retriever
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast
from semvpr.data.images import load_image
from semvpr.reporting.figures import mask_figure
from semvpr.retrieval.features import grid_size

TRAVERSALS = ("day_left", "night_right")


def camvid_teacher(out: Path) -> Path:
    """The CamVid teacher run.sh evaluated: the one its ``semvpr.segment`` run names (trained there, or
    given as ``CAMVID_TEACHER``)."""
    results = out / "camvid" / "results.json"
    if not results.is_file():
        raise SemvprError(f"{results}: not found (run run.sh first)")
    return Path(json.loads(results.read_text())["teacher"]["checkpoint"])


def grid_masks(overrides: list[str], images: torch.Tensor) -> np.ndarray:
    """(B, H, W) static masks of ``images`` from the mask source the overrides give, at image size."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="eval", overrides=overrides)
    explicit = {o.split("=", 1)[0] for o in overrides}
    retriever, _ = load_retriever(cfg, explicit, warn=False)
    source, backbone = retriever.mask_source, retriever.backbone
    hw = tuple(images.shape[-2:])
    with torch.no_grad(), autocast("cpu"):
        outs = backbone.forward_frozen(images, keep_scales=bool(source.trunk_levels(hw)))
        grid = source.grid_mask(images, outs, None, grid_size(backbone, hw), "binary").float()
    return torch.nn.functional.interpolate(grid, size=hw, mode="nearest")[:, 0].numpy()


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the OUT directory of run.sh")
    parser.add_argument("gardens", type=Path, help="the Gardens Point Walking folder")
    parser.add_argument("--frames", type=int, nargs="+", default=[25, 100, 175])
    parser.add_argument("--size", type=int, nargs=2, default=[270, 480])
    parser.add_argument("--out-png", type=Path, default=Path(__file__).with_name("figure_masks.png"))
    args = parser.parse_args()
    paths = [args.gardens / t / f"Image{i:03d}.jpg" for i in args.frames for t in TRAVERSALS]
    names = [f"{t} {i:03d}" for i in args.frames for t in TRAVERSALS]
    images = torch.stack([load_image(p, args.size) for p in paths])
    run = args.out / "synthcity"
    sources = {
        # Quoted: the sweep's job directories hold '=' and ',' (Hydra's override syntax).
        "synthcity_student": [f"ckpt='{run / 'filter=unet,seed=0' / 'checkpoints' / 'best.ckpt'}'"],
        "synthcity_teacher": [f"ckpt='{run / 'filter=mask2former,seed=0' / 'checkpoints' / 'best.ckpt'}'"],
        "camvid_student": [
            "ckpt=none",
            "aggregator=gem",
            "mask=student",
            f"student.checkpoint={args.out / 'camvid' / 'student_efficientnet_lite0'}",
        ],
        "camvid_teacher": [
            "ckpt=none",
            "aggregator=gem",
            "mask=teacher",
            f"teacher.checkpoint={camvid_teacher(args.out)}",
        ],
    }
    size = [f"data.image_size=[{args.size[0]},{args.size[1]}]", f"paths.cache_dir={args.out / 'cache'}"]
    masks = {key: grid_masks([*overrides, *size], images) for key, overrides in sources.items()}
    columns = {
        "synthcity_student": "SynthCity student",
        "synthcity_teacher": "SynthCity teacher",
        "camvid_student": "CamVid student",
        "camvid_teacher": "CamVid teacher",
    }
    rows = [
        (images[i].permute(1, 2, 0).numpy(), names[i], {key: masks[key][i] for key in columns})
        for i in range(len(paths))
    ]
    mask_figure(rows, columns, args.out_png, "Gardens Point: static masks (bright = kept, dark = removed)")
    print(args.out_png)


if __name__ == "__main__":
    main()
