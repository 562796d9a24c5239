"""Bad checkpoints, run directories, caches and file systems through the real CLIs: exit 2 and one line
(tests/bad_input.py runs each row); a replaced image or a planted partial cache is never served as valid."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from tests.bad_input import EVAL, IMMUTABLE, TRAIN, Case, a_file, cli, folder, rows, run_case
from tests.helpers import tiny_config


def _seed_2_70(tmp: Path, ckpt: Path) -> str:
    data = torch.load(ckpt, weights_only=True)
    data["hyper_parameters"]["seed"] = 2**70
    torch.save(data, tmp / "seed.ckpt")
    return str(tmp / "seed.ckpt")


def _empty(tmp: Path) -> str:
    (tmp / "empty.ckpt").touch()
    return str(tmp / "empty.ckpt")


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


def _immutable(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["chattr", "+i", str(folder)], check=True, capture_output=True)
    IMMUTABLE.append(folder)
    return folder


LONG = "x" * 300


def _ok_json(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


CASES: dict[str, Case] = {
    "cache under a file": Case(TRAIN, lambda t, c: [f"paths.cache_dir={a_file(t)}/cache"], "is a file"),
    "resume from 0 bytes": Case(TRAIN, lambda t, c: [f"ckpt_path={_empty(t)}"], "empty.ckpt"),
    "eval 0-byte ckpt": Case(EVAL, lambda t, c: [f"ckpt={_empty(t)}"], "empty.ckpt"),
    "eval seed 2**70": Case(EVAL, lambda t, c: [f"ckpt={_seed_2_70(t, c)}"], "seed=1180591620717411303424"),
    "resume a run whose record names a _target_": Case(TRAIN[:1], _tampered_run, "data.train._target_ is refused"),
    "run dir with $VAR": Case(
        TRAIN, lambda t, c: [f"hydra.run.dir={t.parent / 'run'}/$XV"], "'$' and a leading '~'", env={"XV": "../esc"}
    ),
    "non-finite descriptors": Case(
        EVAL, lambda t, c: folder(t, _huge_checkpoint(t, c), lambda test: None), "are not finite"
    ),
    "checkpoint eval_batch_size=0": Case(
        EVAL,
        lambda t, c: [f"ckpt={_model_value(t, c, 'eval_batch_size', 0)}"],
        "eval_batch_size.ckpt: model.eval_batch_size=0",
    ),
    "checkpoint pca_dim=-1": Case(
        EVAL, lambda t, c: [f"ckpt={_model_value(t, c, 'pca_dim', -1)}"], "pca_dim.ckpt: model.pca_dim"
    ),
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


#: The rows that run by default (each starts a Python with torch): one per class; the whole table with -m slow.
FAST = {
    "eval 0-byte ckpt",
    "resume a run whose record names a _target_",
}


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
    run = lambda n: cli(*EVAL, *args, f"hydra.run.dir={tmp_path / n}", cwd=tmp_path)  # noqa: E731
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
    assert cli(*TRAIN, *args, f"hydra.run.dir={tmp_path / 'r1'}", cwd=tmp_path).returncode == 0
    (labels,) = cache.glob("labels-*")
    planted = cache / f".{labels.name}.partial"
    for png in labels.rglob("*.png"):
        target = planted / png.relative_to(labels)
        target.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((1, 1), np.uint8)).save(target)
    shutil.rmtree(labels)
    proc = cli(*TRAIN, *args, f"hydra.run.dir={tmp_path / 'r2'}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    sizes = set()
    for png in labels.rglob("*.png"):
        with Image.open(png) as img:
            sizes.add(img.size)
    assert sizes == {(80, 64)}  # experiment=tiny's image size, W x H: every planted 1x1 map was relabelled


@pytest.mark.parametrize("case", rows(CASES, FAST))
def test_a_bad_file_is_one_line_and_exit_2(tmp_path: Path, checkpoint: Path, case: str) -> None:
    run_case(CASES[case], tmp_path, checkpoint)
