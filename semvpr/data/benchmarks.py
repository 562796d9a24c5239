"""Readers for the evaluation ground truth the VPR community ships with its benchmarks.

- gsv-cities / salad / BoQ ``.npy`` lists: ``<set>_dbImages.npy`` and ``<set>_qImages.npy`` (image
  paths relative to the dataset folder) with ``<set>_gt.npy`` (per query, the database indices that
  count as correct): Pitts30k/250k, Nordland, SPED, ... as those papers score them.
- Their MSLS-val files: ``msls_val_{dbImages,qImages}.npy`` with ``msls_val_qIdx.npy`` (the queries
  scored) and ``msls_val_pIdx.npy`` (their positives): 740 queries, 18,871 database images.
- Patch-NetVLAD's ``.npz`` (``utmDb``, ``utmQ``, ``posDistThr``) with its image-list text files
  (one path per line, in the order of the positions).
- Frame-aligned traversals (Nordland, Gardens Point, ...): one folder per traversal, images named
  by frame, so the positives of query frame ``f`` are the database frames ``f - N .. f + N``.

Sets without positions (the first, second and last) carry NaN UTMs; their ground truth is the
shipped one. A set recognised by name has its counts checked against ``published.yaml``.
Object arrays (``_gt.npy``, ``pIdx``) are pickles: they are unpickled with only numpy's array
classes allowed, so a crafted file cannot run code.
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import read_list_text, regular_file
from semvpr.core.patterns import bounded_regex, match_name
from semvpr.data.occluders import OccluderSpec, occlude
from semvpr.data.places import MAX_POSITION, PlaceSet, image_files, listed_image
from semvpr.data.published import check_counts

#: What a pickled numpy object array of index arrays may reference (numpy 1.x and 2.x names).
_ARRAY_CLASSES = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


#: Largest frame number or window (a frame is a position: one unit is one frame, within MAX_POSITION;
#: frame + window stays far inside int64).
MAX_FRAME = int(MAX_POSITION)


class _ArrayUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> type:
        if (module, name) in _ARRAY_CLASSES:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not part of a numpy array")


def load_npy(path: Path) -> np.ndarray:
    """An .npy array; an object array is unpickled with numpy's array classes only."""
    if not regular_file(path, "array file"):
        raise SemvprError(f"{path} not found")
    try:
        with path.open("rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read_header(fh)
            if not dtype.hasobject:
                fh.seek(0)
                return np.load(fh, allow_pickle=False)
            array = _ArrayUnpickler(fh).load()
    except Exception as err:  # noqa: BLE001 - numpy's allowed classes raise anything on crafted arguments
        detail = str(err).splitlines()[0][:200] if str(err) else ""
        raise SemvprError(
            f"{path}: not a readable .npy array ({type(err).__name__}{': ' if detail else ''}{detail})"
        ) from None
    if not isinstance(array, np.ndarray) or array.shape != shape:
        raise SemvprError(f"{path}: the pickled content is not the {shape} array its header announces")
    return array


def _names(path: Path) -> list[str]:
    """A 1-D .npy list of relative image paths."""
    array = load_npy(path)
    if array.ndim != 1 or not len(array) or not all(isinstance(n, str) and n for n in array.tolist()):
        raise SemvprError(
            f"{path}: expected a non-empty 1-D array of image paths, got {array.dtype}{list(array.shape)}"
        )
    return [str(n) for n in array.tolist()]


def _index_lists(path: Path, count: int) -> list[np.ndarray]:
    """Per-query database indices: an object array of integer arrays (or a 2-D integer array)."""
    array = load_npy(path)
    rows = list(array) if array.ndim in (1, 2) else []
    if len(rows) != count:
        raise SemvprError(
            f"{path}: {len(rows)} rows of positives ({array.dtype}{list(array.shape)}) for {count} queries"
        )
    out = []
    for i, row in enumerate(rows):
        idx = np.asarray(row).ravel()
        if idx.size and not np.issubdtype(idx.dtype, np.integer):
            raise SemvprError(f"{path}: row {i} holds {idx.dtype} values, expected database indices")
        out.append(idx.astype(np.int64))
    return out


def _check_images(image_root: Path, db: list[str], q: list[str], where: Path) -> None:
    """The image folder exists and holds the first listed image of each side (one stat each; every
    image is checked when the set's cache key is taken)."""
    if not image_root.is_dir():
        raise SemvprError(
            f"image folder {image_root} does not exist; set data.root=... to the folder the "
            f"paths in {where} are relative to"
        )
    for side, names in (("database", db), ("query", q)):
        if not listed_image(image_root, names[0], where).is_file():
            raise SemvprError(f"{where}: first {side} image {names[0]!r} not found under {image_root}")


def _set(name: str, image_root: Path, db: list[str], q: list[str], where: Path, **truth: object) -> PlaceSet:
    return PlaceSet(
        name=name,
        root=image_root,
        db_paths=tuple(listed_image(image_root, n, where) for n in db),
        q_paths=tuple(listed_image(image_root, n, where) for n in q),
        db_utm=np.full((len(db), 2), np.nan),
        q_utm=np.full((len(q), 2), np.nan),
        **truth,
    )  # type: ignore[arg-type]


def read_npy_lists(gt_dir: str | Path, image_root: str | Path, set_name: str) -> PlaceSet:
    """gsv-cities / salad / BoQ ground truth: ``gt_dir/<set_name>_{dbImages,qImages,gt}.npy``."""
    gt_dir, image_root = Path(gt_dir).expanduser(), Path(image_root).expanduser()
    db = _names(gt_dir / f"{set_name}_dbImages.npy")
    q = _names(gt_dir / f"{set_name}_qImages.npy")
    truth = _index_lists(gt_dir / f"{set_name}_gt.npy", len(q))
    check_counts(set_name, len(db), len(q), str(gt_dir / f"{set_name}_*.npy"))
    _check_images(image_root, db, q, gt_dir / f"{set_name}_dbImages.npy")
    return _set(set_name, image_root, db, q, gt_dir / f"{set_name}_*Images.npy", ground_truth=tuple(truth))


def read_msls_val_npy(gt_dir: str | Path, image_root: str | Path) -> PlaceSet:
    """MSLS val as gsv-cities / salad / BoQ score it: ``msls_val_{dbImages,qImages,qIdx,pIdx}.npy``;
    the queries are ``qImages[qIdx]`` and ``pIdx`` their positives (paths relative to the MSLS root)."""
    gt_dir, image_root = Path(gt_dir).expanduser(), Path(image_root).expanduser()
    db = _names(gt_dir / "msls_val_dbImages.npy")
    all_q = _names(gt_dir / "msls_val_qImages.npy")
    q_idx = load_npy(gt_dir / "msls_val_qIdx.npy")
    if (
        q_idx.ndim != 1
        or not np.issubdtype(q_idx.dtype, np.integer)
        or (q_idx.size and (q_idx.min() < 0 or q_idx.max() >= len(all_q)))
    ):
        raise SemvprError(
            f"{gt_dir / 'msls_val_qIdx.npy'}: expected 1-D indices into the {len(all_q)} "
            f"query images, got {q_idx.dtype}{list(q_idx.shape)}"
        )
    q = [all_q[i] for i in q_idx.tolist()]
    truth = _index_lists(gt_dir / "msls_val_pIdx.npy", len(q))
    check_counts("msls_val", len(db), len(q), str(gt_dir / "msls_val_*.npy"))
    _check_images(image_root, db, q, gt_dir / "msls_val_dbImages.npy")
    return _set("msls_val", image_root, db, q, gt_dir / "msls_val_*Images.npy", ground_truth=tuple(truth))


def _lines(path: Path) -> list[str]:
    if not regular_file(path, "image list"):
        raise SemvprError(f"image list {path} not found")
    names = [line.strip() for line in read_list_text(path, "image list").splitlines() if line.strip()]
    if not names:
        raise SemvprError(f"image list {path} is empty")
    return names


def read_patchnetvlad(
    npz_path: str | Path, db_list: str | Path, q_list: str | Path, image_root: str | Path
) -> PlaceSet:
    """Patch-NetVLAD ground truth: positions (``utmDb``, ``utmQ``) and the positive radius
    (``posDistThr``) from the .npz, image paths from the two lists (one per line, same order)."""
    npz_path, image_root = Path(npz_path).expanduser(), Path(image_root).expanduser()
    if not regular_file(npz_path, "ground truth file"):
        raise SemvprError(f"{npz_path} not found")
    try:
        with np.load(npz_path, allow_pickle=False) as npz:
            fields = {k: npz[k] for k in npz.files}
    except Exception as err:  # noqa: BLE001 - zipfile, pickle refusal and format errors alike
        raise SemvprError(
            f"{npz_path}: not a readable .npz ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"
        ) from None
    missing = [k for k in ("utmDb", "utmQ", "posDistThr") if k not in fields]
    if missing:
        raise SemvprError(
            f"{npz_path}: lacks {missing} (found {sorted(fields)}); is it a Patch-NetVLAD dataset_gt_files .npz?"
        )
    db, q = _lines(Path(db_list).expanduser()), _lines(Path(q_list).expanduser())
    for key, names in (("utmDb", db), ("utmQ", q)):
        if fields[key].shape != (len(names), 2) or not _real(fields[key]):
            raise SemvprError(
                f"{npz_path}: {key} is {fields[key].dtype}{list(fields[key].shape)}, expected "
                f"({len(names)}, 2) positions for the {len(names)} images listed"
            )
    radius = fields["posDistThr"]
    if radius.size != 1 or not _real(radius) or not 0 < float(radius.ravel()[0]) < np.inf:
        raise SemvprError(f"{npz_path}: posDistThr is {radius.tolist()!r}, expected one positive radius in metres")
    check_counts(npz_path.stem, len(db), len(q), str(npz_path))
    _check_images(image_root, db, q, Path(db_list))
    return PlaceSet(
        name=npz_path.stem,
        root=image_root,
        db_paths=tuple(listed_image(image_root, n, Path(db_list)) for n in db),
        q_paths=tuple(listed_image(image_root, n, Path(q_list)) for n in q),
        db_utm=fields["utmDb"],
        q_utm=fields["utmQ"],
        eval_radius=float(radius),
    )


def _real(array: np.ndarray) -> bool:
    """Whether an array holds real numbers (integers or floats; not complex, not bool, not objects)."""
    return np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)


