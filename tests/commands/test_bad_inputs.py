"""Bad input through the real CLIs: exit code 2, exactly one stderr line, nothing written outside.

Each row runs ``python -m <cli> ...`` from an empty working directory with its run directory and
cache under the test's tmp dir, and lists every file before and after: new files may appear only
in the run directory and the cache. A second table holds the inputs that must not fail but must not
be silently wrong either (a replaced image, a planted partial cache, a hostile sweep directory): each
row runs the real CLI and checks what it wrote. Rows that start a Python with torch take seconds each:
one per class runs by default, the whole table with ``-m slow``.
"""

from __future__ import annotations

import ast
import json
import os
import resource
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from tests.camvid_fixture import write_camvid
from tests.helpers import (
    REPO,
    make_folder,
    object_array,
    tiny_config,
    write_gsv_cities,
    write_image,
    write_lists,
    write_pitts_mat,
)

EVAL_SIZE = ["data.image_size=[32,48]"]
#: Folders made immutable by a row (root ignores permissions); made mutable again after the row.
IMMUTABLE: list[Path] = []


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


# ------------------------------------------------------------------ fixtures of the rows below


#: The config choices of ``experiment=tiny`` as Hydra records them in a run's .hydra/hydra.yaml.
TINY_CHOICES = {
    "data": "synthcity",
    "backbone": "efficientnet_lite0",
    "aggregator": "netvlad",
    "mask": "none",
    "filter": "none",
    "teacher": "mask2former",
    "student": "unet",
    "recipe": "triplet",
    "trainer": "cpu",
    "logger": "default",
    "experiment": "tiny",
}


