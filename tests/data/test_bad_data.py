"""Bad datasets through the real CLIs (SynthCity's generator, GSV-Cities, CamVid, list files, images, positions):
exit 2 and one line, nothing written outside the run and cache (tests/bad_input.py runs each row)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.data.places import folder_images
from tests.bad_input import EVAL, LOCALIZE, TRAIN, Case, a_file, dangling, folder, nordland, rows, run_case
from tests.camvid_fixture import write_camvid
from tests.helpers import make_folder, object_array, write_gsv_cities, write_image, write_lists, write_pitts_mat


def _nan_folder(tmp: Path) -> str:
    root = make_folder(tmp / "folder", n=2)
    write_image(root / "images" / "test" / "queries" / "@nan@4477000.00@17@T@@@@@@@@@@@.jpg", 9)
    return str(root)


def _string_utm_pitts(tmp: Path) -> str:
    names = ["000/000000_pitch1_yaw1.jpg"]
    for name in names:
        write_image(tmp / "pitts" / name, 0)
        write_image(tmp / "pitts" / "queries_real" / name, 0)
    write_pitts_mat(tmp / "pitts" / "datasets" / "pitts30k_test.mat", "test", names, names)
    from scipy.io import loadmat, savemat

    mat = loadmat(tmp / "pitts" / "datasets" / "pitts30k_test.mat")
    mat["dbStruct"][0, 0]["utmQ"] = np.array(["585000 4477000"])
    savemat(tmp / "pitts" / "datasets" / "pitts30k_test.mat", {"dbStruct": mat["dbStruct"]})
    return str(tmp / "pitts")


def _list_dataset(t: Path, db: list[str], q: list[str]) -> Path:
    """Images db0..2 / q0..2 under t/img, the gsv-cities lists ``x_*.npy`` of ``db`` / ``q`` in t/gt."""
    for i in range(3):
        write_image(t / "img" / f"db{i}.jpg", i)
        write_image(t / "img" / f"q{i}.jpg", i)
    write_lists(t / "gt", "x", db, q, object_array([[0], [1], [2]]))
    return t


def _gsv(t: Path) -> list[str]:
    return ["data=gsv_npy", "data.set=x", f"data.gt_dir={t / 'gt'}", f"data.root={t / 'img'}"]


def _absolute_in_npy(t: Path, c: Path) -> list[str]:
    write_image(t / "secret" / "outside.jpg", 7)
    _list_dataset(t, ["db0.jpg", "db1.jpg", str(t / "secret" / "outside.jpg")], ["q0.jpg", "q1.jpg", "q2.jpg"])
    return [f"ckpt={c}", *_gsv(t)]


def _fifo_npy_list(t: Path, c: Path) -> list[str]:
    _list_dataset(t, ["db0.jpg", "db1.jpg", "db2.jpg"], ["q0.jpg", "q1.jpg", "q2.jpg"])
    (t / "gt" / "x_qImages.npy").unlink()
    os.mkfifo(t / "gt" / "x_qImages.npy")
    return [f"ckpt={c}", *_gsv(t)]


def _fifo_patchnetvlad_list(t: Path, c: Path) -> list[str]:
    args = _absolute_in_patchnetvlad(t, c)
    (t / "db.txt").unlink()
    os.mkfifo(t / "db.txt")
    return args


def _absolute_in_patchnetvlad(t: Path, c: Path) -> list[str]:
    write_image(t / "secret" / "outside.jpg", 7)
    _list_dataset(t, ["db0.jpg"], ["q0.jpg"])
    utm = np.array([[0.0, 0], [100, 0], [200, 0]])
    np.savez(t / "x.npz", utmDb=utm, utmQ=utm, posDistThr=np.array(25.0))
    (t / "db.txt").write_text(f"db0.jpg\ndb1.jpg\n{t / 'secret' / 'outside.jpg'}\n")
    (t / "q.txt").write_text("q0.jpg\nq1.jpg\nq2.jpg\n")
    return [
        f"ckpt={c}",
        "data=patchnetvlad",
        f"data.npz={t / 'x.npz'}",
        f"data.db_list={t / 'db.txt'}",
        f"data.q_list={t / 'q.txt'}",
        f"data.root={t / 'img'}",
    ]


def _nul_in_npy(t: Path, c: Path) -> list[str]:
    _list_dataset(t, ["db0.jpg", "db1\x00.jpg", "db2.jpg"], ["q0.jpg", "q1.jpg", "q2.jpg"])
    return [f"ckpt={c}", *_gsv(t)]


def _object_npy(t: Path, c: Path) -> list[str]:
    """A ground-truth .npy whose pickle calls numpy.dtype (an allowed class) with a bad argument."""
    _list_dataset(t, ["db0.jpg", "db1.jpg", "db2.jpg"], ["q0.jpg", "q1.jpg", "q2.jpg"])
    with open(t / "gt" / "x_gt.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "|O", "fortran_order": False, "shape": (3,)})
        fh.write(b"cnumpy\ndtype\n(Vzzz\ntR.")
    return [f"ckpt={c}", *_gsv(t)]


def _first(side: Path) -> Path:
    return sorted(side.iterdir())[0]


def _sixteen_bit_png(test: Path) -> None:
    q = _first(test / "queries")
    pixels = np.random.default_rng(0).integers(0, 65535, (48, 64)).astype(np.uint16)
    Image.fromarray(pixels).save(q.with_suffix(".png"))
    q.unlink()


def _float_tiff_as_jpg(test: Path) -> None:
    pixels = np.random.default_rng(1).random((48, 64)).astype(np.float32)
    Image.fromarray(pixels, mode="F").save(_first(test / "queries"), format="TIFF")


def _fifo(test: Path) -> None:
    q = _first(test / "queries")
    q.unlink()
    os.mkfifo(q)


def _looping(test: Path) -> None:
    a, b = (test / "database" / f"@58{n}00.00@4477000.00@17@T@@@@@@@@@@@.jpg" for n in (59, 60))
    a.symlink_to(b.name)
    b.symlink_to(a.name)


def _utm_1e308(test: Path) -> None:
    write_image(test / "queries" / "@1e308@4477000.00@17@T@@@@@@@@@@@.jpg", 9)


def _complex_utm_pitts(t: Path, c: Path) -> list[str]:
    from scipy.io import loadmat, savemat

    names = [f"000/00000{i}_pitch1_yaw1.jpg" for i in range(3)]
    for i, name in enumerate(names):
        write_image(t / "pitts" / name, i)
        write_image(t / "pitts" / "queries_real" / name, i)
    mat_path = t / "pitts" / "datasets" / "pitts30k_test.mat"
    write_pitts_mat(mat_path, "test", names, names)
    mat = loadmat(mat_path)
    mat["dbStruct"][0, 0]["utmQ"] = mat["dbStruct"][0, 0]["utmQ"].astype(complex) + 5e5j
    savemat(mat_path, {"dbStruct": mat["dbStruct"]})
    return [f"ckpt={c}", "data=pitts30k", f"data.root={t / 'pitts'}"]


def _pitts_missing_second(t: Path, c: Path) -> list[str]:
    names = [f"000/00000{i}_pitch1_yaw1.jpg" for i in range(3)]
    for i, name in enumerate(names):
        write_image(t / "pitts" / name, i)
        write_image(t / "pitts" / "queries_real" / name, i)
    write_pitts_mat(t / "pitts" / "datasets" / "pitts30k_test.mat", "test", names, names)
    (t / "pitts" / names[1]).unlink()
    return [f"ckpt={c}", "data=pitts30k", f"data.root={t / 'pitts'}"]


def _bad_year_gsv(tmp: Path) -> str:
    root = write_gsv_cities(tmp / "gsv")
    csv = root / "Dataframes" / "London.csv"
    csv.write_text(csv.read_text().replace("\n130,", "\n130.5,", 1))
    return str(root)


def _gsv_csv(tmp: Path, damage: str) -> list[str]:
    """recipe=gsv on a GSV-Cities root whose London.csv is damaged: a field over the csv module's limit, or
    bytes that are not UTF-8."""
    root = write_gsv_cities(tmp / "gsv")
    csv = root / "Dataframes" / "London.csv"
    if damage == "long field":
        csv.write_text(csv.read_text().replace("\n", "\n" + "9" * 140_000, 1))
    else:
        csv.write_bytes(csv.read_bytes().replace(b"\n", "\nM\u00fcnchen-".encode("cp1252"), 1))
    return ["recipe=gsv", "data=gsv_cities", f"data.root={root}"]


def _camvid(tmp: Path, damage: str) -> list[str]:
    """A tiny CamVid root with one thing wrong in its train split."""
    root = write_camvid(tmp / "camvid")
    if damage == "list a FIFO":
        (root / "train.txt").unlink()
        os.mkfifo(root / "train.txt")
    elif damage == "list not UTF-8":
        (root / "train.txt").write_bytes((root / "train.txt").read_bytes() + b"train/\xff.png trainannot/\xff.png\n")
    elif damage == "no known class":
        for label in (root / "trainannot").glob("*.png"):
            Image.fromarray(np.full((36, 48), 254, np.uint8)).save(label)
    return [f"seg.root={root}"]


def _fifo_queries(t: Path) -> Path:
    write_image(t / "q" / "a.jpg", 0)
    os.mkfifo(t / "q" / "b.jpg")
    return t / "q"


CASES: dict[str, Case] = {
    "eval NaN UTMs": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=folder", f"data.root={_nan_folder(t)}"], "non-finite position"
    ),
    "eval utmQ string": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=pitts30k", f"data.root={_string_utm_pitts(t)}"], "utmQ"
    ),
    "synthcity --seed -5": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", str(t / "city"), "--seed", "-5"], "seed=-5"
    ),
    "synthcity view_m=inf": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", str(t / "city"), "--render", "view_m=inf"], "view_m"
    ),
    "synthcity --out under a file": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", f"{a_file(t)}/city"], "is a file"
    ),
    "gsv_cities bad place_id": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "data=gsv_cities", f"data.root={_bad_year_gsv(t)}"],
        "place_id='130.5' is not a whole number",
    ),
    "gsv_cities csv field over the limit": Case(
        TRAIN, lambda t, c: _gsv_csv(t, "long field"), "London.csv: line 2: not a readable csv row"
    ),
    "gsv_cities csv not UTF-8": Case(TRAIN, lambda t, c: _gsv_csv(t, "cp1252"), "London.csv: not UTF-8 text"),
    "segment CamVid split list a FIFO": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "list a FIFO"), "train.txt is not a regular file", timeout=600
    ),
    "segment CamVid split list not UTF-8": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "list not UTF-8"), "train.txt is not UTF-8 text (a byte 0xff"
    ),
    "segment CamVid labels of no known class": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "no known class"), "holds a pixel of a known class"
    ),
    "absolute path in a gsv-cities list": Case(EVAL, _absolute_in_npy, "leaves the folder"),
    "absolute path in a Patch-NetVLAD list": Case(EVAL, _absolute_in_patchnetvlad, "leaves the folder"),
    "NUL in a listed name": Case(EVAL, _nul_in_npy, "control character"),
    "a gsv-cities list that is a FIFO": Case(EVAL, _fifo_npy_list, "x_qImages.npy is not a regular file", timeout=600),
    "a Patch-NetVLAD list that is a FIFO": Case(
        EVAL, _fifo_patchnetvlad_list, "db.txt is not a regular file", timeout=600
    ),
    "16-bit PNG": Case(EVAL, lambda t, c: folder(t, c, _sixteen_bit_png), "PIL mode I"),
    "float TIFF named .jpg": Case(EVAL, lambda t, c: folder(t, c, _float_tiff_as_jpg), "PIL mode F"),
    "FIFO named .jpg": Case(EVAL, lambda t, c: folder(t, c, _fifo), "not a regular file", timeout=600),
    "localize FIFO named .jpg": Case(
        LOCALIZE,
        lambda t, c: [
            f"ckpt={c}",
            f"queries={_fifo_queries(t)}",
            "data=folder",
            f"data.root={make_folder(t / 'folder', n=2)}",
        ],
        "not a regular file",
        timeout=600,
    ),
    "dangling symlink": Case(EVAL, lambda t, c: folder(t, c, dangling), "not found"),
    "looping symlinks": Case(EVAL, lambda t, c: folder(t, c, _looping), "Too many levels of symbolic links"),
    "later-listed image missing": Case(EVAL, _pitts_missing_second, "000001_pitch1_yaw1.jpg not found"),
    "object .npy calling numpy.dtype badly": Case(EVAL, _object_npy, "not a readable .npy array"),
    "complex UTMs": Case(EVAL, _complex_utm_pitts, "utmQ is not real numbers"),
    "UTM 1e308": Case(EVAL, lambda t, c: folder(t, c, _utm_1e308), "q_utm has 1 non-finite position"),
    "30-digit frame number": Case(EVAL, lambda t, c: nordland(t, c, frame="9" * 30), "frame number 999"),
}


#: The rows that run by default (each starts a Python with torch): one per class; the whole table with -m slow.
FAST = {
    "synthcity --seed -5",
    "gsv_cities csv not UTF-8",
    "segment CamVid split list not UTF-8",
    "absolute path in a gsv-cities list",
    "16-bit PNG",
    "FIFO named .jpg",
    "dangling symlink",
}


@pytest.mark.parametrize("case", rows(CASES, FAST))
def test_bad_data_is_one_line_and_exit_2(tmp_path: Path, checkpoint: Path, case: str) -> None:
    run_case(CASES[case], tmp_path, checkpoint)


def test_localize_names_what_is_wrong_with_the_query_folder(tmp_path: Path) -> None:
    """A file or a missing path as ``queries=`` says which; a folder without images says so."""
    image = tmp_path / "q.jpg"
    write_image(image, seed=0)
    with pytest.raises(SemvprError, match=r"q.jpg is a file: queries= names the folder of images"):
        folder_images(image, "queries")
    with pytest.raises(SemvprError, match=r"absent does not exist \(queries=DIR\)"):
        folder_images(tmp_path / "absent", "queries")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SemvprError, match=r"no .jpg/.png images in"):
        folder_images(tmp_path / "empty", "queries")
    assert folder_images(tmp_path, "queries") == [image]
    # Subfolders are read (VPR-methods-evaluation's queries_folder: glob(**/*)); hidden names are not.
    write_image(tmp_path / "walk" / "b.png", seed=1)
    (tmp_path / "._q.jpg").write_bytes(b"\x00\x05\x16\x07")
    assert folder_images(tmp_path, "queries") == [image, tmp_path / "walk" / "b.png"]
