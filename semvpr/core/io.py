"""File output shared by every entry point: the config directory and writes never seen half done.

Every file a run or a cache holds is written through :func:`atomic_file` or :func:`atomic_dir`:
the content goes to a fresh temporary name beside the target (random, created exclusively, so a
pre-planted file or link is never followed and two writers never share one), and is renamed
onto the target only when complete. A failed or killed write leaves no target behind, and the
temporary name records its writer (``.<name>.<host>-<pid>.<random>.tmp``): what a killed process
left is reclaimed by the next build there (:func:`reclaim_orphans`).
Per-item paths inside an artifact (one file per image) go through :func:`inside`, which refuses
any that would leave the artifact's directory.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from semvpr.core.errors import SemvprError

CONF_DIR = str(Path(__file__).resolve().parents[2] / "conf")


@contextmanager
def atomic_file(final: Path) -> Iterator[IO[bytes]]:
    """A binary file object to write ``final``'s content to; renamed onto ``final`` on success."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent)
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
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent))
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


_TEMP = re.compile(r"^\..+\.(?P<host>[^.]+)-(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp$")


def temp_prefix(name: str) -> str:
    """Prefix of a temporary name for ``name`` that records this host and process."""
    return f".{name}.{socket.gethostname().split('.')[0]}-{os.getpid()}."


def reclaim_orphans(folder: Path) -> list[Path]:
    """Delete the temporary files and directories in ``folder`` whose writer (on this host) is dead."""
    host, removed = socket.gethostname().split(".")[0], []
    for entry in Path(folder).iterdir() if Path(folder).is_dir() else ():
        match = _TEMP.match(entry.name)
        if match is None or match["host"] != host or _alive(int(match["pid"])):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def ensure_free(folder: Path, nbytes: int, what: str) -> None:
    """Refuse, in one line, to start writing ``nbytes`` into ``folder`` when the disk lacks room."""
    free = shutil.disk_usage(folder).free
    if nbytes > free:
        raise SemvprError(
            f"{what} needs {nbytes / 2**30:.2f} GiB in {folder}, but only {free / 2**30:.2f} GiB "
            f"are free; free some space or point paths.cache_dir elsewhere"
        )


def open_array(path: Path, dtype: Any, shape: tuple[int, ...], what: str) -> Any:
    """A new ``.npy`` memory map whose blocks are reserved up front: a full disk is one line here,
    never a bus error while writing into it."""
    import numpy as np

    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    ensure_free(Path(path).parent, size, what)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    if size:
        fd = os.open(path, os.O_RDWR)
        try:
            os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
        except OSError as err:
            raise SemvprError(
                f"{what}: cannot reserve {size / 2**30:.2f} GiB in {Path(path).parent} "
                f"({err.strerror}); free some space or point paths.cache_dir elsewhere"
            ) from None
        finally:
            os.close(fd)
    return out
