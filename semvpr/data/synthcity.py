"""SynthCity: procedural street routes with pixel labels in the @UTM@ and Cityscapes layouts.

Each route is a long strip of facades (``synthcity_render``) over a road seen in perspective
(``synthcity_ground``). The database traversal captures it every 5 m in June; the query traversal
at random positions in November (autumn foliage), at another time of day, with other vehicles and
people. Everything is a pure function of (preset, seed, GENERATOR_VERSION).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import multiprocessing
import os
import signal
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from semvpr.core.cache import build_once
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import atomic_dir, check_dir_path, reclaim_orphans
from semvpr.core.logs import Progress
from semvpr.data.classes import TRAIN_ID_NAMES, train_ids_to_label_ids
from semvpr.data.synthcity_ground import make_ground_pool
from semvpr.data.synthcity_render import DYNAMIC_MIN, SKY, RenderSpec, build_panorama, make_texture_pool, render_capture

# 2: calibrated difficulty (coverage 0.64, lighting 0.25, 3 liveries).
# 3: static classes of different value: seasonal vegetation (June database, November queries), ground in
#    perspective paved from a city-wide pool, signs designed per place; per-class pixel fractions in stats;
#    coverage 0.78, lighting 0.1 (calibrated on val).
GENERATOR_VERSION = 3
DB_STEP_M = 5.0
ZONE, LETTER = "17", "T"
EAST0, NORTH0, ROUTE_SPACING_M = 580_000.0, 4_470_000.0, 1_000.0  # one northing line per route
DATES = ("20240612", "20241119")  # database / query traversal timestamps
JPEG_QUALITY = 90


@dataclass(frozen=True)
class SplitSpec:
    """Routes of one split and how many captures each route gets."""

    routes: int
    db_per_route: int  # database spacing is DB_STEP_M, so this also sets the route length
    q_per_route: int


@dataclass(frozen=True)
class Preset:
    """Image size, difficulty and split sizes of one SynthCity variant."""

    render: RenderSpec
    vpr: dict[str, SplitSpec]
    seg: dict[str, SplitSpec]  # Cityscapes-format captures on their own routes (db_per_route = length/5 m)
    dynamic_bounds: tuple[float, float]  # acceptable mean measured dynamic fraction (checked by tests)


PRESETS: dict[str, Preset] = {
    "tiny": Preset(RenderSpec(64, 80), {"train": SplitSpec(1, 24, 16), "val": SplitSpec(1, 12, 12),
                                        "test": SplitSpec(1, 24, 24)},
                   {"train": SplitSpec(1, 40, 16), "val": SplitSpec(1, 40, 8)}, (0.45, 0.7)),
    # 180x240: at 120x160 a conv5_3 cell sees the whole frame, and the binary oracle's calibration gain
    # stayed below +10 with every scene knob tried (experiments/synthcity-calibration).
    "default": Preset(RenderSpec(180, 240), {"train": SplitSpec(3, 200, 134), "val": SplitSpec(3, 150, 200),
                                             "test": SplitSpec(3, 200, 350)},
                      {"train": SplitSpec(2, 200, 200), "val": SplitSpec(1, 200, 100)}, (0.5, 0.65)),
}  # fmt: skip


#: RenderSpec knobs a dataset may override (difficulty); the image size is the preset's unless given.
KNOBS = tuple(f.name for f in dataclasses.fields(RenderSpec) if f.name not in ("height", "width"))
UNIT_KNOBS = ("coverage", "lighting", "season")  # fractions in [0, 1]
POSITIVE_KNOBS = ("view_m", "liveries")  # the others may be 0 (no jitter, no pitch range)
MIN_SIDE = 32  # pixels: both trunks (VGG16 conv5_3, ResNet50 layer3) reduce by 16, so >= 2x2 feature cells


def get_preset(
    preset: str, render: Mapping[str, float] | None = None, image_size: Sequence[int] | None = None
) -> Preset:
    """Preset by name, with RenderSpec difficulty knobs overridden (e.g. ``{"pitch_m": 8.0}``) and the
    images drawn at ``image_size`` ([H, W]; None = the preset's own size)."""
    if preset not in PRESETS:
        raise SemvprError(f"unknown SynthCity preset {preset!r}; choose one of {sorted(PRESETS)}")
    p = PRESETS[preset]
    changes: dict[str, float | int] = {}
    if image_size is not None:
        size = list(image_size)
        if len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and v >= MIN_SIDE for v in size):
            raise SemvprError(f"SynthCity image_size={size!r} must be [height, width], whole numbers >= {MIN_SIDE}")
        changes["height"], changes["width"] = size
    for name, value in (render or {}).items():
        if name not in KNOBS:
            raise SemvprError(
                f"SynthCity has no render knob {name!r}; choose among {list(KNOBS)} "
                "(the image size is data.image_size, --image-size on the command line)"
            )
        default = getattr(p.render, name)
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
            or (isinstance(default, int) and not float(value).is_integer())
        ):
            raise SemvprError(
                f"SynthCity {name}={value!r} must be {'a whole' if isinstance(default, int) else 'a'} number"
            )
        value = type(default)(value)
        if name in UNIT_KNOBS and not 0.0 <= value <= 1.0:
            raise SemvprError(f"SynthCity {name}={value} is outside [0, 1]")
        if value < 0 or (name in POSITIVE_KNOBS and value == 0):
            raise SemvprError(f"SynthCity {name}={value} must be {'> 0' if name in POSITIVE_KNOBS else '>= 0'}")
        changes[name] = value
    return dataclasses.replace(p, render=dataclasses.replace(p.render, **changes))


