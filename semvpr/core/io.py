"""File output shared by every entry point: the config directory and writes never seen half done.

Every file a run or a cache holds is written through :func:`atomic_file` or :func:`atomic_dir`:
the content goes to a fresh temporary name beside the target (random, created exclusively, so a
pre-planted file or link is never followed and two writers never share one), and is renamed
onto the target only when complete. A failed or killed write leaves no target behind, and the
temporary name records its writer (``.<name>.<host>-<pid>.<random>.tmp``): what a killed process
left is reclaimed by the next build there (:func:`reclaim_orphans`).
Per-item paths inside an artifact (one file per image) go through :func:`inside`, which refuses
any that would leave the artifact's directory.

Directories a command writes into (its run directory, ``paths.cache_dir``) are used exactly as written:
:func:`check_dir_path` refuses ``$`` and a leading ``~`` (a logger would expand them and write
elsewhere), names the file system cannot hold, a file on the way and a folder that cannot be written,
before anything is written. Files that runs and other people write (a sweep's ``.hydra`` YAML, job JSON)
are read as plain data with limits (:func:`read_yaml`, :func:`read_json`): no YAML aliases, bounded
size and nesting, so a small hostile file cannot cost minutes or gigabytes.
"""

from __future__ import annotations

import csv
import errno
import fcntl
import io
import json
import os
import re
import shutil
import socket
import stat
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO, Any

from semvpr.core.errors import SemvprError

CONF_DIR = str(Path(__file__).resolve().parents[2] / "conf")
#: Largest YAML / JSON file a run directory may hand to the readers (a .hydra record is a few KiB).
MAX_RECORD_BYTES = 16 * 2**20
#: Deepest nesting a record may have (a config is a few levels deep).
MAX_RECORD_DEPTH = 64


@contextmanager
def atomic_file(final: Path) -> Iterator[IO[bytes]]:
    """A binary file object to write ``final``'s content to; renamed onto ``final`` on success."""
    final = Path(final)
    check_replaceable(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent)
    try:
        with suppress(OSError):  # a file system without modes (some network or FUSE mounts) keeps its own
            os.fchmod(fd, created_mode(directory=False))
        with os.fdopen(fd, "wb") as fh:
            yield fh
        os.replace(name, final)
    except BaseException as err:
        full = disk_full(final.parent, err, f"writing {final}")
        Path(name).unlink(missing_ok=True)
        if full is not None:
            raise full from None
        raise


@contextmanager
def atomic_dir(final: Path) -> Iterator[Path]:
    """A fresh empty directory to build ``final`` in; it replaces ``final`` on success."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_dir(final.parent, final.name)
    try:
        yield tmp
        if final.is_symlink() or final.is_file():
            final.unlink()
        elif final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
    except BaseException as err:
        full = disk_full(final.parent, err, f"writing {final}")
        shutil.rmtree(tmp, ignore_errors=True)
        if full is not None:
            raise full from None
        raise


#: Free space below which a failed write is blamed on a full disk.
FULL_DISK_BYTES = 2**20


def disk_full(folder: Path, err: BaseException, what: str) -> SemvprError | None:
    """One line for ``what`` failing as ``err`` because the disk of ``folder`` is full, else None (call it
    before the partial output is deleted). torch's and other C++ writers lose the system's "no space left"
    in their own error ("iostream error"), so the free space decides, not the error's kind."""
    if isinstance(err, SemvprError) or not isinstance(err, Exception):
        return None
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return None
    if free >= FULL_DISK_BYTES and not (isinstance(err, OSError) and err.errno == errno.ENOSPC):
        return None
    detail = str(err).splitlines()[0][:120] if str(err).strip() else ""
    return SemvprError(
        f"{what} failed with {free / 2**20:.1f} MiB left on the disk of {folder} ({type(err).__name__}"
        f"{': ' if detail else ''}{detail}): the disk is full; free space there or write elsewhere "
        "(paths.cache_dir, hydra.run.dir)"
    )


