"""Real dynamic objects pasted into a place set's images: a derived set with its ground-truth dynamic mask.

The objects are cut from CamVid's **test** split only (no segmenter here trains or chooses on it). An
object is a connected component (8-connected) of CamVid's moving classes (Car, Pedestrian, Bicyclist:
Cityscapes car, person, rider) in a test label map, each pixel keeping its own class, that

- covers at least ``min_area`` of its frame's pixels,
- touches neither the left, the right nor the top border of its frame (a cut-off object would paste
  with a straight edge; one cut by the bottom border stays, as it is pasted touching the bottom too),
- stands on the lower part of its frame: its lowest row lies in the frame's lower half.

Placement keeps each object where the camera saw it: it is scaled by the ratio of the two frames'
heights (so it fills the same share of the frame's height as in its source frame) and its lowest row
goes to the same relative row; only its horizontal position is drawn. Objects are pasted one after
another, a later one in front of an earlier one, until the pasted pixels cover the asked fraction of
the image (within ``TOLERANCE``); a candidate that would overshoot is skipped. Pixels are replaced
outright (no blending): the artefacts this leaves are what ``paste=false`` measures.

``coverage`` is a fixed fraction, or ``camvid``: each image's fraction drawn from the shares of CamVid
**train** frames' pixels that its moving classes cover (measured from the split's label maps, frames with
none included: :func:`camvid_shares`), so the occlusion is as much as real street frames hold.

Each image gets its own draw, seeded by ``seed`` and the image's name below the set's root, so two
traversals (the database and the queries) see different objects, as two visits do, and one image
gets the same objects in every set it belongs to. The composites and their label maps are a cached
artifact (``occluded-<hash>``, keyed by the set's images, the CamVid test files and every setting).

The label maps give the pasted pixels their Cityscapes class and every other pixel ``building``: the
ground truth covers the pasted objects only (the real frames' own content is not labelled), and any
static class marks a pixel as kept under the binary oracle mask.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from semvpr.core.cache import build_once, files_identity
from semvpr.core.errors import SemvprError
from semvpr.core.logs import Progress
from semvpr.core.spec import from_mapping, setting
from semvpr.data.camvid import read_camvid
from semvpr.data.classes import DYNAMIC_NAMES, TRAIN_ID_NAMES
from semvpr.data.images import eight_bit_rgb, open_image
from semvpr.data.places import PlaceSet

#: Where the objects come from (``data.occluders.source``): ``none`` leaves the set as it is.
SOURCES = ("none", "camvid")
#: The coverage that draws each image's fraction from CamVid train's frames (:func:`camvid_shares`).
MEASURED = "camvid"
#: Cityscapes classes an object may be made of: the moving ones (every dynamic class but sky).
OBJECT_CLASSES: tuple[int, ...] = tuple(TRAIN_ID_NAMES.index(n) for n in DYNAMIC_NAMES if n != "sky")
#: The label of every pixel that is not pasted: a static class.
BACKGROUND = TRAIN_ID_NAMES.index("building")
#: How far the pasted fraction of an image may end from the asked coverage (a fraction of its pixels).
TOLERANCE = 0.01
#: Candidates drawn for one image before the asked coverage is declared out of reach.
MAX_TRIES = 2000
#: Largest coverage accepted: objects stand on the lower part of the frame.
MAX_COVERAGE = 0.5
#: JPEG quality of a composite written as JPEG (as its source was).
JPEG_QUALITY = 95
#: Part of the cache key: a change to how composites are drawn makes new ones.
VERSION = 1


@dataclass(frozen=True)
class OccluderSpec:
    """``data.occluders``: the objects' source and CamVid root, the pixel fraction, the draw's seed, the
    smallest object (a fraction of its source frame) and whether to paste (``paste=false``: the images
    unchanged, the label maps of the same draw: the holes a mask makes, without the objects)."""

    source: str = setting("none", choices=SOURCES)
    root: str | None = None
    coverage: float | str = 0.2
    seed: int = setting(0, low=0)
    min_area: float = 0.002
    paste: bool = True

    @classmethod
    def from_mapping(cls, node: object) -> OccluderSpec:
        spec = from_mapping(cls, node or {}, "data.occluders")  # type: ignore[arg-type]
        if spec.source == "none":
            return spec
        if not spec.root:
            raise SemvprError(
                "data.occluders.root is not set: the CamVid folder (SegNet layout) whose test split gives the objects"
            )
        if (
            isinstance(spec.coverage, str)
            and spec.coverage != MEASURED
            or not (isinstance(spec.coverage, str) or 0 < spec.coverage <= MAX_COVERAGE)
        ):
            raise SemvprError(
                f"data.occluders.coverage={spec.coverage!r}: expected a fraction of the pixels in (0, {MAX_COVERAGE}] "
                f"or {MEASURED} (each image's drawn from CamVid train's frames; data.occluders.source=none for the "
                "set without objects)"
            )
        if not 0 < spec.min_area < 1:
            raise SemvprError(f"data.occluders.min_area={spec.min_area!r}: expected a fraction of a frame in (0, 1)")
        return spec

    @property
    def label(self) -> str:
        """How a set's name gives the coverage: ``20%``, or ``at train coverage`` (CamVid train's frames')."""
        return "at train coverage" if self.coverage == MEASURED else f"{self.coverage:.0%}"