def _tampered_run(t: Path, c: Path) -> list[str]:
    """A run dir whose recorded config names builtins.open as its training set (a resume ran it)."""
    run = t.parent / "run"
    own = OmegaConf.to_container(tiny_config(t.parent / "cache"), resolve=False)
    own["data"]["train"] = {"_target_": "builtins.open", "file": str(t.parent / "cwd" / "PWNED"), "mode": "w"}
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(own), run / ".hydra" / "config.yaml")
    hydra_record = {"hydra": {"runtime": {"choices": TINY_CHOICES}}}
    (run / ".hydra" / "hydra.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(hydra_record)))
    return ["ckpt_path=last", f"hydra.run.dir={run}"]


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


def _folder(t: Path, c: Path, edit: Callable[[Path], None]) -> list[str]:
    root = make_folder(t / "folder", n=3)
    edit(root / "images" / "test")
    return [f"ckpt={c}", "data=folder", f"data.root={root}"]


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


def _dangling(test: Path) -> None:
    (test / "database" / "@585900.00@4477000.00@17@T@@@@@@@@@@@.jpg").symlink_to("/nonexistent/x.jpg")


def _looping(test: Path) -> None:
    a, b = (test / "database" / f"@58{n}00.00@4477000.00@17@T@@@@@@@@@@@.jpg" for n in (59, 60))
    a.symlink_to(b.name)
    b.symlink_to(a.name)


def _utm_1e308(test: Path) -> None:
    write_image(test / "queries" / "@1e308@4477000.00@17@T@@@@@@@@@@@.jpg", 9)


def _huge_checkpoint(t: Path, c: Path) -> str:
    """Finite weights whose logits overflow: the descriptors come out NaN."""
    data = torch.load(c, weights_only=True)
    weight = data["state_dict"]["aggregator.conv.weight"]
    data["state_dict"]["aggregator.conv.weight"] = torch.full_like(weight, 3e38)
    torch.save(data, t / "huge.ckpt")
    return str(t / "huge.ckpt")


def _model_value(t: Path, c: Path, key: str, value: object) -> str:
    """The checkpoint with a recorded model value of the right type but out of range."""
    data = torch.load(c, weights_only=True)
    data["hyper_parameters"]["config"]["model"][key] = value
    torch.save(data, t / f"{key}.ckpt")
    return str(t / f"{key}.ckpt")


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


def _nordland(t: Path, c: Path, *extra: str, frame: str | None = None) -> list[str]:
    for i in range(3):
        write_image(t / "nord" / "ref" / f"{i:05d}.jpg", i)
        write_image(t / "nord" / "query" / f"{i:05d}.jpg", i)
    if frame is not None:
        write_image(t / "nord" / "query" / f"{frame}.jpg", 5)
    return [f"ckpt={c}", "data=nordland", f"data.root={t / 'nord'}", *extra]


def _immutable(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["chattr", "+i", str(folder)], check=True, capture_output=True)
    IMMUTABLE.append(folder)
    return folder


LONG = "x" * 300


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


TRAIN = ["semvpr.train", "experiment=tiny"]
EVAL = ["semvpr.eval", "experiment=tiny", *EVAL_SIZE]
LOCALIZE = ["semvpr.localize", *EVAL_SIZE, "data.num_workers=0"]


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


@dataclass
class Case:
    """A bad input: the CLI and its fixed args, the bad args (given the tmp inputs dir and a checkpoint),
    a fragment of the one line; a row may name its own run dir / cache, environment and time limit, and
    check what the cache holds afterwards."""

    cli: list[str]
    args: Callable[[Path, Path], list[str]]
    fragment: str
    env: dict[str, str] = field(default_factory=dict)
    timeout: int = 300
    cache_check: Callable[[Path], None] | None = None


def _no_descriptors(cache: Path) -> None:
    """The bad value was refused before the descriptor pass."""
    assert not cache.is_dir() or not any(p.name.startswith("descriptors-") for p in cache.iterdir())


CASES: dict[str, Case] = {
    "num_clusters=abc": Case(TRAIN, lambda t, c: ["model.num_clusters=abc"], "model.num_clusters='abc'"),
    "seed=abc": Case(TRAIN, lambda t, c: ["seed=abc"], "seed='abc'"),
    "student.flip=maybe": Case(TRAIN, lambda t, c: ["student.flip=maybe"], "student.flip='maybe': expected true"),
    "seed=-1": Case(TRAIN, lambda t, c: ["seed=-1"], "seed=-1"),
    "lr=-1": Case(TRAIN, lambda t, c: ["recipe.optimizer.lr=-1"], "recipe.optimizer.lr=-1"),
    "num_figure_queries=0": Case(TRAIN, lambda t, c: ["num_figure_queries=0"], "num_figure_queries=0"),
    "precision=foo": Case(TRAIN, lambda t, c: ["trainer.precision=foo"], "trainer.precision='foo'"),
    "cache under a file": Case(TRAIN, lambda t, c: [f"paths.cache_dir={_a_file(t)}/cache"], "is a file"),
    "resume from 0 bytes": Case(TRAIN, lambda t, c: [f"ckpt_path={_empty(t)}"], "empty.ckpt"),
    "negative radius": Case(TRAIN, lambda t, c: ["recipe.positive_radius=-5"], "recipe.positive_radius=-5"),
    "model=netvlad": Case(TRAIN, lambda t, c: ["model=netvlad"], "model=netvlad is recipe=triplet"),
    "model.margin": Case(TRAIN, lambda t, c: ["model.margin=0.2"], "recipe.margin=0.2"),
    "eval model=netvlad": Case(EVAL, lambda t, c: [f"ckpt={c}", "model=netvlad"], "recipe=triplet"),
    "eval 0-byte ckpt": Case(EVAL, lambda t, c: [f"ckpt={_empty(t)}"], "empty.ckpt"),
    "eval ckpt in a sweep job's folder, unquoted": Case(
        EVAL, lambda t, c: [f"ckpt={t}/filter=unet,seed=0/tested.ckpt"], "\"ckpt='"
    ),
    "eval seed 2**70": Case(EVAL, lambda t, c: [f"ckpt={_seed_2_70(t, c)}"], "seed=1180591620717411303424"),
    "eval NaN UTMs": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=folder", f"data.root={_nan_folder(t)}"], "non-finite position"
    ),
    "eval utmQ string": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=pitts30k", f"data.root={_string_utm_pitts(t)}"], "utmQ"
    ),
    "localize top_k=0": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=0"], "top_k=0"),
    "localize top_k=-1": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=-1"], "top_k=-1"),
    "localize top_k=abc": Case(LOCALIZE, lambda t, c: [f"ckpt={c}", f"queries={t}", "top_k=abc"], "top_k='abc'"),
    "synthcity --seed -5": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", str(t / "city"), "--seed", "-5"], "seed=-5"
    ),
    "synthcity view_m=inf": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", str(t / "city"), "--render", "view_m=inf"], "view_m"
    ),
    "synthcity --out under a file": Case(
        ["semvpr.data.synthcity"], lambda t, c: ["--out", f"{_a_file(t)}/city"], "is a file"
    ),
    # ---- recipe=gsv and its data
    "gsv recipe.optimizer.lr": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "recipe.optimizer.lr=0.1"],
        "override aggregator.gsv.optimizer.lr=0.1, or recipe.default.optimizer.lr=0.1",
    ),
    "gsv places_per_batch=1": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.places_per_batch=1"], "places_per_batch=1"
    ),
    "gsv under ddp": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"],
        "use trainer=cpu or trainer=gpu",
    ),
    "gsv_cities bad place_id": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "data=gsv_cities", f"data.root={_bad_year_gsv(t)}"],
        "place_id='130.5' is not a whole number",
    ),
    "traversals=-1": Case(TRAIN, lambda t, c: ["data.traversals=-1"], "data.traversals=-1"),
    "gsv_cities csv field over the limit": Case(
        TRAIN, lambda t, c: _gsv_csv(t, "long field"), "London.csv: line 2: not a readable csv row"
    ),
    "gsv_cities csv not UTF-8": Case(TRAIN, lambda t, c: _gsv_csv(t, "cp1252"), "London.csv: not UTF-8 text"),
    # ---- the command line names no _target_ (nor any _ key): only the project's files do
    "train data.test._target_=builtins.print": Case(
        TRAIN, lambda t, c: ["data.test._target_=builtins.print"], "the key _target_ is refused"
    ),
    "eval a mapping value holding _target_": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "+data.extra={_target_:os.getcwd}"], "the key _target_ is refused"
    ),
    "segment CamVid split list a FIFO": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "list a FIFO"), "train.txt is not a regular file", timeout=90
    ),
    "segment CamVid split list not UTF-8": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "list not UTF-8"), "train.txt is not UTF-8 text (a byte 0xff"
    ),
    "segment CamVid labels of no known class": Case(
        ["semvpr.segment"], lambda t, c: _camvid(t, "no known class"), "holds a pixel of a known class"
    ),
    "segment model._partial_": Case(
        ["semvpr.segment"], lambda t, c: [f"seg.root={t}", "teacher.model._partial_=true"], "the key _partial_"
    ),
    # ---- patterns from the command line run with a bounded cost: a backtracking bomb is refused at once
    "frame_pattern alternation in a repeat": Case(
        EVAL,
        lambda t, c: _nordland(t, c, "data.frame_pattern='(x|xx)*(\\d+)\\.jpg'", frame="x" * 40),
        "repeats a repeat or an alternation",
        timeout=90,
    ),
    "frame_pattern nested repeat": Case(
        EVAL,
        lambda t, c: _nordland(t, c, "data.frame_pattern='(?:y+)+z?(\\d+)\\.jpg'", frame="y" * 40),
        "repeats a repeat or an alternation",
        timeout=90,
    ),
    "frame_pattern backreference": Case(
        EVAL, lambda t, c: _nordland(t, c, "data.frame_pattern='(\\d)\\1(\\d*)\\.jpg'"), "backreference"
    ),
    "frame_pattern four unbounded repeats": Case(
        EVAL,
        lambda t, c: _nordland(t, c, "data.frame_pattern='.*_.*_.*_(\\d+)\\.jpg'"),
        "at most three unbounded repeats",
    ),
    # ---- a run directory is data: resume composes from the project's files, checks the record's values
    "resume a run whose record names a _target_": Case(TRAIN[:1], _tampered_run, "data.train._target_ is refused"),
    # ---- list files: one rule for every reader (relative, no '..', no control characters)
    "absolute path in a gsv-cities list": Case(EVAL, _absolute_in_npy, "leaves the folder"),
    "absolute path in a Patch-NetVLAD list": Case(EVAL, _absolute_in_patchnetvlad, "leaves the folder"),
    "NUL in a listed name": Case(EVAL, _nul_in_npy, "control character"),
    "a gsv-cities list that is a FIFO": Case(EVAL, _fifo_npy_list, "x_qImages.npy is not a regular file", timeout=90),
    "a Patch-NetVLAD list that is a FIFO": Case(
        EVAL, _fifo_patchnetvlad_list, "db.txt is not a regular file", timeout=90
    ),
    # ---- run dirs are used as written: '$' would be expanded by the TensorBoard logger
    "run dir with $VAR": Case(
        TRAIN, lambda t, c: [f"hydra.run.dir={t.parent / 'run'}/$XV"], "'$' and a leading '~'", env={"XV": "../esc"}
    ),
    # ---- images: regular 8-bit files only
    "16-bit PNG": Case(EVAL, lambda t, c: _folder(t, c, _sixteen_bit_png), "PIL mode I"),
    "float TIFF named .jpg": Case(EVAL, lambda t, c: _folder(t, c, _float_tiff_as_jpg), "PIL mode F"),
    "FIFO named .jpg": Case(EVAL, lambda t, c: _folder(t, c, _fifo), "not a regular file", timeout=90),
    "localize FIFO named .jpg": Case(
        LOCALIZE,
        lambda t, c: [
            f"ckpt={c}",
            f"queries={_fifo_queries(t)}",
            "data=folder",
            f"data.root={make_folder(t / 'folder', n=2)}",
        ],
        "not a regular file",
        timeout=90,
    ),
    "dangling symlink": Case(EVAL, lambda t, c: _folder(t, c, _dangling), "not found"),
    "looping symlinks": Case(EVAL, lambda t, c: _folder(t, c, _looping), "Too many levels of symbolic links"),
    "later-listed image missing": Case(EVAL, _pitts_missing_second, "000001_pitch1_yaw1.jpg not found"),
    "object .npy calling numpy.dtype badly": Case(EVAL, _object_npy, "not a readable .npy array"),
    # ---- numbers: finite, real, in range
    "non-finite descriptors": Case(
        EVAL, lambda t, c: _folder(t, _huge_checkpoint(t, c), lambda test: None), "are not finite"
    ),
    "complex UTMs": Case(EVAL, _complex_utm_pitts, "utmQ is not real numbers"),
    "UTM 1e308": Case(EVAL, lambda t, c: _folder(t, c, _utm_1e308), "q_utm has 1 non-finite position"),
    "30-digit frame number": Case(EVAL, lambda t, c: _nordland(t, c, frame="9" * 30), "frame number 999"),
    "frame_window 1e20": Case(
        EVAL, lambda t, c: _nordland(t, c, "data.frame_window=100000000000000000000"), "data.frame_window="
    ),
    "frame_window int64 max": Case(
        EVAL, lambda t, c: _nordland(t, c, f"data.frame_window={2**63 - 1}"), f"data.frame_window={2**63 - 1}"
    ),
    "checkpoint eval_batch_size=0": Case(
        EVAL,
        lambda t, c: [f"ckpt={_model_value(t, c, 'eval_batch_size', 0)}"],
        "eval_batch_size.ckpt: model.eval_batch_size=0",
    ),
    "checkpoint pca_dim=-1": Case(
        EVAL, lambda t, c: [f"ckpt={_model_value(t, c, 'pca_dim', -1)}"], "pca_dim.ckpt: model.pca_dim"
    ),
    "recipe.margin=nan": Case(TRAIN, lambda t, c: ["recipe.margin=nan"], "recipe.margin=nan"),
    "recipe.loss.epsilon=nan": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.loss.epsilon=nan"], "recipe.loss.epsilon=nan is not a finite"
    ),
    "recipe.loss.beta=-inf": Case(
        TRAIN, lambda t, c: ["recipe=gsv", "recipe.loss.beta=-inf"], "recipe.loss.beta=-inf is not a finite"
    ),
    # ---- a fit that learns nothing fails: a loss with no gradient at any step (no pair mined) is not ok
    "gsv loss without a gradient": Case(
        TRAIN,
        lambda t, c: ["recipe=gsv", "recipe.loss.epsilon=-5", "trainer.max_epochs=1", "threads=1"],
        "the loss gave no parameter a gradient in any of",
    ),
    # ---- sizes and class lists of the teacher and student settings: bounded, as their directories' values
    "teacher.model.num_queries=1e9": Case(
        TRAIN, lambda t, c: ["teacher.model.num_queries=1e9"], "teacher.model.num_queries=1000000000.0"
    ),
    "teacher.model.hidden_dim past the bound": Case(
        TRAIN, lambda t, c: ["teacher.model.hidden_dim=200000"], "teacher.model.hidden_dim=200000"
    ),
    "student.static_classes=[]": Case(
        TRAIN, lambda t, c: ["student.static_classes=[]"], "student.static_classes=[]: expected a non-empty"
    ),
    "eval data.image_size past the bound": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[48,20000]"], "data.image_size[1]=20000"
    ),
    "eval teacher.inference_size past the bound": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "teacher.inference_size=[9000,9000]"], "teacher.inference_size=[9000, 9000]"
    ),
    "recipe.margin=-1": Case(TRAIN, lambda t, c: ["recipe.margin=-1"], "recipe.margin=-1"),
    "recipe.negative_candidates=0": Case(
        TRAIN, lambda t, c: ["recipe.negative_candidates=0"], "recipe.negative_candidates=0"
    ),
    "recipe.batch_size=nan": Case(TRAIN, lambda t, c: ["recipe.batch_size=nan"], "recipe.batch_size=nan"),
    "recipe.batch_size=abc": Case(TRAIN, lambda t, c: ["recipe.batch_size=abc"], "recipe.batch_size='abc'"),
    "trainer.max_epochs=-5": Case(TRAIN, lambda t, c: ["trainer.max_epochs=-5"], "trainer.max_epochs"),
    "trainer.max_epochs=abc": Case(TRAIN, lambda t, c: ["trainer.max_epochs=abc"], "trainer.max_epochs"),
    "model.pca_dim=-1": Case(TRAIN, lambda t, c: ["model.pca_dim=-1"], "model.pca_dim"),
    "trainer.devices=0": Case(TRAIN, lambda t, c: ["trainer.devices=0"], "trainer.devices"),
    "trainer.devices=2 without ddp": Case(TRAIN, lambda t, c: ["trainer.devices=2"], "needs trainer=ddp"),
    "unknown key +model.fooo": Case(TRAIN, lambda t, c: ["+model.fooo=1"], "model.fooo is not a setting"),
    "unknown key +fooo": Case(TRAIN, lambda t, c: ["+fooo=1"], "fooo is not a setting"),
    "unknown key model.fooo": Case(TRAIN, lambda t, c: ["model.fooo=1"], "model.fooo is not a setting"),
    "train data.eval_radius=0": Case(TRAIN, lambda t, c: ["data.eval_radius=0"], "data.eval_radius=0"),
    "eval data.image_size=[0,0]": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[0,0]"], "data.image_size"),
    "eval data.image_size=[-1,80]": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=[-1,80]"], "data.image_size[0]"
    ),
    "eval data.image_size=null": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.image_size=null"], "data.image_size"),
    "eval data.num_workers=-1": Case(EVAL, lambda t, c: [f"ckpt={c}", "data.num_workers=-1"], "data.num_workers=-1"),
    **{
        f"eval data.eval_radius={v}": Case(
            EVAL,
            lambda t, c, v=v: [
                f"ckpt={c}",
                "data=folder",
                f"data.root={make_folder(t / 'f', 2)}",
                f"data.eval_radius={v}",
            ],
            f"data.eval_radius={v}",
            cache_check=_no_descriptors,
        )
        for v in ("0", "-5", "nan")
    },
    # ---- the file system: read-only or immutable folders, names too long
    "immutable cache dir": Case(
        EVAL, lambda t, c: [f"ckpt={c}", f"paths.cache_dir={_immutable(t / 'ro-cache')}"], "cannot be written"
    ),
    "immutable run dir": Case(
        EVAL, lambda t, c: [f"ckpt={c}", f"hydra.run.dir={_immutable(t / 'ro-run')}"], "cannot be written"
    ),
    "cache dir name too long": Case(EVAL, lambda t, c: [f"ckpt={c}", f"paths.cache_dir={t}/{LONG}"], "bytes long"),
    "run dir name too long": Case(EVAL, lambda t, c: [f"ckpt={c}", f"hydra.run.dir={t}/{LONG}"], "bytes long"),
    "data.root name too long": Case(
        EVAL, lambda t, c: [f"ckpt={c}", "data=folder", f"data.root={t}/{LONG}"], "bytes long"
    ),
}


