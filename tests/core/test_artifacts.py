"""The artifact cache: built once, atomically, even by concurrent jobs."""

from __future__ import annotations

import fcntl
import multiprocessing as mp
import threading
import time
from pathlib import Path

import pytest

from semvpr.config.schema import typed
from semvpr.core.cache import LOCK_DIR, artifact_dir, build_once


def _slow_build(log: str, tmp: Path) -> None:
    with open(log, "a") as handle:
        handle.write("built\n")
    time.sleep(0.5)
    (tmp / "content.txt").write_text("done")


def _job(cache: str, log: str, out: mp.Queue[str]) -> None:
    out.put(str(build_once(cache, "thing", {"a": 1}, lambda tmp: _slow_build(log, tmp))))


def test_concurrent_jobs_build_an_artifact_once(tmp_path: Path) -> None:
    cache, log = tmp_path / "cache", tmp_path / "builds.log"
    ctx = mp.get_context("fork")
    out: mp.Queue[str] = ctx.Queue()
    jobs = [ctx.Process(target=_job, args=(str(cache), str(log), out)) for _ in range(3)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(timeout=30)
        assert job.exitcode == 0
    paths = {out.get(timeout=5) for _ in jobs}
    assert paths == {str(artifact_dir(cache, "thing", {"a": 1}))}
    assert log.read_text().count("built") == 1
    assert (Path(paths.pop()) / "content.txt").read_text() == "done"


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (Linux /proc), in seconds."""
    import os

    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads /proc")
def test_a_job_waiting_for_a_build_sleeps(tmp_path: Path) -> None:
    """A job that needs an artifact another job is building blocks on the lock in the kernel: it takes no CPU
    while it waits (a sweep's jobs side by side share the cores)."""
    cache, log = tmp_path / "cache", tmp_path / "builds.log"
    ctx = mp.get_context("fork")
    out: mp.Queue[str] = ctx.Queue()
    builder = ctx.Process(target=_job_slow, args=(str(cache), str(log), out, 3.0))
    builder.start()
    while not log.is_file():  # the builder holds the lock
        time.sleep(0.05)
    waiter = ctx.Process(target=_job, args=(str(cache), str(log), out))
    waiter.start()
    time.sleep(0.5)
    before = _cpu_seconds(waiter.pid)
    time.sleep(1.5)
    spent = _cpu_seconds(waiter.pid) - before
    state = next(
        line for line in Path(f"/proc/{waiter.pid}/status").read_text().splitlines() if line.startswith("State")
    )
    for job in (builder, waiter):
        job.join(timeout=30)
        assert job.exitcode == 0
    assert spent < 0.1, spent  # 1.5 s of waiting; a spinning wait would take ~1.5 s of CPU
    assert "S (sleeping)" in state
    assert log.read_text().count("built") == 1


def _job_slow(cache: str, log: str, out: mp.Queue[str], seconds: float) -> None:
    def build(tmp: Path) -> None:
        with open(log, "a") as handle:
            handle.write("built\n")
        time.sleep(seconds)

    out.put(str(build_once(cache, "thing", {"a": 1}, build)))


def test_a_job_waiting_for_a_build_says_so_once(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    cache = tmp_path / "cache"
    final = artifact_dir(cache, "thing", {"a": 1})
    lock = cache / LOCK_DIR / f"{final.name}.lock"
    lock.parent.mkdir(parents=True)
    with open(lock, "wb") as held:  # another job's build holds the lock
        fcntl.flock(held, fcntl.LOCK_EX)
        waiter = threading.Thread(target=build_once, args=(cache, "thing", {"a": 1}, lambda tmp: None))
        waiter.start()
        time.sleep(0.5)
        assert waiter.is_alive()
        final.mkdir()  # ... which ends
        fcntl.flock(held, fcntl.LOCK_UN)
    waiter.join(timeout=30)
    err = capfd.readouterr().err.splitlines()
    assert err == [f"semvpr: cache: waiting for another job building the thing artifact {final}", err[1]]
    assert err[1].startswith("semvpr: cache: waited ")
    # The lock free, nothing is said.
    build_once(cache, "other", {"a": 1}, lambda tmp: None)
    assert capfd.readouterr().err == ""


def test_failed_build_leaves_nothing_and_the_next_call_builds(tmp_path: Path) -> None:
    def failing(tmp: Path) -> None:
        (tmp / "half.txt").write_text("partial")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        build_once(tmp_path, "thing", {"a": 2}, failing)
    assert [p.name for p in tmp_path.iterdir() if p.name != LOCK_DIR] == []
    final = build_once(tmp_path, "thing", {"a": 2}, lambda tmp: (tmp / "ok.txt").write_text("ok"))
    assert (final / "ok.txt").read_text() == "ok" and (final / "key.json").is_file()


def test_a_files_key_follows_its_bytes_not_its_mtime(tmp_path: Path) -> None:
    import os
    import shutil

    from semvpr.core.cache import files_identity

    for size in (100, 12_288, 50_000):  # shorter than the three blocks, exactly them, and longer
        path = tmp_path / f"a{size}.jpg"
        path.write_bytes(bytes(size))
        before = files_identity(["a.jpg"], [path])
        st = path.stat()
        for offset in (0, size // 4, size // 2, size - 1):
            changed = bytearray(size)
            changed[offset] = 1
            path.write_bytes(bytes(changed))
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
            assert path.stat().st_size == st.st_size and path.stat().st_mtime_ns == st.st_mtime_ns
            moved = files_identity(["a.jpg"], [path])
            # Only a change between the blocks of a file longer than 12 KiB goes unseen (it would need forging).
            assert (moved != before) == (size <= 12_288 or offset != size // 4), (size, offset)
        path.write_bytes(bytes(size))
        assert files_identity(["a.jpg"], [path]) == before
        # The same bytes copied elsewhere, with another mtime, keep the key; another name does not.
        copy = tmp_path / "copied" / path.name
        copy.parent.mkdir(exist_ok=True)
        shutil.copyfile(path, copy)
        os.utime(copy, ns=(st.st_atime_ns + 10**12, st.st_mtime_ns + 10**12))
        assert files_identity(["a.jpg"], [copy]) == before
        assert files_identity(["b.jpg"], [copy]) != before


def test_files_that_are_not_regular_files_are_one_line(tmp_path: Path) -> None:
    import os

    from semvpr.core.cache import files_identity
    from semvpr.core.errors import SemvprError

    os.mkfifo(tmp_path / "fifo.jpg")  # opening it would block forever
    (tmp_path / "dangling.jpg").symlink_to(tmp_path / "nothing")
    (tmp_path / "a.jpg").symlink_to("b.jpg")
    (tmp_path / "b.jpg").symlink_to("a.jpg")
    for name, message in (
        ("fifo.jpg", "not a regular file"),
        ("dangling.jpg", "not found"),
        ("a.jpg", "Too many levels of symbolic links"),
        ("x\0.jpg", "cannot name a file"),
        ("folder", "not a regular file"),
    ):
        (tmp_path / "folder").mkdir(exist_ok=True)
        with pytest.raises(SemvprError, match=message) as err:
            files_identity([name], [f"{tmp_path}/{name}"])
        assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("group", "values", "line"),
    [
        # Taken before, and saved as a trained segmenter: no training at all, or the encoder trained uphill.
        ("teacher", {"epochs": 0}, r"^teacher\.train\.epochs=0 must be a whole number >= 1$"),
        ("teacher", {"backbone_lr_factor": -0.1}, r"^teacher\.train\.backbone_lr_factor=-0\.1 must be .* >= 0$"),
        ("teacher", {"warmup_steps": -1}, r"^teacher\.train\.warmup_steps=-1 must be a whole number >= 0$"),
        ("teacher", {"val_every": 0}, r"^teacher\.train\.val_every=0 must be a whole number >= 1 \(or null"),
        ("student", {"max_images": 0}, r"^student\.max_images=0 must be a whole number >= 1 \(or null: all\)$"),
        # torch's or the loader's traceback once the teacher had trained and labelled the set.
        ("teacher", {"batch_size": 0}, r"^teacher\.train\.batch_size=0 must be a whole number >= 1$"),
        ("teacher", {"lr": 0}, r"^teacher\.train\.lr=0 must be a finite number > 0$"),
        ("teacher", {"weight_decay": -1}, r"^teacher\.train\.weight_decay=-1 must be a finite number >= 0$"),
        ("teacher", {"num_workers": -1}, r"^teacher\.train\.num_workers=-1 must be a whole number >= 0$"),
        ("student", {"epochs": 0}, r"^student\.epochs=0 must be a whole number >= 1$"),
        ("student", {"batch_size": 0}, r"^student\.batch_size=0 must be a whole number >= 1$"),
        ("student", {"lr": -1}, r"^student\.lr=-1 must be a finite number > 0$"),
        ("student", {"weight_decay": -1e-4}, r"^student\.weight_decay=-0\.0001 must be a finite number >= 0$"),
        ("student", {"num_workers": -1}, r"^student\.num_workers=-1 must be a whole number >= 0$"),
    ],
)
def test_segmenter_counts_and_rates_out_of_range_are_one_line(group: str, values: dict, line: str) -> None:
    from semvpr.core.errors import SemvprError
    from semvpr.models.student import StudentSpec
    from semvpr.models.teacher import TeacherSpec

    with pytest.raises(SemvprError, match=line):
        if group == "teacher":
            typed(TeacherSpec, {"train": values}, "teacher")
        else:
            typed(StudentSpec, values, "student")


def test_segmenter_counts_and_rates_at_their_bounds_are_taken() -> None:
    from semvpr.models.student import StudentSpec
    from semvpr.models.teacher import TeacherSpec

    low = {"epochs": 1, "batch_size": 1, "weight_decay": 0, "num_workers": 0}
    teacher = typed(TeacherSpec, {"train": {**low, "lr": 1e-9, "warmup_steps": 0, "backbone_lr_factor": 0}}, "teacher")
    assert (teacher.train.epochs, teacher.train.backbone_lr_factor, teacher.train.val_every) == (1, 0, None)
    student = typed(StudentSpec, {**low, "lr": 1e-9, "max_images": 1}, "student")
    assert (student.epochs, student.max_images) == (1, 1)


def test_typed_settings_refuse_values_of_another_kind() -> None:
    """A config value of the wrong kind is one line naming it: a string where a switch is expected was
    truthy (``student.flip=maybe`` mirrored), a fraction where a count is expected reached range()."""
    from semvpr.core.errors import SemvprError
    from semvpr.models.student import StudentSpec
    from semvpr.models.teacher import TeacherSpec

    for node, message in (
        ({"flip": "maybe"}, "student.flip='maybe' must be true or false"),
        ({"epochs": 2.5}, "student.epochs=2.5 must be a whole number >= 1"),
        ({"epochs": True}, "student.epochs=True must be a whole number >= 1"),
        ({"max_images": "all"}, r"student.max_images='all' must be a whole number >= 1 \(or null: all\)"),
        ({"strides": [4, "8"]}, r"student.strides\[1\]='8' must be a whole number from 1 to 64"),
        ({"strides": []}, r"student.strides=\[\] must be a list of strides from 1 to 64"),
        ({"lr": "fast"}, "student.lr='fast' must be a finite number > 0"),
        ({"fooo": 1}, "student.fooo is not a setting of student"),
    ):
        with pytest.raises(SemvprError, match=message):
            typed(StudentSpec, node, "student")
    with pytest.raises(SemvprError, match="teacher.train.val_every='x' must be a whole number >= 1"):
        typed(TeacherSpec, {"train": {"val_every": "x"}}, "teacher")
    with pytest.raises(SemvprError, match=r"teacher.train.fooo is not a setting of teacher.train .*: epochs, "):
        typed(TeacherSpec, {"train": {"fooo": 1}}, "teacher")
    with pytest.raises(SemvprError, match=r"teacher.inference_size=7 must be \[H, W\]: two whole numbers, or null"):
        typed(TeacherSpec, {"inference_size": 7}, "teacher")
    # What fits is taken as given: ints for floats, null where allowed, lists for sequences.
    spec = typed(StudentSpec, {"flip": True, "lr": 1, "max_images": None, "strides": [8, 16]}, "student")
    assert spec.flip is True and spec.lr == 1 and spec.max_images is None and list(spec.strides) == [8, 16]
    assert typed(TeacherSpec, {"inference_size": None, "train": {"val_every": 3}}, "teacher").train.val_every == 3
