"""`python -m semvpr.data.inspect`: summary + JSON last line, one-line errors with exit code 2."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from semvpr.data.inspect import main

REPO = Path(__file__).resolve().parents[1]
MINIMAL_DATA = """\
root: ???
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
    return subprocess.run([sys.executable, "-m", "semvpr.data.inspect", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)


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
    assert json.loads(lines[-1]) == {"database": 4, "queries": 3, "queries_with_positives": 2,
                                     "mean_positives": 1.33}


def test_cli_bad_root_one_line_exit_2(tmp_path: Path, conf_dir: Path) -> None:
    proc = run_cli("--config-dir", str(conf_dir), f"data.root={tmp_path / 'missing'}")
    assert proc.returncode == 2
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in proc.stderr
    assert err[0].startswith("semvpr: error: ") and str(tmp_path / "missing") in err[0]
    assert proc.stdout == ""


def test_missing_override_and_bad_group_are_user_errors(conf_dir: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--config-dir", str(conf_dir)])
    assert exc.value.code == 2
    assert "Missing mandatory value" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--config-dir", str(conf_dir), "data=nosuch"])
    assert "data/nosuch" in capsys.readouterr().err


def test_repo_conf_folder_dataset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The default config dir is the repo's conf/, where `data=folder` reads an @UTM@ folder."""
    root = make_folder(tmp_path / "tiny")
    main(["data=folder", f"data.root={root}"])
    out = capsys.readouterr()
    assert json.loads(out.out.strip().splitlines()[-1])["queries_with_positives"] == 2, out.err
