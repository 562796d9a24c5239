"""PlaceSet positives and the @UTM@ folder, dbStruct .mat and MSLS readers, incl. bad input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from semvpr.core.errors import SemvprError
from semvpr.data.places import PlaceSet, parse_utm_name, read_dbstruct_mat, read_msls, read_utm_folder
from tests.helpers import (
    REPO,
    write_dbstruct,
    write_image,
    write_jpg,
    write_msls_cities,
    write_msls_side,
    write_msls_test_ground_truth,
)


def utm_name(east: float, north: float) -> str:
    """A VPR-datasets-downloader file name at (east, north)."""
    return f"@{east:.2f}@{north:.2f}@17@T@40.44@-79.99@pano@@0@@@@201311@@.jpg"


def make_utm_folder(root: Path, split: str = "test") -> Path:
    """3 database images along a street, 2 queries: one near db 1, one far from everything."""
    for e, n in [(100.0, 0.0), (110.0, 0.0), (150.0, 0.0)]:
        write_jpg(root / "images" / split / "database" / utm_name(e, n))
    for e, n in [(112.0, 3.0), (900.0, 900.0)]:
        write_jpg(root / "images" / split / "queries" / utm_name(e, n))
    return root


def test_positives_hand_made_case() -> None:
    db = np.array([[0.0, 0.0], [10.0, 0.0], [30.0, 0.0], [0.0, 24.0]])
    q = np.array([[9.0, 0.0], [1000.0, 0.0], [0.0, 20.0]])
    places = PlaceSet("toy", tuple(f"d{i}" for i in range(4)), ("q0", "q1", "q2"), db, q)
    pos = places.positives(25.0)
    # q0→d3 is sqrt(81+576)=25.6 m: just outside.
    assert [p.tolist() for p in pos] == [[1, 0, 2], [], [3, 0, 1]]
    assert [p.tolist() for p in places.positives(10.0)] == [[1, 0], [], [3]]
    with pytest.raises(SemvprError, match="no evaluation ground truth: set data.eval_radius"):
        places.positives()
    assert [p.tolist() for p in places.with_eval_radius(10.0).positives()] == [[1, 0], [], [3]]
    assert places.with_eval_radius(None) is places
    assert places.db_utm.dtype == np.float64 and isinstance(places.db_paths[0], Path)


def test_placeset_rejects_mismatched_lengths() -> None:
    with pytest.raises(SemvprError, match="2 paths but 3 positions"):
        PlaceSet("bad", ("a", "b"), ("q",), np.zeros((3, 2)), np.zeros((1, 2)))


def test_parse_utm_name() -> None:
    assert parse_utm_name("/x/" + utm_name(584321.5, 4477654.25)) == (584321.5, 4477654.25)
    with pytest.raises(SemvprError, match="holiday.jpg"):
        parse_utm_name("/x/holiday.jpg")
    with pytest.raises(SemvprError, match="@abc@"):
        parse_utm_name("@abc@12@17@T@.jpg")


@pytest.mark.parametrize("use_images_dir", [False, True])
def test_read_utm_folder(tmp_path: Path, use_images_dir: bool) -> None:
    root = make_utm_folder(tmp_path / "city")
    places = read_utm_folder(root / "images" if use_images_dir else root, "test")
    assert places.name == "city/test"
    assert len(places.db_paths) == 3 and len(places.q_paths) == 2
    # Sorted file order: "@100" < "@110" < "@150" lexicographically too.
    np.testing.assert_allclose(places.db_utm, [[100, 0], [110, 0], [150, 0]])
    np.testing.assert_allclose(places.q_utm, [[112, 3], [900, 900]])
    assert [p.tolist() for p in places.positives(25.0)] == [[1, 0], []]
    assert all(p.is_file() for p in places.db_paths + places.q_paths)


def test_read_utm_folder_reads_subfolders_as_the_references_glob_and_skips_hidden_files(tmp_path: Path) -> None:
    """A split's images at any depth under database/ and queries/ (gmberton's readers: glob(folder/**/*.jpg));
    hidden names skipped as glob skips them: the ``._*.jpg`` a copy from macOS leaves beside each image, a
    ``.thumbnails/`` folder; a subfolder linked back to its parent is read once."""
    root = make_utm_folder(tmp_path / "city")
    database = root / "images" / "test" / "database"
    write_jpg(database / "2013" / "06" / utm_name(130.0, 0.0))  # was left out of the set
    (database / ("._" + utm_name(100.0, 0.0))).write_bytes(b"\x00\x05\x16\x07")  # was 'not an @UTM@ image name'
    write_jpg(database / ".thumbnails" / utm_name(999.0, 999.0))
    (database / "2013" / "loop").symlink_to(database, target_is_directory=True)
    places = read_utm_folder(root, "test")
    # Sorted by path, as glob's list is sorted: '2013/...' before '@...'.
    np.testing.assert_allclose(places.db_utm, [[130, 0], [100, 0], [110, 0], [150, 0]])
    assert places.db_paths[0] == database / "2013" / "06" / utm_name(130.0, 0.0)
    assert len(places.q_paths) == 2


def test_read_utm_folder_bad_inputs(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"nowhere.*data\.root="):
        read_utm_folder(tmp_path / "nowhere", "test")
    root = make_utm_folder(tmp_path / "city")
    with pytest.raises(SemvprError, match=r"images/val.*splits there: \['test'\]"):
        read_utm_folder(root, "val")
    write_jpg(root / "images" / "test" / "queries" / "IMG_0001.jpg")
    with pytest.raises(SemvprError, match="IMG_0001.jpg"):
        read_utm_folder(root, "test")
    (root / "images" / "train" / "database").mkdir(parents=True)
    write_jpg(root / "images" / "train" / "queries" / utm_name(1, 2))
    with pytest.raises(SemvprError, match=r"train/database: no database images"):
        read_utm_folder(root, "train")


def test_read_dbstruct_mat(tmp_path: Path) -> None:
    root = tmp_path / "pitts"
    db_names = ["000/000000_pitch1_yaw1.jpg", "000/000001_pitch1_yaw2.jpg", "001/001000_pitch2_yaw1.jpg"]
    q_names = ["000/000002_pitch1_yaw1.jpg", "000/000003_pitch1_yaw1.jpg"]
    for n in db_names:
        write_jpg(root / n)
    for n in q_names:  # pytorch-NetVlad layout: query names relative to queries_real/
        write_jpg(root / "queries_real" / n)
    db_utm = np.array([[585000.0, 4477000.0], [585020.0, 4477000.0], [586000.0, 4478000.0]])
    q_utm = np.array([[585010.0, 4477001.0], [590000.0, 4470000.0]])
    mat = tmp_path / "pitts30k_test.mat"
    write_dbstruct(mat, db_names, db_utm, q_names, q_utm)
    places = read_dbstruct_mat(mat, root)
    assert places.name == "pitts30k_test/test"
    assert places.db_paths[2] == root / db_names[2]
    assert places.q_paths[0] == root / "queries_real" / q_names[0]
    np.testing.assert_allclose(places.db_utm, db_utm)
    np.testing.assert_allclose(places.q_utm, q_utm)
    assert [p.tolist() for p in places.positives(25.0)] == [[0, 1], []]
    assert read_dbstruct_mat(mat, root, name="p30k").name == "p30k"


def test_dbstruct_query_with_a_database_stem_resolves_to_the_query(tmp_path: Path) -> None:
    # Real Pitts30k-test names: 003/003504_pitch1_yaw1.jpg is a database image and, under
    # queries_real/, a query image; the .mat lists both names without the prefix.
    root = tmp_path / "pitts"
    name = "003/003504_pitch1_yaw1.jpg"
    write_jpg(root / name)
    write_jpg(root / "queries_real" / name)
    utm = np.array([[585000.0, 4477000.0]])
    write_dbstruct(tmp_path / "pitts30k_test.mat", [name], utm, [name], utm)
    places = read_dbstruct_mat(tmp_path / "pitts30k_test.mat", root)
    assert places.db_paths == (root / name,) and places.q_paths == (root / "queries_real" / name,)
    assert places.relative(places.db_paths[0]) != places.relative(places.q_paths[0])
    # Lists that carry the prefix (gsv-cities, some re-exports) resolve under the root as they are.
    write_dbstruct(tmp_path / "prefixed.mat", [name], utm, [f"queries_real/{name}"], utm)
    assert read_dbstruct_mat(tmp_path / "prefixed.mat", root).q_paths == (root / "queries_real" / name,)


def test_read_dbstruct_mat_bad_inputs(tmp_path: Path) -> None:
    names, utm = ["a.jpg"], np.zeros((1, 2))
    mat = tmp_path / "broken.mat"
    write_dbstruct(mat, names, utm, names, utm, drop="utmQ")
    with pytest.raises(SemvprError, match=r"broken\.mat.*lacks field 'utmQ'"):
        read_dbstruct_mat(mat, tmp_path)
    with pytest.raises(SemvprError, match=r"missing\.mat not found"):
        read_dbstruct_mat(tmp_path / "missing.mat", tmp_path)
    mat = tmp_path / "ok.mat"
    write_dbstruct(mat, names, utm, names, utm)
    with pytest.raises(SemvprError, match=r"ok\.mat.*'a\.jpg' not found"):
        read_dbstruct_mat(mat, tmp_path)
    (tmp_path / "junk.mat").write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(SemvprError, match=r"junk\.mat"):
        read_dbstruct_mat(tmp_path / "junk.mat", tmp_path)


def test_read_msls_follows_the_official_splits(tmp_path: Path) -> None:
    root = write_msls_cities(tmp_path / "msls")
    val = read_msls(root, "val")
    # Official val cities, panoramas excluded, query frames outside the subtask dropped.
    assert [p.name for p in val.db_paths] == ["c_db0.jpg", "c_db1.jpg", "s_db0.jpg"]
    assert [p.name for p in val.q_paths] == ["c_q0.jpg", "s_q0.jpg"]
    assert val.db_paths[0] == root / "train_val" / "cph" / "database" / "images" / "c_db0.jpg"
    assert [p.tolist() for p in val.positives(25.0)] == [[0], [2]]
    with pytest.raises(SemvprError, match="empty MSLS split 'val'"):
        read_msls(root, "val", subtask="s2w")  # no frame of the fixture is in the summer-to-winter subtask
    # Train: the official train cities only (london here), never the val ones; no subtask filter.
    train = read_msls(root, "train")
    assert [p.name for p in train.db_paths] == ["l_db0.jpg"] and [p.name for p in train.q_paths] == ["l_q0.jpg"]
    everything = read_msls(root, "train", cities=["cph", "london"])
    assert [p.name for p in everything.q_paths] == ["c_q0.jpg", "c_q_other.jpg", "l_q0.jpg"]
    # Same (east, north) in two cities must not make them positives of each other.
    assert [p.tolist() for p in everything.positives(25.0)] == [[0], [1], [2]]
    with_panos = read_msls(root, "train", exclude_panos=False)
    assert [p.name for p in with_panos.db_paths] == ["l_db0.jpg", "l_pano.jpg"]
    # Selection: the held-out training city (zurich), read as training cities are (no subtask filter).
    selection = read_msls(root, "selection")
    assert [p.name for p in selection.db_paths] == ["z_db0.jpg"] and [p.name for p in selection.q_paths] == ["z_q0.jpg"]


def test_msls_config_selects_on_held_out_train_cities_and_tests_on_val_cities(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    root = write_msls_cities(tmp_path / "msls")
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["data=msls", f"data.root={root}"])
    train, val, test = (instantiate(cfg.data[s]) for s in ("train", "val", "test"))
    city = {
        name: {p.parts[-4] for p in s.db_paths + s.q_paths}
        for name, s in (("train", train), ("val", val), ("test", test))
    }
    # Epoch selection never sees the reported cities, and neither does training.
    assert city == {"train": {"london"}, "val": {"zurich"}, "test": {"cph", "sf"}}


def test_msls_test_cities_are_scored_where_their_ground_truth_lies_beside_their_images(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    root = write_msls_test_ground_truth(write_msls_cities(tmp_path / "msls"))
    test = read_msls(root, "test")
    # The subtask filters the test frames as it does val's; with no raw.csv, the panorama m_db0 stays in.
    assert [p.name for p in test.db_paths] == ["m_db0.jpg"] and [p.name for p in test.q_paths] == ["m_q0.jpg"]
    assert test.name == "msls/test" and [p.tolist() for p in test.positives(25.0)] == [[0]]
    # Where a test city's ground truth comes with raw.csv, its panoramas are excluded as everywhere else.
    write_msls_side(
        root / "test" / "miami" / "database", [("m_db0", 10.0, 0.0, True, True), ("m_db2", 11.0, 0.0, False, True)]
    )
    assert [p.name for p in read_msls(root, "test").db_paths] == ["m_db2.jpg"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["data=msls", f"data.root={root}", "data.test.split=test"])
    assert {p.parts[-4] for p in instantiate(cfg.data.test).q_paths} == {"miami"}


def test_read_msls_bad_inputs(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"train_val.*not found.*data\.root="):
        read_msls(tmp_path / "none", "train")
    root = write_msls_cities(tmp_path / "msls")
    with pytest.raises(SemvprError, match=r"'miami' has no ground truth.*val cities"):
        read_msls(root, "test")
    with pytest.raises(SemvprError, match="city folder 'nowhere' not found"):
        read_msls(root, "val", cities=["nowhere"])
    write_msls_side(root / "train_val" / "sf" / "query", [("s_q0", 5.0, 6.0, False, True)], columns="utm_x,utm_y")
    with pytest.raises(SemvprError, match=r"sf/query/postprocessed\.csv: missing column.*easting"):
        read_msls(root, "val")
    with pytest.raises(SemvprError, match="split 'dev' unknown"):
        read_msls(root, "dev")


def test_ground_truth_shipped_with_a_set_is_its_positives() -> None:
    db, q = np.zeros((3, 2)), np.zeros((2, 2))  # every UTM equal: a radius would make all positive
    places = PlaceSet("gt", ("d0", "d1", "d2"), ("q0", "q1"), db, q, ground_truth=(np.array([2]), np.array([], int)))
    assert [p.tolist() for p in places.positives()] == [[2], []]
    assert [p.tolist() for p in places.positives(25.0)] == [[0, 1, 2], [0, 1, 2]]
    with pytest.raises(SemvprError, match="scored by the ground truth shipped with it"):
        places.with_eval_radius(25.0)
    with pytest.raises(SemvprError, match="ground truth for 1 queries, but 2 queries"):
        PlaceSet("gt", ("d0",), ("q0", "q1"), np.zeros((1, 2)), q, ground_truth=(np.array([0]),))
    with pytest.raises(SemvprError, match=r"ground truth of query 1 holds \[3\], not database indices in \[0, 3\)"):
        PlaceSet("gt", ("d0", "d1", "d2"), ("q0", "q1"), db, q, ground_truth=(np.array([0]), np.array([3])))


@pytest.mark.parametrize("radius", [-25.0, 0.0, float("nan"), float("inf")])
def test_impossible_radii_are_refused(radius: float) -> None:
    # scipy squares the radius: -25 found the same positives as 25.
    places = PlaceSet("toy", ("d0",), ("q0",), np.zeros((1, 2)), np.zeros((1, 2)))
    with pytest.raises(SemvprError, match="finite distance > 0"):
        places.positives(radius)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_utms_are_refused_where_they_are_read(tmp_path: Path, bad: float) -> None:
    with pytest.raises(SemvprError, match=r"q_utm has 1 non-finite position\(s\), the first at row 1"):
        PlaceSet("toy", ("d0",), ("q0", "q1"), np.zeros((1, 2)), np.array([[0.0, 0.0], [bad, 5.0]]))
    root = tmp_path / "pitts"
    write_jpg(root / "a.jpg")
    write_jpg(root / "queries_real" / "q.jpg")
    write_dbstruct(tmp_path / "p.mat", ["a.jpg"], np.array([[bad, 1.0]]), ["q.jpg"], np.zeros((1, 2)))
    with pytest.raises(SemvprError, match="db_utm has 1 non-finite"):
        read_dbstruct_mat(tmp_path / "p.mat", root)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (
            lambda p: p.write_bytes(p.read_bytes() + b"9,caf\xe9,1,2\n"),
            r"postprocessed\.csv: not UTF-8 text \(a byte 0xe9\)",
        ),
        (lambda p: p.write_text(p.read_text() + '9,"' + "x" * 140_000 + '",1,2\n'), r"not a readable csv row"),
        (lambda p: (p.unlink(), os.mkfifo(p)), r"MSLS csv .*postprocessed\.csv is not a regular file"),
    ],
    ids=["not UTF-8", "a field over csv's limit", "a FIFO"],
)
def test_a_damaged_msls_csv_is_one_line_naming_it(tmp_path: Path, damage, message: str) -> None:
    root = write_msls_cities(tmp_path / "msls")
    damage(root / "train_val" / "cph" / "database" / "postprocessed.csv")
    with pytest.raises(SemvprError, match=message) as err:
        read_msls(root, "val")
    assert "\n" not in str(err.value)


def test_a_record_names_a_position_as_the_set_has_it() -> None:
    """UTM metres, a frame of a frame-aligned set, or nothing for a set without positions (it wrote a bare NaN,
    which is not JSON)."""
    utm = np.array([[585000.5, 4477000.25]])
    assert PlaceSet("u", ("d",), ("q",), utm, utm).position("db", 0) == {"utm": [585000.5, 4477000.25]}
    frames = PlaceSet("f", ("d",), ("q",), [[12, 0]], [[7, 0]], ground_truth=(np.array([0]),), positions="frame")
    assert frames.position("db", 0) == {"frame": 12} and frames.position("q", 0) == {"frame": 7}
    nan = np.full((1, 2), np.nan)
    assert PlaceSet("n", ("d",), ("q",), nan, nan, ground_truth=(np.array([0]),)).position("q", 0) == {}


def test_any_two_folders_are_a_place_set_named_below_their_common_parent(tmp_path: Path) -> None:
    """data=folders: VPR-methods-evaluation's --database_folder / --queries_folder, any two folders of @UTM@
    images (nested at any depth), not the images/<split>/{database,queries} layout."""
    from semvpr.data.places import read_utm_folders

    db_dir, q_dir = tmp_path / "maps" / "2019" / "db", tmp_path / "phone" / "q"
    for i, folder in enumerate((db_dir, db_dir / "more", q_dir)):
        write_image(folder / f"@{585000 + 10 * i:.2f}@4477000.00@17@T@@@@@@@@@@@.jpg", i)
    places = read_utm_folders(db_dir, q_dir)
    assert places.root == tmp_path and places.name == "db→q"
    assert [places.relative(p) for p in places.db_paths] == [
        "maps/2019/db/@585000.00@4477000.00@17@T@@@@@@@@@@@.jpg",
        "maps/2019/db/more/@585010.00@4477000.00@17@T@@@@@@@@@@@.jpg",
    ]
    assert places.q_utm.tolist() == [[585020.0, 4477000.0]]
    assert [list(p) for p in places.positives(25.0)] == [[1, 0]]  # within 25 m, nearest first
    with pytest.raises(SemvprError, match=r"^queries folder .*nowhere is not a directory; set data.queries=DIR"):
        read_utm_folders(db_dir, tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SemvprError, match=r"^database folder .*empty: no images \(.jpg/.jpeg/.png\) found below it$"):
        read_utm_folders(tmp_path / "empty", q_dir)