def _frames(folder: Path, pattern: str | None) -> tuple[list[Path], np.ndarray]:
    """Images of one traversal and their frame numbers, sorted by frame: the last integer in each file
    name, or ``pattern``'s first group (matched against the whole file name, with a bounded cost:
    ``core.patterns``)."""
    if not folder.is_dir():
        raise SemvprError(
            f"traversal folder {folder} not found; data.root should hold one folder per traversal "
            "(data.database, data.queries)"
        )
    images = image_files(folder)
    if not images:
        raise SemvprError(f"{folder}: no images (.jpg/.png)")
    regex = bounded_regex(pattern, "data.frame_pattern") if pattern is not None else None
    frames = []
    for path in images:
        if regex is not None:
            match = match_name(regex, path.name, "data.frame_pattern")
            digits = [match.group(1)] if match and match.groups() and (match.group(1) or "").isdecimal() else []
            expected = f"a name matching data.frame_pattern={pattern!r}"
        else:
            digits = re.findall(r"\d+", path.stem)
            expected = "the frame number in the file name"
        if not digits:
            raise SemvprError(f"{path}: no frame number in the file name (expected {expected})")
        frame = int(digits[-1])
        if frame > MAX_FRAME:
            raise SemvprError(f"{path}: frame number {digits[-1][:40]} is beyond {MAX_FRAME:.0e}; not a frame number")
        frames.append(frame)
    order = np.argsort(frames, kind="stable")
    images, numbers = [images[i] for i in order], np.asarray(frames, dtype=np.int64)[order]
    repeated = np.flatnonzero(numbers[1:] == numbers[:-1])
    if len(repeated):
        i = int(repeated[0])
        raise SemvprError(f"{folder}: {images[i].name} and {images[i + 1].name} are both frame {numbers[i]}")
    return images, numbers


