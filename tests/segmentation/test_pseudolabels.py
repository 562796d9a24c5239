"""Pseudo-label cache: one PNG per image, built once, resumable after an interruption."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.core.cache import artifact_dir
from semvpr.core.errors import SemvprError
from semvpr.data.images import Reading
from semvpr.segmentation.pseudolabels import label_path, pseudo_labels
from tests.helpers import LABEL_SIZE, REALDATA, CountingTeacher, labels_key, make_images

SIZE = LABEL_SIZE


def test_labels_every_image_once(tmp_path: Path) -> None:
    paths = make_images(tmp_path / "img")
    teacher = CountingTeacher()
    root = tmp_path / "img"
    out = pseudo_labels(teacher, paths, Reading(SIZE, 4, 0), tmp_path / "cache", root)
    assert teacher.seen == len(paths)
    assert sorted(p.name for p in out.glob("*.png")) == sorted(f"{p.name}.png" for p in paths)
    assert not list(out.glob(".*"))  # no temp files left behind
    first = np.asarray(Image.open(label_path(out, paths[4], root)))
    assert first.shape == SIZE and set(np.unique(first)) == {0, 13}
    assert (first[:, :10] == 13).all() and (first[:, 12:] == 0).all()  # 20 of 40 columns bright → 10 of 20

    again = CountingTeacher()
    assert pseudo_labels(again, paths, Reading(SIZE, 16, 0), tmp_path / "cache", root) == out
    assert again.seen == 0
    other = pseudo_labels(
        CountingTeacher(teacher_key="teacher-xyz"), paths, Reading(SIZE, 16, 0), tmp_path / "cache", root
    )
    assert other != out  # a different teacher gets its own labels


def test_labels_in_another_precision_are_cached_apart_and_a_batch_size_shares_them(tmp_path: Path) -> None:
    """The teacher's arithmetic moves its labels' bits: fp32 and bf16 labels are two entries (where the CPU runs
    bf16 natively; elsewhere bf16 runs fp32, the same labels); the batch size moves no bit, one entry."""
    from semvpr.core.precision import bf16_native, job_precision

    paths, root = make_images(tmp_path / "img"), tmp_path / "img"
    with job_precision("32-true", "cpu"):
        fp32 = pseudo_labels(CountingTeacher(), paths, Reading(SIZE, 4, 0), tmp_path / "cache", root)
        again = CountingTeacher()
        assert pseudo_labels(again, paths, Reading(SIZE, 16, 0), tmp_path / "cache", root) == fp32
        assert again.seen == 0
    with job_precision("bf16-mixed", "cpu"):
        bf16 = pseudo_labels(CountingTeacher(), paths, Reading(SIZE, 4, 0), tmp_path / "cache", root)
    assert (bf16 != fp32) == bf16_native("cpu")
    assert len(list((tmp_path / "cache").glob("labels-*"))) == (2 if bf16_native("cpu") else 1)


def test_interrupted_run_resumes_with_the_rest(tmp_path: Path) -> None:
    paths = make_images(tmp_path / "img")
    key_args = (paths, Reading(SIZE, 2, 0), tmp_path / "cache", tmp_path / "img")
    with pytest.raises(KeyboardInterrupt):
        pseudo_labels(CountingTeacher(fail_after=4), *key_args)
    final = artifact_dir(tmp_path / "cache", "labels", labels_key(paths, tmp_path / "img"))
    assert not final.exists()  # a partial run never counts as complete
    partial = [d for d in (tmp_path / "cache").iterdir() if d.name.endswith(".partial")]
    assert len(partial) == 1 and len(list(partial[0].glob("*.png"))) == 4

    resumed = CountingTeacher()
    out = pseudo_labels(resumed, *key_args)
    assert out == final and resumed.seen == len(paths) - 4
    assert len(list(out.glob("*.png"))) == len(paths)
    assert not partial[0].exists()


# Real Pitts30k-test names (pytorch-NetVlad layout): the same stem as a database and as a query
# image (288 stems do; ../shared/realdata/pitts30k_test_{db,q}Images.npy).
PITTS_PAIRS = [
    ("003/003504_pitch1_yaw1.jpg", "queries_real/003/003504_pitch1_yaw1.jpg"),
    ("003/003504_pitch1_yaw2.jpg", "queries_real/003/003504_pitch1_yaw2.jpg"),
]


def _write_named(root: Path, names: list[str]) -> list[Path]:
    """Images at the given relative paths, bright where the name is a query (so labels differ)."""
    paths = []
    for name in names:
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((32, 40, 3), 255 if name.startswith("queries") else 0, np.uint8)).save(path)
        paths.append(path)
    return paths


def test_same_stem_in_database_and_queries_gets_two_labels(tmp_path: Path) -> None:
    root = tmp_path / "pitts30k"
    paths = _write_named(root, [n for pair in PITTS_PAIRS for n in pair])
    assert len({p.stem for p in paths}) == len(paths) // 2  # the stems do collide
    teacher = CountingTeacher(teacher_key="t")
    out = pseudo_labels(teacher, paths, Reading(SIZE, 16, 0), tmp_path / "cache", root)
    assert teacher.seen == len(paths)
    for db, q in PITTS_PAIRS:
        db_label, q_label = label_path(out, root / db, root), label_path(out, root / q, root)
        assert db_label != q_label
        assert (np.asarray(Image.open(db_label)) == 0).all() and (np.asarray(Image.open(q_label)) == 13).all()
    with pytest.raises(SemvprError, match="not under the dataset root"):
        pseudo_labels(CountingTeacher(teacher_key="t"), paths, Reading(SIZE, 16, 0), tmp_path / "cache", root / "003")


@pytest.mark.skipif(not (REALDATA / "pitts30k_test_qImages.npy").is_file(), reason="../shared/realdata absent")
def test_label_paths_of_the_real_pitts30k_test_lists_are_unique() -> None:
    root = Path("/data/pitts30k")
    names = [*np.load(REALDATA / "pitts30k_test_dbImages.npy"), *np.load(REALDATA / "pitts30k_test_qImages.npy")]
    assert len({Path(n).stem for n in names}) == len(names) - 288
    assert len({label_path("labels", root / n, root) for n in names}) == len(names)


def test_a_corrupt_cached_label_is_one_line_naming_it(tmp_path: Path) -> None:
    from semvpr.segmentation.pseudolabels import read_label

    paths = make_images(tmp_path / "img", n=2)
    out = pseudo_labels(
        CountingTeacher(teacher_key="t"), paths, Reading(SIZE, 16, 0), tmp_path / "cache", tmp_path / "img"
    )
    assert read_label(out, paths[0], tmp_path / "img").shape == SIZE
    label_path(out, paths[0], tmp_path / "img").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SemvprError, match=r"pseudo-label .*@000@img@\.png\.png is unreadable.*delete"):
        read_label(out, paths[0], tmp_path / "img")


def test_a_planted_partial_directory_is_checked_before_its_labels_are_kept(tmp_path: Path) -> None:
    """Anyone may leave a `.labels-*.partial` in a cache: a kept label must be one this module writes."""
    paths = make_images(tmp_path / "img")
    root = tmp_path / "img"
    final = artifact_dir(tmp_path / "cache", "labels", labels_key(paths, root))
    partial = final.parent / f".{final.name}.partial"
    partial.mkdir(parents=True)
    for i, path in enumerate(paths):
        target = label_path(partial, path, root)
        if i == 0:
            (tmp_path / "victim.png").write_bytes(b"x")
            target.symlink_to(tmp_path / "victim.png")  # a link is never kept
        elif i == 1:
            Image.fromarray(np.zeros(SIZE, np.uint8)).save(target)  # a good label: kept
        elif i == 2:
            Image.fromarray(np.full(SIZE, 77, np.uint8)).save(target)  # not a trainId
        elif i == 3:
            Image.fromarray(np.zeros((*SIZE, 3), np.uint8)).save(target)  # RGB, not ids
        else:
            Image.fromarray(np.zeros((1, 1), np.uint8)).save(target)  # the wrong size
    (partial / "stray.txt").write_text("not a label")  # kept in the finished artifact, as if it were its own
    (partial / "folder").mkdir()
    teacher = CountingTeacher()
    out = pseudo_labels(teacher, paths, Reading(SIZE, 4, 0), tmp_path / "cache", root)
    assert out == final and teacher.seen == len(paths) - 1
    for path in paths:
        label = label_path(out, path, root)
        assert not label.is_symlink()
        with Image.open(label) as img:
            assert img.mode == "L" and img.size == SIZE[::-1]
    assert (tmp_path / "victim.png").read_bytes() == b"x"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [*(label_path(out, p, root).name for p in paths), "key.json"]
    )
