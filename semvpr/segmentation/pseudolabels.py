"""Pseudo-label cache: the teacher labels every training image once, as trainId PNGs.

A label is stored at the image's path relative to its dataset root (``<rel path>.png``), never by
file stem alone: stems repeat within a dataset (Pitts30k: ``000/000546_pitch1_yaw1.jpg`` is a
database image, ``queries_real/000/000546_pitch1_yaw1.jpg`` a query).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from torch.utils.data import DataLoader

from semvpr.core.cache import build_once, files_identity
from semvpr.core.errors import SemvprError
from semvpr.core.io import atomic_file, inside
from semvpr.core.logs import Progress
from semvpr.core.precision import autocast, compute_key
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES
from semvpr.data.images import ImageDataset, Reading


@dataclass(frozen=True)
class LabelledImages:
    """Training images with their pseudo-labels: the folder :func:`pseudo_labels` built and the root the
    images' label names are relative to (:func:`label_path`)."""

    images: Sequence[Path]
    labels: Path
    root: Path


VERSION = 2  # 2: labels keyed by the path relative to the dataset root (1: by stem)
#: The values a label PNG may hold: Cityscapes trainIds and the ignore id.
VALID_IDS = np.array([*range(len(TRAIN_ID_NAMES)), IGNORE], dtype=np.uint8)

#: The linked trunk's cached ``forward_frozen`` outputs of some images (``Teacher.link_trunk``).
TrunkOutputs = Callable[[Sequence[Path]], list[Tensor | None]]


def _remove_strays(out: Path, wanted: set[Path]) -> None:
    """Remove everything under ``out`` (a resumed build's directory, left by anyone) that is neither one of the
    ``wanted`` labels nor a folder on the way to one: the finished artifact holds its labels only."""
    folders = {parent for path in wanted for parent in path.parents}
    for top, dirs, files in os.walk(out, followlinks=False):
        for name in files:
            if (path := Path(top) / name) not in wanted:
                path.unlink()
        for name in list(dirs):
            path = Path(top) / name
            if path.is_symlink() or path not in folders:
                shutil.rmtree(path) if not path.is_symlink() else path.unlink()
                dirs.remove(name)


def _label_name(image: str | Path, root: str | Path) -> Path:
    """The pseudo-label's path of ``image`` (under dataset ``root``) relative to a labels directory."""
    try:
        rel = Path(image).relative_to(root)
    except ValueError:
        raise SemvprError(f"image {image} is not under the dataset root {root}") from None
    return rel.parent / f"{rel.name}.png"


def label_path(label_dir: str | Path, image: str | Path, root: str | Path) -> Path:
    """Where the pseudo-label of ``image`` (under dataset ``root``) lives in a labels directory."""
    return inside(Path(label_dir), _label_name(image, root))


def read_label(label_dir: str | Path, image: str | Path, root: str | Path) -> np.ndarray:
    """The trainId map of ``image`` from a labels directory; a damaged file is one line naming it."""
    path = label_path(label_dir, image, root)
    try:
        with Image.open(path) as img:
            return np.array(img)  # writable: callers hand it to torch
    except (OSError, ValueError, SyntaxError) as err:
        raise SemvprError(
            f"pseudo-label {path} is unreadable ({type(err).__name__}); delete {Path(label_dir)} to rebuild the labels"
        ) from None


def image_list_identity(paths: Sequence[Path], root: Path) -> str:
    """Hash of the (sorted) relative paths, sizes and contents: the same images give the same labels."""
    named = sorted((p.relative_to(root).as_posix(), p) for p in paths)
    return files_identity([n for n, _ in named], [p for _, p in named])


def _write_png(ids: np.ndarray, final: Path) -> None:
    """Write a uint8 trainId PNG under a temporary name, then rename, so a kill never leaves half a file."""
    with atomic_file(final) as fh:
        Image.fromarray(ids.astype(np.uint8)).save(fh, format="PNG")