def frames_name(name: str, database: str, queries: str, frame_window: int) -> str:
    """A frame-aligned set's name in tables: the set, its traversals and the window."""
    return f"{name} {database}→{queries} ±{frame_window}"


def read_frames(
    root: str | Path,
    database: str,
    queries: str,
    frame_window: int,
    name: str | None = None,
    frame_pattern: str | None = None,
    occluders: Mapping[str, Any] | None = None,
    cache_dir: str | Path | None = None,
) -> PlaceSet:
    """Two frame-aligned traversals of one route (Nordland, Gardens Point, ...): ``root/database`` and
    ``root/queries``, one folder each, images named by frame; frame f of every traversal shows the same
    place, so the positives of query frame f are the database frames within ``frame_window`` of f.
    Positions are (frame, 0): one unit is one frame. ``name`` (default: the root folder's name) heads
    the set's name in tables, which also says the traversals and the window. ``occluders``
    (``data.occluders``) pastes CamVid's dynamic objects into every image, with their label maps
    (``data/occluders.py``; the composites are cached in ``cache_dir``)."""
    spec = OccluderSpec.from_mapping(occluders)
    root = Path(root).expanduser()
    if not isinstance(frame_window, int) or isinstance(frame_window, bool) or not 0 <= frame_window <= MAX_FRAME:
        raise SemvprError(
            f"data.frame_window={frame_window!r}: expected a number of frames >= 0 and <= {MAX_FRAME:.0e}"
        )
    for key, value in (("data.database", database), ("data.queries", queries)):
        if not isinstance(value, str) or not value or Path(value).name != value or value in (".", ".."):
            raise SemvprError(f"{key}={value!r}: expected the name of a traversal folder under data.root")
    if database == queries:
        raise SemvprError(
            f"data.database and data.queries are both {database!r}: every query would find itself; pick two traversals"
        )
    db_paths, db_frames = _frames(root / database, frame_pattern)
    q_paths, q_frames = _frames(root / queries, frame_pattern)
    lo = np.searchsorted(db_frames, q_frames - frame_window, side="left")
    hi = np.searchsorted(db_frames, q_frames + frame_window, side="right")
    truth = tuple(np.arange(a, b, dtype=np.int64) for a, b in zip(lo, hi))
    places = PlaceSet(
        name=frames_name(name or root.resolve().name, database, queries, frame_window),
        root=root,
        db_paths=tuple(db_paths),
        q_paths=tuple(q_paths),
        db_utm=np.stack([db_frames, np.zeros_like(db_frames)], 1),
        q_utm=np.stack([q_frames, np.zeros_like(q_frames)], 1),
        ground_truth=truth,
        positions="frame",
    )
    if spec.source != "none" and cache_dir is None:
        raise SemvprError("data.occluders needs a cache folder for its composites (paths.cache_dir)")
    return occlude(places, spec, cache_dir) if spec.source != "none" else places
