"""Values read from a teacher or student directory are checked as command-line values are: the same type,
range and finiteness in the dtype they are used in, nested keys allow-listed, sizes bounded before
anything is built, non-regular files refused. Each row damages a copy of a genuine directory and runs the
real eval CLI with it as the mask source: exit code 2, one ``semvpr: error:`` line, nothing written
outside the run and cache directories. One row per folder kind runs by default, the rest with ``-m slow``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from tests.helpers import (
    FRAME_SIZE,
    REPO,
    frame_images,
    tiny_config,
    write_checkpoint,
    write_frames,
    write_student_dir,
    write_teacher_dir,
)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A frame-aligned set, a checkpoint without a mask, and a genuine student and teacher directory."""
    from semvpr.config.build import build_backbone

    tmp = tmp_path_factory.mktemp("folders")
    frames = write_frames(tmp / "frames", {"day": [0, 1, 2, 3], "night": [0, 1, 2, 3]})
    write_checkpoint(tiny_config(tmp / "cache", "filter=attention"), tmp / "plain.ckpt")
    backbone = build_backbone(tiny_config(tmp / "cache").backbone, 0).eval()
    student = write_student_dir(tmp / "student", backbone, frame_images(frames, "day"))
    return {
        "frames": frames,
        "ckpt": tmp / "plain.ckpt",
        "student": student,
        "teacher": write_teacher_dir(tmp / "teacher"),
    }


