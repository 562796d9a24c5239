"""SynthCity: procedural street routes with pixel labels in the @UTM@ and Cityscapes layouts.

Each route is a long strip of facades (``synthcity_render``) over a road seen in perspective
(``synthcity_ground``). The database traversal captures it every 5 m in June; the query traversal
at random positions in November (autumn foliage), at another time of day, with other vehicles and
people. Everything is a pure function of (preset, seed, GENERATOR_VERSION).

The training split is also a set of places (``PlaceIds``): one per database position, holding its
database image and the queries within 2.5 m of it. ``traversals`` > 0 adds that many traversals of the
training routes, each revisiting every database position at another date (November and June in turn,
another time of day each), drawn into an artifact of their own so that the dataset itself is never
touched: every training place then has 1 + ``traversals`` images from different traversals, the
P places × K images that ``recipe=gsv`` trains on (GSV-Cities has several years per place).
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from PIL import Image

from semvpr.core.cache import build_once
from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import atomic_dir, check_dir_path, reclaim_orphans
from semvpr.core.logs import Progress
from semvpr.data.classes import TRAIN_ID_NAMES, train_ids_to_label_ids
from semvpr.data.synthcity_ground import make_ground_pool
from semvpr.data.synthcity_render import (
    DYNAMIC_MIN,
    SKY,
    Panorama,
    RenderSpec,
    build_panorama,
    make_texture_pool,
    render_capture,
)

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
#: What the extra training traversals are (in their artifact's key): 1 = every database position, the
#: November layer for even traversals and June for odd ones, the query traversal's lighting change.
TRAVERSALS_VERSION = 1
TRAVERSAL_LIGHTING = 1.0


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
    "tiny": Preset(
        RenderSpec(64, 80),
        {"train": SplitSpec(1, 24, 16), "val": SplitSpec(1, 12, 12), "test": SplitSpec(1, 24, 24)},
        {"train": SplitSpec(1, 40, 16), "val": SplitSpec(1, 40, 8)},
        (0.45, 0.7),
    ),
    # 180x240: at 120x160 a conv5_3 cell sees the whole frame, and the binary oracle's calibration gain
    # stayed below +10 with every scene knob tried (experiments/synthcity-calibration).
    "default": Preset(
        RenderSpec(180, 240),
        {"train": SplitSpec(3, 200, 134), "val": SplitSpec(3, 150, 200), "test": SplitSpec(3, 200, 350)},
        {"train": SplitSpec(2, 200, 200), "val": SplitSpec(1, 200, 100)},
        (0.5, 0.65),
    ),
}


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


def _route_world(seed: int, spec: RenderSpec, route: Route) -> tuple[np.ndarray, Panorama]:
    """The texture pool of the dataset and the static street of one route (each drawn from its own seed)."""
    pool = make_texture_pool(np.random.default_rng([seed, GENERATOR_VERSION, 7_777]), spec.liveries)
    ground_pool = make_ground_pool(np.random.default_rng([seed, GENERATOR_VERSION, 7_778]))
    length = route.spec.db_per_route * DB_STEP_M
    return pool, build_panorama(np.random.default_rng([seed, GENERATOR_VERSION, route.rid]), length, spec, ground_pool)


def _draw_route(root: Path, seed: int, spec: RenderSpec, route: Route) -> tuple[list[tuple[float, float]], np.ndarray]:
    """Render and save one route's captures; returns their (dynamic, sky) fractions and, for a VPR route,
    its per-class pixel counts. A pure function of its arguments (every random draw is seeded by them)."""
    kind, split, rid, s = route
    pool, pano = _route_world(seed, spec, route)
    length = s.db_per_route * DB_STEP_M
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


def traversal_date(t: int) -> str:
    """Timestamp of extra traversal ``t``: November and June in turn, a year earlier every two."""
    return f"{2023 - t // 2}{'11' if t % 2 == 0 else '06'}15"


def _draw_traversals(root: Path, seed: int, spec: RenderSpec, traversals: int, route: Route) -> None:
    """Render and save ``traversals`` revisits of every database position of one VPR route, under
    ``images/<split>/traversal<t>/`` (labels under ``labels/``). Seeded by (seed, route, 2 + t, position),
    draws the database (0) and query (1) traversals never use."""
    _, split, rid, s = route
    pool, pano = _route_world(seed, spec, route)
    for t in range(traversals):
        for i in range(s.db_per_route):
            x = DB_STEP_M * (i + 0.5)
            rng = np.random.default_rng([seed, GENERATOR_VERSION, rid, 2 + t, i])
            img, label = render_capture(pano, x, rng, spec, pool, query=t % 2 == 0, lighting=TRAVERSAL_LIGHTING)
            name = utm_name(EAST0 + x, NORTH0 + ROUTE_SPACING_M * rid, traversal_date(t), f"r{rid}t{t}p{i:04d}")
            _save(img, root / "images" / split / f"traversal{t}" / name, format="JPEG", quality=JPEG_QUALITY)
            _save(label, root / "labels" / split / f"traversal{t}" / (name[:-4] + ".png"), format="PNG")


def _cores() -> int:
    """Cores this process may run on (the affinity mask, not the host's count, where the OS tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _quiet_worker() -> None:
    """A drawing process leaves Ctrl-C to its parent, which stops the pool, and ends quietly when stopped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _map_routes(
    draw: Callable[[Route], Any], routes: list[Route], sizes: dict[int, int], label: str, workers: int | None = None
) -> dict[int, Any]:
    """``draw`` of every route (by route id) in ``workers`` processes (None: one per core when the routes
    hold PARALLEL_MIN_IMAGES images or more, else inline). Routes are independent, so the files do not
    depend on it."""
    total = sum(sizes.values())
    if workers is None:
        workers = min(_cores(), len(routes)) if total >= PARALLEL_MIN_IMAGES else 1
    bar = Progress(label, total)
    results: dict[int, Any] = {}
    if workers <= 1:
        for route in routes:
            results[route.rid] = draw(route)
            bar.update(sizes[route.rid])
    else:
        # Longest routes first, so that the cores finish together; `with` terminates the pool on an error
        # or a signal (the caller's atomic directory then removes what was drawn). fork: the children draw
        # with NumPy and PIL only (never torch), and a spawned child would re-run a calling script that
        # has no `if __name__ == "__main__"` guard.
        with multiprocessing.get_context("fork").Pool(workers, initializer=_quiet_worker) as pool:
            pending = [
                (route, pool.apply_async(draw, (route,)))
                for route in sorted(routes, key=lambda r: sizes[r.rid], reverse=True)
            ]
            for route, result in pending:
                results[route.rid] = result.get()
                bar.update(sizes[route.rid])
    bar.close()
    return results


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
    draw = functools.partial(_draw_route, root, seed, p.render)
    sizes = {r.rid: r.images for r in routes}
    results = _map_routes(draw, routes, sizes, f"SynthCity {preset} seed {seed}", workers)
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


def generate_traversals(root: Path, p: Preset, seed: int, traversals: int, label: str = "SynthCity") -> None:
    """Write ``traversals`` extra traversals of the training routes of preset ``p``'s dataset drawn with
    ``seed`` under ``root`` (module docstring); the dataset's own files are never read or written. ``label``
    names the dataset in the progress bar."""
    routes = [r for r in _routes(p) if r.kind == "vpr" and r.split == "train"]
    draw = functools.partial(_draw_traversals, root, seed, p.render, traversals)
    sizes = {r.rid: traversals * r.spec.db_per_route for r in routes}
    _map_routes(draw, routes, sizes, f"{label} seed {seed}: {traversals} traversals", None)


def _traversals_key(
    preset: str, seed: int, render: Mapping[str, float] | None, image_size: Sequence[int] | None, traversals: int
) -> dict:
    """Cache key of the extra traversals: the dataset's key, their number and what they are."""
    if isinstance(traversals, bool) or not isinstance(traversals, int) or traversals < 0:
        raise SemvprError(f"data.traversals={traversals!r} must be a whole number >= 0 (extra training traversals)")
    return {"dataset": _key(preset, seed, render, image_size), "traversals": traversals, "version": TRAVERSALS_VERSION}


def ensure_traversals(
    cache_dir: str | Path,
    preset: str,
    seed: int,
    traversals: int,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
) -> Path:
    """Root of the extra training traversals in the artifact cache (kind "synthcity_traversals"), drawn on
    first use."""
    key = _traversals_key(preset, seed, render, image_size, traversals)
    label = f"SynthCity {preset}"
    return build_once(
        cache_dir,
        "synthcity_traversals",
        key,
        lambda tmp: generate_traversals(tmp, get_preset(preset, render, image_size), int(seed), traversals, label),
    )


def training_places(db_utm: np.ndarray, q_utm: np.ndarray, db_per_route: int):
    """The places of a training split: one per database position (route, 5 m step), holding every image
    whose route position is within half a step of it; grouped by route. Read from the images' UTM
    (``utm_name``), so it holds for the split as drawn and for its extra traversals alike."""
    from semvpr.data.places import PlaceIds

    utm = np.concatenate([np.asarray(db_utm).reshape(-1, 2), np.asarray(q_utm).reshape(-1, 2)])
    route = np.rint((utm[:, 1] - NORTH0) / ROUTE_SPACING_M).astype(np.int64)
    step = np.clip(np.floor((utm[:, 0] - EAST0) / DB_STEP_M).astype(np.int64), 0, db_per_route - 1)
    places, ids = np.unique(route * db_per_route + step, return_inverse=True)
    groups = np.unique(places // db_per_route, return_inverse=True)[1]
    n_db = len(np.asarray(db_utm).reshape(-1, 2))
    return PlaceIds(db=ids[:n_db], q=ids[n_db:], groups=groups)


def read_split(
    preset: str,
    seed: int,
    cache_dir: str | Path,
    split: str,
    render: Mapping[str, float] | None = None,
    image_size: Sequence[int] | None = None,
    traversals: int = 0,
):
    """PlaceSet of one VPR split (train/val/test), with the trainId label maps attached; the city is
    drawn at ``image_size`` (``data.image_size``), so the loader never resamples it. The training split
    also carries its places (:func:`training_places`); ``traversals`` > 0 adds that many extra traversals
    of it as queries (``data.traversals``, which ``recipe=gsv`` sets; val and test never change)."""
    from semvpr.data.places import PlaceSet, parse_utm_name, read_utm_folder

    if split not in get_preset(preset).vpr:
        raise SemvprError(f"SynthCity has no VPR split {split!r}; choose one of {sorted(get_preset(preset).vpr)}")
    if split == "train":
        _traversals_key(preset, seed, render, image_size, traversals)  # validate before drawing anything
    root = ensure_synthcity(cache_dir, preset, seed, render, image_size)
    places = read_utm_folder(root, split)

    def labels(paths: tuple[Path, ...], base: Path = root) -> tuple[Path, ...]:
        return tuple(base / "labels" / split / p.parent.name / f"{p.stem}.png" for p in paths)

    drawn = dataclasses.replace(
        places,
        name=f"synthcity-{preset}-s{seed}/{split}",
        db_labels=labels(places.db_paths),
        q_labels=labels(places.q_paths),
    )
    if split != "train":
        return drawn
    db_per_route = get_preset(preset).vpr[split].db_per_route
    drawn = dataclasses.replace(drawn, place_ids=training_places(drawn.db_utm, drawn.q_utm, db_per_route))
    if not traversals:
        return drawn
    extra_root = ensure_traversals(cache_dir, preset, seed, traversals, render, image_size)
    extra = tuple(
        image
        for t in range(traversals)
        for image in sorted((extra_root / "images" / split / f"traversal{t}").glob("*.jpg"))
    )
    q_utm = np.concatenate([drawn.q_utm, np.array([parse_utm_name(p) for p in extra]).reshape(-1, 2)])
    return PlaceSet(
        name=f"{drawn.name}+{traversals}traversals",
        db_paths=drawn.db_paths,
        q_paths=drawn.q_paths + extra,
        db_utm=drawn.db_utm,
        q_utm=q_utm,
        db_labels=drawn.db_labels,
        q_labels=drawn.q_labels + labels(extra, extra_root),
        place_ids=training_places(drawn.db_utm, q_utm, db_per_route),
        semantic_source=drawn,
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


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.data.synthcity``."""
    ap = argparse.ArgumentParser(
        prog="python -m semvpr.data.synthcity", description="Generate a SynthCity dataset into a new directory."
    )
    ap.add_argument("--out", required=True, type=Path, help="new (or empty) output directory")
    ap.add_argument("--preset", default="default", choices=sorted(PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    add_render_arguments(ap)
    return ap


@exit_on_user_error
def main(argv: list[str] | None = None) -> None:
    """CLI: generate a SynthCity dataset into a new directory."""
    args = parser().parse_args(argv)
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
