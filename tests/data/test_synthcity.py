"""SynthCity generator: determinism, layouts, label sanity, cache reuse and the CLI's error handling.

All tests share one tiny-preset dataset built through the artifact cache (module fixture); the
numbers they check come from PRESETS["tiny"], so they hold whatever sizes the preset is tuned to.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import semvpr.data.synthcity as synthcity
import semvpr.data.synthcity_render as render
from semvpr.core.cache import LOCK_DIR, artifact_dir
from semvpr.core.errors import SemvprError
from semvpr.data.classes import TRAIN_ID_NAMES, TRAIN_TO_LABEL, label_ids_to_train_ids
from semvpr.data.places import parse_utm_name
from semvpr.data.segmentation import read_cityscapes
from semvpr.data.synthcity import (
    DATES,
    DB_STEP_M,
    PRESETS,
    ensure_synthcity,
    generate,
    get_preset,
    main,
    read_segmentation,
    read_split,
)
from semvpr.data.synthcity_ground import FACADE_D, build_ground, ground_distance, make_ground_pool
from tests.helpers import REPO

TINY = PRESETS["tiny"]
DYNAMIC_MIN = TRAIN_ID_NAMES.index("sky")  # trainIds >= 10 are dynamic / uninformative
ROAD, BUILDING, POLE, SIGN, VEG, TERRAIN = (
    TRAIN_ID_NAMES.index(n) for n in ("road", "building", "pole", "traffic sign", "vegetation", "terrain")
)


def tree(root: Path, skip: tuple[str, ...] = ("key.json",)) -> dict[str, str]:
    """Relative path → sha256 of every file under ``root`` (``skip``: top-level names left out)."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.relative_to(root).parts[0] not in skip
    }


