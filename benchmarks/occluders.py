"""What pasting CamVid's objects into a place set costs beside describing it: images/s of building the occluded
set (compositing only) against the frozen trunk's pass over the same composites, in one run.

The set is built from the project's config (``data=gardens_point`` by default; any frame-aligned set's
overrides), its composites by ``semvpr.data.occluders.occlude`` into an empty cache folder: cutting the
objects from CamVid's test split, one draw per image, writing each composite and its label map (what a cold
``data.occluders`` run does once per coverage and seed). The trunk pass is what an evaluation without a mask
then runs on them: each composite read and resized to ``data.image_size``, batched, the frozen trunk's forward
pass under the pipeline's precision (bf16 autocast where the CPU runs it natively), on ``--threads`` threads.

    python benchmarks/occluders.py [--root ../shared/realdata/gardens_point] [--camvid ../shared/realdata/camvid] \
        [--coverage 0.2] [--seed 0] [--batch 16] [--threads 1] [--limit N] [--work DIR] [data overrides ...]

``--limit N``: the first N database and N query images only. Last line: ``images=<n> composite_ips=<images/s>
trunk_ips=<images/s> ratio=<composite seconds / trunk seconds>``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from semvpr.config.build import build_backbone, build_places
from semvpr.config.plan import data_settings
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.precision import autocast
from semvpr.data.images import load_image
from semvpr.data.occluders import OccluderSpec, occlude
from semvpr.data.places import PlaceSet


def trunk_seconds(backbone: torch.nn.Module, paths: list[Path], size: list[int], batch: int) -> float:
    """Wall seconds of reading ``paths`` at ``size`` and the frozen trunk's pass over them, ``batch`` at a time."""
    t0 = time.perf_counter()
    with torch.no_grad(), autocast("cpu"):
        for start in range(0, len(paths), batch):
            images = torch.stack([load_image(p, size) for p in paths[start : start + batch]])
            backbone.forward_frozen(images.contiguous(memory_format=torch.channels_last))
    return time.perf_counter() - t0


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("../shared/realdata/gardens_point"))
    ap.add_argument("--camvid", type=Path, default=Path("../shared/realdata/camvid"))
    ap.add_argument("--data", default="gardens_point", help="the place set's config (conf/data)")
    ap.add_argument("--coverage", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--limit", type=int, default=None, help="the first N database and N query images only")
    ap.add_argument("--work", type=Path, help="cache folder for the composites (default: a temporary one, removed)")
    ap.add_argument("overrides", nargs="*", help="overrides of the data config, e.g. data.database=day_right")
    args = ap.parse_intermixed_args()
    if args.batch < 1 or args.threads < 1 or (args.limit is not None and args.limit < 1):
        raise SemvprError("--batch, --threads and --limit take whole numbers >= 1")
    torch.set_num_threads(args.threads)
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("eval", overrides=[f"data={args.data}", f"data.root={args.root.resolve()}", *args.overrides])
    places = build_places(data_settings(cfg), ("test",))["test"]
    if args.limit is not None:
        n = args.limit  # only the images matter here: a set of the first ones, without its ground truth
        places = PlaceSet(
            places.name, places.db_paths[:n], places.q_paths[:n], places.db_utm[:n], places.q_utm[:n], root=places.root
        )
    spec = OccluderSpec.from_mapping(
        {"source": "camvid", "root": str(args.camvid.resolve()), "coverage": args.coverage, "seed": args.seed}
    )
    backbone = build_backbone(cfg.backbone, int(cfg.seed)).eval()
    size = [int(v) for v in cfg.data.image_size]
    with tempfile.TemporaryDirectory(prefix="semvpr-occluders-") as tmp:
        cache = args.work or Path(tmp)
        if cache.exists() and any(cache.glob("occluded-*")):
            raise SemvprError(f"--work {cache} already holds composites; give an empty folder (nothing would be timed)")
        t0 = time.perf_counter()
        occluded = occlude(places, spec, cache)
        composite_s = time.perf_counter() - t0
        paths = list(dict.fromkeys([*occluded.db_paths, *occluded.q_paths]))  # an image on both sides: once
        trunk_seconds(backbone, paths[: args.batch], size, args.batch)  # warm-up, not timed
        trunk_s = trunk_seconds(backbone, paths, size, args.batch)
    print(
        f"{places.name}: {len(paths)} images, coverage {args.coverage:.0%}, seed {args.seed}, {args.threads} thread(s)"
    )
    print(f"compositing: {composite_s:.1f} s; trunk pass at {size[0]}x{size[1]}, batch {args.batch}: {trunk_s:.1f} s")
    print(
        f"images={len(paths)} composite_ips={len(paths) / composite_s:.2f} trunk_ips={len(paths) / trunk_s:.2f} "
        f"ratio={composite_s / trunk_s:.3f}"
    )


if __name__ == "__main__":
    main()
