"""Place-recognition sets (database + queries with UTM positions) and readers for the common formats."""

from __future__ import annotations

import csv
import dataclasses
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from semvpr.core.cache import files_identity
from semvpr.core.errors import SemvprError
from semvpr.core.io import regular_file

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
#: The official MSLS cities of each split (mapillary_sls, ``default_cities``).
MSLS_CITIES: dict[str, tuple[str, ...]] = {
    "train": (
        "trondheim",
        "london",
        "boston",
        "melbourne",
        "amsterdam",
        "helsinki",
        "tokyo",
        "toronto",
        "saopaulo",
        "moscow",
        "zurich",
        "paris",
        "bangkok",
        "budapest",
        "austin",
        "berlin",
        "ottawa",
        "phoenix",
        "goa",
        "amman",
        "nairobi",
        "manila",
    ),
    "val": ("cph", "sf"),
    "test": ("miami", "athens", "buenosaires", "stockholm", "bengaluru", "kampala"),
}
#: Training cities held out to select the epoch (split "selection"; split "train" omits them), so
#: model selection never sees the reported val cities. A fixed choice: two mid-latitude cities on
#: two continents.
MSLS_SELECTION_CITIES: tuple[str, ...] = ("zurich", "ottawa")
#: dbStruct fields in the order MATLAB writes them (Pitts250k/30k, Tokyo 24/7).
DBSTRUCT_FIELDS = (
    "whichSet",
    "dbImageFns",
    "utmDb",
    "qImageFns",
    "utmQ",
    "numImages",
    "numQueries",
    "posDistThr",
    "posDistSqThr",
    "nonTrivPosDistSqThr",
)


#: Largest |coordinate| a place may have, in metres: far beyond any UTM value (MSLS shifts each city by
#: 10,000 km) and far below the float64 range, whose squares the radius search takes.
MAX_POSITION = 1e15


def check_radius(radius: float, what: str) -> float:
    """A search radius in metres: a finite number > 0 (scipy squares it, so -25 would act as 25)."""
    try:
        value = float(radius)
    except (TypeError, ValueError):
        raise SemvprError(f"{what}={radius!r} is not a number (metres)") from None
    if not np.isfinite(value) or value <= 0:
        raise SemvprError(f"{what}={radius!r} must be a finite distance > 0 (metres)")
    return value


def positives_within(db_utm: np.ndarray, q_utm: np.ndarray, radius: float) -> list[np.ndarray]:
    """Per query, the database indices within ``radius`` metres, sorted by distance (exact, float64)."""
    radius = check_radius(radius, "positive radius")
    db = np.asarray(db_utm, np.float64)
    q = np.asarray(q_utm, np.float64)
    tree = cKDTree(db)
    out = []
    for qi, idx in zip(q, tree.query_ball_point(q, r=radius)):
        idx = np.asarray(idx, np.int64)
        dist = np.linalg.norm(db[idx] - qi, axis=1)
        out.append(idx[np.argsort(dist, kind="stable")])
    return out


# eq=False: the arrays make field-wise equality ambiguous and the set unhashable otherwise.
@dataclass(frozen=True, eq=False)
class PlaceIds:
    """Which place each image of a set shows: the supervision of GSV-Cities-style training (P places × K
    images per batch). ``db`` and ``q`` hold a place index in ``[0, num_places)`` per database image and
    per query; ``groups`` holds, per place, the group it belongs to (a GSV-Cities city, a SynthCity
    route): batches are drawn group by group, as gsv-cities draws them city by city."""

    db: np.ndarray
    q: np.ndarray
    groups: np.ndarray

    def __post_init__(self) -> None:
        for field in ("db", "q", "groups"):
            value = np.asarray(getattr(self, field))
            if value.ndim != 1 or (value.size and not np.issubdtype(value.dtype, np.integer)):
                raise SemvprError(f"place ids: {field} must be a 1-D array of whole numbers")
            object.__setattr__(self, field, value.astype(np.int64))
        for field in ("db", "q"):
            ids = getattr(self, field)
            if ids.size and (ids.min() < 0 or ids.max() >= self.num_places):
                raise SemvprError(f"place ids: {field} holds ids outside [0, {self.num_places}) (one group per place)")

    @property
    def num_places(self) -> int:
        return len(self.groups)