def _json(path: Path, edit: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _tensors(path: Path, edit: Callable[[dict[str, torch.Tensor]], None]) -> None:
    state = load_file(path)
    edit(state)
    save_file(state, path)


def _fifo(path: Path) -> None:
    path.unlink()
    os.mkfifo(path)


def _set(key: str, value: object) -> Callable[[dict], None]:
    return lambda data: data.__setitem__(key, value)


def _first_float(state: dict[str, torch.Tensor], suffix: str = "") -> str:
    return next(k for k, v in sorted(state.items()) if v.is_floating_point() and k.endswith(suffix))


def _as_int64(state: dict[str, torch.Tensor]) -> None:
    name = _first_float(state, "weight")
    state[name] = (state[name] * 100).round().to(torch.int64)


def _negative_variance(state: dict[str, torch.Tensor]) -> None:
    name = _first_float(state, "running_var")
    state[name] = state[name].clone()
    state[name][0] = -0.5


class _Pickled:
    """An object whose unpickling would call a function: a weights-only load refuses it."""

    def __reduce__(self) -> tuple:
        return (print, ("unpickled",))


def _pickle_instead(path: Path) -> None:
    """The safetensors weights replaced by a pytorch_model.bin that holds a pickled call."""
    path.unlink()
    torch.save({"x": _Pickled()}, path.with_name("pytorch_model.bin"))


def _backbone(edit: dict) -> Callable[[dict], None]:
    return lambda data: data["backbone_config"].update(edit)


#: name -> (folder kind, file to damage, damage, fragment of the one line)
CASES: dict[str, tuple[str, str, Callable[[Path], None], str]] = {
    # ---- a teacher directory
    "semvpr.json image_size past the bound": (
        "teacher",
        "semvpr.json",
        lambda p: _json(p, _set("image_size", [5000, 7])),
        "image_size=[5000, 7] is not",
    ),
    "semvpr.json a FIFO": ("teacher", "semvpr.json", _fifo, "semvpr.json is not a regular file"),
    "image_std whose inverse overflows float32": (
        "teacher",
        "preprocessor_config.json",
        lambda p: _json(p, _set("image_std", [0.25, 1e-39, 0.25])),
        "image_std=[0.25, 1e-39, 0.25] is not three numbers finite in float32",
    ),
    "image_mean infinite in float32": (
        "teacher",
        "preprocessor_config.json",
        lambda p: _json(p, _set("image_mean", [0.5, 4e38, 0.5])),
        "image_mean=[0.5, 4e+38, 0.5] is not three numbers finite in float32",
    ),
    "do_normalize a string": (
        "teacher",
        "preprocessor_config.json",
        lambda p: _json(p, _set("do_normalize", "no")),
        "do_normalize='no'",
    ),
    "config.json num_queries 1e9": (
        "teacher",
        "config.json",
        lambda p: _json(p, _set("num_queries", 1e9)),
        "num_queries=1000000000.0 is not",
    ),
    "config.json dim_feedforward past the bound": (
        "teacher",
        "config.json",
        lambda p: _json(p, _set("dim_feedforward", 100_000)),
        "dim_feedforward=100000",
    ),
    "config.json a float32-infinite loss weight": (
        "teacher",
        "config.json",
        lambda p: _json(p, _set("dice_weight", 1e300)),
        "dice_weight=1e+300 is not a finite",
    ),
    "config.json float64 dtype": (
        "teacher",
        "config.json",
        lambda p: _json(p, _set("dtype", "float64")),
        "dtype='float64'; the teacher runs",
    ),
    "backbone_config a timm hf-hub name": (
        "teacher",
        "config.json",
        lambda p: _json(p, _set("backbone_config", {"model_type": "timm_backbone", "backbone": "hf-hub:someone/net"})),
        "backbone_config.backbone='hf-hub:someone/net' is not a plain timm model name",
    ),
    "backbone_config an unknown nested key": (
        "teacher",
        "config.json",
        lambda p: _json(p, _backbone({"pretrained_cfg_overlay": {"file": "/etc/hostname"}})),
        "backbone_config.pretrained_cfg_overlay is not a key of a swin config",
    ),
    "backbone_config depths past the bound": (
        "teacher",
        "config.json",
        lambda p: _json(p, _backbone({"depths": [1, 1, 100, 1]})),
        "depths=[1, 1, 100, 1]",
    ),
    "teacher weights an int64 tensor": (
        "teacher",
        "model.safetensors",
        lambda p: _tensors(p, _as_int64),
        "is an integer tensor where the model has",
    ),
    "teacher weights a pickle": (
        "teacher",
        "model.safetensors",
        _pickle_instead,
        "pytorch_model.bin are unreadable (UnpicklingError",
    ),
    # ---- a student directory
    "student.json no static class": (
        "student",
        "student.json",
        lambda p: _json(p, lambda d: d["spec"].__setitem__("static_classes", [])),
        "expected a non-empty list of Cityscapes class names",
    ),
    "student.json a class twice": (
        "student",
        "student.json",
        lambda p: _json(p, lambda d: d["spec"].__setitem__("static_classes", ["road", "road"])),
        "names a class twice",
    ),
    "student.json image_size past the bound": (
        "student",
        "student.json",
        lambda p: _json(p, _set("image_size", [4097, 10])),
        "image_size=[4097, 10]",
    ),
    "student.json a FIFO": ("student", "student.json", _fifo, "student.json is not a regular file"),
    "student weights a FIFO": ("student", "model.safetensors", _fifo, "model.safetensors is not a regular file"),
    "student weights an int64 tensor": (
        "student",
        "model.safetensors",
        lambda p: _tensors(p, _as_int64),
        "torch.int64, the architecture",
    ),
    "student weights a negative BatchNorm variance": (
        "student",
        "model.safetensors",
        lambda p: _tensors(p, _negative_variance),
        "has a negative variance",
    ),
}

FAST = {"semvpr.json image_size past the bound", "student weights an int64 tensor"}


def _files(folder: Path) -> set[Path]:
    return {Path(d) / n for d, dirs, names in os.walk(folder) for n in names + dirs}


@pytest.mark.parametrize("case", [c if c in FAST else pytest.param(c, marks=pytest.mark.slow) for c in sorted(CASES)])
def test_a_damaged_folder_value_is_one_line_and_exit_2(world: dict[str, Path], tmp_path: Path, case: str) -> None:
    kind, name, damage, fragment = CASES[case]
    folder = tmp_path / kind
    shutil.copytree(world[kind], folder)
    damage(folder / name)
    run, cache, cwd = tmp_path / "run", tmp_path / "cache", tmp_path / "cwd"
    cwd.mkdir()
    before = _files(tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "experiment=tiny",
            f"ckpt={world['ckpt']}",
            "data=frames",
            f"data.root={world['frames']}",
            "data.database=day",
            "data.queries=night",
            f"data.image_size=[{FRAME_SIZE[0]},{FRAME_SIZE[1]}]",
            "data.num_workers=0",
            f"mask={kind}",
            f"{kind}.checkpoint={folder}",
            f"paths.cache_dir={cache}",
            f"hydra.run.dir={run}",
        ],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("semvpr: error: ") and fragment in lines[0], lines[0]
    new = _files(tmp_path) - before
    assert {p for p in new if not (p.is_relative_to(run) or p.is_relative_to(cache))} == set()