def camvid_shares(root: str | Path) -> np.ndarray:
    """Per CamVid **train** frame, the fraction of its pixels that its moving classes (:data:`OBJECT_CLASSES`)
    cover, in the split's order (float64; frames without any included)."""
    seg = read_camvid(root, "train", "data.occluders.root")
    lut = np.asarray(seg.label_lut, dtype=np.uint8)
    moving = np.zeros(256, dtype=bool)
    moving[list(OBJECT_CLASSES)] = True
    return np.array([moving[lut[np.asarray(open_image(p, "CamVid label map"))]].mean() for p in seg.labels])


@dataclass(frozen=True)
class CutObject:
    """One object: its pixels (RGB crop), its classes (trainIds, 255 outside it), its source frame's height,
    the relative row below its lowest one, and where it came from."""

    rgb: np.ndarray
    classes: np.ndarray
    frame_height: int
    foot: float
    source: str


def cut_objects(root: str | Path, min_area: float) -> list[CutObject]:
    """The objects of CamVid's test split (see the module's docstring for what counts as one)."""
    seg = read_camvid(root, "test", "data.occluders.root")
    lut = np.asarray(seg.label_lut, dtype=np.uint8)
    moving = np.zeros(256, dtype=bool)
    moving[list(OBJECT_CLASSES)] = True
    eight = np.ones((3, 3), dtype=bool)
    objects = []
    for image_path, label_path in zip(seg.images, seg.labels):
        classes = lut[np.asarray(open_image(label_path, "CamVid label map"))]
        h, w = classes.shape
        components, _ = ndimage.label(moving[classes], structure=eight)
        rgb = None
        for index, box in enumerate(ndimage.find_objects(components), start=1):
            if box is None:
                continue
            rows, cols = box
            inside = components[box] == index
            if inside.sum() < min_area * h * w or rows.start == 0 or cols.start == 0 or cols.stop == w:
                continue
            if rows.stop <= h // 2:
                continue
            if rgb is None:
                rgb = np.asarray(eight_bit_rgb(open_image(image_path, "CamVid image"), image_path))
                if rgb.shape[:2] != (h, w):
                    raise SemvprError(f"{image_path}: {rgb.shape[1]}x{rgb.shape[0]}, its label map {w}x{h}")
            crop_classes = np.where(inside, classes[box], 255).astype(np.uint8)
            objects.append(CutObject(rgb[box].copy(), crop_classes, h, rows.stop / h, Path(image_path).name))
    if not objects:
        raise SemvprError(
            f"CamVid test split under {root}: no object of the moving classes covers {min_area} of a frame "
            "away from its side and top borders; lower data.occluders.min_area"
        )
    return objects