# eq=False: the arrays make field-wise equality ambiguous and the set unhashable otherwise.
@dataclass(frozen=True, eq=False)
class PlaceSet:
    """A database and a query set of images with (east, north) UTM positions in metres."""

    name: str
    db_paths: tuple[Path, ...]
    q_paths: tuple[Path, ...]
    db_utm: np.ndarray
    q_utm: np.ndarray
    db_labels: tuple[Path, ...] | None = None
    q_labels: tuple[Path, ...] | None = None
    #: Dataset root: per-image artifacts are keyed by the image path relative to it, since file
    #: stems repeat (Pitts30k has the same stem as a database and as a query image). None = the
    #: deepest folder holding every image of the set; a given root must hold every image.
    root: Path | None = None
    #: Evaluation ground truth shipped with the set's release (gsv-cities ``_gt.npy``, MSLS-val
    #: ``pIdx``, Nordland frame windows): per query, the database indices that count as correct.
    ground_truth: tuple[np.ndarray, ...] | None = None
    #: Without ``ground_truth``, the database images within this many metres are the positives
    #: (``data.eval_radius``, applied by :meth:`with_eval_radius`).
    eval_radius: float | None = None
    #: The place each image shows, where the set is grouped into places (SynthCity's training split,
    #: GSV-Cities): what ``recipe=gsv`` trains on. None: the set has only positions.
    place_ids: PlaceIds | None = None
    #: The set semantic artifacts are made from (the teacher's pseudo-labels of its images, keyed below its
    #: root, and the student trained on them); None: this one. SynthCity's training split with extra
    #: traversals names the split as drawn, so the student is the same whichever recipe trains.
    semantic_source: PlaceSet | None = None
    #: What a position is: "utm" ((east, north) in metres) or "frame" ((frame, 0): a frame-aligned set,
    #: ``data.benchmarks.read_frames``). A set scored by shipped ground truth may have none (NaN throughout).
    positions: Literal["utm", "frame"] = "utm"

    def __post_init__(self) -> None:
        # Normalise here so every reader (and hand-built sets) gets the same types and checks.
        for field in ("db_paths", "q_paths", "db_labels", "q_labels"):
            value = getattr(self, field)
            if value is not None:
                object.__setattr__(self, field, tuple(Path(p) for p in value))
        for paths, utm_field in ((self.db_paths, "db_utm"), (self.q_paths, "q_utm")):
            raw = getattr(self, utm_field)
            try:
                if np.iscomplexobj(raw):
                    raise TypeError
                utm = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
            except (TypeError, ValueError):
                raise SemvprError(f"place set {self.name!r}: {utm_field} is not (east, north) real numbers") from None
            with np.errstate(invalid="ignore"):
                bad = np.flatnonzero(~(np.isfinite(utm) & (np.abs(utm) <= MAX_POSITION)).all(1))
            # A set scored by shipped ground truth may have no positions at all (NaN throughout).
            no_positions = self.ground_truth is not None and bool(np.isnan(utm).all())
            if len(bad) and not no_positions:
                raise SemvprError(
                    f"place set {self.name!r}: {utm_field} has {len(bad)} non-finite position(s), the first at "
                    f"row {bad[0]} ({utm[bad[0]].tolist()}); positions must be finite, within ±{MAX_POSITION:.0e} m"
                )
            if len(utm) != len(paths):
                raise SemvprError(
                    f"place set {self.name!r}: {len(paths)} paths but {len(utm)} positions in {utm_field}"
                )
            object.__setattr__(self, utm_field, utm)
        for labels, paths, field in (
            (self.db_labels, self.db_paths, "db_labels"),
            (self.q_labels, self.q_paths, "q_labels"),
        ):
            if labels is not None and len(labels) != len(paths):
                raise SemvprError(f"place set {self.name!r}: {len(paths)} images but {len(labels)} {field}")
        if self.ground_truth is not None:
            object.__setattr__(self, "ground_truth", self._checked_ground_truth(self.ground_truth))
        if self.place_ids is not None and (
            len(self.place_ids.db) != len(self.db_paths) or len(self.place_ids.q) != len(self.q_paths)
        ):
            raise SemvprError(
                f"place set {self.name!r}: place ids for {len(self.place_ids.db)} database images and "
                f"{len(self.place_ids.q)} queries, but the set has {len(self.db_paths)} and {len(self.q_paths)}"
            )
        images = self.db_paths + self.q_paths
        root = Path(self.root) if self.root is not None else common_root(images)
        outside = next((p for p in images if not p.is_relative_to(root)), None)
        if outside is not None:
            raise SemvprError(f"place set {self.name!r}: image {outside} is not under the dataset root {root}")
        # An image's key (its path below the root) names its cached artifacts: it must not climb out.
        climbing = next((p for p in images if ".." in p.relative_to(root).parts), None)
        if climbing is not None:
            raise SemvprError(f"place set {self.name!r}: image {climbing} climbs out of the dataset root {root}")
        object.__setattr__(self, "root", root)

    def relative(self, path: Path) -> str:
        """Key of one of the set's images: its path relative to the dataset root, POSIX style."""
        return Path(path).relative_to(self.root).as_posix()

    def identity(self, side: str) -> str:
        """Hash of one side's ("db" or "q") images and labels by key, size and content
        (``files_identity``: every file is checked to be a readable regular file). Taken once per set."""
        known = self.__dict__.setdefault("_identities", {})
        if side not in known:
            paths, labels = (self.db_paths, self.db_labels) if side == "db" else (self.q_paths, self.q_labels)
            files = [*paths, *(labels or ())]
            names = [self.relative(p) for p in paths] + [f"label:{p}" for p in labels or ()]
            known[side] = files_identity(names, files)
        return known[side]

    def _checked_ground_truth(self, truth: tuple[np.ndarray, ...] | list[np.ndarray]) -> tuple[np.ndarray, ...]:
        if len(truth) != len(self.q_paths):
            raise SemvprError(
                f"place set {self.name!r}: ground truth for {len(truth)} queries, but {len(self.q_paths)} queries"
            )
        out = []
        for i, positives in enumerate(truth):
            idx = np.asarray(positives).ravel()
            if idx.size and (
                not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= len(self.db_paths)
            ):
                raise SemvprError(
                    f"place set {self.name!r}: ground truth of query {i} holds {idx[:5].tolist()}, "
                    f"not database indices in [0, {len(self.db_paths)})"
                )
            out.append(idx.astype(np.int64))
        return tuple(out)

    def positives(self, radius: float | None = None) -> list[np.ndarray]:
        """Per query, the database indices that count as correct: the set's ground truth, or those
        within ``eval_radius`` metres (nearest first); ``radius`` asks for another radius instead."""
        if radius is None and self.ground_truth is not None:
            return list(self.ground_truth)
        radius = self.eval_radius if radius is None else radius
        if radius is None:
            raise SemvprError(
                f"place set {self.name!r} has no evaluation ground truth: set data.eval_radius "
                f"(metres; 25 in the VPR benchmarks)"
            )
        if len(self.db_utm) == 0:
            return [np.zeros(0, dtype=np.int64) for _ in range(len(self.q_utm))]
        return positives_within(self.db_utm, self.q_utm, radius)

    def position(self, side: Literal["db", "q"], i: int) -> dict[str, Any]:
        """Image ``i`` of the database or the queries where a record names it: ``{"utm": [east, north]}``,
        ``{"frame": f}``, or ``{}`` where the set has no positions."""
        utm = (self.db_utm if side == "db" else self.q_utm)[i]
        if not np.isfinite(utm).all():
            return {}
        return {"frame": int(utm[0])} if self.positions == "frame" else {"utm": utm.tolist()}

    def with_eval_radius(self, radius: float | None) -> PlaceSet:
        """The set scored by positives within ``radius`` metres (None: as it is). A set whose release
        ships its ground truth keeps it; a radius for it is refused."""
        if radius is None:
            return self
        if self.ground_truth is not None:
            raise SemvprError(
                f"place set {self.name!r} is scored by the ground truth shipped with it; "
                f"data.eval_radius={radius} does not apply (drop it)"
            )
        return dataclasses.replace(self, eval_radius=float(radius))

    @property
    def for_semantics(self) -> PlaceSet:
        """The set the semantic side labels and trains the student on (:attr:`semantic_source`)."""
        return self.semantic_source if self.semantic_source is not None else self

    def summary(self) -> str:
        """Short human-readable description: counts and the extent of the positions (UTM metres, or the
        frames of a frame-aligned set)."""
        lines = [f"{self.name}: {len(self.db_paths)} database, {len(self.q_paths)} queries"]
        if self.place_ids is not None:
            lines[0] += f", {self.place_ids.num_places} places"
        for label, utm in (("database", self.db_utm), ("queries", self.q_utm)):
            if len(utm) and np.isfinite(utm).all():
                lo, hi = utm.min(0), utm.max(0)
                if self.positions == "frame":
                    lines.append(f"  {label} frames {lo[0]:.0f}..{hi[0]:.0f}")
                else:
                    lines.append(
                        f"  {label} UTM east {lo[0]:.1f}..{hi[0]:.1f}, north {lo[1]:.1f}..{hi[1]:.1f}"
                        f" ({hi[0] - lo[0]:.0f} x {hi[1] - lo[1]:.0f} m)"
                    )
        return "\n".join(lines)


