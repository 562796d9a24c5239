"""Atomic writes: a reader never sees half a file, a planted temp name or link is never followed, and what is
written has the modes the umask gives (a cache or run folder shared with a group)."""

from __future__ import annotations

import gc
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from semvpr.core.cache import LOCK_DIR, artifact_dir, build_once
from semvpr.core.errors import SemvprError
from semvpr.core.io import atomic_dir, atomic_file, open_lock, write_json


def test_a_failed_write_leaves_neither_target_nor_temp(tmp_path: Path) -> None:
    target = tmp_path / "metrics.json"
    with pytest.raises(RuntimeError), atomic_file(target) as fh:
        fh.write(b"{half")
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_planted_links_at_old_fixed_temp_names_are_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("keep")
    run = tmp_path / "run"
    run.mkdir()
    for name in (".metrics.json.tmp", f".metrics.json.{os.getpid()}.tmp"):  # the names used before
        (run / name).symlink_to(victim)
    write_json(run / "metrics.json", {"status": "ok"})
    assert victim.read_text() == "keep"
    assert (run / "metrics.json").read_text().startswith("{")


def test_two_writers_never_share_a_temp_name(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    with atomic_file(target) as first, atomic_file(target) as second:
        assert first.name != second.name
        first.write(b"1")
        second.write(b"2")
    # Each writer's content arrives whole: the inner (second) block is renamed first, the outer last.
    assert target.read_bytes() == b"1"


def test_atomic_dir_replaces_the_target_only_when_complete(tmp_path: Path) -> None:
    out = tmp_path / "teacher"
    out.mkdir()
    (out / "old").write_text("old")
    with pytest.raises(ValueError), atomic_dir(out) as tmp:
        (tmp / "new").write_text("new")
        raise ValueError
    assert [p.name for p in tmp_path.iterdir()] == ["teacher"] and (out / "old").exists()
    with atomic_dir(out) as tmp:
        (tmp / "new").write_text("new")
    assert [p.name for p in out.iterdir()] == ["new"]


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_written_files_and_folders_get_the_modes_the_umask_gives(tmp_path: Path, umask: int) -> None:
    """A checkpoint, a job's JSON or a cache artifact is readable by whoever the umask lets read a file
    made with open() (a group sharing the cache), not only by its writer, as temp files are."""
    old = os.umask(umask)
    try:
        write_json(tmp_path / "metrics.json", {"status": "ok"})
        with atomic_dir(tmp_path / "teacher") as tmp:
            (tmp / "weights.pt").write_bytes(b"w")
        art = build_once(tmp_path / "cache", "labels", {"k": 1}, lambda tmp: (tmp / "a.png").write_bytes(b"p"))
        lock = open_lock(tmp_path / "x.lock")
        os.close(lock)
    finally:
        os.umask(old)
    files, folders = 0o666 & ~umask, 0o777 & ~umask
    for path, mode in (
        (tmp_path / "metrics.json", files),
        (tmp_path / "teacher", folders),
        (tmp_path / "teacher" / "weights.pt", files),
        (art, folders),
        (art / "a.png", files),
        (art / "key.json", files),
        (tmp_path / "x.lock", files),
    ):
        assert stat.S_IMODE(path.stat().st_mode) == mode, path


#: Run a command as user nobody.
_NOBODY = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]

_AS_ANOTHER_USER = """
import os, sys
from pathlib import Path
from semvpr.core.cache import build_once
from semvpr.core.errors import SemvprError
cache = Path(sys.argv[1])
assert build_once(cache, "labels", {"k": 1}, lambda tmp: 1 / 0).name.startswith("labels-")  # built: read only
try:
    build_once(cache, "labels", {"k": 2}, lambda tmp: None)
except SemvprError as err:
    print(err)
shared = Path(sys.argv[2])
build_once(shared, "labels", {"k": 3}, lambda tmp: (tmp / "a.png").write_bytes(b"p"))
print("built beside the other user's lock")
"""


