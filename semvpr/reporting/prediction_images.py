"""Predictions to look at (``save.images`` of ``conf/eval.yaml``, VPR-methods-evaluation's
``--num_preds_to_save``): one JPEG per drawn query, ``predictions/<query index>.jpg``: the query, then its first
``k`` retrieved database images left to right, each framed (the query in blue, a positive of the set's ground
truth in green, any other in red) and captioned with its rank, its descriptor distance and, where the set gives
positions, how far it was taken from the query (metres, or frames for a frame-aligned set). Where the model
weights its features by a mask, each image's mask darkens what it weights down.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from semvpr.core.io import atomic_file
from semvpr.data.images import eight_bit_rgb, open_image
from semvpr.data.places import PlaceSet

#: Frame colours: the query, a positive, a retrieved image that is not one, one whose query has no ground truth.
QUERY, RIGHT, WRONG, UNKNOWN = (31, 119, 180), (44, 160, 44), (214, 39, 40), (150, 150, 150)
#: A thumbnail's height, its frame's width, the caption band above it and the gap between tiles (pixels).
THUMB_H, FRAME, CAPTION, GAP = 192, 6, 18, 8
#: How dark a location the mask weights by 0 is drawn (its pixels times 1 - DIM).
DIM = 0.7
FOLDER = "predictions"

#: A mask for an image of one side ("db", "q") and index: its weight map (h, w) in [0, 1], or None.
MaskOf = Callable[[str, int], np.ndarray | None]


def drawn_queries(top1_right: np.ndarray, count: int, only_wrong: bool) -> np.ndarray:
    """The query indices drawn: ``count`` of them spread evenly over the set's queries (over those whose first
    retrieved image is not a positive, with ``only_wrong``), in query order."""
    candidates = np.flatnonzero(~top1_right) if only_wrong else np.arange(len(top1_right))
    if not len(candidates) or count < 1:
        return candidates[:0]
    picks = np.linspace(0, len(candidates) - 1, min(count, len(candidates))).round().astype(int)
    return candidates[np.unique(picks)]


def write_prediction_images(
    out_dir: Path,
    places: PlaceSet,
    queries: Sequence[int],
    top: np.ndarray,
    distances: np.ndarray,
    positives: Sequence[np.ndarray],
    image_size: Sequence[int],
    mask_of: MaskOf | None = None,
) -> list[str]:
    """Draw each of ``queries`` with its retrieved database images (``top``, a row per drawn query: their
    indices, nearest first; ``distances``: their descriptor distances), every tile at ``image_size``'s aspect;
    returns the files' names below ``out_dir``."""
    return [
        save_row(
            out_dir,
            i,
            len(places.q_paths),
            query_row(places, i, top[r], distances[r], positives[i], image_size, mask_of),
        )
        for r, i in enumerate(int(i) for i in queries)
    ]


def save_row(out_dir: Path, i: int, queries: int, row: Image.Image) -> str:
    """Query ``i``'s drawn row (of ``queries``) as ``predictions/<i>.jpg`` below ``out_dir``, the index padded to
    the queries' width; its name."""
    name = f"{FOLDER}/{i:0{len(str(max(queries - 1, 1)))}d}.jpg"
    (out_dir / FOLDER).mkdir(exist_ok=True)
    with atomic_file(out_dir / name) as fh:
        row.save(fh, "JPEG", quality=90)
    return name


def query_row(
    places: PlaceSet,
    i: int | tuple[Path, dict],
    top: Sequence[int],
    distances: Sequence[float] | None,
    positives: np.ndarray | None,
    image_size: Sequence[int],
    mask_of: MaskOf | None = None,
) -> Image.Image:
    """Query ``i`` of ``places`` (or another image: its path and position, ``{"utm": [e, n]}`` or ``{}``) and its
    retrieved database images ``top`` (nearest first; ``distances`` their descriptor distances, None: not
    captioned) side by side, every tile at ``image_size``'s aspect, framed by ``positives`` (None: no ground
    truth, grey) (module docstring)."""
    height, width = image_size
    thumb = (max(1, round(THUMB_H * width / height)), THUMB_H)
    query, at = (places.q_paths[i], places.position("q", i)) if isinstance(i, int) else i
    right = None if positives is None else set(np.asarray(positives).tolist())
    name = f"query {i}" if isinstance(i, int) else "query"
    tiles = [_tile(query, thumb, QUERY, name, mask_of("q", i) if mask_of and isinstance(i, int) else None)]
    for rank, j in enumerate((int(j) for j in top), start=1):
        shown = f"d={distances[rank - 1]:.3f}" if distances is not None else ""
        caption = ", ".join(t for t in (f"{rank}: {shown}" if shown else f"{rank}", _offset(at, places, j)) if t)
        colour = UNKNOWN if right is None else RIGHT if j in right else WRONG
        tiles.append(_tile(places.db_paths[j], thumb, colour, caption, mask_of and mask_of("db", j)))
    return _row(tiles)


def _offset(q: dict, places: PlaceSet, j: int) -> str:
    """How far database image ``j`` was taken from the query at ``q``, where both positions are known."""
    db = places.position("db", j)
    if "utm" in q and "utm" in db:
        return f"{float(np.hypot(*np.subtract(db['utm'], q['utm']))):.0f} m"
    if "frame" in q and "frame" in db:
        return f"{abs(db['frame'] - q['frame'])} frames"
    return ""


def _tile(
    path: Path, size: tuple[int, int], colour: tuple[int, int, int], caption: str, mask: np.ndarray | None
) -> Image.Image:
    """One framed, captioned thumbnail; ``mask`` (h, w) in [0, 1] darkens what it weights down."""
    image = eight_bit_rgb(open_image(Path(path), "image"), path).resize(size, Image.BILINEAR)
    if mask is not None:
        weight = Image.fromarray(np.uint8(255 * np.clip(mask, 0, 1))).resize(size, Image.NEAREST)
        shade = 1 - DIM * (1 - np.asarray(weight, np.float32)[..., None] / 255)
        image = Image.fromarray(np.uint8(np.asarray(image, np.float32) * shade))
    tile = Image.new("RGB", (size[0] + 2 * FRAME, size[1] + 2 * FRAME + CAPTION), "white")
    tile.paste(Image.new("RGB", (size[0] + 2 * FRAME, size[1] + 2 * FRAME), colour), (0, CAPTION))
    tile.paste(image, (FRAME, CAPTION + FRAME))
    ImageDraw.Draw(tile).text((FRAME, 3), caption, fill="black")
    return tile


def _row(tiles: list[Image.Image]) -> Image.Image:
    """The tiles side by side, ``GAP`` pixels apart."""
    width = sum(t.width for t in tiles) + GAP * (len(tiles) - 1)
    row = Image.new("RGB", (width, tiles[0].height), "white")
    x = 0
    for tile in tiles:
        row.paste(tile, (x, 0))
        x += tile.width + GAP
    return row