def common_root(paths: tuple[Path, ...] | list[Path]) -> Path:
    """Deepest folder holding every path (``Path()`` for none)."""
    return Path(os.path.commonpath([str(p.parent) for p in paths])) if paths else Path()


def parse_utm_name(path: str | Path) -> tuple[float, float]:
    """(east, north) from a VPR-datasets-downloader name `@east@north@zone@...@.jpg`."""
    fields = Path(path).name.split("@")
    try:
        if len(fields) < 4 or fields[0] != "":
            raise ValueError
        return float(fields[1]), float(fields[2])
    except ValueError:
        raise SemvprError(f"{path}: not an @UTM@ image name (expected @utm_east@utm_north@zone@...@.jpg)") from None


def listed_image(folder: Path, name: str, source: Path) -> Path:
    """``folder / name`` for an image name read from a list file (every reader's one rule): the name must
    be relative, without ``..`` and without control characters (a NUL cannot name a file)."""
    rel = Path(name)
    if not name or any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise SemvprError(f"{source}: image name {name!r} is empty or holds a control character")
    if rel.is_absolute() or ".." in rel.parts:
        raise SemvprError(
            f"{source}: image name {name!r} leaves the folder {folder}; names must be relative, without '..'"
        )
    return folder / rel


def folder_images(folder: str | Path | None, key: str) -> list[Path]:
    """The images a command is given as a folder (``key``: the setting that names it, e.g. ``queries``): its
    image files and its subfolders' (:func:`image_files`), sorted; one clear line where the folder is unset,
    missing, a file, holds no image or lists something that is not a regular file."""
    if folder is None:
        raise SemvprError(f"{key}=null: name the folder of {'query ' if key == 'queries' else ''}images ({key}=DIR)")
    folder = Path(folder)
    if not folder.is_dir():
        problem = f"is a file: {key}= names the folder of images" if folder.exists() else f"does not exist ({key}=DIR)"
        raise SemvprError(f"{'query folder' if key == 'queries' else 'image folder'} {folder} {problem}")
    paths = image_files(folder, nested=True)
    if not paths:
        raise SemvprError(f"no .jpg/.png images in {folder}")
    for path in paths:
        try:
            regular = stat.S_ISREG(path.stat().st_mode)
        except OSError as err:
            raise SemvprError(f"image {path} cannot be read ({err.strerror or type(err).__name__})") from None
        if not regular:
            raise SemvprError(f"image {path} is not a regular file (a folder, FIFO or device)")
    return paths


