"""Config-hash cache for built artifacts (SynthCity, teacher, pseudo-labels, student, feature caches).

An artifact lives in ``<cache_dir>/<kind>-<hash>/``. It is built in a temporary sibling directory
and renamed when complete, so a directory with the final name is always a finished artifact.
Builders of the same artifact are serialised by an advisory lock (``flock`` on
``<cache_dir>/.locks/<kind>-<hash>.lock``; lock files are kept, as deleting them would race), so
the jobs of a parallel sweep (e.g. hydra-submitit-launcher on a shared file system) build it once:
the first takes the lock, the others wait and then reuse its result.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from semvpr.core.errors import SemvprError
from semvpr.core.io import reclaim_orphans, temp_prefix, write_text

LOCK_DIR = ".locks"


def config_hash(key: Any, length: int = 12) -> str:
    """Stable short hash of a JSON-able (or OmegaConf) object."""
    if isinstance(key, (DictConfig, ListConfig)):
        key = OmegaConf.to_container(key, resolve=True)
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


def files_identity(names: Sequence[str], paths: Sequence[str | Path]) -> str:
    """Hash of each file's name (as the caller keys it), size and modification time in ns.

    What a cache built from files is keyed by: the same names with other bytes (a dataset whose
    images were replaced) give another key. One ``stat`` per file, no read.
    """
    digest = hashlib.sha256()
    for name, path in zip(names, paths, strict=True):
        st = os.stat(path)
        digest.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]


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
    ``build`` call, which may skip the files already there.
    """
    final = artifact_dir(cache_dir, kind, key)
    if final.is_dir():
        return final
    (final.parent / LOCK_DIR).mkdir(parents=True, exist_ok=True)
    reclaim_orphans(final.parent)
    with _exclusive(final.parent / LOCK_DIR / f"{final.name}.lock"):
        if final.is_dir():  # another job built it while we waited for the lock
            return final
        _build_into(final, key, build, resumable)
    return final


@contextmanager
def _exclusive(lock_path: Path) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``lock_path`` (blocks until it is free); a link there is refused."""
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as err:
        raise SemvprError(
            f"lock file {lock_path} cannot be opened ({err.strerror}); a link there is never followed: remove it"
        ) from None
    with os.fdopen(fd, "r+") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
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
        tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent))
    try:
        build(tmp)
        if isinstance(key, (DictConfig, ListConfig)):
            key = OmegaConf.to_container(key, resolve=True)
        write_text(tmp / "key.json", json.dumps(key, sort_keys=True, indent=1, default=str))
        os.rename(tmp, final)
    except BaseException:
        if not resumable:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