def _fifo_queries(t: Path) -> Path:
    write_image(t / "q" / "a.jpg", 0)
    os.mkfifo(t / "q" / "b.jpg")
    return t / "q"


def _stage_line(line: str) -> bool:
    """A progress line of semvpr's own (``semvpr: <set> db: 3/6 images``), not an error."""
    return line.startswith("semvpr: ") and not line.startswith("semvpr: error: ")


def test_an_unparsable_override_is_named_with_the_quoted_form_that_parses(tmp_path: Path) -> None:
    from semvpr.config.checks import check_overrides
    from semvpr.core.errors import SemvprError

    bad = f"ckpt={tmp_path}/filter=unet,seed=0/checkpoints/tested.ckpt"
    with pytest.raises(SemvprError) as err:
        check_overrides(["experiment=tiny", bad], "eval")
    message = str(err.value)
    assert f"cannot parse the override {bad!r}" in message and "\n" not in message
    suggested = message.rsplit(": ", 1)[1].strip('"')
    assert suggested == f"ckpt='{bad.partition('=')[2]}'"
    check_overrides(["experiment=tiny", suggested], "eval")  # parses and composes


def files(folder: Path) -> set[Path]:
    return {Path(d) / n for d, dirs, names in os.walk(folder) for n in names + dirs}