def image_files(folder: Path, nested: bool = False) -> list[Path]:
    """The .jpg/.jpeg/.png files of ``folder`` and, ``nested``, of its subfolders at any depth (the references
    read a split as ``glob(folder/**/*.jpg)``), sorted. Hidden names are skipped as glob skips them (the
    ``._*.jpg`` a copy from macOS leaves beside each image, a ``.thumbnails/`` folder); a folder reached again
    through a link is read once."""
    found: list[Path] = []
    seen: set[str] = set()
    for top, dirs, files in os.walk(folder, followlinks=True):
        real = os.path.realpath(top)
        if real in seen:
            dirs.clear()
            continue
        seen.add(real)
        dirs[:] = [d for d in dirs if nested and not d.startswith(".")]
        found += [Path(top, f) for f in files if not f.startswith(".") and Path(f).suffix.lower() in IMAGE_SUFFIXES]
    return sorted(found)


def dataset_root(root: str | Path, what: str, key: str, holds: str) -> Path:
    """``root`` (``~`` expanded), refused in one line unless it is a directory: ``what`` it is, the setting that
    names it (``key``) and what the folder holds."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise SemvprError(f"{what} {root} is not a directory; set {key} to the folder holding {holds}")
    return root


def read_utm_folders(database: str | Path, queries: str | Path) -> PlaceSet:
    """Any two folders of @UTM@-named images (at any depth below each), the database's and the queries', as
    VPR-methods-evaluation takes them (``--database_folder``, ``--queries_folder``). The set's root is the
    folders' nearest common parent, which names its images; its name is the two folders'."""
    folders = {
        side: dataset_root(folder, f"{side} folder", f"data.{side}=DIR", "@UTM@-named images")
        for side, folder in (("database", database), ("queries", queries))
    }
    paths = {}
    for side, folder in folders.items():
        paths[side] = image_files(folder.absolute(), nested=True)
        if not paths[side]:
            raise SemvprError(f"{side} folder {folder}: no images (.jpg/.jpeg/.png) found below it")
    root = Path(os.path.commonpath([f.absolute() for f in folders.values()]))
    db, q = (paths[s] for s in ("database", "queries"))
    return PlaceSet(
        name=f"{folders['database'].name}→{folders['queries'].name}",
        root=root,
        db_paths=tuple(db),
        q_paths=tuple(q),
        db_utm=np.array([parse_utm_name(p) for p in db], dtype=np.float64),
        q_utm=np.array([parse_utm_name(p) for p in q], dtype=np.float64),
    )


def read_utm_folder(root: str | Path, split: str) -> PlaceSet:
    """Read `root/images/<split>/{database,queries}/*.jpg` (@UTM@ names); root may also be images/."""
    root = dataset_root(root, "dataset root", "data.root=...", f"images/{split}/database and images/{split}/queries")
    base = root / "images" if (root / "images").is_dir() else root
    split_dir = base / split
    if not split_dir.is_dir():
        found = sorted(p.name for p in base.iterdir() if p.is_dir())
        raise SemvprError(
            f"split folder {split_dir} not found (splits there: {found or 'none'}); "
            f"expected images/{split}/database and images/{split}/queries under data.root"
        )
    paths = {}
    for sub in ("database", "queries"):
        folder = split_dir / sub
        images = image_files(folder, nested=True) if folder.is_dir() else []
        if not images:
            raise SemvprError(
                f"{folder}: no {sub} images (.jpg/.png) found; the @UTM@ layout needs "
                f"images/{split}/database and images/{split}/queries"
            )
        paths[sub] = images
    name = base.parent.name if base.name == "images" else base.name
    return PlaceSet(
        name=f"{name}/{split}",
        root=base,
        db_paths=tuple(paths["database"]),
        q_paths=tuple(paths["queries"]),
        db_utm=np.array([parse_utm_name(p) for p in paths["database"]], dtype=np.float64),
        q_utm=np.array([parse_utm_name(p) for p in paths["queries"]], dtype=np.float64),
    )


def _mat_strings(cell: np.ndarray) -> list[str]:
    """Names from a MATLAB cell array of char arrays as scipy.io.loadmat returns it."""
    out = []
    for item in np.asarray(cell, dtype=object).ravel():
        flat = np.asarray(item).ravel()
        out.append(str(flat[0]).strip() if flat.size else "")
    return out


def _mat_utm(value: np.ndarray, count: int, mat_path: Path, field: str) -> np.ndarray:
    try:
        if np.iscomplexobj(value):
            raise TypeError
        utm = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SemvprError(
            f"{mat_path}: dbStruct.{field} is not real numbers (found {np.asarray(value).dtype})"
        ) from None
    if utm.size == 0 and count == 0:
        return np.zeros((0, 2))
    if utm.ndim == 2 and utm.shape[0] == 2 and utm.shape[1] == count:
        return utm.T.copy()
    if utm.ndim == 2 and utm.shape == (count, 2):  # already transposed by whoever re-saved the file
        return utm
    raise SemvprError(f"{mat_path}: dbStruct.{field} has shape {utm.shape}, expected (2, {count})")


def _resolve_root(names: list[str], candidates: list[Path], mat_path: Path, what: str) -> Path:
    """First candidate folder holding the first listed image (one stat, not one per image)."""
    if not names:
        return candidates[0]
    for folder in candidates:
        if (folder / names[0]).exists():
            return folder
    looked = ", ".join(str(c / names[0]) for c in candidates)
    raise SemvprError(
        f"{mat_path}: first {what} image {names[0]!r} not found (looked at {looked}); "
        f"point image_root (data.root) and, if elsewhere, query_root at the image folders"
    )


def read_dbstruct_mat(
    mat_path: str | Path, image_root: str | Path, name: str | None = None, query_root: str | Path | None = None
) -> PlaceSet:
    """Read a Pitts250k/30k or Tokyo 24/7 `dbStruct` .mat; image names resolve under image_root."""
    from scipy.io import loadmat

    mat_path, image_root = Path(mat_path).expanduser(), Path(image_root).expanduser()
    if not regular_file(mat_path, "dbStruct file"):
        raise SemvprError(
            f"dbStruct file {mat_path} not found; check data.root (it should hold "
            f"datasets/<name>.mat of the Pittsburgh / Tokyo 24/7 release, and the images)"
        )
    try:
        mat = loadmat(str(mat_path))
    except NotImplementedError:
        raise SemvprError(f"{mat_path}: MATLAB v7.3 (HDF5) file; re-save it with save(..., '-v7')") from None
    except Exception as err:  # scipy raises several types for corrupt files
        raise SemvprError(f"{mat_path}: not a readable .mat file ({err})") from None
    if "dbStruct" not in mat:
        keys = sorted(k for k in mat if not k.startswith("__"))
        raise SemvprError(f"{mat_path}: no 'dbStruct' variable (found {keys})")
    struct = mat["dbStruct"]
    names_present = struct.dtype.names or ()
    record = struct.ravel()[0] if struct.size else None

    def field(key: str) -> np.ndarray:
        if record is None or key not in names_present:
            raise SemvprError(
                f"{mat_path}: dbStruct lacks field '{key}' (fields found: "
                f"{list(names_present)}); is this a Pitts/Tokyo dbStruct file?"
            )
        return record[key]

    db_names, q_names = _mat_strings(field("dbImageFns")), _mat_strings(field("qImageFns"))
    db_utm = _mat_utm(field("utmDb"), len(db_names), mat_path, "utmDb")
    q_utm = _mat_utm(field("utmQ"), len(q_names), mat_path, "utmQ")
    which = _mat_strings(field("whichSet"))
    if not db_names or not q_names:
        raise SemvprError(f"{mat_path}: empty split ({len(db_names)} database, {len(q_names)} query names)")
    if not image_root.is_dir():
        raise SemvprError(
            f"image root {image_root} does not exist; set data.root=... to the folder "
            f"holding the images listed in {mat_path.name}"
        )
    db_root = _resolve_root(db_names, [image_root], mat_path, "database")
    # pytorch-NetVlad joins Pitts query names onto <root>/queries_real; other releases (Tokyo 24/7,
    # lists with the prefix) resolve under the root. queries_real first: a query stem may also be a
    # database image's (288 in Pitts30k-test), and <root>/<name> would then find the database image.
    q_candidates = [Path(query_root).expanduser()] if query_root else [image_root / "queries_real", image_root]
    q_root = _resolve_root(q_names, q_candidates, mat_path, "query")
    return PlaceSet(
        name=name or f"{mat_path.stem}" + (f"/{which[0]}" if which and which[0] else ""),
        root=image_root if q_root.is_relative_to(image_root) else common_root([image_root / "x", q_root / "x"]),
        db_paths=tuple(listed_image(db_root, n, mat_path) for n in db_names),
        q_paths=tuple(listed_image(q_root, n, mat_path) for n in q_names),
        db_utm=db_utm,
        q_utm=q_utm,
    )


def _read_csv(path: Path, required: tuple[str, ...]) -> list[dict[str, str]]:
    """Rows of an MSLS csv (its unnamed first column is the frame index, as pandas writes it)."""
    if not regular_file(path, "MSLS csv"):
        raise SemvprError(f"{path} not found; MSLS needs <city>/{{query,database}}/{path.name}")
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        try:
            columns = set(reader.fieldnames or ())
            missing = [c for c in required if c not in columns]
            if missing:
                raise SemvprError(f"{path}: missing column(s) {missing} (found {sorted(columns)})")
            return list(reader)
        except csv.Error as err:
            raise SemvprError(f"{path}: line {reader.line_num + 1}: not a readable csv row ({err})") from None
        except UnicodeDecodeError as err:
            byte = err.object[err.start : err.start + 1].hex()
            raise SemvprError(f"{path}: not UTF-8 text (a byte 0x{byte})") from None


def _frame(row: dict[str, str], position: int) -> int:
    """Frame index of a row: the csv's unnamed index column, else its position."""
    try:
        return int(row[""]) if row.get("") not in (None, "") else position
    except ValueError:
        return position