def _scaled(obj: CutObject, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The object's pixels and classes for a frame ``height`` pixels high (its share of the height kept)."""
    scale = height / obj.frame_height
    h, w = obj.classes.shape
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    rgb = np.asarray(Image.fromarray(obj.rgb).resize(size, Image.BILINEAR))
    classes = np.asarray(Image.fromarray(obj.classes).resize(size, Image.NEAREST))
    return rgb, classes


def draw_seed(seed: int, name: str) -> np.random.Generator:
    """The generator of one image's draw: the seed and the image's name below the set's root."""
    digest = hashlib.sha256(f"occluders v{VERSION}\0{seed}\0{name}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def composite(
    image: np.ndarray,
    objects: list[CutObject],
    coverage: float,
    rng: np.random.Generator,
    scaled: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, list[dict[str, object]]]:
    """``image`` (H,W,3) with objects pasted over ``coverage`` of its pixels (± ``TOLERANCE``), its label map
    (H,W) and what was pasted where. ``scaled`` memoises (object, height) → its scaled pixels."""
    height, width = image.shape[:2]
    out = image.copy()
    labels = np.full((height, width), BACKGROUND, dtype=np.uint8)
    covered = np.zeros((height, width), dtype=bool)
    total, target, pasted = 0, coverage * height * width, []
    if target <= TOLERANCE * height * width:  # the frame as it is is within the tolerance of the asked fraction
        return out, labels, pasted
    for _ in range(MAX_TRIES):
        index = int(rng.integers(len(objects)))
        obj = objects[index]
        if (index, height) not in scaled:
            scaled[index, height] = _scaled(obj, height)
        rgb, classes = scaled[index, height]
        h, w = classes.shape
        if w > width or h > height:
            continue
        x = int(rng.integers(0, width - w + 1))
        y = min(height, round(obj.foot * height)) - h
        y = max(0, y)
        inside = classes[: height - y] != 255
        box = (slice(y, y + inside.shape[0]), slice(x, x + w))
        added = int((inside & ~covered[box]).sum())
        if total + added > target + TOLERANCE * height * width:
            continue
        out[box][inside] = rgb[: inside.shape[0]][inside]
        labels[box][inside] = classes[: inside.shape[0]][inside]
        covered[box] |= inside
        total += added
        pasted.append({"object": obj.source, "x": x, "y": y, "width": w, "height": h})
        if total >= target - TOLERANCE * height * width:
            return out, labels, pasted
    raise SemvprError(
        f"could not cover {coverage:.0%} of a {width}x{height} image with CamVid test objects in {MAX_TRIES} draws "
        f"(reached {total / (height * width):.1%}); lower data.occluders.coverage"
    )


def _save(image: np.ndarray, path: Path) -> None:
    """Written in its source's format (a JPEG at ``JPEG_QUALITY``)."""
    suffix = path.suffix.lower()
    options = {"quality": JPEG_QUALITY} if suffix in (".jpg", ".jpeg") else {}
    Image.fromarray(image).save(path, **options)


def occlude(places: PlaceSet, spec: OccluderSpec, cache_dir: str | Path) -> PlaceSet:
    """``places`` with CamVid test objects pasted into every database and query image, and the label maps
    of the pasted pixels (``db_labels`` / ``q_labels``: what ``mask=oracle`` reads); the set itself when
    ``spec.source`` is none. Built once into ``cache_dir``."""
    if spec.source == "none":
        return places
    if places.root is None:
        raise SemvprError(f"place set {places.name!r} has no root folder to key its images by")
    camvid = read_camvid(spec.root, "test", "data.occluders.root")
    train = read_camvid(spec.root, "train", "data.occluders.root") if spec.coverage == MEASURED else None
    sides = {"db": places.db_paths, "q": places.q_paths}
    names = {side: [places.relative(p) for p in paths] for side, paths in sides.items()}
    key = {
        "version": VERSION,
        "images": {side: files_identity(names[side], paths) for side, paths in sides.items()},
        "camvid_test": files_identity(
            [f"image:{p.name}" for p in camvid.images] + [f"label:{p.name}" for p in camvid.labels],
            [*camvid.images, *camvid.labels],
        ),
        "coverage": spec.coverage,
        **({"camvid_train": files_identity([p.name for p in train.labels], list(train.labels))} if train else {}),
        "seed": spec.seed,
        "min_area": spec.min_area,
        "paste": spec.paste,
    }

    def build(tmp: Path) -> None:
        objects = cut_objects(spec.root, spec.min_area)
        shares = camvid_shares(spec.root) if spec.coverage == MEASURED else None
        scaled: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        record: dict[str, object] = {"objects": len(objects), "coverage": spec.coverage, "images": {}}
        if shares is not None:
            record["camvid_train_shares"] = {
                "frames": len(shares),
                **{k: float(f(shares)) for k, f in (("mean", np.mean), ("median", np.median), ("max", np.max))},
                "p90": float(np.percentile(shares, 90)),
            }
        bar = Progress(
            f"{places.name}: CamVid objects ({len(objects)} cut from its test split)",
            len(set(names["db"] + names["q"])),
        )
        for side, paths in sides.items():
            for name, path in zip(names[side], paths):
                if name in record["images"]:  # an image on both sides: one draw
                    continue
                image = np.asarray(eight_bit_rgb(open_image(path, "image"), path))
                rng = draw_seed(spec.seed, name)
                asked = float(shares[rng.integers(len(shares))]) if shares is not None else float(spec.coverage)
                pixels, labels, pasted = composite(image, objects, asked, rng, scaled)
                (tmp / "images" / name).parent.mkdir(parents=True, exist_ok=True)
                (tmp / "labels" / name).parent.mkdir(parents=True, exist_ok=True)
                if spec.paste:
                    _save(pixels, tmp / "images" / name)
                else:
                    shutil.copyfile(path, tmp / "images" / name)
                Image.fromarray(labels).save((tmp / "labels" / name).with_suffix(".png"))
                covered = float((labels != BACKGROUND).mean())
                record["images"][name] = {"asked": asked, "coverage": covered, "pasted": pasted}
                bar.update()
        bar.close()
        (tmp / "occluders.json").write_text(json.dumps(record, indent=1))

    folder = build_once(cache_dir, "occluded", key, build)
    image_root = folder / "images"

    def moved(side: str) -> tuple[tuple[Path, ...], tuple[Path, ...]]:
        return (
            tuple(image_root / n for n in names[side]),
            tuple((folder / "labels" / n).with_suffix(".png") for n in names[side]),
        )

    (db_paths, db_labels), (q_paths, q_labels) = moved("db"), moved("q")
    return replace(
        places,
        name=f"{places.name} + CamVid {spec.label} seed {spec.seed}{'' if spec.paste else ' (holes only)'}",
        root=image_root,
        db_paths=db_paths,
        q_paths=q_paths,
        db_labels=db_labels,
        q_labels=q_labels,
    )
