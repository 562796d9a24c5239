"""What an evaluation job writes for other tools, on request (``save.*`` of ``conf/eval.yaml``; docs/evaluation.md):

- ``descriptors``: ``db_descriptors.npy`` and ``q_descriptors.npy`` (float32, one row per image, in the set's
  order) with ``db_images.txt`` and ``q_images.txt`` (each image's name, one per line, in the same order);
- ``hloc``: hloc's global-features file ``global-feats.h5`` (one group per image name holding its
  ``global_descriptor``, as hloc's ``extract_features`` writes it) and ``pairs-retrieval.txt`` (each query with
  its ``pairs`` nearest database images, one ``query database`` pair per line, as hloc's
  ``pairs_from_retrieval`` writes them), for hloc's matching and localization; needs h5py
  (``pip install 'semvpr[hloc]'``);
- ``predictions``: ``predictions.csv``, every query's top ``pairs`` retrieved database images (rank, image,
  descriptor distance, and whether it is a positive);
- ``images``: that many queries drawn with their first ``image_top`` retrieved images (``only_wrong``: of the
  queries whose first is not a positive), ``predictions/<query>.jpg`` (``reporting.prediction_images``).

An image's name is its path below the set's root (``PlaceSet.relative``); where a name stands on both sides
(one folder read as database and queries), every name gets its side's prefix (``db/``, ``q/``), so no group of
the h5 file is two images'.
"""

from __future__ import annotations

import csv
import io
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import check_replaceable, temp_prefix, write_npy, write_text
from semvpr.core.spec import setting
from semvpr.data.places import PlaceSet
from semvpr.reporting.prediction_images import MaskOf, drawn_queries, write_prediction_images


@dataclass(frozen=True)
class SaveSpec:
    """``save``: which of the module's files an evaluation writes, and how many database images per query the
    pairs and predictions list."""

    descriptors: bool = False
    hloc: bool = False
    predictions: bool = False
    pairs: int = setting(20, low=1, also="database images per query")
    images: int = setting(0, low=0, also="queries drawn")
    image_top: int = setting(5, low=1, also="database images beside each drawn query")
    only_wrong: bool = False

    def __post_init__(self) -> None:
        if self.hloc:
            try:
                import h5py  # noqa: F401
            except ImportError:
                raise SemvprError(
                    "save.hloc=true writes an h5 file and needs h5py: pip install 'semvpr[hloc]'"
                ) from None

    @property
    def any(self) -> bool:
        return self.descriptors or self.hloc or self.predictions or self.images > 0


def image_names(places: PlaceSet) -> tuple[list[str], list[str]]:
    """The database's and the queries' image names (module docstring)."""

    def name(path: Path) -> str:
        return places.relative(path) if places.root is not None else Path(path).as_posix().lstrip("/")

    db, q = [name(p) for p in places.db_paths], [name(p) for p in places.q_paths]
    if set(db) & set(q) or len(set(db)) < len(db) or len(set(q)) < len(q):
        db, q = [f"db/{n}" for n in db], [f"q/{n}" for n in q]
    if len(set(db)) < len(db) or len(set(q)) < len(q):
        raise SemvprError(f"place set {places.name!r} lists an image twice on one side: its names cannot key a file")
    return db, q


def write_exports(
    spec: SaveSpec,
    out_dir: Path,
    places: PlaceSet,
    db: np.ndarray,
    q: np.ndarray,
    top: np.ndarray,
    positives: list[np.ndarray],
    image_size: Sequence[int] = (480, 640),
    mask_of: MaskOf | None = None,
) -> list[str]:
    """Write the files ``spec`` asks for into ``out_dir`` (``top``: each query's retrieved database indices,
    nearest first; ``image_size`` the drawn tiles' aspect, ``mask_of`` each drawn image's mask); returns their
    names."""
    db_names, q_names = image_names(places)
    k = min(spec.pairs, top.shape[1])
    written: list[str] = []
    if spec.descriptors:
        for side, desc, names in (("db", db, db_names), ("q", q, q_names)):
            write_npy(out_dir / f"{side}_descriptors.npy", np.asarray(desc, dtype=np.float32))
            write_text(out_dir / f"{side}_images.txt", "".join(f"{n}\n" for n in names))
            written += [f"{side}_descriptors.npy", f"{side}_images.txt"]
    if spec.hloc:
        _write_h5(out_dir / "global-feats.h5", [(db_names, db), (q_names, q)])
        lines = (f"{q_names[i]} {db_names[j]}\n" for i in range(len(q_names)) for j in top[i, :k])
        write_text(out_dir / "pairs-retrieval.txt", "".join(lines))
        written += ["global-feats.h5", "pairs-retrieval.txt"]
    if spec.predictions:
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(["query", "rank", "database", "distance", "correct"])
        for i, name in enumerate(q_names):
            found = top[i, :k]
            distances = np.linalg.norm(np.asarray(db[found], np.float64) - np.asarray(q[i], np.float64), axis=1)
            right = set(np.asarray(positives[i]).tolist())
            for rank, (j, d) in enumerate(zip(found, distances, strict=True), start=1):
                writer.writerow([name, rank, db_names[j], f"{d:.6f}", str(int(j) in right).lower()])
        write_text(out_dir / "predictions.csv", buffer.getvalue())
        written.append("predictions.csv")
    if spec.images:
        right = np.array([int(top[i, 0]) in set(np.asarray(p).tolist()) for i, p in enumerate(positives)], bool)
        queries = drawn_queries(right, spec.images, spec.only_wrong)
        drawn = top[queries, : spec.image_top]
        distances = np.linalg.norm(
            np.asarray(db[drawn], np.float64) - np.asarray(q[queries], np.float64)[:, None], axis=2
        )
        written += write_prediction_images(out_dir, places, queries, drawn, distances, positives, image_size, mask_of)
    return written


def _write_h5(path: Path, sides: list[tuple[list[str], Any]]) -> None:
    """hloc's global-features file: per image name a group holding ``global_descriptor`` (float32); written
    beside ``path`` and renamed onto it when whole."""
    import h5py

    check_replaceable(path)
    fd, name = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".h5", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(name, "w") as fh:
            for names, desc in sides:
                for image, row in zip(names, desc, strict=True):
                    fh.create_group(image).create_dataset("global_descriptor", data=np.asarray(row, dtype=np.float32))
        os.replace(name, path)
    finally:
        Path(name).unlink(missing_ok=True)