def _flag(value: str | None) -> bool:
    return str(value).strip().lower() in ("true", "1")


def _read_msls_side(
    folder: Path, subtask: str | None, exclude_panos: bool
) -> tuple[list[Path], list[tuple[float, float]]]:
    """Images and UTMs of one city side, filtered as mapillary_sls does (panoramas, val subtask)."""
    rows = _read_csv(folder / "postprocessed.csv", ("key", "easting", "northing"))
    keep: set[int] | None = None
    if exclude_panos:
        raw = _read_csv(folder / "raw.csv", ("pano",))
        keep = {_frame(r, i) for i, r in enumerate(raw) if not _flag(r["pano"])}
    if subtask is not None:
        index = _read_csv(folder / "subtask_index.csv", (subtask,))
        chosen = {_frame(r, i) for i, r in enumerate(index) if _flag(r[subtask])}
        keep = chosen if keep is None else keep & chosen
    paths, utm = [], []
    for position, row in enumerate(rows):
        if keep is not None and _frame(row, position) not in keep:
            continue
        try:
            utm.append((float(row["easting"]), float(row["northing"])))
        except (TypeError, ValueError):
            raise SemvprError(
                f"{folder / 'postprocessed.csv'}: bad easting/northing in row key={row['key']!r}"
            ) from None
        paths.append(listed_image(folder / "images", f"{row['key']}.jpg", folder / "postprocessed.csv"))
    return paths, utm