def created_mode(directory: bool) -> int:
    """The mode ``open`` or ``mkdir`` gives a new file or directory: what the umask leaves of 0o666 / 0o777.

    ``mkstemp`` and ``mkdtemp`` make theirs owner-only (0o600 / 0o700); a checkpoint, run folder or cache
    renamed from them would keep that, unreadable to the group that shares the cache or the results."""
    return (0o777 if directory else 0o666) & ~_umask()


def _umask() -> int:
    """This process's umask, read from /proc where Linux has it (setting it to read it races with threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def temp_dir(parent: Path, name: str) -> Path:
    """A fresh directory beside ``parent / name`` (exclusive, random name recording this process) with the
    mode ``mkdir`` would give it, to build ``name`` in and rename onto it."""
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(name), suffix=".tmp", dir=parent))
    with suppress(OSError):  # a file system without modes keeps its own
        os.chmod(tmp, created_mode(directory=True))
    return tmp


def open_lock(path: Path) -> int:
    """A descriptor to ``flock`` the lock file ``path`` through, created where absent (mode as the umask
    gives). A link there is refused; another user's lock file in a shared folder opens read-only (flock
    needs no write access to it; ``filelock``'s native lock does, which is why the cache keeps its own)."""
    try:
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
        except PermissionError:
            if not path.is_file():
                raise
            return os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as err:
        hint = "a link there is never followed: remove it" if err.errno == errno.ELOOP else "check the folder"
        raise SemvprError(f"lock file {path} cannot be opened ({err.strerror}); {hint}") from None


@contextmanager
def sole_writer(folder: Path, what: str) -> Iterator[None]:
    """Hold ``folder`` (an advisory lock on the directory itself, released with the process) while a job writes
    into it: a second live process given the same folder is one line, not two jobs overwriting each other's
    checkpoints and metrics. A file system without ``flock`` on directories goes unchecked."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SemvprError(
                f"another process is running a job in {folder}: two jobs in one directory overwrite each other's "
                f"files; give this one its own {what}, or wait for the other to end"
            ) from None
        except OSError:
            pass
        yield
    finally:
        os.close(fd)


def write_text(path: Path, text: str) -> None:
    """Write UTF-8 text atomically."""
    with atomic_file(path) as fh:
        fh.write(text.encode("utf-8"))


def write_csv(path: Path, fieldnames: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> None:
    """Write rows of named fields as CSV atomically (a header, ``\n`` line ends, a missing field empty)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(fieldnames), restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buf.getvalue())


def write_npy(path: Path, array: Any) -> None:
    """Write a NumPy array as ``.npy`` atomically (no pickled objects: ``allow_pickle=False``)."""
    import numpy as np

    with atomic_file(Path(path)) as handle:
        np.save(handle, np.asarray(array), allow_pickle=False)


def write_npz(path: Path, arrays: Mapping[str, Any]) -> None:
    """Write NumPy arrays of numbers, booleans or text as one uncompressed ``.npz`` atomically (no pickled objects)."""
    import numpy as np

    with atomic_file(Path(path)) as handle:
        np.savez(handle, **{name: np.asarray(a) for name, a in arrays.items()})


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


def check_replaceable(final: Path) -> None:
    """Refuse to write a file where a directory stands (a rename onto it would fail after the work)."""
    if final.is_dir() and not final.is_symlink():
        raise SemvprError(f"{final} is a directory, not a file; remove or rename it to write {final.name}")


def check_path_text(path: str | Path, what: str) -> None:
    """Refuse a path the file system cannot hold: a NUL byte, a name longer than 255 bytes, a path
    longer than 4,095 bytes."""
    text = str(path)
    if "\0" in text:
        raise SemvprError(f"{what}={text!r} holds a NUL byte; no file can be named that")
    if len(os.fsencode(text)) > 4095:
        raise SemvprError(f"{what}: the path is {len(os.fsencode(text))} bytes long; the limit is 4,095")
    long = next((part for part in Path(text).parts if len(os.fsencode(part)) > 255), None)
    if long is not None:
        raise SemvprError(
            f"{what}: the name {long[:40]}... is {len(os.fsencode(long))} bytes long; the limit is 255 per name"
        )


