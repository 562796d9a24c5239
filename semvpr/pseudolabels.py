"""Pseudo-label cache: the teacher labels every training image once, as trainId PNGs named by image stem."""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch.utils.data import DataLoader
from tqdm import tqdm

from semvpr.artifacts import build_once, config_hash
from semvpr.errors import SemvprError

VERSION = 1


def label_path(label_dir: str | Path, image: str | Path) -> Path:
    """Where the pseudo-label of ``image`` lives in a labels directory."""
    return Path(label_dir) / f"{Path(image).stem}.png"


def image_list_identity(paths: Sequence[Path]) -> str:
    """Hash of the (sorted) image names and byte sizes: the same images give the same labels."""
    return config_hash(sorted((p.name, p.stat().st_size) for p in paths))


def _write_png(ids: np.ndarray, final: Path) -> None:
    """Write a uint8 trainId PNG under a temporary name, then rename, so a kill never leaves half a file."""
    tmp = final.with_name(f".{final.name}.tmp")
    Image.fromarray(ids.astype(np.uint8)).save(tmp, format="PNG")
    os.replace(tmp, final)


def _label_missing(
    teacher: Any, paths: Sequence[Path], image_size: tuple[int, int], out: Path, batch_size: int, num_workers: int
) -> None:
    """Label the images whose PNG is not in ``out`` yet (a resumed run skips the finished ones)."""
    from semvpr.data.datamodule import ImageDataset

    todo = [p for p in paths if not label_path(out, p).is_file()]
    bar = tqdm(total=len(paths), initial=len(paths) - len(todo), desc="pseudo-labels", unit="img", disable=None)
    if not todo:
        bar.close()
        return
    device = getattr(teacher, "device", torch.device("cpu"))
    loader = DataLoader(ImageDataset(todo, image_size), batch_size=batch_size, num_workers=num_workers)
    with bar, torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16):
        for images, index in loader:
            ids = teacher.predict_train_ids(images.to(device)).cpu().numpy()
            for i, k in enumerate(index.tolist()):
                _write_png(ids[i], label_path(out, todo[k]))
            bar.update(len(index))


def pseudo_labels(
    teacher: Any,
    teacher_key: str,
    paths: Sequence[str | Path],
    image_size: Sequence[int],
    cache_dir: str | Path,
    *,
    batch_size: int = 16,
    num_workers: int = 2,
) -> Path:
    """Directory of one trainId PNG per image (``<stem>.png``, at ``image_size``), built once and resumable."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise SemvprError("pseudo-labels: no images given to label")
    stems: dict[str, Path] = {}
    for p in paths:
        if p.stem in stems and stems[p.stem] != p:
            raise SemvprError(f"pseudo-labels are named by image stem, but {stems[p.stem]} and {p} share '{p.stem}'")
        stems[p.stem] = p
    paths = list(stems.values())
    size = (int(image_size[0]), int(image_size[1]))
    key = {"version": VERSION, "teacher": teacher_key, "images": image_list_identity(paths), "image_size": list(size)}
    return build_once(
        cache_dir, "labels", key,
        lambda out: _label_missing(teacher, paths, size, out, batch_size, num_workers),
        resumable=True,
    )  # fmt: skip
