"""Readers of the community's ground-truth formats: real Pitts30k-test lists and tiny fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from semvpr.core.errors import SemvprError
from semvpr.data.benchmarks import (
    load_npy,
    read_frames,
    read_msls_val_npy,
    read_npy_lists,
    read_patchnetvlad,
)
from tests.helpers import EVAL_SIZE, REALDATA, make_folder, object_array, same_images_as_lists, write_lists

# ../shared/realdata beside the checkout (or beside the folder of worktrees).
REAL = REALDATA
needs_real = pytest.mark.skipif(
    not (REAL / "pitts30k_test.npz").is_file() or not (REAL / "pitts30k_test_qImages.npy").is_file(),
    reason="real Pitts30k-test lists (../shared/realdata) not present",
)


def touch(root: Path, *names: str) -> None:
    for name in names:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(b"")


def brute_force_positives(db: np.ndarray, q: np.ndarray, radius: float) -> list[list[int]]:
    """Per query, the database indices within `radius` metres (squared distances, no tree)."""
    d2 = ((q[:, None, :] - db[None, :, :]) ** 2).sum(-1)
    return [sorted(np.flatnonzero(row <= radius * radius).tolist()) for row in d2]


def test_npy_lists_carry_the_shipped_positives(tmp_path: Path) -> None:
    db, q = ["ref/a.jpg", "ref/b.jpg", "ref/c.jpg"], ["qry/x.jpg", "qry/y.jpg"]
    write_lists(tmp_path / "gt", "tiny_test", db, q, object_array([[2, 0], []]))
    touch(tmp_path / "img", db[0], q[0])
    places = read_npy_lists(tmp_path / "gt", tmp_path / "img", "tiny_test")
    assert places.name == "tiny_test" and places.db_paths[1] == tmp_path / "img" / "ref" / "b.jpg"
    assert [p.tolist() for p in places.positives()] == [[2, 0], []]
    assert "database" in places.summary() and "nan" not in places.summary()


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing_gt", r"tiny_test_gt.npy not found"),
        ("short_gt", r"1 rows of positives .* for 2 queries"),
        ("float_gt", r"row 0 holds float64 values, expected database indices"),
        ("out_of_range", r"ground truth of query 1 holds \[3\], not database indices in \[0, 3\)"),
        ("names_2d", r"expected a non-empty 1-D array of image paths"),
        ("not_npy", r"not a readable .npy array"),
        (
            "code_in_pickle",
            r"not a readable .npy array .*posix.system is not part of a numpy array|nt.system is not part",
        ),
        ("no_image", r"first query image 'qry/x.jpg' not found"),
    ],
)
def test_npy_lists_bad_files_give_one_line(tmp_path: Path, case: str, match: str) -> None:
    db, q = ["ref/a.jpg", "ref/b.jpg", "ref/c.jpg"], ["qry/x.jpg", "qry/y.jpg"]
    gt_dir = tmp_path / "gt"
    write_lists(gt_dir, "tiny_test", db, q, object_array([[0], [1]]))
    touch(tmp_path / "img", db[0], q[0])
    if case == "missing_gt":
        (gt_dir / "tiny_test_gt.npy").unlink()
    elif case == "short_gt":
        np.save(gt_dir / "tiny_test_gt.npy", object_array([[0]]), allow_pickle=True)
    elif case == "float_gt":
        rows = np.empty(2, dtype=object)
        rows[0], rows[1] = np.array([0.5]), np.array([1.0])
        np.save(gt_dir / "tiny_test_gt.npy", rows, allow_pickle=True)
    elif case == "out_of_range":
        np.save(gt_dir / "tiny_test_gt.npy", object_array([[0], [3]]), allow_pickle=True)
    elif case == "names_2d":
        np.save(gt_dir / "tiny_test_dbImages.npy", np.array([db, db]))
    elif case == "not_npy":
        (gt_dir / "tiny_test_qImages.npy").write_text("qry/x.jpg\nqry/y.jpg\n")
    elif case == "code_in_pickle":
        np.save(gt_dir / "tiny_test_gt.npy", np.array([Exploit(), Exploit()], dtype=object), allow_pickle=True)
    elif case == "no_image":
        (tmp_path / "img" / q[0]).unlink()
    with pytest.raises(SemvprError, match=match) as err:
        read_npy_lists(gt_dir, tmp_path / "img", "tiny_test")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "pwned").exists()


class Exploit:
    """An object whose unpickling would run a shell command."""

    def __reduce__(self) -> tuple:
        return os.system, (f"touch {Path.cwd() / 'pwned'}",)


def test_load_npy_reads_plain_and_object_arrays(tmp_path: Path) -> None:
    np.save(tmp_path / "a.npy", np.arange(4))
    np.save(tmp_path / "b.npy", object_array([[1, 2], [], [7]]), allow_pickle=True)
    assert load_npy(tmp_path / "a.npy").tolist() == [0, 1, 2, 3]
    assert [r.tolist() for r in load_npy(tmp_path / "b.npy")] == [[1, 2], [], [7]]


def test_msls_val_queries_are_the_indexed_ones(tmp_path: Path) -> None:
    gt_dir, img = tmp_path / "gt", tmp_path / "msls"
    gt_dir.mkdir()
    db = [f"train_val/cph/database/images/d{i}.jpg" for i in range(3)]
    q = [f"train_val/cph/query/images/q{i}.jpg" for i in range(5)]
    np.save(gt_dir / "msls_val_dbImages.npy", np.array(db))
    np.save(gt_dir / "msls_val_qImages.npy", np.array(q))
    np.save(gt_dir / "msls_val_qIdx.npy", np.array([1, 3]))
    np.save(gt_dir / "msls_val_pIdx.npy", object_array([[0], [2, 1]]), allow_pickle=True)
    touch(img, db[0], q[1])
    # The real files hold 740 queries and 18,871 database images; a fixture of another size is refused.
    with pytest.raises(SemvprError, match=r"3 database / 2 query images, but msls_val has 18871 / 740"):
        read_msls_val_npy(gt_dir, img)
    from semvpr.data import published

    published.published.cache_clear()
    original = published.PUBLISHED
    try:
        fixture = tmp_path / "published.yaml"
        fixture.write_text("sets:\n  msls_val: {database: 3, queries: 2, source: fixture}\nresults: []\n")
        published.PUBLISHED = fixture
        places = read_msls_val_npy(gt_dir, img)
        np.save(gt_dir / "msls_val_qIdx.npy", np.array([1, 5]))
        with pytest.raises(SemvprError, match=r"msls_val_qIdx.npy: expected 1-D indices into the 5 query images"):
            read_msls_val_npy(gt_dir, img)
    finally:
        published.PUBLISHED = original
        published.published.cache_clear()
    assert [p.name for p in places.q_paths] == ["q1.jpg", "q3.jpg"] and places.name == "msls_val"
    assert [p.tolist() for p in places.positives()] == [[0], [2, 1]]


@needs_real
def test_real_pitts30k_lists_read_with_their_published_counts(tmp_path: Path) -> None:
    db = np.load(REAL / "pitts30k_test_dbImages.npy").tolist()
    q = np.load(REAL / "pitts30k_test_qImages.npy").tolist()
    with np.load(REAL / "pitts30k_test.npz") as npz:
        utm_db, utm_q = npz["utmDb"], npz["utmQ"]
    # gsv-cities' pitts30k_test_gt.npy: the database images within 25 m, in the lists' order.
    truth = brute_force_positives(utm_db, utm_q, 25.0)
    write_lists(tmp_path / "gt", "pitts30k_test", db, q, object_array(truth))
    touch(tmp_path / "Pittsburgh", db[0], q[0])  # placeholders: the reader looks at the first of each side
    places = read_npy_lists(tmp_path / "gt", tmp_path / "Pittsburgh", "pitts30k_test")
    assert (len(places.db_paths), len(places.q_paths)) == (10000, 6816)
    assert places.q_paths[0] == tmp_path / "Pittsburgh" / "queries_real/000/000546_pitch1_yaw1.jpg"
    assert [p.tolist() for p in places.positives()] == truth
    # One image short: not the published Pitts30k-test.
    write_lists(tmp_path / "gt", "pitts30k_test", db[:-1], q, object_array(truth))
    with pytest.raises(SemvprError, match=r"9999 database / 6816 query images, but pitts30k_test has 10000 / 6816"):
        read_npy_lists(tmp_path / "gt", tmp_path / "Pittsburgh", "pitts30k_test")


@needs_real
def test_real_patchnetvlad_npz_scores_within_its_radius(tmp_path: Path) -> None:
    db = np.load(REAL / "pitts30k_test_dbImages.npy").tolist()
    q = np.load(REAL / "pitts30k_test_qImages.npy").tolist()
    (tmp_path / "db.txt").write_text("\n".join(db) + "\n")
    (tmp_path / "q.txt").write_text("\n".join(q) + "\n")
    touch(tmp_path / "img", db[0], q[0])
    places = read_patchnetvlad(REAL / "pitts30k_test.npz", tmp_path / "db.txt", tmp_path / "q.txt", tmp_path / "img")
    assert places.name == "pitts30k_test" and places.eval_radius == 25.0
    assert (len(places.db_paths), len(places.q_paths)) == (10000, 6816)
    with np.load(REAL / "pitts30k_test.npz") as npz:
        expected = brute_force_positives(npz["utmDb"], npz["utmQ"], float(npz["posDistThr"]))
    assert [sorted(p.tolist()) for p in places.positives()] == expected
    assert sum(len(p) > 0 for p in expected) == 6816  # every Pitts30k-test query has a positive


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing_key", r"lacks \['posDistThr'\]"),
        ("short_list", r"utmQ is float64\[3, 2\], expected \(2, 2\) positions for the 2 images listed"),
        ("bad_radius", r"posDistThr is -5.0, expected one positive radius in metres"),
        ("empty_list", r"image list .*db.txt is empty"),
        ("not_npz", r"not a readable .npz"),
    ],
)
def test_patchnetvlad_bad_files_give_one_line(tmp_path: Path, case: str, match: str) -> None:
    fields = {
        "utmDb": np.array([[0.0, 0.0], [30.0, 0.0]]),
        "utmQ": np.array([[1.0, 0.0], [29.0, 0.0], [90.0, 0.0]]),
        "posDistThr": np.array(25.0),
    }
    (tmp_path / "db.txt").write_text("d0.jpg\nd1.jpg\n")
    (tmp_path / "q.txt").write_text("q0.jpg\nq1.jpg\nq2.jpg\n")
    touch(tmp_path, "d0.jpg", "q0.jpg")
    if case == "missing_key":
        fields.pop("posDistThr")
    elif case == "short_list":
        (tmp_path / "q.txt").write_text("q0.jpg\nq1.jpg\n")
    elif case == "bad_radius":
        fields["posDistThr"] = np.array(-5.0)
    elif case == "empty_list":
        (tmp_path / "db.txt").write_text("\n")
    np.savez(tmp_path / "tiny.npz", **fields)
    if case == "not_npz":
        (tmp_path / "tiny.npz").write_text("not a zip")
    if case in ("missing_key", "short_list", "bad_radius", "empty_list", "not_npz"):
        with pytest.raises(SemvprError, match=match) as err:
            read_patchnetvlad(tmp_path / "tiny.npz", tmp_path / "db.txt", tmp_path / "q.txt", tmp_path)
        assert "\n" not in str(err.value)


def test_patchnetvlad_fixture_positives(tmp_path: Path) -> None:
    np.savez(
        tmp_path / "tiny.npz",
        utmDb=np.array([[0.0, 0.0], [30.0, 0.0]]),
        utmQ=np.array([[1.0, 0.0], [29.0, 0.0], [90.0, 0.0]]),
        posDistThr=np.array(5),
    )
    (tmp_path / "db.txt").write_text("d0.jpg\nd1.jpg\n")
    (tmp_path / "q.txt").write_text("q0.jpg\nq1.jpg\nq2.jpg\n")
    touch(tmp_path, "d0.jpg", "q0.jpg")
    places = read_patchnetvlad(tmp_path / "tiny.npz", tmp_path / "db.txt", tmp_path / "q.txt", tmp_path)
    assert [p.tolist() for p in places.positives()] == [[0], [1], []]


def test_frame_aligned_positives_are_a_frame_window(tmp_path: Path) -> None:
    for i in range(10):
        touch(tmp_path, f"ref/{i:05d}.png")
    for i in (0, 5, 9):
        touch(tmp_path, f"query/{i:05d}.png")
    places = read_frames(tmp_path, "ref", "query", frame_window=1, name="nordland")
    assert places.name == "nordland ref→query ±1"
    # Positions are frames, not metres: the summary says so.
    assert places.summary().splitlines()[1:] == ["  database frames 0..9", "  queries frames 0..9"]
    assert [p.tolist() for p in places.positives()] == [[0, 1], [4, 5, 6], [8, 9]]
    assert [p.tolist() for p in read_frames(tmp_path, "ref", "query", 10).positives()] == [list(range(10))] * 3
    assert [p.tolist() for p in read_frames(tmp_path, "ref", "query", 0).positives()] == [[0], [5], [9]]
    assert read_frames(tmp_path, "ref", "query", 0).name == f"{tmp_path.name} ref→query ±0"
    with pytest.raises(SemvprError, match=r"data.frame_window=-1: expected a number of frames >= 0"):
        read_frames(tmp_path, "ref", "query", frame_window=-1)
    with pytest.raises(SemvprError, match=r"data.database and data.queries are both 'ref'"):
        read_frames(tmp_path, "ref", "ref", 1)
    with pytest.raises(SemvprError, match=r"data.queries='../x': expected the name of a traversal folder"):
        read_frames(tmp_path, "ref", "../x", 1)
    touch(tmp_path, "query/._00005.png")  # a copy from macOS: hidden, skipped (was 'both frame 5')
    assert [p.tolist() for p in read_frames(tmp_path, "ref", "query", 0).positives()] == [[0], [5], [9]]
    touch(tmp_path, "query/cover.png")
    with pytest.raises(SemvprError, match=r"cover.png: no frame number in the file name"):
        read_frames(tmp_path, "ref", "query", frame_window=1)
    with pytest.raises(SemvprError, match=r"traversal folder .*summer not found"):
        read_frames(tmp_path, "summer", "query", frame_window=1)
    touch(tmp_path, "query/frame_5.png")
    (tmp_path / "query" / "cover.png").unlink()
    with pytest.raises(SemvprError, match=r"00005.png and frame_5.png are both frame 5"):
        read_frames(tmp_path, "ref", "query", frame_window=1)


def test_a_frame_pattern_reads_the_frame_number_from_its_group(tmp_path: Path) -> None:
    """Gardens Point's naming (ImageNNN.jpg): the number in the pattern's group, whatever else the name holds."""
    for i in range(4):
        touch(tmp_path, f"day/Image{i:03d}.jpg", f"night/Image{i:03d}.jpg")
    places = read_frames(tmp_path, "day", "night", 1, name="gp", frame_pattern=r"Image(\d+)\.jpg")
    assert [p.name for p in places.q_paths] == [f"Image{i:03d}.jpg" for i in range(4)]
    assert [p.tolist() for p in places.positives()] == [[0, 1], [0, 1, 2], [1, 2, 3], [2, 3]]
    touch(tmp_path, "night/Image004_v2.jpg")
    with pytest.raises(SemvprError, match=r"Image004_v2.jpg: no frame number .*data.frame_pattern"):
        read_frames(tmp_path, "day", "night", 1, frame_pattern=r"Image(\d+)\.jpg")
    with pytest.raises(SemvprError, match=r"data.frame_pattern='Image\(' is not a regular expression"):
        read_frames(tmp_path, "day", "night", 1, frame_pattern="Image(")
    # A group that captures digits int() cannot read (a superscript is a digit to str.isdigit) is one line.
    (tmp_path / "night" / "Image004_v2.jpg").rename(tmp_path / "night" / "Image\u00b2.jpg")
    with pytest.raises(SemvprError, match="no frame number"):
        read_frames(tmp_path, "day", "night", 1, frame_pattern=r"Image(\S+)\.jpg")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tests.helpers import tiny_config, write_checkpoint

    tmp = tmp_path_factory.mktemp("ckpt")
    write_checkpoint(tiny_config(tmp, "filter=none"), tmp / "tested.ckpt")
    return tmp / "tested.ckpt"


def _gsv_npy(tmp: Path, root: Path) -> list[str]:
    db, q = same_images_as_lists(root)
    write_lists(tmp / "gt", "tiny_test", db, q, object_array([[i] for i in range(len(q))]))
    return ["data=gsv_npy", "data.set=tiny_test", f"data.gt_dir={tmp / 'gt'}"]


def _msls_val(tmp: Path, root: Path) -> list[str]:
    db, q = same_images_as_lists(root)
    (tmp / "gt").mkdir()
    np.save(tmp / "gt" / "msls_val_dbImages.npy", np.array(db))
    np.save(tmp / "gt" / "msls_val_qImages.npy", np.array(["unscored.jpg", *q]))  # qIdx skips the first
    np.save(tmp / "gt" / "msls_val_qIdx.npy", np.arange(1, len(q) + 1))
    np.save(tmp / "gt" / "msls_val_pIdx.npy", object_array([[i] for i in range(len(q))]), allow_pickle=True)
    return ["data=msls_val", f"data.gt_dir={tmp / 'gt'}"]


def _patchnetvlad(tmp: Path, root: Path) -> list[str]:
    from semvpr.data.places import parse_utm_name

    db, q = same_images_as_lists(root)
    (tmp / "db.txt").write_text("\n".join(db))
    (tmp / "q.txt").write_text("\n".join(q))
    utm = np.array([parse_utm_name(n) for n in db])
    np.savez(tmp / "tiny.npz", utmDb=utm, utmQ=utm, posDistThr=np.array(25))
    return [
        "data=patchnetvlad",
        f"data.npz={tmp / 'tiny.npz'}",
        f"data.db_list={tmp / 'db.txt'}",
        f"data.q_list={tmp / 'q.txt'}",
    ]


def _nordland(tmp: Path, root: Path) -> list[str]:
    db, q = same_images_as_lists(root)
    for i, (d, qq) in enumerate(zip(db, q)):
        for side, name in (("ref", d), ("query", qq)):
            (root / side).mkdir(exist_ok=True)
            (root / side / f"{i:05d}.jpg").write_bytes((root / name).read_bytes())
    return ["data=nordland", "data.frame_window=0"]


@pytest.mark.parametrize("make", [_gsv_npy, _msls_val, _patchnetvlad, _nordland], ids=lambda f: f.__name__[1:])
def test_each_benchmark_config_evaluates_a_checkpoint(
    checkpoint: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, make
) -> None:
    from semvpr.data import published
    from semvpr.eval import evaluate_checkpoint
    from tests.helpers import config

    root = make_folder(tmp_path / "city", n=4)
    overrides = make(tmp_path, root)
    fixture = tmp_path / "published.yaml"
    fixture.write_text("sets:\n  msls_val: {database: 4, queries: 4, source: fixture}\nresults: []\n")
    monkeypatch.setattr(published, "PUBLISHED", fixture)
    published.published.cache_clear()
    try:
        cfg = config(
            *overrides,
            f"data.root={root}",
            f"+ckpt={checkpoint}",
            f"paths.cache_dir={tmp_path / 'cache'}",
            *EVAL_SIZE,
            config_name="eval",
        )
        result = evaluate_checkpoint(cfg)
    finally:
        published.published.cache_clear()
    assert (result["database"], result["queries"]) == (4, 4)
    # Each query is its place's database image again: any model retrieves it first.
    assert result["test/R@1"] == 100.0 and result["queries_without_positives"] == 0
    assert (
        result["benchmark"]
        == {"gsv_npy": "tiny_test", "msls_val": "msls_val", "patchnetvlad": None, "nordland": "nordland±0"}[
            result["data"]
        ]
    )
    if result["data"] == "nordland":
        # The protocol id (published lookups) keeps its name; the set's name says the traversals.
        assert result["set"] == "nordland ref→query ±0"


needs_gardens = pytest.mark.skipif(
    not all((REAL / "gardens_point" / t).is_dir() for t in ("day_left", "day_right", "night_right")),
    reason="Gardens Point Walking (../shared/realdata/gardens_point) not present",
)


@needs_gardens
@pytest.mark.parametrize(("database", "queries"), [("day_left", "night_right"), ("day_left", "day_right")])
def test_real_gardens_point_reads_as_two_frame_aligned_traversals(database: str, queries: str) -> None:
    """The preset on the real folder: 200 frames a side, frame i's positives the frames i-2 .. i+2."""
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings
    from tests.helpers import config

    cfg = config(
        "data=gardens_point",
        f"data.root={REAL / 'gardens_point'}",
        f"data.database={database}",
        f"data.queries={queries}",
        "+ckpt=none",
        config_name="eval",
    )
    test = build_places(data_settings(cfg), ("test",))["test"]
    assert test.name == f"gardens_point {database}→{queries} ±2"
    assert (len(test.db_paths), len(test.q_paths)) == (200, 200)
    assert [p.name for p in test.q_paths[:2]] == ["Image000.jpg", "Image001.jpg"]
    positives = test.positives()
    assert [positives[i].tolist() for i in (0, 100, 199)] == [[0, 1, 2], list(range(98, 103)), [197, 198, 199]]