def existing_dir(path: str | Path, what: str, hint: str) -> Path:
    """``path`` (``~`` expanded) as a folder to read, or one line saying ``what`` it should be, why it is not
    (an empty name, none there, a file) and ``hint``: how to name the right one."""
    if not str(path):
        raise SemvprError(f"{what}: an empty name names no folder; {hint}")
    folder = Path(path).expanduser()
    if not folder.is_dir():
        raise SemvprError(f"{what} {folder} {'is a file' if folder.exists() else 'does not exist'}; {hint}")
    return folder


def check_dir_path(path: str | Path, what: str, *, writable: bool = True) -> None:
    """Refuse a directory to write into that would not be the one named or could not be written.

    The path is used as written: ``$`` and a leading ``~`` are refused (a logger would expand them and
    write elsewhere). Then: a name the file system cannot hold, a file on the way, or (``writable``) a
    deepest existing folder where no file can be created (read-only, immutable, another user's) is one
    line here, before anything is written. Nothing is created: the probe file is removed at once. A
    cache dir is checked without ``writable``: a complete cache may be read-only, and a build that
    must write there says so in one line (``core.cache.build_once``).
    """
    text = str(path)
    if "$" in text or text.startswith("~"):
        raise SemvprError(
            f"{what}={text!r}: '$' and a leading '~' are not expanded in directories semvpr writes into "
            f"(a logger would expand them and write elsewhere); write the path out"
        )
    check_path_text(text, what)
    path = Path(text)
    for folder in (path, *path.parents):
        try:
            exists = folder.exists()
        except OSError as err:
            raise SemvprError(f"{what}={text}: {folder} cannot be checked ({err.strerror})") from None
        if not exists:
            continue
        if not folder.is_dir():
            raise SemvprError(f"{what}={text}: {folder} is a file, not a directory")
        if not writable:
            return
        try:
            fd, probe = tempfile.mkstemp(prefix=".semvpr-write-check.", dir=folder)
        except OSError as err:
            reason = err.strerror or type(err).__name__
            if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
                reason = f"read-only or immutable: {reason}"
            raise SemvprError(f"{what}={text}: {folder} cannot be written ({reason})") from None
        os.close(fd)
        os.unlink(probe)
        return


def read_yaml(path: Path, what: str) -> Any:
    """A YAML file someone else wrote, as plain data: safe types only, no aliases (a 400-byte alias
    bomb expands to gigabytes), at most ``MAX_RECORD_BYTES`` and ``MAX_RECORD_DEPTH`` levels; nothing
    is resolved. A file that breaks a rule is one line naming it."""
    import yaml

    class _Loader(yaml.SafeLoader):
        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.AliasEvent):
                raise SemvprError(f"{what} {path} uses a YAML alias (*name); a run's record never does")
            self._depth = getattr(self, "_depth", 0) + 1
            try:
                if self._depth > MAX_RECORD_DEPTH:
                    raise SemvprError(f"{what} {path} is nested deeper than {MAX_RECORD_DEPTH} levels")
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

    text = _read_limited(path, what)
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except SemvprError:
        raise
    except Exception as err:  # noqa: BLE001 - every malformed file gets the same one line
        raise SemvprError(f"{what} {path} is not readable YAML ({type(err).__name__})") from None