#: The rows that run by default (each starts a Python with torch): one per class; the whole table with -m slow.
FAST = {
    "seed=abc",
    "student.flip=maybe",
    "eval 0-byte ckpt",
    "eval ckpt in a sweep job's folder, unquoted",
    "localize top_k=abc",
    "synthcity --seed -5",
    "resume a run whose record names a _target_",
    "absolute path in a gsv-cities list",
    "16-bit PNG",
    "FIFO named .jpg",
    "dangling symlink",
    "eval data.eval_radius=0",
    "unknown key +model.fooo",
    "gsv recipe.optimizer.lr",
    "gsv_cities csv not UTF-8",
    "train data.test._target_=builtins.print",
    "frame_pattern nested repeat",
    "gsv loss without a gradient",
    "teacher.model.num_queries=1e9",
    "segment CamVid split list not UTF-8",
}


@pytest.mark.parametrize("case", [c if c in FAST else pytest.param(c, marks=pytest.mark.slow) for c in sorted(CASES)])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, checkpoint: Path, case: str) -> None:  # noqa: F811
    row = CASES[case]
    (module, *fixed), bad, fragment = row.cli, row.args, row.fragment
    inputs, run, cache, cwd = tmp_path / "in", tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    inputs.mkdir()
    cwd.mkdir()
    try:
        args = bad(inputs, checkpoint)
        if module != "semvpr.data.synthcity":
            if not any(a.startswith("paths.cache_dir=") for a in args):
                args.append(f"paths.cache_dir={cache}")
            if not any(a.startswith("hydra.run.dir=") for a in args):
                args.append(f"hydra.run.dir={run}")
            # A row may name its own run dir or cache: files may appear there.
            run = Path(next(a for a in args if a.startswith("hydra.run.dir=")).partition("=")[2])
            cache = Path(next(a for a in args if a.startswith("paths.cache_dir=")).partition("=")[2])
        before = files(tmp_path)
        proc = subprocess.run(
            [sys.executable, "-m", module, *fixed, *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=row.timeout,
            env={**os.environ, "PYTHONPATH": str(REPO), **row.env},
        )
        # Besides semvpr's own stage lines (a pass may have started), exactly one line: the error, last.
        lines = [ln for ln in proc.stderr.strip().splitlines() if not _stage_line(ln)]
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
        assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
        assert proc.stderr.strip().splitlines()[-1] == lines[0]
        new = files(tmp_path) - before
        assert {p for p in new if not (p.is_relative_to(run) or p.is_relative_to(cache))} == set()
        if row.cache_check is not None:
            row.cache_check(cache)
    finally:
        while IMMUTABLE:
            subprocess.run(["chattr", "-i", str(IMMUTABLE.pop())], check=False, capture_output=True)


# ------------------------------------------------------------------ inputs that must not be silently wrong


def _cli(module: str, *args: str, cwd: Path, timeout: int = 300, env: dict | None = None, limit_gb: float = 0):
    """Run ``python -m module args`` (optionally with its address space limited, so a blow-up fails fast)."""

    def limit() -> None:
        if limit_gb:
            size = int(limit_gb * 2**30)
            resource.setrlimit(resource.RLIMIT_AS, (size, size))

    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})},
        preexec_fn=limit,
    )