def test_another_users_cache_is_read_where_built_and_refused_in_one_line_where_not() -> None:
    """A cache someone else built is read without writing to it; one that lacks an artifact says it
    cannot be written; in a folder both may write, the other user's lock file (not writable by us)
    still serialises the build."""
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to act as another user")
    if subprocess.run([*_NOBODY, sys.executable, "-c", "import semvpr"], capture_output=True).returncode != 0:
        pytest.skip("another user cannot read this checkout or its environment (a folder only its owner reads)")
    with tempfile.TemporaryDirectory() as scratch:  # pytest's own folders are the owner's only
        Path(scratch).chmod(0o755)
        _as_another_user(Path(scratch))


def _as_another_user(tmp_path: Path) -> None:
    cache, shared = tmp_path / "cache", tmp_path / "shared"
    old = os.umask(0o022)
    try:
        build_once(cache, "labels", {"k": 1}, lambda tmp: (tmp / "a.png").write_bytes(b"p"))
        shared.mkdir()
        shared.chmod(0o1777)
        (shared / LOCK_DIR).mkdir()
        (shared / LOCK_DIR).chmod(0o1777)
        owner_only_lock = artifact_dir(shared, "labels", {"k": 3})
        os.close(open_lock(shared / LOCK_DIR / f"{owner_only_lock.name}.lock"))  # 0o644, root's
    finally:
        os.umask(old)
    run = subprocess.run(
        [*_NOBODY, sys.executable, "-c", _AS_ANOTHER_USER, str(cache), str(shared)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "HOME": str(tmp_path)},
    )
    assert run.returncode == 0, run.stderr
    refused, built = run.stdout.splitlines()
    assert refused == (
        f"cache dir {cache} cannot be written (Permission denied) and holds no labels artifact for this run; "
        "point paths.cache_dir at a writable folder"
    )
    assert built == "built beside the other user's lock" and (owner_only_lock / "a.png").read_bytes() == b"p"


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 256 KiB file system (tmpfs), for writes that run out of room."""
    folder = tmp_path / "disk"
    folder.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a small file system")
    if subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)], capture_output=True
    ).returncode:
        pytest.skip("this machine does not let tests mount a tmpfs")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def test_a_full_disk_is_one_line_and_leaves_nothing(small_disk: Path) -> None:
    """torch's writer loses the system's 'no space left' in a RuntimeError of its own; the line says the
    disk is full, and neither the file nor the artifact nor a temporary is left."""
    weights = {"w": torch.ones(2**18)}  # 1 MiB
    with (
        pytest.raises(
            SemvprError, match=r"^writing .*best\.ckpt failed with 0\.0 MiB left on the disk of .*: the disk is full"
        ),
        atomic_file(small_disk / "best.ckpt") as fh,
    ):
        torch.save(weights, fh)
    with pytest.raises(SemvprError, match=r"^building the cache teacher-\w+ failed with .*: the disk is full"):
        build_once(small_disk, "teacher", {"k": 1}, lambda tmp: torch.save(weights, tmp / "model.pt"))
    assert sorted(p.name for p in small_disk.iterdir()) == [LOCK_DIR]
    gc.collect()  # torch's writer holds the deleted file open until it is collected
    assert shutil.disk_usage(small_disk).free > 2**17


def test_a_failed_write_with_room_on_the_disk_keeps_its_own_error(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="^iostream error$"), atomic_file(tmp_path / "a.ckpt") as fh:
        fh.write(b"half")
        raise RuntimeError("iostream error")
    with pytest.raises(RuntimeError, match="^iostream error$"):
        build_once(tmp_path, "teacher", {"k": 1}, lambda tmp: (_ for _ in ()).throw(RuntimeError("iostream error")))
    assert sorted(p.name for p in tmp_path.iterdir()) == [LOCK_DIR]
