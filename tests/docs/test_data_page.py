"""docs/data.md's "You have → run" table: every line, run as written on a fixture in the layout it names
(the placeholders DIR, DB_DIR, ... filled with the fixture's paths), reads the set with the counts and
positives the fixture holds."""

from __future__ import annotations

import json
import re
import shlex
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from semvpr.data.inspect import main
from tests.helpers import (
    REPO,
    make_folder,
    place_utm,
    same_images_as_lists,
    write_frames,
    write_image,
    write_lists,
    write_msls_cities,
    write_msls_test_ground_truth,
    write_pitts_mat,
)

#: What each fixture holds: (database images, queries, queries with a positive).
Expected = tuple[int, int, int]
Fixture = Callable[[Path], tuple[dict[str, str], Expected]]


def _rows() -> list[tuple[str, str]]:
    """The table's (you have, command) rows."""
    page = (REPO / "docs" / "data.md").read_text(encoding="utf-8")
    section = page.split("## You have → run", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "`python -m" in line]
    return [
        (have.strip(), re.search(r"`(python -m [^`]+)`", run)[1]) for have, run in (r[2:].split(" | ", 1) for r in rows)
    ]


def _dataset(command: str) -> str:
    """A line's fixture: its ``data=`` set, and ``msls:test`` where it scores MSLS's official test cities."""
    name = re.search(r"\bdata=(\w+)", command)[1]
    return f"{name}:test" if "data.test.split=test" in command else name


def _folder(tmp: Path) -> tuple[dict[str, str], Expected]:
    return {"DIR": str(make_folder(tmp / "set", n=4))}, (4, 4, 4)


def _folders(tmp: Path) -> tuple[dict[str, str], Expected]:
    root = make_folder(tmp / "set", n=3) / "images" / "test"
    return {"DB_DIR": str(root / "database"), "Q_DIR": str(root / "queries")}, (3, 3, 3)


def _mat(name: str, which: str) -> Fixture:
    def build(tmp: Path) -> tuple[dict[str, str], Expected]:
        db, q = [f"db/{i}.jpg" for i in range(5)], [f"q/{i}.jpg" for i in range(3)]
        for i, path in enumerate(db + q):
            write_image(tmp / "set" / ("queries_real" if name == "pitts30k_test" else "") / path, i)
            write_image(tmp / "set" / path, i)
        write_pitts_mat(tmp / "set" / "datasets" / f"{name}.mat", which, db, q)
        return {"DIR": str(tmp / "set")}, (5, 3, 3)

    return build


def _gsv_npy(tmp: Path) -> tuple[dict[str, str], Expected]:
    root = make_folder(tmp / "set", n=4)
    db, q = same_images_as_lists(root)
    gt = np.empty(len(q), dtype=object)
    gt[:] = [np.array([i]) for i in range(len(q))]
    write_lists(tmp / "lists", "mycity_test", db, q, gt)
    return {"SET": "mycity_test", "GT_DIR": str(tmp / "lists"), "DIR": str(root)}, (4, 4, 4)


def _patchnetvlad(tmp: Path) -> tuple[dict[str, str], Expected]:
    db, q = [f"db{i}.jpg" for i in range(4)], [f"q{i}.jpg" for i in range(2)]
    for i, name in enumerate(db + q):
        write_image(tmp / "img" / name, i)
    utm_db = np.array([place_utm(i) for i in range(4)])
    utm_q = np.array([place_utm(0), (0.0, 0.0)])  # the second query has no database image within 25 m
    np.savez(tmp / "mycity.npz", utmDb=utm_db, utmQ=utm_q, posDistThr=np.array(25.0))
    (tmp / "db.txt").write_text("\n".join(db) + "\n")
    (tmp / "q.txt").write_text("\n".join(q) + "\n")
    paths = {"NPZ": tmp / "mycity.npz", "DB_LIST": tmp / "db.txt", "Q_LIST": tmp / "q.txt", "DIR": tmp / "img"}
    return {k: str(v) for k, v in paths.items()}, (4, 2, 1)


def _msls(tmp: Path) -> tuple[dict[str, str], Expected]:
    # test = the official val cities: cph (database c_db0, c_db1; queries c_q0, c_q_other) and sf.
    return {"DIR": str(write_msls_cities(tmp / "set"))}, (3, 2, 2)


def _msls_test(tmp: Path) -> tuple[dict[str, str], Expected]:
    # miami's frames of the 'all' subtask: the database panorama m_db0 (kept: no raw.csv) and the query m_q0.
    return {"DIR": str(write_msls_test_ground_truth(write_msls_cities(tmp / "set")))}, (1, 1, 1)


def _nordland(tmp: Path) -> tuple[dict[str, str], Expected]:
    return {"DIR": str(write_frames(tmp / "set", {"ref": list(range(12)), "query": list(range(12))}))}, (12, 12, 12)


def _frames(tmp: Path) -> tuple[dict[str, str], Expected]:
    return {"DIR": str(write_frames(tmp / "set", {"A": list(range(5)), "B": list(range(5))}))}, (5, 5, 5)


FIXTURES: dict[str, Fixture] = {
    "folder": _folder,
    "folders": _folders,
    "pitts30k": _mat("pitts30k_test", "test"),
    "tokyo247": _mat("tokyo247", "test"),
    "gsv_npy": _gsv_npy,
    "patchnetvlad": _patchnetvlad,
    "msls": _msls,
    "msls:test": _msls_test,
    "nordland": _nordland,
    "frames": _frames,
}


def test_every_line_of_the_table_has_a_fixture() -> None:
    assert sorted(_dataset(command) for _, command in _rows()) == sorted(FIXTURES)


@pytest.mark.parametrize(("have", "command"), [pytest.param(h, c, id=_dataset(c)) for h, c in _rows()])
def test_a_line_reads_its_layout(tmp_path: Path, capsys: pytest.CaptureFixture[str], have: str, command: str) -> None:
    paths, (database, queries, with_positives) = FIXTURES[_dataset(command)](tmp_path)
    words = shlex.split(command)
    assert words[:3] == ["python", "-m", "semvpr.data.inspect"], command
    placeholder = re.compile(r"\b(" + "|".join(sorted(paths, key=len, reverse=True)) + r")\b")
    main([placeholder.sub(lambda m: paths[m[1]], word) for word in words[3:]])
    stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (stats["database"], stats["queries"], stats["queries_with_positives"]) == (
        database,
        queries,
        with_positives,
    ), have
