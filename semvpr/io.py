"""File output shared by every entry point: the config directory and writes never seen half done.

Every file a run or a cache holds is written through :func:`atomic_file` or :func:`atomic_dir`:
the content goes to a fresh temporary name beside the target (random, created exclusively, so a
pre-planted file or link is never followed and two writers never share one), and is renamed
onto the target only when complete. A failed or killed write leaves no target behind.
Per-item paths inside an artifact (one file per image) go through :func:`inside`, which refuses
any that would leave the artifact's directory.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from semvpr.errors import SemvprError

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


@contextmanager
def atomic_file(final: Path) -> Iterator[IO[bytes]]:
    """A binary file object to write ``final``'s content to; renamed onto ``final`` on success."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
        os.replace(name, final)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise


@contextmanager
def atomic_dir(final: Path) -> Iterator[Path]:
    """A fresh empty directory to build ``final`` in; it replaces ``final`` on success."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent))
    try:
        yield tmp
        if final.is_symlink() or final.is_file():
            final.unlink()
        elif final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_text(path: Path, text: str) -> None:
    """Write UTF-8 text atomically."""
    with atomic_file(path) as fh:
        fh.write(text.encode("utf-8"))


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically (numpy scalars as floats)."""
    write_text(path, json.dumps(obj, indent=1, default=float))


def inside(base: Path, rel: str | Path) -> Path:
    """``base / rel``, refused unless it stays inside ``base`` both as written (no absolute path, no
    ``..``) and on disk (no symlink under ``base`` leading elsewhere)."""
    base, rel = Path(base), Path(rel)
    if rel.is_absolute() or ".." in rel.parts:
        raise SemvprError(f"{rel.as_posix()!r} would leave {base}; refusing to write there")
    path = base / rel
    real_base = base.resolve()
    if not path.resolve().is_relative_to(real_base):
        raise SemvprError(f"{path} leads outside {real_base} through a symlink; refusing to write there")
    return path


def check_dir_path(path: Path, what: str) -> None:
    """Refuse a directory path that cannot be made because a file sits on the way."""
    path = Path(path).expanduser()
    for folder in (path, *path.parents):
        if folder.exists():
            if not folder.is_dir():
                raise SemvprError(f"{what}={path}: {folder} is a file, not a directory")
            return