def _eval_json(job: dict, **extra: object) -> dict:
    return {
        "status": "ok",
        "data": "folder",
        "set": "a",
        "benchmark": None,
        "model": "m",
        "aggregator": "a",
        "mask": "none",
        "checkpoint": "/abs/machine/path/tested.ckpt",
        **{f"test/R@{n}": 1.0 for n in (1, 5, 10, 20)},
        "queries": 1,
        "database": 1,
        "descriptor_dim": 1,
        "wall_s": 1.0,
        **job,
        **extra,
    }


def _metrics(**labels: object) -> dict:
    return {
        "status": "ok",
        "error": None,
        "mask": "none",
        "weights": "binary",
        "backbone": "efficientnet_lite0",
        "backbone_weights": "imagenet",
        "seed": 0,
        **{f"test/R@{n}": 50.0 + n for n in (1, 5, 10, 20)},
        "wall_time_s": 1.0,
        "baseline_aggregator": False,
        **labels,
    }


def _alias_bomb(levels: int = 8, as_list: bool = False) -> str:
    """A few hundred bytes of YAML whose aliases expand to 9**levels strings."""
    prefix = "- " if as_list else ""
    lines = [f'{prefix}{"" if as_list else "a0: "}&a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels + 1):
        lines.append(f"{prefix}{'' if as_list else f'a{i}: '}&a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    lines.append(f"{prefix}{'' if as_list else 'seed: '}*a{levels}" if not as_list else "- data=folder")
    return "\n".join(lines) + "\n"


def _sweep_with(tmp: Path, kind: str) -> Path:
    sweep = tmp / "sweep"
    if kind == "report":
        for name, agg in (("a", "netvlad"), ("b", "gem")):
            (sweep / name).mkdir(parents=True)
            (sweep / name / "metrics.json").write_text(
                json.dumps(_metrics(aggregator=agg, baseline_aggregator=agg == "netvlad"))
            )
    else:
        for name in ("0", "1"):
            (sweep / name / ".hydra").mkdir(parents=True)
            (sweep / name / "eval.json").write_text(json.dumps(_eval_json({})))
    return sweep


def test_an_alias_bomb_in_a_sweeps_record_costs_nothing(tmp_path: Path) -> None:
    """A 400-byte YAML alias bomb as a job's config.yaml (report) or overrides.yaml (evaltable) once cost
    minutes and gigabytes; aliases are refused where a run's record is read."""
    report = _sweep_with(tmp_path / "r", "report")
    (report / "a" / ".hydra").mkdir()
    (report / "a" / ".hydra" / "config.yaml").write_text(_alias_bomb())
    table = _sweep_with(tmp_path / "e", "evaltable")
    (table / "0" / "eval.json").write_text(json.dumps({"status": "failed", "error": "x"}))
    (table / "0" / ".hydra" / "overrides.yaml").write_text(_alias_bomb(as_list=True))
    for module, sweep in (("semvpr.report", report), ("semvpr.evaltable", table)):
        proc = _cli(module, str(sweep), cwd=tmp_path, timeout=60, limit_gb=3)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert (sweep / "results.md").is_file()


def test_a_sweep_whose_results_md_is_a_folder_is_one_line_and_moves_nothing(tmp_path: Path) -> None:
    for module, kind in (("semvpr.report", "report"), ("semvpr.evaltable", "evaltable")):
        sweep = _sweep_with(tmp_path / kind, kind)
        (sweep / "results.md").mkdir()
        before = files(sweep)
        proc = _cli(module, str(sweep), cwd=tmp_path)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and "results.md is a directory" in lines[0], proc.stderr
        assert files(sweep) == before  # nothing moved in beside the old report (no new csv, no figure)


def test_deeply_nested_json_in_a_sweep_is_a_failed_row(tmp_path: Path) -> None:
    for module, kind, name in (
        ("semvpr.report", "report", "a/metrics.json"),
        ("semvpr.evaltable", "evaltable", "1/eval.json"),
    ):
        sweep = _sweep_with(tmp_path / kind, kind)
        (sweep / name).write_text("[" * 100_000 + "]" * 100_000)
        proc = _cli(module, str(sweep), cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert "not readable JSON" in (sweep / "results.md").read_text()


def test_evaltable_reads_overrides_as_text_and_escapes_every_cell(tmp_path: Path) -> None:
    sweep = _sweep_with(tmp_path, "evaltable")
    (sweep / "0" / ".hydra" / "overrides.yaml").write_text("- data=folder\n- data.root=${oc.env:SECRETV}\n")
    (sweep / "0" / "eval.json").write_text(json.dumps({"status": "failed", "error": "boom\n# Heading <script>x"}))
    hostile = {"data": "<script>alert(1)</script>", "set": "a\n# Injected heading\n<img src=x>", "benchmark": "<b>"}
    (sweep / "1" / "eval.json").write_text(json.dumps(_eval_json(hostile)))
    (sweep / "2").mkdir()
    (sweep / "2" / "eval.json").write_text(json.dumps({"status": "ok"}))  # keys missing: a failed row, no KeyError
    proc = _cli("semvpr.evaltable", str(sweep), cwd=tmp_path, env={"SECRETV": "/home/secret-token-123"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (sweep / "results.md").read_text()
    assert "secret-token" not in text and "data.root=${oc.env:SECRETV}" in text
    assert "<script" not in text and "<img" not in text and "<b>" not in text
    assert not [line for line in text.splitlines() if line.startswith(("# Injected", "# Heading"))]
    assert "eval.json has no usable 'data'" in text
    assert ", /abs/machine/path" not in text and "/abs/machine/path/tested.ckpt" in text  # relative to the sweep


def test_report_escapes_the_gain_line_and_leaves_the_sweep_path_out(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    for name, agg in (("a", "net`vlad</p>\n# HEAD <script>x</script>"), ("b", "gem")):
        (sweep / name).mkdir(parents=True)
        (sweep / name / "metrics.json").write_text(
            json.dumps(_metrics(aggregator=agg, baseline_aggregator=name == "a"))
        )
    proc = _cli("semvpr.report", str(sweep), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (sweep / "results.md").read_text()
    assert "<script" not in text and "</p>" not in text and not any(ln.startswith("# HEAD") for ln in text.splitlines())
    assert str(tmp_path) not in text  # no absolute path of the machine that made it


def test_report_names_rows_by_the_preset_asked_for(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    presets = {"none": ("netvlad", "none"), "attention": ("sral", "none"), "unet": ("sral", "student")}
    for preset, (agg, mask) in presets.items():
        job = sweep / f"filter={preset},seed=0"
        job.mkdir(parents=True)
        labels = {"aggregator": agg, "mask": mask, "filter": preset, "baseline_aggregator": agg == "netvlad"}
        (job / "metrics.json").write_text(json.dumps(_metrics(**labels)))
    job = sweep / "aggregator=gem,seed=0"  # not asked for by a preset: named by what it ran
    job.mkdir()
    (job / "metrics.json").write_text(json.dumps(_metrics(aggregator="gem", filter="none")))
    proc = _cli("semvpr.report", str(sweep), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [
        ln.split("|")[2].strip() for ln in (sweep / "results.md").read_text().splitlines() if ln.startswith("| eff")
    ]
    assert rows == ["none (netvlad · none)", "gem · none", "attention (sral · none)", "unet (sral · student)"]


def _ok_json(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_an_image_replaced_by_one_of_the_same_size_and_mtime_is_not_served_from_the_cache(
    tmp_path: Path, checkpoint: Path
) -> None:
    root = tmp_path / "folder"
    for i in range(6):
        for side in ("database", "queries"):
            path = root / "images" / "test" / side / f"@{585000 + 100 * i:.2f}@4477000.00@17@T@@@@@@@@@@@.jpg"
            path.parent.mkdir(parents=True, exist_ok=True)
            pixels = np.random.default_rng(i).integers(0, 255, (48, 64, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(path, format="BMP")  # every file the same size
    args = [f"ckpt={checkpoint}", "data=folder", f"data.root={root}", f"paths.cache_dir={tmp_path / 'cache'}"]
    run = lambda n: _cli(*EVAL, *args, f"hydra.run.dir={tmp_path / n}", cwd=tmp_path)  # noqa: E731
    assert _ok_json(run("r1"))["test/R@1"] == 100.0
    database = sorted((root / "images" / "test" / "database").iterdir())
    data, stats = [p.read_bytes() for p in database], [p.stat() for p in database]
    for i, path in enumerate(database):  # each place now shows the next place's image: no query matches
        path.write_bytes(data[(i + 1) % len(database)])
        os.utime(path, ns=(stats[i].st_atime_ns, stats[i].st_mtime_ns))
    assert [p.stat().st_size for p in database] == [s.st_size for s in stats]
    assert _ok_json(run("r2"))["test/R@1"] == 0.0


@pytest.mark.slow
def test_a_planted_partial_labels_dir_is_checked_not_adopted(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    args = ["filter=attention", f"paths.cache_dir={cache}"]
    assert _cli(*TRAIN, *args, f"hydra.run.dir={tmp_path / 'r1'}", cwd=tmp_path).returncode == 0
    (labels,) = cache.glob("labels-*")
    planted = cache / f".{labels.name}.partial"
    for png in labels.rglob("*.png"):
        target = planted / png.relative_to(labels)
        target.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((1, 1), np.uint8)).save(target)
    shutil.rmtree(labels)
    proc = _cli(*TRAIN, *args, f"hydra.run.dir={tmp_path / 'r2'}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    sizes = set()
    for png in labels.rglob("*.png"):
        with Image.open(png) as img:
            sizes.add(img.size)
    assert sizes == {(80, 64)}  # experiment=tiny's image size, W x H: every planted 1x1 map was relabelled


@pytest.mark.slow
def test_one_failing_job_of_an_eval_multirun_is_a_failed_row(tmp_path: Path, checkpoint: Path) -> None:
    good = make_folder(tmp_path / "good", n=3)
    broken = make_folder(tmp_path / "broken", n=3)
    _dangling(broken / "images" / "test")
    sweep = tmp_path / "sweep"
    proc = _cli(
        "semvpr.eval",
        "-m",
        "experiment=tiny",
        *EVAL_SIZE,
        f"ckpt={checkpoint}",
        "data=folder",
        f"data.root={broken},{good}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [
        ln
        for ln in (sweep / "results.md").read_text().splitlines()
        if ln.startswith("| data=folder") or "measured" in ln
    ]
    assert len(rows) == 2 and "failed: " in rows[0] and "not found" in rows[0] and "measured" in rows[1]


# ------------------------------------------------------------------ the torch.hub entry point


@pytest.mark.parametrize("folder", ["a,b", "a=b", "it's"])
def test_hub_paths_with_override_syntax_load(tmp_path: Path, checkpoint: Path, folder: str) -> None:
    path = tmp_path / folder / "tested.ckpt"
    path.parent.mkdir()
    shutil.copy(checkpoint, path)
    model = torch.hub.load(str(REPO), "semvpr", ckpt=str(path), source="local")
    assert model.feature_dim > 0


def test_hub_loads_the_file_named_not_an_interpolation_of_it(
    tmp_path: Path, checkpoint: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semvpr.core.errors import SemvprError

    named = tmp_path / "${oc.env:HUBX}" / "tested.ckpt"
    named.parent.mkdir()
    named.touch()  # the file named is empty; an interpolation would have loaded another
    (tmp_path / "other").mkdir()
    shutil.copy(checkpoint, tmp_path / "other" / "tested.ckpt")
    monkeypatch.setenv("HUBX", "other")
    with pytest.raises(SemvprError, match=r"\$\{oc\.env:HUBX\}/tested\.ckpt is not a readable checkpoint"):
        torch.hub.load(str(REPO), "semvpr", ckpt=str(named), source="local")


# ------------------------------------------------------------------ the benchmark and experiment scripts

SCRIPTS = sorted([*(REPO / "benchmarks").glob("*.py"), *(REPO / "experiments").glob("*/*.py")])


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_script_main_turns_a_user_error_into_one_line(script: Path) -> None:
    tree = ast.parse(script.read_text())
    mains = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"]
    assert len(mains) == 1, "a script's entry point is one main()"
    assert [ast.unparse(d) for d in mains[0].decorator_list] == ["exit_on_user_error"]


@pytest.mark.parametrize(
    ("script", "args", "fragment"),
    [
        (
            "experiments/camvid-semantic/paired_masks.py",
            ["{tmp}/a", "{tmp}/b", "--root", "{tmp}/camvid"],
            "CamVid root",
        ),
        (
            "experiments/camvid-semantic/paired_masks.py",
            ["{tmp}/a", "{tmp}/b", "--root", "{camvid}"],
            "student directory",
        ),
        ("experiments/real-streets/figure.py", ["{tmp}/out", "{tmp}/gardens", "--out-png", "{tmp}/f.png"], "not found"),
    ],
)
def test_a_script_given_a_missing_folder_says_so_in_one_line(
    tmp_path: Path, script: str, args: list[str], fragment: str
) -> None:
    camvid = tmp_path / "cv"  # a CamVid folder of one val frame, so the students are what is missing
    for part, mode in (("val", "RGB"), ("valannot", "L")):
        (camvid / part).mkdir(parents=True)
        Image.new(mode, (48, 36)).save(camvid / part / "f.png")
    (camvid / "val.txt").write_text("/SegNet/CamVid/val/f.png /SegNet/CamVid/valannot/f.png\n")
    proc = subprocess.run(
        [sys.executable, str(REPO / script), *(a.format(tmp=tmp_path, camvid=camvid) for a in args)],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    lines = [ln for ln in proc.stderr.strip().splitlines() if not _stage_line(ln)]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
    assert not (tmp_path / "f.png").exists()
