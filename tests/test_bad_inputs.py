"""Bad input through the real CLIs: exit code 2, exactly one stderr line, nothing written outside.

Each row runs ``python -m <cli> ...`` from an empty working directory with its run directory and
cache under the test's tmp dir, and lists every file before and after: new files may appear only
in the run directory and the cache.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import make_folder, write_gsv_cities, write_image, write_pitts_mat

REPO = Path(__file__).resolve().parents[1]
EVAL_SIZE = ["data.image_size=[32,48]"]


def _seed_2_70(tmp: Path, ckpt: Path) -> str:
    data = torch.load(ckpt, weights_only=True)
    data["hyper_parameters"]["seed"] = 2**70
    torch.save(data, tmp / "seed.ckpt")
    return str(tmp / "seed.ckpt")


def _empty(tmp: Path) -> str:
    (tmp / "empty.ckpt").touch()
    return str(tmp / "empty.ckpt")


def _a_file(tmp: Path) -> str:
    (tmp / "file").write_text("x")
    return str(tmp / "file")


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


def _bad_year_gsv(tmp: Path) -> str:
    root = write_gsv_cities(tmp / "gsv")
    csv = root / "Dataframes" / "London.csv"
    csv.write_text(csv.read_text().replace("\n130,", "\n130.5,", 1))
    return str(root)


TRAIN = ["semvpr.train", "experiment=tiny"]
EVAL = ["semvpr.eval", "experiment=tiny", *EVAL_SIZE]
# (cli and fixed args, bad args given tmp dir and checkpoint, a fragment of the one line)
CASES: dict[str, tuple[list[str], Callable[[Path, Path], list[str]], str]] = {
    "num_clusters=abc": (TRAIN, lambda t, c: ["model.num_clusters=abc"], "model.num_clusters='abc'"),
    "seed=abc": (TRAIN, lambda t, c: ["seed=abc"], "seed='abc'"),
    "seed=-1": (TRAIN, lambda t, c: ["seed=-1"], "seed=-1"),
    "lr=-1": (TRAIN, lambda t, c: ["recipe.optimizer.lr=-1"], "recipe.optimizer.lr=-1"),
    "num_figure_queries=0": (TRAIN, lambda t, c: ["num_figure_queries=0"], "num_figure_queries=0"),
    "precision=foo": (TRAIN, lambda t, c: ["trainer.precision=foo"], "trainer.precision='foo'"),
    "cache under a file": (TRAIN, lambda t, c: [f"paths.cache_dir={_a_file(t)}/cache"], "is a file"),
    "resume from 0 bytes": (TRAIN, lambda t, c: [f"ckpt_path={_empty(t)}"], "empty.ckpt"),
    "negative radius": (TRAIN, lambda t, c: ["recipe.positive_radius=-5"], "recipe.positive_radius=-5"),
    "model=netvlad": (TRAIN, lambda t, c: ["model=netvlad"], "model=netvlad is recipe=triplet"),
    "model.margin": (TRAIN, lambda t, c: ["model.margin=0.2"], "recipe.margin=0.2"),
    "gsv recipe.optimizer.lr": (
        TRAIN,
        lambda t, c: ["recipe=gsv", "recipe.optimizer.lr=0.1"],
        "override aggregator.gsv.optimizer.lr=0.1, or recipe.default.optimizer.lr=0.1",
    ),
    "gsv places_per_batch=1": (TRAIN, lambda t, c: ["recipe=gsv", "recipe.places_per_batch=1"], "places_per_batch=1"),
    "gsv under ddp": (
        TRAIN,
        lambda t, c: ["recipe=gsv", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"],
        "use trainer=cpu or trainer=gpu",
    ),
    "gsv_cities bad place_id": (
        TRAIN,
        lambda t, c: ["recipe=gsv", "data=gsv_cities", f"data.root={_bad_year_gsv(t)}"],
        "place_id='130.5' is not a whole number",
    ),
    "traversals=-1": (TRAIN, lambda t, c: ["data.traversals=-1"], "data.traversals=-1"),
    "eval model=netvlad": (EVAL, lambda t, c: [f"ckpt={c}", "model=netvlad"], "recipe=triplet"),
    "eval 0-byte ckpt": (EVAL, lambda t, c: [f"ckpt={_empty(t)}"], "empty.ckpt"),
    "eval seed 2**70": (EVAL, lambda t, c: [f"ckpt={_seed_2_70(t, c)}"], "seed=1180591620717411303424"),
    "eval NaN UTMs": (
        EVAL,
        lambda t, c: [f"ckpt={c}", "data=folder", f"data.root={_nan_folder(t)}"],
        "non-finite position",
    ),
    "eval utmQ string": (
        EVAL,
        lambda t, c: [f"ckpt={c}", "data=pitts30k", f"data.root={_string_utm_pitts(t)}"],
        "utmQ",
    ),
    "localize top_k=0": (
        ["semvpr.localize", *EVAL_SIZE],
        lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=0"],
        "top_k=0",
    ),
    "localize top_k=-1": (
        ["semvpr.localize", *EVAL_SIZE],
        lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=-1"],
        "top_k=-1",
    ),
    "localize top_k=abc": (
        ["semvpr.localize", *EVAL_SIZE],
        lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=abc"],
        "top_k='abc'",
    ),
    "synthcity --seed -5": (
        ["semvpr.data.synthcity"],
        lambda t, c: ["--out", str(t / "city"), "--seed", "-5"],
        "seed=-5",
    ),
    "synthcity view_m=inf": (
        ["semvpr.data.synthcity"],
        lambda t, c: ["--out", str(t / "city"), "--render", "view_m=inf"],
        "view_m",
    ),
    "synthcity --out under a file": (
        ["semvpr.data.synthcity"],
        lambda t, c: ["--out", f"{_a_file(t)}/city"],
        "is a file",
    ),
}


def files(folder: Path) -> set[Path]:
    return {Path(d) / n for d, dirs, names in os.walk(folder) for n in names + dirs}


#: One row per CLI runs by default; the whole table with -m slow (each row starts a Python with torch).
FAST = {"seed=abc", "eval 0-byte ckpt", "localize top_k=abc", "synthcity --seed -5", "gsv recipe.optimizer.lr"}


@pytest.mark.parametrize("case", [c if c in FAST else pytest.param(c, marks=pytest.mark.slow) for c in sorted(CASES)])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, checkpoint: Path, case: str) -> None:  # noqa: F811
    (module, *fixed), bad, fragment = CASES[case]
    inputs, run, cache, cwd = tmp_path / "in", tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    inputs.mkdir()
    cwd.mkdir()
    args = bad(inputs, checkpoint)
    if module != "semvpr.data.synthcity":
        args += (
            [f"paths.cache_dir={cache}", f"hydra.run.dir={run}"]
            if not any(a.startswith("paths.cache_dir=") for a in args)
            else [f"hydra.run.dir={run}"]
        )
    before = files(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", module, *fixed, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
    new = files(tmp_path) - before
    assert {p for p in new if not (p.is_relative_to(run) or p.is_relative_to(cache))} == set()
