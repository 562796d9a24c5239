"""Config-hash cache for built artifacts (SynthCity, teacher, pseudo-labels, student, feature caches).

An artifact lives in ``<cache_dir>/<kind>-<hash>/``. It is built in a temporary sibling directory
and renamed when complete, so a directory with the final name is always a finished artifact.
Builders of the same artifact are serialised by an advisory lock (``flock`` on
``<cache_dir>/.locks/<kind>-<hash>.lock``; lock files are kept, as deleting them would race), so
the jobs of a parallel sweep (e.g. hydra-submitit-launcher on a shared file system) build it once:
the first takes the lock, the others wait (a line says so, and how long) and then reuse its result.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import shutil
import stat
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from semvpr.core.errors import SemvprError
from semvpr.core.io import disk_full, open_lock, reclaim_orphans, temp_dir, write_text
from semvpr.core.logs import say

LOCK_DIR = ".locks"


def config_hash(key: Any, length: int = 12) -> str:
    """Stable short hash of a JSON-able object."""
    text = json.dumps(key, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def state_hash(state: dict[str, Any], length: int = 16) -> str:
    """Stable hash of a state dict's names and tensor bytes (identifies weights exactly)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(state.items()):
        digest.update(name.encode())
        # reshape(-1): 0-dim buffers (BatchNorm's num_batches_tracked) cannot be viewed as bytes
        digest.update(tensor.detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()[:length]


#: Bytes of each of the three blocks (start, middle, end) of a file that its content key hashes (the whole
#: file when it is no longer than the three).
CONTENT_BYTES = 4096


def files_identity(names: Sequence[str], paths: Sequence[str | Path]) -> str:
    """Hash of each file's name (as the caller keys it), size and content (a SHA-256 of its first, middle
    and last ``CONTENT_BYTES``; the whole file when it is no longer than those three blocks).

    What a cache built from files is keyed by: the same names with other bytes give another key, even an
    image replaced by another of the same size (a JPEG's first block holds its tables and header, its last
    the end of the entropy-coded data). The modification time is not part of it: a dataset copied to another
    disk (``cp``, ``rsync`` without ``-t``, a container image) keeps its caches, which an mtime key would
    rebuild, a trained teacher included. Three reads of 4 KiB per file; a file that cannot be read as a
    regular file (missing, a dangling or looping link, a FIFO or device, a NUL in its name) is one line
    naming it.
    """
    digest = hashlib.sha256(b"files-identity v3\n")
    for name, path in zip(names, paths, strict=True):
        size, content = _file_fingerprint(path)
        digest.update(f"{name}\0{size}\0".encode())
        digest.update(content)
        digest.update(b"\n")
    return digest.hexdigest()[:16]


def _content_offsets(size: int) -> tuple[int, ...]:
    """Where the blocks a file's content key hashes start: the whole file in one read when it is short."""
    if size <= 3 * CONTENT_BYTES:
        return (0,)
    return 0, (size - CONTENT_BYTES) // 2, size - CONTENT_BYTES


def _file_fingerprint(path: str | Path) -> tuple[int, bytes]:
    """(size, SHA-256 of the blocks of :func:`_content_offsets`) of a regular file, or one line."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise SemvprError(
                f"{path} is not a regular file (a folder, FIFO or device); image lists must name image files"
            )
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        try:
            opened = os.fstat(fd)
            if not stat.S_ISREG(opened.st_mode):
                raise SemvprError(f"{path} is not a regular file; image lists must name image files")
            offsets = _content_offsets(opened.st_size)
            length = opened.st_size if len(offsets) == 1 else CONTENT_BYTES
            content = b"".join(os.pread(fd, length, offset) for offset in offsets)
        finally:
            os.close(fd)
    except FileNotFoundError:
        raise SemvprError(f"image {path} not found (missing, or a link to nothing)") from None
    except OSError as err:
        raise SemvprError(f"image {path} cannot be read ({err.strerror or type(err).__name__})") from None
    except ValueError as err:  # an embedded NUL byte
        raise SemvprError(f"image name {str(path)!r} cannot name a file ({err})") from None
    return opened.st_size, hashlib.sha256(content).digest()


def artifact_dir(cache_dir: str | Path, kind: str, key: Any) -> Path:
    """Final directory of the artifact ``kind`` identified by ``key``."""
    return Path(cache_dir) / f"{kind}-{config_hash(key)}"


def build_once(
    cache_dir: str | Path,
    kind: str,
    key: Any,
    build: Callable[[Path], None],
    resumable: bool = False,
) -> Path:
    """Return the artifact directory, calling ``build(tmp_dir)`` first if it does not exist yet.

    ``build`` writes into a temporary directory; on success it is renamed into place and ``key``
    is saved beside the content as ``key.json``. A failed build leaves nothing behind, unless
    ``resumable``: then the temporary directory is kept under a fixed name and handed to the next
    ``build`` call, which may keep a file already there only after checking it is one it would have
    written (that directory may have been left by anyone; pseudo-labels check size, mode and ids).
    """
    final = artifact_dir(cache_dir, kind, key)
    if final.is_dir():
        return final
    try:
        (final.parent / LOCK_DIR).mkdir(parents=True, exist_ok=True)
        for folder in (final.parent, final.parent / LOCK_DIR):  # another user's cache, shared read-only
            if not os.access(folder, os.W_OK | os.X_OK):
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))
        reclaim_orphans(final.parent)
    except OSError as err:
        raise SemvprError(
            f"cache dir {final.parent} cannot be written ({err.strerror or type(err).__name__}) and holds no "
            f"{kind} artifact for this run; point paths.cache_dir at a writable folder"
        ) from None
    with _exclusive(final.parent / LOCK_DIR / f"{final.name}.lock", f"{kind} artifact {final}"):
        if final.is_dir():  # another job built it while we waited for the lock
            return final
        _build_into(final, key, build, resumable)
    return final


@contextmanager
def _exclusive(lock_path: Path, what: str) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``lock_path`` (blocks until it is free, saying so once: a teacher
    another job trains can take hours); a link there is refused."""
    fd = open_lock(lock_path)
    with os.fdopen(fd, "rb") as handle:
        try:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                say(f"cache: waiting for another job building the {what}")
                tic = time.monotonic()
                fcntl.flock(handle, fcntl.LOCK_EX)
                say(f"cache: waited {time.monotonic() - tic:.0f} s")
        except OSError as err:
            if err.errno not in (errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOLCK):
                raise
            raise SemvprError(
                f"the cache's file system cannot lock {lock_path} ({err.strerror}: Lustre or NFS without flock?); "
                "point paths.cache_dir at a local or flock-capable folder"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _build_into(final: Path, key: Any, build: Callable[[Path], None], resumable: bool) -> None:
    """Run ``build`` in a temporary sibling of ``final`` and rename it into place on success.

    A one-off build gets a fresh directory of a random name (created exclusively); a resumable
    one reuses ``.<name>.partial`` only if that is a plain directory, never a link.
    """
    if resumable:
        tmp = final.parent / f".{final.name}.partial"
        if tmp.is_symlink() or (tmp.exists() and not tmp.is_dir()):
            raise SemvprError(f"{tmp} is not a plain directory (a link?); refusing to build there: remove it")
        tmp.mkdir(exist_ok=True)
    else:
        tmp = temp_dir(final.parent, final.name)
    try:
        build(tmp)
        write_text(tmp / "key.json", json.dumps(key, sort_keys=True, indent=1, default=str))
        os.rename(tmp, final)
    except BaseException as err:
        full = disk_full(final.parent, err, f"building the cache {final.name}")
        if not resumable:
            shutil.rmtree(tmp, ignore_errors=True)
        if full is not None:
            raise full from None
        raise