def _msls_city_dir(root: Path, city: str) -> Path:
    """A city's folder: train_val/<city> or test/<city>."""
    for sub in ("train_val", "test"):
        if (root / sub / city).is_dir():
            return root / sub / city
    raise SemvprError(f"MSLS city folder {city!r} not found under {root / 'train_val'} or {root / 'test'}")


def read_msls(
    root: str | Path, split: str, cities: list[str] | None = None, subtask: str = "all", exclude_panos: bool = True
) -> PlaceSet:
    """Read Mapillary SLS following mapillary_sls: official cities per split, panoramas excluded,
    and for the scored splits (``val``, ``test``) only the frames of ``subtask`` (subtask_index.csv; "all"
    by default).

    The benchmarks report the val cities (cph, sf), which is what ``data=msls`` tests on. The official
    test cities (``split="test"``) are read where their ground truth lies beside their images
    (``postprocessed.csv`` with easting and northing, as in train_val); their release has no ``raw.csv``, and
    where a test city's ground truth comes without one its panoramas stay in, as in mapillary_sls's test mode.
    ``split="selection"`` reads the training cities held out for epoch selection
    (:data:`MSLS_SELECTION_CITIES`, as train cities are read); ``split="train"`` the others.
    """
    root = Path(root).expanduser()
    official = {
        **MSLS_CITIES,
        "train": tuple(c for c in MSLS_CITIES["train"] if c not in MSLS_SELECTION_CITIES),
        "selection": MSLS_SELECTION_CITIES,
    }
    if split not in official:
        raise SemvprError(f"MSLS split {split!r} unknown; use one of {sorted(official)}")
    if not (root / "train_val").is_dir() and not (root / "test").is_dir():
        raise SemvprError(
            f"MSLS folders {root / 'train_val'} / {root / 'test'} not found; set data.root=... "
            f"to the folder holding train_val/ and test/"
        )
    if cities is None:
        cities = [c for c in official[split] if (root / "train_val" / c).is_dir() or (root / "test" / c).is_dir()]
        if not cities:
            raise SemvprError(
                f"{root}: none of the MSLS {split} cities {list(official[split])} "
                f"is there; pass data.cities.<split>=[...]"
            )
    db_paths: list[Path] = []
    q_paths: list[Path] = []
    db_utm: list[tuple[float, float]] = []
    q_utm: list[tuple[float, float]] = []
    for i, city in enumerate(cities):
        folder = _msls_city_dir(root, city)
        if not (folder / "query" / "postprocessed.csv").is_file() and (folder / "query").is_dir():
            raise SemvprError(
                f"MSLS city {city!r} has no ground truth ({folder / 'query' / 'postprocessed.csv'} "
                f"missing): place its postprocessed.csv beside each side's images, or evaluate "
                f"on the val cities (cph, sf) as the benchmarks do"
            )
        # Cities sit in different UTM zones whose (east, north) ranges overlap; shifting each
        # city's easting by 10,000 km keeps radius searches from ever pairing two cities.
        shift = i * 1e7
        for side, paths, utms in (("database", db_paths, db_utm), ("query", q_paths, q_utm)):
            released_without_panos = split == "test" and not (folder / side / "raw.csv").is_file()
            found, utm = _read_msls_side(
                folder / side,
                subtask if split in ("val", "test") else None,
                exclude_panos and not released_without_panos,
            )
            paths += found
            utms += [(e + shift, n) for e, n in utm]
    if not db_paths or not q_paths:
        raise SemvprError(
            f"{root}: empty MSLS split {split!r} for cities {cities} ({len(db_paths)} database, {len(q_paths)} queries)"
        )
    return PlaceSet(
        name=f"msls/{split}",
        db_paths=tuple(db_paths),
        q_paths=tuple(q_paths),
        db_utm=np.array(db_utm).reshape(-1, 2),
        q_utm=np.array(q_utm).reshape(-1, 2),
        root=root,
    )