def _label_ok(path: Path, image_size: tuple[int, int]) -> bool:
    """Whether a label left in a resumed build is one this module writes: a regular 8-bit PNG at
    ``image_size`` holding trainIds (or 255). Anything else is removed, to be labelled again."""
    if not path.is_file() or path.is_symlink():
        if path.is_symlink() or path.exists():
            path.unlink()
        return False
    try:
        with Image.open(path) as img:
            ok = img.format == "PNG" and img.mode == "L" and img.size == (image_size[1], image_size[0])
            ids = np.asarray(img) if ok else None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        ok, ids = False, None
    if ids is not None:
        ok = bool(np.isin(ids, VALID_IDS).all())
    if not ok:
        path.unlink()
    return ok


def pseudo_labels(
    teacher: Any,
    paths: Sequence[str | Path],
    reading: Reading,
    cache_dir: str | Path,
    root: str | Path,
    trunk: TrunkOutputs | None = None,
) -> Path:
    """Directory of one trainId PNG per image (at ``reading.image_size``, see ``label_path``; the images read in
    its batches by its workers), built once and resumable,
    keyed by the teacher's ``teacher_key`` (what identifies its weights: ``segmentation.training.build_teacher``)
    and the arithmetic it labels in (``precision.compute_key``: device, precision, CPU threads).

    ``trunk``: the images' cached outputs of the trunk the teacher is linked to (``Teacher.link_trunk``); the
    teacher then runs only its decoder. Its labels differ from those of the teacher's own encoder by float
    rounding at most, and are cached apart from them."""
    root = Path(root)
    paths = list(dict.fromkeys(Path(p) for p in paths))  # each image once, first-seen order
    if not paths:
        raise SemvprError("pseudo-labels: no images given to label")
    for p in paths:
        label_path("", p, root)  # every image must sit under the root: fail before any work
    size = (int(reading.image_size[0]), int(reading.image_size[1]))
    batch_size = reading.batch_size
    device = getattr(teacher, "device", torch.device("cpu"))
    key = {
        "version": VERSION,
        "teacher": teacher.teacher_key,
        "images": image_list_identity(paths, root),
        "image_size": list(size),
        **compute_key(device),
    }
    if trunk is not None:
        key["encoder"] = "trunk"

    def label_missing(out: Path) -> None:
        """Label the images whose PNG is not in ``out`` yet, from the images or, given ``trunk``, from the linked
        trunk's cached outputs (no image is read); a resumed run keeps the finished ones that pass
        :func:`_label_ok` (``out`` may be a ``.partial`` directory left by anyone)."""
        for p in paths:  # a link left in a resumed build is never followed, never kept
            planted = out / _label_name(p, root)
            if planted.is_symlink():
                planted.unlink()
        _remove_strays(out, {out / _label_name(p, root) for p in paths})
        todo = [p for p in paths if not _label_ok(label_path(out, p, root), size)]
        bar = Progress("pseudo-labels", len(paths), done=len(paths) - len(todo))
        if not todo:
            return
        with torch.no_grad(), autocast(device):
            if trunk is not None:
                for first in range(0, len(todo), batch_size):
                    chunk = todo[first : first + batch_size]
                    outputs = [o.to(device) if o is not None else None for o in trunk(chunk)]
                    ids = teacher.trunk_train_ids(outputs, size).cpu().numpy()
                    for i, path in enumerate(chunk):
                        _write_png(ids[i], label_path(out, path, root))
                    bar.update(len(chunk))
            else:
                loader = DataLoader(ImageDataset(todo, size), batch_size=batch_size, num_workers=reading.num_workers)
                for images, index in loader:
                    ids = teacher.predict_train_ids(images.to(device)).cpu().numpy()
                    for i, k in enumerate(index.tolist()):
                        _write_png(ids[i], label_path(out, todo[k], root))
                    bar.update(len(index))
        bar.close()

    return build_once(cache_dir, "labels", key, label_missing, resumable=True)
