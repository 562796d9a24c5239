"""`python -m semvpr.data.inspect`: summary + JSON last line, one-line errors with exit code 2."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.data.inspect import main
from tests.helpers import REPO, write_dbstruct

MINIMAL_DATA = """\
root: ???
eval_radius: 25
test:
  _target_: semvpr.data.places.read_utm_folder
  root: ${data.root}
  split: test
"""


def make_folder(root: Path) -> Path:
    """db at east 0, 10, 20, 100; queries at 5 (3 within 25 m), 95 (1), 5000 (0): mean 4/3."""
    name = "@{e}@0@17@T@0@0@@@@@@@@@.jpg"
    for sub, easts in (("database", [0, 10, 20, 100]), ("queries", [5, 95, 5000])):
        folder = root / "images" / "test" / sub
        folder.mkdir(parents=True)
        for e in easts:
            Image.new("RGB", (4, 4)).save(folder / name.format(e=e))
    return root


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-m", "semvpr.data.inspect", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture()
def conf_dir(tmp_path: Path) -> Path:
    conf = tmp_path / "conf"
    (conf / "data").mkdir(parents=True)
    (conf / "train.yaml").write_text("defaults:\n  - data: tiny\n  - _self_\n")
    (conf / "data" / "tiny.yaml").write_text(MINIMAL_DATA)
    return conf


def test_cli_prints_summary_and_json_last_line(tmp_path: Path, conf_dir: Path) -> None:
    root = make_folder(tmp_path / "tiny")
    proc = run_cli("--config-dir", str(conf_dir), f"data.root={root}")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith("tiny/test: 4 database, 3 queries")
    assert json.loads(lines[-1]) == {"database": 4, "queries": 3, "queries_with_positives": 2, "mean_positives": 1.33}


def test_cli_bad_root_one_line_exit_2(tmp_path: Path, conf_dir: Path) -> None:
    proc = run_cli("--config-dir", str(conf_dir), f"data.root={tmp_path / 'missing'}")
    assert proc.returncode == 2
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in proc.stderr
    assert err[0].startswith("semvpr: error: ") and str(tmp_path / "missing") in err[0]
    assert proc.stdout == ""


def test_missing_override_and_bad_group_are_user_errors(conf_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--config-dir", str(conf_dir)])
    assert exc.value.code == 2
    assert "data.root is not set; pass it on the command line (data.root=...)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--config-dir", str(conf_dir), "data=nosuch"])
    assert "data/nosuch" in capsys.readouterr().err


def test_repo_conf_folder_dataset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The default config dir is the repo's conf/, where `data=folder` reads an @UTM@ folder."""
    root = make_folder(tmp_path / "tiny")
    main(["data=folder", f"data.root={root}"])
    out = capsys.readouterr()
    assert json.loads(out.out.strip().splitlines()[-1])["queries_with_positives"] == 2, out.err


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("malformed_name", r"IMG_0001\.jpg: not an @UTM@ image name"),
        ("empty_split", r"images/test/queries: no queries images"),
        ("mat_lacks_field", r"pitts30k_test\.mat: dbStruct lacks field 'utmQ'"),
        ("mat_empty_split", r"pitts30k_test\.mat: empty split \(0 database, 1 query names\)"),
    ],
)
def test_bad_dataset_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str, expected: str
) -> None:
    """Each broken dataset gives exit 2 and one `semvpr: error:` line naming the problem."""
    root = tmp_path / "data"
    if case.startswith("mat"):
        (root / "datasets").mkdir(parents=True)
        names, utm = (["a.jpg"], np.zeros((1, 2)))
        db_names, db_utm = ([], np.zeros((0, 2))) if case == "mat_empty_split" else (names, utm)
        write_dbstruct(
            root / "datasets" / "pitts30k_test.mat",
            db_names,
            db_utm,
            names,
            utm,
            drop="utmQ" if case == "mat_lacks_field" else None,
        )
        overrides = ["data=pitts30k", f"data.root={root}"]
    else:
        make_folder(root)
        queries = root / "images" / "test" / "queries"
        if case == "malformed_name":
            Image.new("RGB", (4, 4)).save(queries / "IMG_0001.jpg")
        else:
            for p in queries.iterdir():
                p.unlink()
        overrides = ["data=folder", f"data.root={root}"]
    with pytest.raises(SystemExit) as exc:
        main(overrides)
    assert exc.value.code == 2
    out = capsys.readouterr()
    err = out.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("semvpr: error: "), out.err
    assert re.search(expected, err[0]), err[0]
    assert out.out == ""