def read_json(path: Path, what: str) -> Any:
    """A JSON file someone else wrote, at most ``MAX_RECORD_BYTES`` and ``MAX_RECORD_DEPTH`` levels deep;
    a file that breaks a rule (or is no JSON) is one line naming it."""
    text = _read_limited(path, what)
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as err:
        raise SemvprError(f"{what} {path} is not readable JSON ({type(err).__name__})") from None
    if _depth(data) > MAX_RECORD_DEPTH:
        raise SemvprError(f"{what} {path} is nested deeper than {MAX_RECORD_DEPTH} levels")
    return data


def read_list_text(path: Path, what: str) -> str:
    """A list file's text (one name per line): a regular file of at most ``MAX_RECORD_BYTES``, UTF-8; a
    file that breaks a rule is one line naming it, never taken as absent or read with replaced bytes."""
    data = _read_limited(path, what, decode=False)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        byte = data[err.start : err.start + 1].hex()
        raise SemvprError(f"{what} {path} is not UTF-8 text (a byte 0x{byte} at offset {err.start})") from None


def regular_file(path: Path, what: str) -> bool:
    """Whether the file a reader may use is at ``path``: False where nothing is there, True for a regular
    file (or a link to one). Anything else there (a FIFO, a device, a folder, a dangling or looping link)
    is one line naming it, the same for every reader: never taken as absent, never opened."""
    if not os.path.lexists(path):
        return False
    try:
        mode = os.stat(path).st_mode
    except OSError as err:
        raise SemvprError(f"{what} {path} cannot be read ({err.strerror or type(err).__name__})") from None
    if not stat.S_ISREG(mode):
        raise SemvprError(f"{what} {path} is not a regular file: {file_kind(mode)}")
    return True


def file_kind(mode: int) -> str:
    """What a file of ``mode`` (``os.stat``'s) is, in words: a FIFO, a character device, ..."""
    kinds = {stat.S_ISDIR: "a folder", stat.S_ISFIFO: "a FIFO (named pipe)", stat.S_ISCHR: "a character device"}
    kinds |= {stat.S_ISBLK: "a block device", stat.S_ISSOCK: "a socket", stat.S_ISREG: "a regular file"}
    return next((name for test, name in kinds.items() if test(mode)), "of an unknown kind")


def _read_limited(path: Path, what: str, decode: bool = True) -> Any:
    """The text (``decode=False``: the bytes) of a regular file of at most ``MAX_RECORD_BYTES`` (a FIFO or
    device is never opened)."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise SemvprError(f"{what} {path} is not a regular file: {file_kind(st.st_mode)}")
        if st.st_size > MAX_RECORD_BYTES:
            raise SemvprError(f"{what} {path} is {st.st_size} bytes; the limit is {MAX_RECORD_BYTES}")
        with open(path, "rb") as fh:
            data = fh.read(MAX_RECORD_BYTES + 1)
    except OSError as err:
        raise SemvprError(f"{what} {path} cannot be read ({err.strerror or type(err).__name__})") from None
    if len(data) > MAX_RECORD_BYTES:
        raise SemvprError(f"{what} {path} is over {MAX_RECORD_BYTES} bytes")
    return data.decode("utf-8", errors="replace") if decode else data


def _depth(node: Any) -> int:
    """Nesting depth of plain JSON data, without recursion."""
    deepest, stack = 0, [(node, 1)]
    while stack:
        item, level = stack.pop()
        deepest = max(deepest, level)
        if isinstance(item, dict):
            stack.extend((v, level + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, level + 1) for v in item)
    return deepest


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
            f"{what} needs {_bytes(nbytes)} in {folder}, but only {_bytes(free)} are free; free some space or "
            "point paths.cache_dir elsewhere"
        )


def _bytes(n: int) -> str:
    """A size in MiB below 1 GiB, else in GiB."""
    return f"{n / 2**20:.1f} MiB" if n < 2**30 else f"{n / 2**30:.2f} GiB"


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
                f"{what}: cannot reserve {_bytes(size)} in {Path(path).parent} "
                f"({err.strerror}); free some space or point paths.cache_dir elsewhere"
            ) from None
        finally:
            os.close(fd)
    return out