def utm_name(east: float, north: float, timestamp: str, note: str) -> str:
    """VPR-datasets-downloader name: 14 '@'-separated fields, empty ones allowed."""
    fields = [f"{east:.2f}", f"{north:.2f}", ZONE, LETTER, "", "", "", "", "", "", "", "", timestamp, note]
    return "@" + "@".join(fields) + "@.jpg"


def _save(img: np.ndarray, path: Path, **kw: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(path, **kw)


class Route(NamedTuple):
    """One route: what it is drawn for (``vpr`` or ``seg``), its split, its global id (which fixes its
    seeds and northing line) and its capture counts."""

    kind: str
    split: str
    rid: int
    spec: SplitSpec

    @property
    def images(self) -> int:
        return self.spec.db_per_route + self.spec.q_per_route if self.kind == "vpr" else self.spec.q_per_route


def _routes(p: Preset) -> list[Route]:
    """Every route of the preset, ids counted across VPR and segmentation routes."""
    out: list[Route] = []
    for kind, splits in (("vpr", p.vpr), ("seg", p.seg)):
        for split, spec in splits.items():
            for _ in range(spec.routes):
                out.append(Route(kind, split, len(out), spec))
    return out


#: A dataset of at least this many images is drawn by one process per core (route by route); a smaller
#: one inline, where starting the processes would cost more than it saves. Both write the same files.
PARALLEL_MIN_IMAGES = 1000


def _draw_route(root: Path, seed: int, spec: RenderSpec, route: Route) -> tuple[list[tuple[float, float]], np.ndarray]:
    """Render and save one route's captures; returns their (dynamic, sky) fractions and, for a VPR route,
    its per-class pixel counts. A pure function of its arguments (every random draw is seeded by them)."""
    kind, split, rid, s = route
    pool = make_texture_pool(np.random.default_rng([seed, GENERATOR_VERSION, 7_777]), spec.liveries)
    ground_pool = make_ground_pool(np.random.default_rng([seed, GENERATOR_VERSION, 7_778]))
    length = s.db_per_route * DB_STEP_M
    pano = build_panorama(np.random.default_rng([seed, GENERATOR_VERSION, rid]), length, spec, ground_pool)
    q_x = np.sort(np.random.default_rng([seed, GENERATOR_VERSION, rid, 99]).uniform(0, length, s.q_per_route))
    if kind == "vpr":
        captures = [(DB_STEP_M * (i + 0.5), 0, i) for i in range(s.db_per_route)]
        captures += [(x, 1, i) for i, x in enumerate(q_x)]
    else:
        captures = [(x, i % 2, i) for i, x in enumerate(q_x)]
    fractions: list[tuple[float, float]] = []
    class_pixels = np.zeros(len(TRAIN_ID_NAMES), np.int64)
    for x, trav, i in captures:
        rng = np.random.default_rng([seed, GENERATOR_VERSION, rid, trav, i])
        img, label = render_capture(pano, float(x), rng, spec, pool, query=trav == 1)
        fractions.append((float((label >= DYNAMIC_MIN).mean()), float((label == SKY).mean())))
        if kind == "vpr":
            class_pixels += np.bincount(label.ravel(), minlength=len(TRAIN_ID_NAMES))[: len(TRAIN_ID_NAMES)]
            sub = "queries" if trav else "database"
            name = utm_name(EAST0 + x, NORTH0 + ROUTE_SPACING_M * rid, DATES[trav], f"r{rid}{sub[0]}{i:04d}")
            _save(img, root / "images" / split / sub / name, format="JPEG", quality=JPEG_QUALITY)
            _save(label, root / "labels" / split / sub / (name[:-4] + ".png"), format="PNG")
        else:
            city = f"route{rid}"
            stem = f"{city}_{rid:06d}_{i:06d}"
            _save(img, root / "seg" / "leftImg8bit" / split / city / f"{stem}_leftImg8bit.png", format="PNG")
            _save(
                train_ids_to_label_ids(label),
                root / "seg" / "gtFine" / split / city / f"{stem}_gtFine_labelIds.png",
                format="PNG",
            )
    return fractions, class_pixels


def _cores() -> int:
    """Cores this process may run on (the affinity mask, not the host's count, where the OS tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _quiet_worker() -> None:
    """A drawing process leaves Ctrl-C to its parent, which stops the pool, and ends quietly when stopped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def generate(
    root: Path,
    preset: str,
    seed: int,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
    workers: int | None = None,
) -> dict:
    """Write the whole dataset under ``root``; returns (and saves as stats.json) measured statistics.

    ``workers``: drawing processes (None: one per core for a dataset of PARALLEL_MIN_IMAGES or more, else
    inline). Routes are independent, so the files and statistics do not depend on it."""
    p = get_preset(preset, render, image_size)
    routes = _routes(p)
    total = sum(r.images for r in routes)
    if workers is None:
        workers = min(_cores(), len(routes)) if total >= PARALLEL_MIN_IMAGES else 1
    draw = functools.partial(_draw_route, root, seed, p.render)
    bar = Progress(f"SynthCity {preset} seed {seed}", total)
    results: dict[int, tuple[list[tuple[float, float]], np.ndarray]] = {}
    if workers <= 1:
        for route in routes:
            results[route.rid] = draw(route)
            bar.update(route.images)
    else:
        # Longest routes first, so that the cores finish together; `with` terminates the pool on an error
        # or a signal (the caller's atomic directory then removes what was drawn). fork: the children draw
        # with NumPy and PIL only (never torch), and a spawned child would re-run a calling script that
        # has no `if __name__ == "__main__"` guard.
        with multiprocessing.get_context("fork").Pool(workers, initializer=_quiet_worker) as pool:
            pending = [
                (route, pool.apply_async(draw, (route,)))
                for route in sorted(routes, key=lambda r: r.images, reverse=True)
            ]
            for route, result in pending:
                results[route.rid] = result.get()
                bar.update(route.images)
    bar.close()
    fractions: dict[str, list[tuple[float, float]]] = {}
    class_pixels = np.zeros(len(TRAIN_ID_NAMES), np.int64)  # over every VPR capture
    for kind, split, rid, _ in routes:
        route_fractions, route_pixels = results[rid]
        fractions.setdefault(f"{'seg-' if kind == 'seg' else ''}{split}", []).extend(route_fractions)
        class_pixels += route_pixels
    stats = {
        "preset": preset,
        "seed": seed,
        "version": GENERATOR_VERSION,
        "render": dataclasses.asdict(p.render),
        "dynamic_fraction": {k: round(float(np.mean([f[0] for f in v])), 4) for k, v in fractions.items()},
        "sky_fraction": {k: round(float(np.mean([f[1] for f in v])), 4) for k, v in fractions.items()},
        "images": {k: len(v) for k, v in fractions.items()},
        "class_fraction": {n: round(float(c / class_pixels.sum()), 4) for n, c in zip(TRAIN_ID_NAMES, class_pixels)},
    }
    (root / "stats.json").write_text(json.dumps(stats, indent=1, sort_keys=True))
    return stats


def _key(preset: str, seed: int, render: Mapping[str, float] | None, image_size: Sequence[int] | None = None) -> dict:
    """Cache key: the preset, seed, generator version and every effective render setting (size included)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SemvprError(f"SynthCity seed={seed!r} must be a whole number >= 0")
    return {
        "preset": preset,
        "seed": int(seed),
        "version": GENERATOR_VERSION,
        "render": dataclasses.asdict(get_preset(preset, render, image_size).render),
    }


def ensure_synthcity(
    cache_dir: str | Path,
    preset: str = "default",
    seed: int = 0,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
) -> Path:
    """Dataset root in the artifact cache, generated on first use (kind "synthcity")."""
    key = _key(preset, seed, render, image_size)
    return build_once(cache_dir, "synthcity", key, lambda tmp: generate(tmp, preset, int(seed), render, image_size))


def read_split(
    preset: str,
    seed: int,
    cache_dir: str | Path,
    split: str,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
):
    """PlaceSet of one VPR split (train/val/test), with the trainId label maps attached; the city is
    drawn at ``image_size`` (``data.image_size``), so the loader never resamples it."""
    from semvpr.data.places import read_utm_folder

    if split not in get_preset(preset).vpr:
        raise SemvprError(f"SynthCity has no VPR split {split!r}; choose one of {sorted(get_preset(preset).vpr)}")
    root = ensure_synthcity(cache_dir, preset, seed, render, image_size)
    places = read_utm_folder(root, split)

    def labels(paths: tuple[Path, ...]) -> tuple[Path, ...]:
        return tuple(root / "labels" / split / p.parent.name / f"{p.stem}.png" for p in paths)

    return dataclasses.replace(
        places,
        name=f"synthcity-{preset}-s{seed}/{split}",
        db_labels=labels(places.db_paths),
        q_labels=labels(places.q_paths),
    )


def read_segmentation(
    preset: str,
    seed: int,
    cache_dir: str | Path,
    split: str,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
):
    """SegmentationSet (Cityscapes format) of the separate segmentation routes (train/val)."""
    from semvpr.data.segmentation import read_cityscapes

    if split not in get_preset(preset).seg:
        raise SemvprError(
            f"SynthCity has no segmentation split {split!r}; choose one of {sorted(get_preset(preset).seg)}"
        )
    return read_cityscapes(ensure_synthcity(cache_dir, preset, seed, render, image_size) / "seg", split)


def parse_knob(text: str) -> tuple[str, float]:
    """``knob=value`` from the command line (validated by ``get_preset``)."""
    name, _, value = text.partition("=")
    try:
        return name, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected <knob>=<number>, got {text!r}") from None


def add_render_arguments(ap: argparse.ArgumentParser) -> None:
    """``--render KNOB=VALUE`` (repeatable, into ``args.render``) and ``--image-size H W``: what
    ``get_preset`` takes as ``dict(args.render)`` and ``args.image_size``."""
    ap.add_argument(
        "--render",
        type=parse_knob,
        action="append",
        default=[],
        metavar="KNOB=VALUE",
        help=f"override a difficulty knob (repeatable), one of {', '.join(KNOBS)}",
    )
    ap.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), help="image size (default: the preset's)")


def _stopped(signum: int, _frame: object) -> None:
    raise SemvprError(f"stopped by {signal.Signals(signum).name}; the unfinished dataset was removed")


@exit_on_user_error
def main(argv: list[str] | None = None) -> None:
    """CLI: generate a SynthCity dataset into a new directory."""
    ap = argparse.ArgumentParser(prog="python -m semvpr.data.synthcity", description=main.__doc__)
    ap.add_argument("--out", required=True, type=Path, help="new (or empty) output directory")
    ap.add_argument("--preset", default="default", choices=sorted(PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    add_render_arguments(ap)
    args = ap.parse_args(argv)
    out: Path = args.out
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SemvprError(f"--out {out} already exists and is not an empty directory; choose a new path or remove it")
    check_dir_path(out, "--out")
    render = dict(args.render)
    _key(args.preset, args.seed, render, args.image_size)  # validate before creating anything
    out.parent.mkdir(parents=True, exist_ok=True)
    reclaim_orphans(out.parent)
    for sig in (signal.SIGTERM, signal.SIGINT):  # a kill ends in atomic_dir's cleanup and one line
        signal.signal(sig, _stopped)
    with atomic_dir(out) as tmp:
        stats = generate(tmp, args.preset, args.seed, render, args.image_size)
    print(
        f"wrote {sum(stats['images'].values())} images to {out} (measured dynamic fraction {stats['dynamic_fraction']})"
    )


if __name__ == "__main__":
    main()