def ids(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


def vpr_images(root: Path, split: str, sub: str) -> list[Path]:
    return sorted((root / "images" / split / sub).glob("*.jpg"))


def label_of(root: Path, image: Path) -> Path:
    return root / "labels" / image.parent.parent.name / image.parent.name / f"{image.stem}.png"


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def dataset(cache_dir: Path) -> Path:
    """The tiny preset, seed 0, generated once into the artifact cache."""
    return ensure_synthcity(cache_dir, "tiny", 0)


# --- determinism -------------------------------------------------------------------------------


def test_same_seed_is_byte_identical(dataset: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    again.mkdir()
    stats = generate(again, "tiny", 0)
    first, second = tree(dataset), tree(again)
    assert sorted(first) == sorted(second) and len(first) > 100
    assert first == second
    assert stats == json.loads((dataset / "stats.json").read_text())


def test_drawing_processes_write_the_same_files(dataset: Path, tmp_path: Path) -> None:
    """Routes drawn by two processes, longest first, give the inline generator's files and statistics."""
    stats = generate(tmp_path, "tiny", 0, workers=2)
    assert tree(tmp_path) == tree(dataset)
    assert stats == json.loads((dataset / "stats.json").read_text())


def test_other_seed_gives_other_images(dataset: Path, tmp_path: Path) -> None:
    other = tmp_path / "seed1"
    other.mkdir()
    generate(other, "tiny", 1)
    # Database captures sit at fixed route positions, so their names repeat; their pixels must not.
    db0, db1 = vpr_images(dataset, "test", "database"), vpr_images(other, "test", "database")
    assert [p.name for p in db0] == [p.name for p in db1]
    for a, b in zip(db0, db1):
        assert a.read_bytes() != b.read_bytes(), a.name
    # Query positions are random per seed.
    q0, q1 = ({p.name for p in vpr_images(root, "test", "queries")} for root in (dataset, other))
    assert q0 != q1
    assert json.loads((other / "stats.json").read_text())["seed"] == 1


# --- layout ------------------------------------------------------------------------------------


def test_vpr_layout_counts_names_and_labels(dataset: Path) -> None:
    assert {p.name for p in dataset.iterdir()} == {"images", "labels", "seg", "stats.json", "key.json"}
    assert sorted(p.name for p in (dataset / "images").iterdir()) == sorted(TINY.vpr)
    for split, spec in TINY.vpr.items():
        for sub, per_route, date in (
            ("database", spec.db_per_route, DATES[0]),
            ("queries", spec.q_per_route, DATES[1]),
        ):
            images = vpr_images(dataset, split, sub)
            assert len(images) == spec.routes * per_route, (split, sub)
            assert len(list((dataset / "labels" / split / sub).iterdir())) == len(images)
            for image in images:
                fields = image.name.split("@")
                assert len(fields) == 16 and fields[13] == date, image.name
                east, north = parse_utm_name(image)
                assert np.isfinite([east, north]).all()
                with Image.open(image) as img:
                    assert img.format == "JPEG" and img.mode == "RGB"
                    assert img.size == (TINY.render.width, TINY.render.height)
                    size = img.size
                with Image.open(label_of(dataset, image)) as lab:
                    assert lab.format == "PNG" and lab.mode == "L" and lab.size == size, image.name


def route_positions(root: Path, split: str, sub: str) -> dict[float, np.ndarray]:
    """Northing line → sorted eastings of one split's images."""
    utm = np.array([parse_utm_name(p) for p in vpr_images(root, split, sub)])
    return {float(n): np.sort(utm[utm[:, 1] == n, 0]) for n in np.unique(utm[:, 1])}


def test_routes_disjoint_and_database_every_5m(dataset: Path) -> None:
    lines: dict[str, set[float]] = {}
    for split, spec in TINY.vpr.items():
        db, q = route_positions(dataset, split, "database"), route_positions(dataset, split, "queries")
        assert len(db) == spec.routes and set(q) == set(db), split
        lines[split] = set(db)
        for north, east in db.items():
            assert len(east) == spec.db_per_route
            np.testing.assert_allclose(np.diff(east), DB_STEP_M, atol=0.011)
            assert pytest.approx(5.0) == DB_STEP_M
            # Queries fall along the same stretch, each within half a step of a database image.
            gaps = np.abs(q[north][:, None] - east[None, :]).min(1)
            assert len(q[north]) == spec.q_per_route and gaps.max() <= DB_STEP_M / 2 + 0.011
    splits = sorted(lines)
    for i, a in enumerate(splits):
        for b in splits[i + 1 :]:
            assert not lines[a] & lines[b], (a, b)
            # Far beyond any positive radius: no cross-split positives.
            assert min(abs(x - y) for x in lines[a] for y in lines[b]) > 100.0


def test_segmentation_layout(dataset: Path) -> None:
    seg = dataset / "seg"
    assert sorted(p.name for p in (seg / "leftImg8bit").iterdir()) == sorted(TINY.seg)
    assert sorted(p.name for p in (seg / "gtFine").iterdir()) == sorted(TINY.seg)
    for split, spec in TINY.seg.items():
        pairs = read_cityscapes(seg, split)
        assert len(pairs) == spec.routes * spec.q_per_route
        assert len(list((seg / "gtFine" / split).rglob("*.png"))) == len(pairs)
        for image, label in zip(pairs.images, pairs.labels):
            with Image.open(image) as img, Image.open(label) as lab:
                assert img.mode == "RGB" and lab.mode == "L" and img.size == lab.size
                assert img.size == (TINY.render.width, TINY.render.height)
    val = TINY.seg["val"]
    assert len(read_segmentation("tiny", 0, dataset.parent, "val")) == val.routes * val.q_per_route


# --- labels and statistics ---------------------------------------------------------------------


def test_labels_are_valid_train_ids(dataset: Path) -> None:
    seen: set[int] = set()
    for label in (dataset / "labels").rglob("*.png"):
        arr = ids(label)
        assert arr.max() < len(TRAIN_ID_NAMES), label
        seen |= set(np.unique(arr).tolist())
    # Both a static street (with the v3 classes of different value) and road users are drawn.
    names = ("road", "sidewalk", "building", "pole", "traffic sign", "vegetation", "sky", "car")
    assert {TRAIN_ID_NAMES.index(n) for n in names} <= seen
    for label in (dataset / "seg" / "gtFine").rglob("*_gtFine_labelIds.png"):
        arr = ids(label)
        assert set(np.unique(arr).tolist()) <= set(TRAIN_TO_LABEL), label
        assert label_ids_to_train_ids(arr).max() < len(TRAIN_ID_NAMES), label


def measured(labels: list[np.ndarray]) -> tuple[float, float]:
    """Mean dynamic and mean sky fraction over label maps (trainIds)."""
    sky = TRAIN_ID_NAMES.index("sky")
    return (
        float(np.mean([(a >= DYNAMIC_MIN).mean() for a in labels])),
        float(np.mean([(a == sky).mean() for a in labels])),
    )


def test_dynamic_fraction_in_bounds_and_stats_agree(dataset: Path) -> None:
    stats = json.loads((dataset / "stats.json").read_text())
    assert (stats["preset"], stats["seed"], stats["version"]) == ("tiny", 0, synthcity.GENERATOR_VERSION)
    assert stats["render"] == dataclasses.asdict(TINY.render)
    queries = [ids(label_of(dataset, p)) for p in vpr_images(dataset, "test", "queries")]
    lo, hi = TINY.dynamic_bounds
    assert lo <= measured(queries)[0] <= hi
    for split in TINY.vpr:  # stats keys: VPR split (database + queries), "seg-<split>"
        labels = [ids(label_of(dataset, p)) for sub in ("database", "queries") for p in vpr_images(dataset, split, sub)]
        dyn, sky = measured(labels)
        assert stats["images"][split] == len(labels)
        assert stats["dynamic_fraction"][split] == pytest.approx(dyn, abs=1e-3)
        assert stats["sky_fraction"][split] == pytest.approx(sky, abs=1e-3)
    for split in TINY.seg:
        pairs = read_cityscapes(dataset / "seg", split)
        dyn, sky = measured([label_ids_to_train_ids(ids(p)) for p in pairs.labels])
        assert stats["images"][f"seg-{split}"] == len(pairs)
        assert stats["dynamic_fraction"][f"seg-{split}"] == pytest.approx(dyn, abs=1e-3)
        assert stats["sky_fraction"][f"seg-{split}"] == pytest.approx(sky, abs=1e-3)
    assert set(stats["images"]) == set(TINY.vpr) | {f"seg-{s}" for s in TINY.seg}
    every = [
        ids(label_of(dataset, p))
        for split in TINY.vpr
        for sub in ("database", "queries")
        for p in vpr_images(dataset, split, sub)
    ]
    counts = np.bincount(np.concatenate([a.ravel() for a in every]), minlength=len(TRAIN_ID_NAMES))
    assert list(stats["class_fraction"]) == sorted(TRAIN_ID_NAMES)
    for i, name in enumerate(TRAIN_ID_NAMES):
        assert stats["class_fraction"][name] == pytest.approx(counts[i] / counts.sum(), abs=1e-4), name
    # Enough vegetation and road for their weights to matter.
    assert stats["class_fraction"]["vegetation"] > 0.03 and stats["class_fraction"]["road"] > 0.04


# --- static classes of different value (generator v3) ----------------------------------------


def chromaticity(root: Path, sub: str, cls: int) -> np.ndarray:
    """Mean (r, g, b) / (r + g + b) of one class's pixels over every VPR image of one traversal."""
    per_image = []
    for image in (p for split in TINY.vpr for p in vpr_images(root, split, sub)):
        rgb, mask = np.asarray(Image.open(image), np.float32), ids(label_of(root, image)) == cls
        if mask.sum() >= 20:
            per_image.append((rgb[mask] / (rgb[mask].sum(-1, keepdims=True) + 1e-6)).mean(0))
    assert len(per_image) >= 10, (sub, cls)
    return np.mean(per_image, 0)


def test_vegetation_changes_between_traversals_buildings_do_not(dataset: Path) -> None:
    """June database vs November queries: foliage turns from green to autumn colours; facades keep theirs."""
    june, november = chromaticity(dataset, "database", VEG), chromaticity(dataset, "queries", VEG)
    assert june[1] > 0.45 and november[1] < june[1] - 0.15 and november[0] > june[0] + 0.15
    facade = chromaticity(dataset, "database", BUILDING) - chromaticity(dataset, "queries", BUILDING)
    assert np.abs(facade).max() < 0.02  # only the (moderate) lighting change


def still_spec() -> render.RenderSpec:
    """The tiny preset's camera without jitter, pitch or lighting change: renders differ only by the world."""
    return dataclasses.replace(TINY.render, jitter_m=0.0, scale_jitter=0.0, pitch_m=0.0, lighting=0.0)


@pytest.fixture(scope="module")
def street() -> render.Panorama:
    """One 200 m route of the tiny preset's street."""
    return render.build_panorama(
        np.random.default_rng(5), 200.0, TINY.render, make_ground_pool(np.random.default_rng(6))
    )


def test_same_pose_both_traversals_differ_only_in_vegetation(
    street: render.Panorama, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Facades, poles and signs are world-fixed and identical in both traversals; only foliage colours change."""
    monkeypatch.setattr(render, "add_dynamic_objects", lambda *args, **kwargs: None)
    pool, spec = render.make_texture_pool(np.random.default_rng(0), 3), still_spec()
    furniture, foliage, changed = 0, 0, 0
    for i, x in enumerate(np.arange(10.0, 190.0, 6.0)):
        (img0, lab0), (img1, lab1) = (
            render.render_capture(street, float(x), np.random.default_rng(i), spec, pool, query=q)
            for q in (False, True)
        )
        assert (lab0 == lab1).all(), x  # a crown keeps its outline (and label) when its leaves fall
        seasonal = np.isin(lab0, (VEG, TERRAIN))
        assert (img0[~seasonal] == img1[~seasonal]).all(), x
        furniture += int(np.isin(lab0, (POLE, SIGN)).sum())
        diff = np.abs(img0[seasonal].astype(int) - img1[seasonal].astype(int)).max(-1)
        foliage, changed = foliage + int(seasonal.sum()), changed + int((diff > 40).sum())
    assert furniture > 50  # the comparison covered poles and signs
    assert changed > 0.8 * foliage > 0


def best_shift(a: np.ndarray, b: np.ndarray, rows: slice, valid: np.ndarray, max_shift: int) -> int:
    """Shift s (pixels) minimising the mean |a[:, j + s] - b[:, j]| over rows where ``valid`` holds in both."""
    errors = []
    for s in range(max_shift + 1):
        ok = valid[rows, s:] & valid[rows, : valid.shape[1] - s]
        diff = np.abs(a[rows, s:].astype(np.float32) - b[rows, : b.shape[1] - s].astype(np.float32)).mean(-1)
        errors.append(diff[ok].mean() if ok.sum() > 20 else np.inf)
    return int(np.argmin(errors))


def test_ground_is_seen_in_perspective(street: render.Panorama, monkeypatch: pytest.MonkeyPatch) -> None:
    """Moving the camera by dx shifts facades by dx·ppm pixels and the near road FACADE_D / d times more."""
    monkeypatch.setattr(render, "add_dynamic_objects", lambda *args, **kwargs: None)
    pool, spec, dx = render.make_texture_pool(np.random.default_rng(0), 3), still_spec(), 1.5
    ppm = spec.width / spec.view_m
    h = spec.height
    near = ground_distance(render.VIEW_BOTTOM + 0.5 / ppm)  # what the bottom row sees
    for i, x in enumerate((40.0, 90.0, 140.0)):
        (a, la), (b, lb) = (
            render.render_capture(street, x + off, np.random.default_rng(i), spec, pool, query=False)
            for off in (0.0, dx)
        )
        static = (la < DYNAMIC_MIN) & (lb < DYNAMIC_MIN)
        assert (la[h - 3 :] == ROAD).mean() > 0.9
        assert abs(best_shift(a, b, slice(h // 3, h // 2), static, 40) - dx * ppm) <= 1, x
        assert abs(best_shift(a, b, slice(h - 2, h), static, 40) - dx * ppm * FACADE_D / near) <= 3, x


def test_road_marks_at_the_end_of_a_route_are_cut_not_fatal() -> None:
    """A zebra crossing that starts near a route's end is cut at the map's edge (it raised a broadcast
    error, so some dataset seeds could not be generated at all)."""
    pool = make_ground_pool(np.random.default_rng(1))
    for seed in range(150):  # 5 m routes: the first mark is often past the end, a crossing 3-4 m wide
        ground = build_ground(np.random.default_rng(seed), 0.0, 5.0, pool)
        assert ground.rgb.shape[1] == 60 and np.isfinite(ground.rgb).all()


def test_ground_patterns_repeat_across_routes_facades_do_not() -> None:
    """Perceptual aliasing: two routes share many identical stretches of road, and no facade column."""
    pool = make_ground_pool(np.random.default_rng(1))
    a, b = (build_ground(np.random.default_rng(r), -20.0, 300.0, pool) for r in (2, 3))
    road = int((a.label == ROAD).sum())

    def columns(rgb: np.ndarray) -> set[bytes]:
        return {rgb[:, c].tobytes() for c in range(rgb.shape[1])}

    shared = columns(a.rgb[:road]) & columns(b.rgb[:road])
    assert len(shared) > 0.1 * len(columns(a.rgb[:road]))
    facades = [render.build_panorama(np.random.default_rng(r), 300.0, TINY.render, pool).rgb[0] for r in (2, 3)]
    assert not columns(facades[0]) & columns(facades[1])


# --- place sets --------------------------------------------------------------------------------


def test_read_split_labels_and_query_differs_from_its_database_image(dataset: Path) -> None:
    places = read_split("tiny", 0, dataset.parent, "test")
    spec = TINY.vpr["test"]
    assert places.name == "synthcity-tiny-s0/test"
    assert len(places.db_paths) == spec.routes * spec.db_per_route
    assert len(places.q_paths) == spec.routes * spec.q_per_route
    assert places.db_labels is not None and places.q_labels is not None
    for image, label in zip(places.db_paths + places.q_paths, places.db_labels + places.q_labels):
        assert label.is_file() and label.stem == image.stem and label.parent.name == image.parent.name
    for qi, pos in enumerate(places.positives(25.0)):
        assert len(pos) > 0, places.q_paths[qi].name
        di = int(pos[0])
        assert np.linalg.norm(places.q_utm[qi] - places.db_utm[di]) <= DB_STEP_M / 2 + 0.011
        q_img = np.asarray(Image.open(places.q_paths[qi]), np.float32)
        d_img = np.asarray(Image.open(places.db_paths[di]), np.float32)
        assert np.abs(q_img - d_img).mean() > 2.0  # another time of day, other traffic
        q_dyn, d_dyn = ids(places.q_labels[qi]) >= DYNAMIC_MIN, ids(places.db_labels[di]) >= DYNAMIC_MIN
        assert (q_dyn != d_dyn).any()
    with pytest.raises(SemvprError, match="no VPR split 'seg'"):
        read_split("tiny", 0, dataset.parent, "seg")
    with pytest.raises(SemvprError, match="no segmentation split 'test'"):
        read_segmentation("tiny", 0, dataset.parent, "test")


# --- cache -------------------------------------------------------------------------------------


def test_ensure_synthcity_reuses_cache(dataset: Path, cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    before = tree(dataset, skip=())
    mtimes = {p: p.stat().st_mtime_ns for p in dataset.rglob("*")}

    def regenerate(*args: object, **kwargs: object) -> dict:
        raise AssertionError("generated again")

    monkeypatch.setattr(synthcity, "generate", regenerate)
    assert ensure_synthcity(cache_dir, "tiny", 0) == dataset
    # Spelling out the preset's own knobs is the same dataset.
    assert ensure_synthcity(cache_dir, "tiny", 0, {"coverage": TINY.render.coverage, "liveries": 3.0}) == dataset
    assert ensure_synthcity(cache_dir, "tiny", 0, None, [TINY.render.height, TINY.render.width]) == dataset
    assert tree(dataset, skip=()) == before and {p: p.stat().st_mtime_ns for p in dataset.rglob("*")} == mtimes
    assert json.loads((dataset / "key.json").read_text()) == {
        "preset": "tiny",
        "seed": 0,
        "version": synthcity.GENERATOR_VERSION,
        "render": dataclasses.asdict(TINY.render),
    }
    # Another seed or any other knob is another artifact; a failed build leaves nothing in the cache.
    assert artifact_dir(cache_dir, "synthcity", synthcity._key("tiny", 1, None)) != dataset
    for knob in ({"coverage": 0.2}, {"pitch_m": 8.0}, {"liveries": 2}):
        assert artifact_dir(cache_dir, "synthcity", synthcity._key("tiny", 0, knob)) != dataset, knob
    assert artifact_dir(cache_dir, "synthcity", synthcity._key("tiny", 0, None, [48, 72])) != dataset
    with pytest.raises(AssertionError, match="generated again"):
        ensure_synthcity(cache_dir, "tiny", 1)
    assert [p.name for p in cache_dir.iterdir() if p.name != LOCK_DIR] == [dataset.name]


def test_config_render_knobs_make_another_dataset(dataset: Path, cache_dir: Path) -> None:
    """``+data.render.<knob>=`` reaches the readers: a dataset generated with that knob, keyed by it."""
    from semvpr.config.components import instantiate_node
    from tests.helpers import tiny_config

    default = instantiate_node(tiny_config(cache_dir).data.test)
    assert default.root.parent == dataset  # <dataset>/images
    steep = instantiate_node(tiny_config(cache_dir, "+data.render.pitch_m=0.5").data.test)
    root = steep.root.parent
    assert root != dataset and json.loads((root / "key.json").read_text())["render"]["pitch_m"] == 0.5
    assert json.loads((root / "stats.json").read_text())["render"]["pitch_m"] == 0.5
    assert len(steep.q_paths) == len(default.q_paths)
    with pytest.raises(SemvprError, match="no render knob 'sky'"):
        instantiate_node(tiny_config(cache_dir, "+data.render.sky=1").data.test)


def test_config_image_size_draws_the_city_at_that_size(dataset: Path, cache_dir: Path) -> None:
    """``data.image_size`` is the size the city is drawn at (not an upsampling of the preset's images)."""
    from semvpr.config.components import instantiate_node
    from tests.helpers import tiny_config

    cfg = tiny_config(cache_dir, "data.image_size=[48,72]")
    small = instantiate_node(cfg.data.test)
    root = small.root.parent
    assert root != dataset and json.loads((root / "key.json").read_text())["render"] == {
        **dataclasses.asdict(TINY.render),
        "height": 48,
        "width": 72,
    }
    for image in (small.q_paths[0], small.db_paths[-1]):
        assert Image.open(image).size == (72, 48)
        assert ids(label_of(root, image)).shape == (48, 72)
    seg = instantiate_node(cfg.data.segmentation.train)
    assert Image.open(seg.images[0]).size == (72, 48) and seg.images[0].is_relative_to(root)
    assert len(small.q_paths) == len(instantiate_node(tiny_config(cache_dir).data.test).q_paths)
    with pytest.raises(SemvprError, match=r"image_size=\[16, 72\] must be \[height, width\], whole numbers >= 32"):
        instantiate_node(tiny_config(cache_dir, "data.image_size=[16,72]").data.test)


def test_get_preset_overrides_and_bad_values() -> None:
    p = get_preset("tiny", {"coverage": 0.2, "lighting": 0, "pitch_m": 8, "liveries": 2.0})
    assert (p.render.coverage, p.render.lighting, p.render.pitch_m, p.render.liveries) == (0.2, 0.0, 8.0, 2)
    assert type(p.render.liveries) is int and p.vpr == TINY.vpr
    assert (p.render.height, p.render.width, p.render.season) == (
        TINY.render.height,
        TINY.render.width,
        TINY.render.season,
    )
    assert get_preset("tiny") == get_preset("tiny", {}) == TINY
    with pytest.raises(SemvprError, match=r"unknown SynthCity preset 'huge'.*tiny"):
        get_preset("huge")
    with pytest.raises(SemvprError, match=r"lighting=-0\.1 is outside \[0, 1\]"):
        get_preset("tiny", {"lighting": -0.1})
    with pytest.raises(SemvprError, match=r"no render knob 'height'.*pitch_m.*image size"):
        get_preset("tiny", {"height": 480})
    big = get_preset("tiny", {"pitch_m": 8}, [96, 128])
    assert (big.render.height, big.render.width, big.render.pitch_m) == (96, 128, 8.0)
    assert get_preset("tiny", None, [TINY.render.height, TINY.render.width]) == TINY
    for size in ([64], [64, 80, 3], [64.0, 80], [64, 31], [True, 80]):
        with pytest.raises(SemvprError, match=r"must be \[height, width\], whole numbers >= 32"):
            get_preset("tiny", None, size)
    with pytest.raises(SemvprError, match=r"liveries=2\.5 must be a whole number"):
        get_preset("tiny", {"liveries": 2.5})
    with pytest.raises(SemvprError, match=r"pitch_m='steep' must be a number"):
        get_preset("tiny", {"pitch_m": "steep"})
    with pytest.raises(SemvprError, match=r"liveries=0 must be > 0"):
        get_preset("tiny", {"liveries": 0})
    with pytest.raises(SemvprError, match=r"view_m=0\.0 must be > 0"):
        get_preset("tiny", {"view_m": 0})
    assert get_preset("tiny", {"pitch_m": 0, "jitter_m": 0}).render.pitch_m == 0.0
    with pytest.raises(SemvprError, match=r"pitch_m=-1\.0 must be >= 0"):
        get_preset("tiny", {"pitch_m": -1})


# --- CLI ---------------------------------------------------------------------------------------


def one_error_line(err: str) -> str:
    """The one error line of stderr; stage lines (``semvpr: <stage>: i/N ...``) may precede it."""
    lines = [ln for ln in err.strip().splitlines() if not re.match(r"semvpr: [^:]+: \d+/\d+ ", ln)]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("semvpr: error: "), err
    return lines[0]


def test_cli_writes_dataset_identical_to_generate(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "new" / "city"  # parent does not exist yet
    main(["--out", str(out), "--preset", "tiny", "--seed", "0"])
    printed = capsys.readouterr().out.strip().splitlines()
    total = sum(json.loads((dataset / "stats.json").read_text())["images"].values())
    assert len(printed) == 1 and printed[0].startswith(f"wrote {total} images to {out}")
    assert "dynamic fraction" in printed[0]
    assert tree(out) == tree(dataset)
    assert [p.name for p in out.parent.iterdir()] == ["city"]  # no .tmp- sibling left
    empty = tmp_path / "empty"  # an existing empty directory is accepted too
    empty.mkdir()
    main(["--out", str(empty), "--preset", "tiny", "--seed", "0"])
    assert tree(empty) == tree(dataset)


def test_cli_refuses_non_empty_out(tmp_path: Path) -> None:
    """Subprocess: the real entry point prints one line, no traceback, and touches nothing."""
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-m", "semvpr.data.synthcity", "--out", str(out), "--preset", "tiny"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 2, proc.stderr
    line = one_error_line(proc.stderr)
    assert "--out" in line and str(out) in line and "not an empty directory" in line
    assert proc.stdout == ""
    assert tree(out) == {"keep.txt": hashlib.sha256(b"precious").hexdigest()}
    assert [p.name for p in tmp_path.iterdir()] == ["taken"]


def test_cli_out_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "file.txt"
    out.write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(["--out", str(out), "--preset", "tiny"])
    assert exc.value.code == 2
    assert str(out) in one_error_line(capsys.readouterr().err)
    assert out.read_text() == "x" and [p.name for p in tmp_path.iterdir()] == ["file.txt"]


def test_cli_bad_preset_is_argparse_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--out", str(tmp_path / "x"), "--preset", "huge"])
    assert exc.value.code == 2
    assert "invalid choice: 'huge'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--render", "coverage=1.5"], "coverage=1.5 is outside [0, 1]"),
        (["--render", "lighting=-0.5"], "lighting=-0.5 is outside [0, 1]"),
        (["--render", "sky=0.5"], "no render knob 'sky'"),
        (["--image-size", "8", "8"], "image_size=[8, 8] must be"),
    ],
)
def test_cli_bad_knob(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], expected: str) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--out", str(tmp_path / "x"), "--preset", "tiny", *args])
    assert exc.value.code == 2
    assert expected in one_error_line(capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []  # validated before anything is created


@pytest.mark.parametrize("error", [SemvprError("disk full"), KeyboardInterrupt()])
def test_cli_failure_mid_generation_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], error: BaseException
) -> None:
    def half_then_fail(root: Path, *args: object) -> dict:
        (root / "images").mkdir()
        (root / "images" / "partial.jpg").write_bytes(b"\xff\xd8")
        raise error

    monkeypatch.setattr(synthcity, "generate", half_then_fail)
    out = tmp_path / "parent" / "city"
    with pytest.raises(SystemExit if isinstance(error, SemvprError) else KeyboardInterrupt) as exc:
        main(["--out", str(out), "--preset", "tiny"])
    if isinstance(error, SemvprError):
        assert exc.value.code == 2
        assert one_error_line(capsys.readouterr().err) == "semvpr: error: disk full"
    assert not out.exists()
    assert list(out.parent.iterdir()) == []  # the .tmp- directory is gone


def test_sigterm_during_generation_is_one_line_and_leaves_nothing(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "parent" / "city"
    proc = subprocess.Popen(
        [sys.executable, "-m", "semvpr.data.synthcity", "--out", str(out), "--preset", "default"],
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    deadline = time.time() + 120
    while time.time() < deadline and not any((tmp_path / "parent").glob(".city.*.tmp/*")):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 2, err[-2000:]
    assert one_error_line(err) == "semvpr: error: stopped by SIGTERM; the unfinished dataset was removed"
    assert list(out.parent.iterdir()) == []
